"""The run folder: atomic writes, per-stage completion markers, and what marks a folder as a run.

Every file is written under a temporary name and moved into place with ``os.replace``: an
interrupted run never leaves a truncated result under a final name. A stage counts as done only
when its marker records the same configuration fingerprint as the current recipe and the same
digest of the inputs it reads (the bytes of the scene's files): a scene replaced at the same path
is not mistaken for the one the results came from, and a run folder copied to another machine
with its scene, and back, resumes there.

``run.json`` (format ``mosiv-run/1``) marks a folder as MOSIV's own: ``mosiv run`` writes into a
new folder, an empty one, or one holding run.json (or the stage markers of a run made before
run.json existed), and refuses any other folder rather than overwrite a user's files.
"""

from __future__ import annotations

import datetime
import hashlib
import io
import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

import torch

from mosiv_framework.errors import OutputError
from mosiv_framework.pipeline.formats import (
    RUN,
    STAGE,
    STAGE_FORMATS,
    check_format,
    formats_of,
    recipe_header,
    stamped,
)

RUN_JSON = "run.json"
#: what ``mosiv run`` writes at the top of its folder, and what the commands reading a run write
#: beside it (diagnose, simulate): the names ``mosiv run --force`` may remove
RUN_FILES = (
    "recipe.yaml",
    RUN_JSON,
    "stages",
    "reconstruction.pt",
    "particles.pt",
    "identified.json",
    "identify",
    "metrics.json",
    "trajectories.png",
    "rollout.pt",
    "rollout.npz",
    "videos",
    "diagnosis.json",
    "diagnosis.md",
    "diagnose",
    "simulate",
)
#: written beside a run before it starts: the diagnosis suite's per-entry log. Kept by --force.
COMPANIONS = ("suite.log",)
#: bytes read at a time while hashing a scene file
HASH_CHUNK = 1 << 20
#: entries named in the message refusing a folder
SHOWN = 5


def fingerprint(*parts: Any) -> str:
    """A short stable hash of JSON-serialisable configuration pieces."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def scene_digest(path: str | Path) -> str:
    """A short hash of a scene folder's contents: every file's relative path and bytes.

    Content, not modification times: a scene folder copied to another machine and back (with
    ``cp -r``, which gives every file a new time) is the same scene, and the stages finished on
    it resume; a scene written again with the same bytes is the same scene too. Each file's
    hash is remembered for the process under its path, size, inode and times (the change time
    too, which no one can set back), so a second digest of an unchanged folder reads nothing
    again."""
    root = Path(path)
    digest = hashlib.sha256()
    for folder, dirs, files in os.walk(root):  # links to folders are not followed
        dirs.sort()
        for name in sorted(files):
            file = Path(folder) / name
            digest.update(f"{file.relative_to(root).as_posix()}\0{file_hash(file)}\n".encode())
    return digest.hexdigest()[:16]


#: (path, size, inode, mtime_ns, ctime_ns) -> the file's content hash, for this process
_FILE_HASHES: dict[tuple, str] = {}


def file_hash(file: Path) -> str:
    """The hash of ``file``'s bytes ("missing" for a broken link or an unreadable file, whose
    name still counts in the folder's digest)."""
    try:
        stat = file.stat()
    except OSError:
        return "missing"
    key = (str(file.resolve()), stat.st_size, stat.st_ino, stat.st_mtime_ns, stat.st_ctime_ns)
    known = _FILE_HASHES.get(key)
    if known is not None:
        return known
    content = hashlib.blake2b(digest_size=16)
    try:
        with open(file, "rb") as handle:
            while chunk := handle.read(HASH_CHUNK):
                content.update(chunk)
    except OSError:
        return "missing"
    _FILE_HASHES[key] = content.hexdigest()
    return _FILE_HASHES[key]


def earlier_scene_digest(path: str | Path) -> str:
    """The scene digest stage markers recorded before the content digest: every file's
    relative path, size and modification time, and the bytes of scene.json, cameras.json and
    gt/params.json. Kept only to recognise those markers (``Progress.carry_earlier_markers``)."""
    root = Path(path)
    digest = hashlib.sha256()
    for folder, dirs, files in os.walk(root):
        dirs.sort()
        for name in sorted(files):
            file = Path(folder) / name
            try:
                stat = file.stat()
            except OSError:
                stat = None
            size, mtime = (stat.st_size, stat.st_mtime_ns) if stat else (-1, -1)
            digest.update(f"{file.relative_to(root).as_posix()}\0{size}\0{mtime}\n".encode())
    for name in ("scene.json", "cameras.json", "gt/params.json"):
        file = root / name
        if file.is_file():
            digest.update(f"{name}\0".encode() + hashlib.sha256(file.read_bytes()).digest())
    return digest.hexdigest()[:16]


