"""Finished steps of a diagnosis kept on disk, so that a diagnosis cut off resumes after them.

A full diagnosis refits and re-identifies five models one after another: about 20 minutes per
scene on a shared H200 (docs/BENCHMARKS.md), and a machine lost mid-diagnosis would lose all of
it. Each expensive step (the location, the screening, each model's refit, each fresh
identification and the converging refits) is saved under ``RUN/diagnose/steps/`` as soon as it
finishes, with a key of everything it depends on (``STEP_FORMAT`` among it); a later
``mosiv diagnose`` of the same run, budget and identified model takes it from there instead of
computing it again.

The saved steps are removed once the report is written: they are for resuming, not a second
record, so that diagnosing a finished run again still recomputes it.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
from collections.abc import Callable
from typing import Any, TypeVar

import torch
from omegaconf import DictConfig, OmegaConf

from mosiv_framework.pipeline.rundir import RunDir, fingerprint

T = TypeVar("T")
log = logging.getLogger(__name__)

#: bump when a saved step's meaning or its classes' fields change (``model.Fit``,
#: ``hypothesise.Screen``, ``locate``'s result), so that old files are recomputed, not misread
STEP_FORMAT = 1
FOLDER = "diagnose/steps"
#: recipe sections a saved step depends on, besides the simulator's
SECTIONS = ("diagnose", "identify", "losses", "physics_terms")


def diagnosis_key(
    run_dir: RunDir,
    *,
    budget: dict,
    fit_frames: list,
    heldout: list,
    recipe,
    simulator_overrides: dict | None = None,
) -> str:
    """What every saved step of one diagnosis depends on: the budget, the frame split, the
    recipe sections that shape a refit (diagnose; identify: which parameters are free and the
    fresh identifications' schedule; losses; the simulator with its overrides; physics terms)
    and the run's identified model (by content, so a run identified again invalidates them).
    Not the device: a step saved on the CPU serves a GPU diagnosis and the other way round."""
    identified = run_dir.path("identified.json").read_bytes()
    simulator = {**(_plain(recipe.get("simulator", None)) or {}), **(simulator_overrides or {})}
    simulator.pop("device", None)
    return fingerprint(
        STEP_FORMAT,
        budget,
        fit_frames,
        heldout,
        {name: _plain(recipe.get(name, None)) for name in SECTIONS},
        simulator,
        hashlib.sha256(identified).hexdigest(),
    )


def _plain(section) -> Any:
    if isinstance(section, DictConfig):
        return OmegaConf.to_container(section, resolve=True)
    return section


#: what ``DiagnosisSteps._saved`` returns for a step that must be computed
_MISSING = object()


class DiagnosisSteps:
    """Get-or-compute of a diagnosis's named steps (``get``), saved atomically.

    Steps are asked for in the diagnosis's fixed order, and the saved ones are used only as an
    unbroken prefix of it: once one step is computed (its file missing, unreadable or from
    another key), every later one is computed too, so that no saved step built on an earlier
    result is combined with a new one (GPU rollouts are not bit-reproducible: a screening
    computed again can differ from the one the saved refits started from).
    """

    def __init__(self, run_dir: RunDir, key: str):
        self.run_dir, self.key = run_dir, key
        self.resumed: list[str] = []
        self._computing = False

    def get(self, step: str, compute: Callable[[], T]) -> T:
        """The saved result of ``step`` if the steps before it were all saved too and it was
        saved under this diagnosis's key, else ``compute()``, saved before it is returned."""
        return self.get_many([step], lambda missing: [compute()])[0]

    def get_many(self, steps: list[str], compute: Callable[[list[str]], list[T]]) -> list[T]:
        """``get`` of consecutive steps whose results are computed together: the saved ones
        are read (an unbroken prefix, as for ``get``), the others computed by one call
        ``compute(names)`` (one result per name, in order) and each saved."""
        values = []
        for step in steps:
            saved = self._saved(step)
            if saved is _MISSING:
                break
            values.append(saved)
        rest = steps[len(values) :]
        if rest:
            self._computing = True
            computed = compute(rest)
            for step, value in zip(rest, computed, strict=True):
                self.run_dir.save_torch(f"{FOLDER}/{step}.pt", {"key": self.key, "value": value})
            values += computed
        return values

    def _saved(self, step: str) -> Any:
        """The saved result of ``step`` under this key, or _MISSING (also once a step has been
        computed: no later saved step is used)."""
        path = self.run_dir.path(f"{FOLDER}/{step}.pt")
        if self._computing or not path.is_file():
            return _MISSING
        try:  # on the CPU: a step saved beside a GPU serves a CPU-only machine as well
            saved = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as exc:  # e.g. a file of another code version: compute it again
            log.warning("could not read the saved step %s (%s); computing it again", step, exc)
            return _MISSING
        if isinstance(saved, dict) and saved.get("key") == self.key:
            self.resumed.append(step)
            return saved["value"]
        return _MISSING

    def clear(self) -> None:
        """Remove every saved step (the diagnosis is complete)."""
        shutil.rmtree(self.run_dir.path(FOLDER), ignore_errors=True)
