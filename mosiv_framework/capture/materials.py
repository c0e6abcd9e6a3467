"""The objects of an imported scene: material families from ``--materials elastic,sand`` or
an objects YAML::

    objects:
      1: {material: elastic, name: apple, initial_velocity: [0.5, 0, 0]}
      2: sand
    offsets: {cam_01: 2}          # optional, as --offsets

Ids run 1..K. Anything an object entry holds besides ``material`` and ``name`` is an initial
hint (e.g. ``initial_velocity``, ``params``) that the import records in ``import.json``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mosiv_framework.capture.common import CaptureError
from mosiv_framework.errors import OutputError
from mosiv_framework.scene import MATERIAL_FAMILIES, SceneObject


def _family(value: Any, where: str) -> str:
    name = str(value).strip()
    if name not in MATERIAL_FAMILIES:
        raise CaptureError(
            f"{where}: unknown material {name!r}; families: {', '.join(MATERIAL_FAMILIES)}"
        )
    return name


def from_flag(text: str) -> list[SceneObject]:
    """``elastic,sand`` -> objects 1..K with those families, named object_1.. object_K."""
    names = [m.strip() for m in text.split(",") if m.strip()]
    if not names:
        raise CaptureError("--materials: give one family per object, e.g. elastic,sand")
    return [
        SceneObject(i, f"object_{i}", _family(m, f"--materials item {i}"))
        for i, m in enumerate(names, start=1)
    ]


def read_objects_yaml(path: str | Path) -> tuple[list[SceneObject], dict[int, dict], Any]:
    """(objects, hints by object id, the ``offsets`` entry or None) of an objects YAML."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise OutputError(f"{path}: cannot be read ({exc})") from exc
    except yaml.YAMLError as exc:
        raise CaptureError(f"{path}: not valid YAML ({exc})") from exc
    entries = data.get("objects") if isinstance(data, dict) else None
    if not isinstance(entries, dict) or not entries:
        raise CaptureError(f"{path}: 'objects' must map object ids 1..K to materials")
    try:
        ids = sorted(int(k) for k in entries)
    except (TypeError, ValueError):
        raise CaptureError(f"{path}: objects: ids must be integers 1..K") from None
    if ids != list(range(1, len(ids) + 1)):
        raise CaptureError(f"{path}: objects: ids are {ids}; they must be 1..{len(ids)}")
    objects, hints = [], {}
    for key, entry in entries.items():
        oid, where = int(key), f"{path}: objects.{key}"
        if isinstance(entry, str):
            entry = {"material": entry}
        if not isinstance(entry, dict) or "material" not in entry:
            raise CaptureError(f"{where}: give a material (a family name or {{material: ...}})")
        name = str(entry.get("name", f"object_{oid}"))
        objects.append(SceneObject(oid, name, _family(entry["material"], f"{where}.material")))
        extra = {k: v for k, v in entry.items() if k not in ("material", "name")}
        if extra:
            hints[oid] = extra
    objects.sort(key=lambda o: o.id)
    return objects, hints, data.get("offsets")
