"""The run folder: atomic writes and per-stage completion markers, so runs resume safely.

Every file is written under a temporary name and moved into place with ``os.replace``: an
interrupted run never leaves a truncated result under a final name. A stage counts as done only
when its marker exists and records the same configuration fingerprint as the current recipe.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import uuid
from pathlib import Path
from typing import Any

import torch

from mosiv_framework.pipeline.formats import STAGE, check_format, formats_of, stamped


def fingerprint(*parts: Any) -> str:
    """A short stable hash of JSON-serialisable configuration pieces."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class RunDir:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

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

    def stage_done(self, stage: str, config_hash: str) -> bool:
        name = f"stages/{stage}.json"
        return self.path(name).is_file() and self.load_json(name).get("config") == config_hash

    def mark_done(self, stage: str, config_hash: str, **info: Any) -> None:
        self.save_json(f"stages/{stage}.json", stamped(STAGE, {"config": config_hash, **info}))
