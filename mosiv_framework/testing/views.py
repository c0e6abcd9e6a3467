"""Scenes whose cameras did not record every frame, made from complete ones, for the tests of
every step that reads images (a rig's camera that started late, or stopped early)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping
from pathlib import Path

from mosiv_framework.scene.check_common import frame_name


def with_recorded_frames(
    scene_dir: str | Path, out_dir: str | Path, spans: Mapping[str, tuple[int, int]]
) -> Path:
    """Copy scene ``scene_dir`` to ``out_dir``, keeping of each camera in ``spans`` only the
    frames (first, last) it names, and declaring them in cameras.json. Returns ``out_dir``."""
    out = Path(out_dir)
    shutil.copytree(scene_dir, out)
    cameras_json = out / "cameras.json"
    data = json.loads(cameras_json.read_text())
    n_frames = json.loads((out / "scene.json").read_text())["n_frames"]
    for entry in data["cameras"]:
        if entry["id"] not in spans:
            continue
        first, last = spans[entry["id"]]
        entry["frames"] = [first, last]
        for t in range(n_frames):
            if not first <= t <= last:
                for kind in ("rgb", "masks"):
                    (out / kind / entry["id"] / frame_name(t)).unlink()
    cameras_json.write_text(json.dumps(data, indent=2))
    return out
