"""The process-wide Taichi runtime: one active architecture at a time.

Taichi allows a single runtime per process. When a simulator asks for another device, the runtime
is reset (``ti.reset``) and re-initialised; every field allocated before becomes invalid, which
simulators notice through ``generation()`` and answer by re-allocating.
"""

from __future__ import annotations

import contextlib
import os
import sys

import taichi as ti
import torch

from mosiv_framework.errors import ConfigError

_state = {"device": None, "generation": 0, "kernel_profiler": False}


def profile_kernels() -> None:
    """Start later runtimes with Taichi's kernel profiler on (``ti.profiler``: the device time
    of every kernel launch; benchmarks/taichi_profile.py). Call before the first rollout."""
    if _state["device"] is not None:
        raise RuntimeError("profile_kernels() must come before the Taichi runtime starts")
    _state["kernel_profiler"] = True


def resolve_device(device: str) -> str:
    """'auto' -> 'cuda' when torch sees a CUDA GPU, else 'cpu'."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def ensure(device: str) -> int:
    """Make the runtime run on ``device`` ('cpu' or 'cuda'); returns its generation number."""
    if _state["device"] == device:
        return _state["generation"]
    if _state["device"] is not None:
        ti.reset()
    arch = ti.cuda if device == "cuda" else ti.cpu
    # the offline kernel cache stays on unless TI_OFFLINE_CACHE=0 (an A/B of two plugin
    # versions in one place needs it off): Taichi lets an explicit argument override that
    # variable, so the argument is only passed when the variable is unset
    cache = {} if "TI_OFFLINE_CACHE" in os.environ else {"offline_cache": True}
    # float32 throughout; fast_math off so NaN/inf checks are not optimised away
    # ti.init prints "Starting on arch=..." on stdout whatever the log level; stdout belongs to
    # the command's own output (`mosiv bench sim --json`), so the line goes to stderr
    with contextlib.redirect_stdout(sys.stderr):
        ti.init(
            arch=arch,
            default_fp=ti.f32,
            fast_math=False,
            log_level="warn",
            kernel_profiler=_state["kernel_profiler"],
            **cache,
        )
    actual = ti.lang.impl.current_cfg().arch
    if device == "cuda" and actual != ti.cuda:
        ti.reset()
        _state["device"] = None
        raise ConfigError(
            f"taichi-mpm option device='cuda' but Taichi could not start on CUDA (got {actual}); "
            "use device='cpu' or 'auto'"
        )
    _state["device"] = device
    _state["generation"] += 1
    return _state["generation"]


def generation() -> int:
    return _state["generation"]
