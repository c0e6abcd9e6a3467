"""What every rule of ``mosiv-scene/1`` shares: the problem list, what the JSON files validly
declare, typed access to JSON fields and a file-type test that never raises.

The rules themselves live in ``check_meta`` (scene.json), ``check_cameras`` (cameras.json),
``check_frames`` (rgb/ and masks/) and ``check_gt`` (gt/); ``check`` runs them.
"""

from __future__ import annotations

import errno
import json
import math
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

FORMAT = "mosiv-scene/1"
MATERIAL_FAMILIES = ("elastic", "plasticine", "sand", "newtonian", "non_newtonian", "snow")


def frame_name(frame: int) -> str:
    """File name of one frame: ``0003.png``."""
    return f"{frame:04d}.png"


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a scene: the file (relative to the scene folder) and why."""

    file: str
    reason: str

    def __str__(self) -> str:
        # a problem of the scene folder itself names its path in the reason
        return self.reason if self.file == "." else f"{self.file}: {self.reason}"


@dataclass
class Meta:
    """What the JSON files validly declare; None/empty where they are broken."""

    n_frames: int | None = None
    object_ids: set[int] | None = None
    materials: dict[int, str] = field(default_factory=dict)
    names: dict[int, str] = field(default_factory=dict)
    # camera id -> (width, height), or None where the size fields are invalid
    cameras: dict[str, tuple[int, int] | None] = field(default_factory=dict)
    # camera id -> (first, last) frames it recorded, for cameras that did not record every frame
    camera_frames: dict[str, tuple[int, int]] = field(default_factory=dict)


class Report:
    """The problems found so far, in the order found."""

    def __init__(self) -> None:
        self.problems: list[Problem] = []

    def add(self, file: str, reason: str) -> None:
        self.problems.append(Problem(file, reason))


# ------------------------------------------------------------------------------ file types
def path_kind(path: Path) -> str:
    """What is at ``path``, without raising: ``"file"``, ``"folder"``, ``"missing"``,
    ``"broken link"``, ``"link loop"``, ``"special"`` (device, fifo, socket) or
    ``"unreadable: <reason>"``. Symbolic links to a file or folder count as that file or folder.
    """
    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        try:
            return "broken link" if path.is_symlink() else "missing"
        except OSError:
            return "missing"
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "link loop"
        return f"unreadable: {exc.strerror or exc}"
    except ValueError as exc:  # e.g. an embedded NUL byte in a name
        return f"unreadable: {exc}"
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "folder"
    return "special"


def kind_reason(kind: str, expected: str) -> str:
    """Why a path of ``kind`` (see ``path_kind``) is not the ``expected`` thing."""
    what = {
        "file": "is a file",
        "folder": "is a folder",
        "missing": "missing",
        "broken link": "is a symbolic link whose target does not exist",
        "link loop": "is a symbolic link loop (it points back at itself)",
        "special": "is not a regular file (device, pipe or socket)",
    }.get(kind, f"cannot be accessed ({kind.removeprefix('unreadable: ')})")
    return what if kind == "missing" else f"{what}; expected {expected}"


# ---------------------------------------------------------------------------- JSON helpers
def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def finite(v: float | int) -> bool:
    """math.isfinite that treats a JSON integer beyond float range as not finite."""
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def non_finite(obj: Any, where: str) -> list[str]:
    """Dotted paths of every NaN/inf number (or integer beyond float range) in parsed JSON."""
    if is_number(obj) and not finite(obj):
        shown = obj if isinstance(obj, float) else f"{str(obj)[:12]}... (beyond float range)"
        return [f"{where or 'value'} = {shown}"]
    if isinstance(obj, dict):
        return [p for k, v in obj.items() for p in non_finite(v, f"{where}.{k}" if where else k)]
    if isinstance(obj, list):
        return [p for i, v in enumerate(obj) for p in non_finite(v, f"{where}[{i}]")]
    return []


def load_json(root: Path, rel: str, report: Report, *, required: bool = True) -> Any:
    """Parse ``root/rel``; report a missing or unreadable file, bad JSON and every non-finite
    number. Returns the top-level object, or None when there is none to check."""
    kind = path_kind(root / rel)
    if kind != "file":
        if required or kind != "missing":
            report.add(rel, kind_reason(kind, "a JSON file"))
        return None
    try:
        data = json.loads((root / rel).read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        report.add(rel, f"is not valid JSON ({exc})")
        return None
    except RecursionError:
        report.add(rel, "is not valid JSON (nested too deeply to parse)")
        return None
    except OSError as exc:
        report.add(rel, f"cannot be read ({exc.strerror or exc})")
        return None
    for where in non_finite(data, ""):
        report.add(rel, f"non-finite number: {where}; every number must be finite")
    if not isinstance(data, dict):
        report.add(rel, f"top level must be a JSON object, got {type(data).__name__}")
        return None
    return data


ABSENT = object()  # marks a missing key, distinct from a JSON null


def shown(value: Any, limit: int = 80) -> str:
    """``repr`` of a JSON value, cut short so one problem stays one readable line."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class Fields:
    """Typed access to one JSON object, reporting bad or missing fields against a file."""

    def __init__(self, report: Report, file: str, data: dict, prefix: str = "") -> None:
        self.report, self.file, self.data, self.prefix = report, file, data, prefix

    def bad(self, key: str, reason: str) -> None:
        self.report.add(self.file, f"{self.prefix}{key}: {reason}")

    def _get(self, key: str, required: bool) -> Any:
        """The value, or ABSENT when the key is missing (reported if required). A JSON null
        is returned as None and then rejected by the type check like any wrong type."""
        if key not in self.data:
            if required:
                self.bad(key, "missing")
            return ABSENT
        return self.data[key]

    def number(self, key: str, *, positive: bool = False, required: bool = True) -> float | None:
        v = self._get(key, required)
        if v is ABSENT:
            return None
        if not is_number(v):
            self.bad(key, f"must be a number, got {shown(v)}")
            return None
        if not finite(v):
            return None  # already reported as non-finite
        if positive and v <= 0:
            self.bad(key, f"must be positive, got {v!r}")
            return None
        return float(v)

    def integer(self, key: str, *, minimum: int | None = None) -> int | None:
        v = self._get(key, True)
        if v is ABSENT:
            return None
        if not (isinstance(v, int) and not isinstance(v, bool)):
            self.bad(key, f"must be an integer, got {shown(v)}")
            return None
        if minimum is not None and v < minimum:
            self.bad(key, f"must be at least {minimum}, got {v}")
            return None
        return v

    def string(self, key: str) -> str | None:
        v = self._get(key, True)
        if v is ABSENT:
            return None
        if not isinstance(v, str) or not v:
            self.bad(key, f"must be a non-empty string, got {shown(v)}")
            return None
        return v

    def vec3(self, key: str, *, required: bool = True) -> tuple[float, float, float] | None:
        v = self._get(key, required)
        if v is ABSENT:
            return None
        if not (isinstance(v, list) and len(v) == 3 and all(is_number(x) for x in v)):
            self.bad(key, f"must be a list of 3 numbers, got {shown(v)}")
            return None
        if not all(finite(x) for x in v):
            return None  # already reported as non-finite
        return (float(v[0]), float(v[1]), float(v[2]))

    def sub(self, key: str, *, required: bool = True) -> Fields | None:
        v = self._get(key, required)
        if v is ABSENT:
            return None
        if not isinstance(v, dict):
            self.bad(key, f"must be a JSON object, got {shown(v)}")
            return None
        return Fields(self.report, self.file, v, f"{self.prefix}{key}.")