class RunDir:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        #: top-level names written through this object (recorded in run.json)
        self.written: set[str] = set()

    def path(self, name: str) -> Path:
        return self.root / name

    def write_bytes(self, name: str, data: bytes) -> Path:
        target = self.path(name)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, target)
        self.written.add(Path(name).parts[0])
        return target

    def save_json(self, name: str, data: Any) -> Path:
        return self.write_bytes(name, (json.dumps(data, indent=2, default=float) + "\n").encode())

    def load_json(self, name: str) -> Any:
        """The JSON file ``name``; a run file of a format this version cannot read raises
        FormatError (see ``mosiv_framework.pipeline.formats``)."""
        data = json.loads(self.path(name).read_text())
        supported = formats_of(name)
        return data if supported is None else check_format(data, supported, path=self.path(name))

    def save_torch(self, name: str, obj: Any) -> Path:
        buffer = io.BytesIO()
        torch.save(obj, buffer)
        return self.write_bytes(name, buffer.getvalue())

    def load_torch(self, name: str) -> Any:
        return torch.load(self.path(name), weights_only=False)

    def stage_state(self, stage: str, config_hash: str, inputs: str | None = None) -> str:
        """``"done"``, ``"missing"`` (no marker, or another configuration) or ``"changed"``
        (same configuration, other inputs). A marker written before inputs were recorded
        counts as done: nothing says its inputs differ."""
        name = f"stages/{stage}.json"
        if not self.path(name).is_file():
            return "missing"
        marker = self.load_json(name)
        if marker.get("config") != config_hash:
            return "missing"
        if inputs is not None and marker.get("inputs", inputs) != inputs:
            return "changed"
        return "done"

    def stage_done(self, stage: str, config_hash: str, inputs: str | None = None) -> bool:
        return self.stage_state(stage, config_hash, inputs) == "done"

    def mark_done(self, stage: str, config_hash: str, inputs: str | None = None, **info) -> None:
        record = {"config": config_hash, **({"inputs": inputs} if inputs else {}), **info}
        self.save_json(f"stages/{stage}.json", stamped(STAGE, record))

    def rekey_marker(self, stage: str, config_hash: str, inputs: str) -> None:
        """Rewrite ``stage``'s marker under another key and inputs, keeping what else it
        records."""
        marker = self.load_json(f"stages/{stage}.json")
        info = {k: v for k, v in marker.items() if k not in ("format", "config", "inputs")}
        self.mark_done(stage, config_hash, inputs, **info)


# --------------------------------------------------------------------- the folder of a run
def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _within(path: Path, folder: Path) -> bool:
    """Whether ``path`` is ``folder`` or lies inside it (both resolved)."""
    return path == folder or folder in path.parents


def _listing(names: list[str]) -> str:
    shown = ", ".join(repr(n) for n in names[:SHOWN])
    return shown + (f" and {len(names) - SHOWN} more" if len(names) > SHOWN else "")


