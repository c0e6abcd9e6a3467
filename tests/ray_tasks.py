"""Tasks and a scene source for tests/test_ray_suite.py, in a module Ray workers can import.

Ray workers are processes of their own: a function or scene source defined in a test module
(which pytest imports under a name no other process knows) cannot reach them. The test puts
this folder on the workers' ``PYTHONPATH`` and names :func:`register_tiny_source` as their
``worker_process_setup_hook``, so the workers' registries know the ``tiny`` scene source.
"""

from __future__ import annotations

import logging
import os
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosiv_framework.interfaces import SceneSource
from mosiv_framework.registry import Component, get_registry, hookimpl
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.scene.io import SceneObject, write_scene


def die_once(marker: str) -> None:
    """Kill this process with SIGKILL unless ``marker`` exists, which it leaves behind: the
    first attempt dies mid-run, the next one passes."""
    path = Path(marker)
    if not path.exists():
        path.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)


def die() -> None:
    """Kill this process with SIGKILL on every attempt."""
    os.kill(os.getpid(), signal.SIGKILL)


@dataclass
class TinyOptions:
    materials: str = "elastic,elastic"
    n_objects: int = 2
    seed: int = 0
    scene_name: str = ""
    kill_marker: str = ""  # materials:path -- the scene of these materials dies once


class TinySource(SceneSource):
    """A blank two-frame scene of the requested materials (8 x 8 pixels, one camera)."""

    def __init__(self, **options):
        self.o = TinyOptions(**options)

    def generate(self, out_dir: Path) -> Path:
        if self.o.kill_marker:
            materials, marker = self.o.kill_marker.split(":", 1)
            if materials == self.o.materials:
                Path(out_dir).mkdir(parents=True)  # a half-written scene left by the death
                die_once(marker)
        materials = self.o.materials.split(",")
        camera = Camera.look_at(
            (1.0, 0.0, 1.0), (0, 0, 0), id="cam", width=8, height=8, fov_deg=40.0
        )
        blank = np.zeros((2, 8, 8, 3), np.uint8)
        return write_scene(
            out_dir,
            name=self.o.scene_name or f"tiny-{self.o.seed}",
            fps=24.0,
            objects=[SceneObject(k, f"o{k}", m) for k, m in enumerate(materials, start=1)],
            cameras=[camera],
            rgb={"cam": blank},
            masks={"cam": blank[..., 0]},
            observed_frames=1,
            domain_lower=(-1, -1, 0),
            domain_upper=(1, 1, 1),
        )


class TinyPlugin:
    @hookimpl
    def mosiv_scene_sources(self, register):
        register(Component("scene_source", "tiny", factory=TinySource, options=TinyOptions))


def register_tiny_source(registry=None) -> None:
    """Add the ``tiny`` source to ``registry`` (default: this process's, as in a worker)."""
    (registry or get_registry()).add_plugin(TinyPlugin(), name="tiny-test")


def entry(name: str, out: str, marker: str = "") -> dict:
    """A trivial suite entry: logs, writes ``out/name.json`` and returns what it wrote;
    with ``marker`` its first attempt is killed before it writes anything."""
    logging.getLogger("mosiv_framework.test_entry").info("info from %s", name)
    logging.getLogger("mosiv_framework.test_entry").warning("warning from %s", name)
    if marker:
        die_once(marker)
    record = {"name": name, "pid": os.getpid(), "gpus": os.environ.get("CUDA_VISIBLE_DEVICES")}
    Path(out, f"{name}.json").write_text(repr(record))
    return record


def fail(name: str) -> None:
    raise ValueError(f"entry {name} is wrong")
