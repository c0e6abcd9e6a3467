"""Finished steps of a diagnosis kept on disk, so that a diagnosis cut off resumes after them.

A full diagnosis refits and re-identifies five models one after another: about 20 minutes per
scene on a shared H200 (docs/BENCHMARKS.md, session 21), where a device lease ended with four
entries 1,450-1,650 s into their diagnoses and every one of those seconds was lost. Each
expensive step (the location, the screening, each model's refit, each fresh identification and
the converging refits) is now saved under ``RUN/diagnose/steps/`` as soon as it finishes, with
a key of everything it depends on; a later ``mosiv diagnose`` of the same run, budget and
identified model takes it from there instead of computing it again.

The saved steps are removed once the report is written: they are for resuming, not a second
record, so that diagnosing a finished run again still recomputes it.
"""

from __future__ import annotations

import hashlib
import shutil
from collections.abc import Callable
from typing import Any, TypeVar

from omegaconf import DictConfig, OmegaConf

from mosiv_framework.pipeline.rundir import RunDir, fingerprint

T = TypeVar("T")

#: bump when a saved step's meaning changes, so that old files are recomputed, not misread
STEP_FORMAT = 1
FOLDER = "diagnose/steps"


def diagnosis_key(run_dir: RunDir, *, budget: dict, fit_frames: list, heldout: list, recipe) -> str:
    """What every saved step of one diagnosis depends on: the budget, the frame split, the
    recipe's diagnose and simulator sections and the run's identified model (by content, so a
    run identified again invalidates them). Not the device: a step saved on the CPU serves a
    GPU diagnosis and the other way round."""
    identified = run_dir.path("identified.json").read_bytes()
    return fingerprint(
        STEP_FORMAT,
        budget,
        fit_frames,
        heldout,
        _plain(recipe.get("diagnose", None)),
        {k: v for k, v in (_plain(recipe.get("simulator", None)) or {}).items() if k != "device"},
        _plain(recipe.get("physics_terms", None)),
        hashlib.sha256(identified).hexdigest(),
    )


def _plain(section) -> Any:
    return OmegaConf.to_container(section) if isinstance(section, DictConfig) else section


class DiagnosisSteps:
    """Get-or-compute of a diagnosis's named steps (``get``), saved atomically."""

    def __init__(self, run_dir: RunDir, key: str, *, say: Callable[[str], None] = print):
        self.run_dir, self.key, self.say = run_dir, key, say
        self.resumed: list[str] = []

    def get(self, step: str, compute: Callable[[], T]) -> T:
        """The saved result of ``step`` if it was saved under this diagnosis's key, else
        ``compute()``, saved before it is returned."""
        name = f"{FOLDER}/{step}.pt"
        if self.run_dir.path(name).is_file():
            try:
                saved = self.run_dir.load_torch(name)
            except Exception as exc:  # a file from another code version: recompute it
                self.say(f"  could not read the saved step {step} ({exc}); computing it again")
            else:
                if isinstance(saved, dict) and saved.get("key") == self.key:
                    self.resumed.append(step)
                    return saved["value"]
        value = compute()
        self.run_dir.save_torch(name, {"key": self.key, "value": value})
        return value

    def clear(self) -> None:
        """Remove every saved step (the diagnosis is complete)."""
        shutil.rmtree(self.run_dir.path(FOLDER), ignore_errors=True)