def _earlier_run(root: Path) -> bool:
    """Whether ``root`` holds the stage markers of a run made before run.json existed, or
    only run files with a recipe.yaml of the run format (such a run stopped before its first
    stage finished)."""
    stages = root / "stages"
    if not stages.is_dir():
        recipe = root / "recipe.yaml"
        try:
            header = recipe.open("rb").readline() if recipe.is_file() else b""
        except OSError:
            return False
        return header == recipe_header() and set(os.listdir(root)) <= set(RUN_FILES)
    for marker in stages.glob("*.json"):
        try:
            data = json.loads(marker.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(data, dict) and "config" in data:
            if data.get("format", STAGE) in STAGE_FORMATS:
                return True
    return False


class OutputFolder:
    """What ``output.dir`` holds before a run writes anything, and which of it is the run's.

    ``kind``: ``"new"`` (missing), ``"empty"`` (nothing but the scene the run reads, or a file
    written beside runs, ``COMPANIONS``), ``"run"`` (holds run.json) or ``"earlier run"`` (stage
    markers without run.json). ``scene_entry``: the entry holding the scene when ``scene.path``
    lies inside the folder (the run's own input, never removed).
    """

    def __init__(self, root: str | Path, *, scene_path: str | Path):
        self.root = Path(root)
        real_root, real_scene = self.root.resolve(), Path(scene_path).resolve()
        if _within(real_root, real_scene):
            raise OutputError(
                f"output.dir={str(root)!r} is scene.path={str(scene_path)!r} or lies inside it: "
                f"a run would write its files into the scene; choose an output folder outside "
                f"the scene"
            )
        self.real_scene = real_scene
        self.existed = self.root.exists()
        self.entries = sorted(os.listdir(self.root)) if self.root.is_dir() else []
        self.scene_entry = self.scene_name()
        self.record: dict | None = None
        if not self.existed:
            self.kind = "new"
        elif (self.root / RUN_JSON).is_file():
            self.kind, self.record = "run", self._read_record()
        elif _earlier_run(self.root):
            self.kind = "earlier run"
        elif not self.foreign():
            self.kind = "empty"
        else:
            raise OutputError(
                f"output.dir={str(root)!r} is not empty and is not a run folder (it has no "
                f"{RUN_JSON}): it holds {_listing(self.foreign())}; choose a new or empty "
                f"folder, or the folder of an earlier run, so no file of yours is overwritten"
            )

    def _read_record(self) -> dict:
        path = self.root / RUN_JSON
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise OutputError(
                f"{path}: not a readable run marker ({exc}); move the folder aside or choose "
                f"another output.dir"
            ) from None
        return check_format(data, (RUN,), path=path)

    def foreign(self) -> list[str]:
        """Entries that are neither the scene nor a companion file."""
        return [e for e in self.entries if e != self.scene_entry and e not in COMPANIONS]

    def own_files(self) -> list[str]:
        """The entries a fresh start removes: the run files and those run.json lists; never
        the scene, a companion or any other file."""
        listed = (self.record or {}).get("files") or []
        names = set(RUN_FILES) | {n for n in listed if isinstance(n, str) and _plain_name(n)}
        names -= {self.scene_entry, *COMPANIONS}
        return [e for e in self.entries if e in names]

    def start_afresh(self, *, force: bool) -> list[str]:
        """Remove the previous run's files (``output.resume=false``); refused without
        ``force`` unless there is no previous run. Returns the names removed."""
        if self.kind in ("new", "empty"):
            return []
        own = self.own_files()
        if not force:
            raise OutputError(
                f"output.dir={str(self.root)!r} holds a previous run and output.resume=false: "
                f"run `mosiv run --force ...` to remove its files ({_listing(own)}; nothing "
                f"else is touched), or choose a new folder"
            )
        for name in own:
            target = self.root / name
            if target.is_dir() and not target.is_symlink():
                shutil.rmtree(target)
            else:
                target.unlink(missing_ok=True)
        self.entries = sorted(os.listdir(self.root))
        self.kind, self.record = "empty", None
        return own

    def undo(self) -> None:
        """After a run failed before any stage finished: remove what it wrote (recipe.yaml,
        run.json) from a folder that was new or empty, and the folder itself, with the scene
        generated into it, if the run created it. A folder holding anything else is left."""
        if self.kind not in ("new", "empty") or not self.root.is_dir():
            return
        scene = self.scene_name()
        left = [n for n in os.listdir(self.root) if not (n.startswith(".") and n.endswith(".tmp"))]
        ours = {"recipe.yaml", RUN_JSON} | ({scene} if not self.existed and scene else set())
        if any(n not in ours and n not in self.entries for n in left):
            return  # something else appeared (a stage's partial output): keep it all
        if not self.existed and set(left) <= ours:
            shutil.rmtree(self.root)
            return
        for name in ("recipe.yaml", RUN_JSON):
            (self.root / name).unlink(missing_ok=True)

    def scene_name(self) -> str | None:
        """The entry holding the scene now (a generated scene appears after inspection)."""
        if not self.root.is_dir():
            return None
        return next(
            (
                e
                for e in os.listdir(self.root)
                if _within(self.real_scene, (self.root / e).resolve())
            ),
            None,
        )


def _plain_name(name: str) -> bool:
    """Whether ``name`` (from run.json) is one entry of the folder, not a path leading out."""
    return name not in ("", ".", "..") and "/" not in name and "\\" not in name


class RunRecord:
    """run.json: the format, the MOSIV version, when the run folder was created and last
    updated, the recipe's fingerprint, the scene's path and digest, the stages done (their
    markers are under ``stages/``) and the top-level files the run wrote."""

    def __init__(self, rd: RunDir, previous: dict | None, *, recipe: str, scene: str, digest: str):
        from mosiv_framework import __version__

        previous = previous or {}
        self.rd = rd
        self.files = {n for n in previous.get("files") or [] if isinstance(n, str)}
        self.data = stamped(
            RUN,
            {
                "mosiv_version": __version__,
                "created": previous.get("created") or _now(),
                "updated": _now(),
                "recipe": recipe,
                "scene": {"path": scene, "digest": digest},
                "stages_done": [],
                "markers": "stages/",
                "files": [],
            },
        )

    def stage_done(self, stage: str) -> None:
        if stage not in self.data["stages_done"]:
            self.data["stages_done"].append(stage)
        self.save()

    def add_files(self, names) -> None:
        self.files.update(n for n in names if _plain_name(n))

    def save(self) -> None:
        self.files.update(self.rd.written)
        self.data["files"] = sorted(self.files | {RUN_JSON})
        self.data["updated"] = _now()
        self.rd.save_json(RUN_JSON, self.data)
