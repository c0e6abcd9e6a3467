"""Exceptions raised by MOSIV with messages meant for users, not only developers."""

from __future__ import annotations


class MosivError(Exception):
    """Base class of every error MOSIV raises on purpose."""


class ConfigError(MosivError):
    """A recipe or component option is invalid. ``problems`` lists every problem found."""

    def __init__(self, problems: list[str] | str):
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(f"- {p}" for p in self.problems))


class SceneFormatError(MosivError):
    """A scene folder does not follow ``mosiv-scene/1``. ``problems`` lists every problem."""

    def __init__(self, problems: list[str] | str):
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(f"- {p}" for p in self.problems))


class SimulationDiverged(MosivError):
    """A simulation produced non-finite values or particles left the domain.

    Carries where it happened so the user can act on it.
    """

    def __init__(self, *, object_id: int, frame: int, substep: int, reason: str, advice: str):
        self.object_id, self.frame, self.substep = object_id, frame, substep
        self.reason, self.advice = reason, advice
        super().__init__(
            f"simulation diverged in object {object_id} at frame {frame}, substep {substep}: "
            f"{reason}. {advice}"
        )

    def __reduce__(self):
        # keyword-only fields: the default pickling (positional args) could not rebuild it, and
        # a job's error travels from its worker process to the suite by pickle
        fields = dict(
            object_id=self.object_id,
            frame=self.frame,
            substep=self.substep,
            reason=self.reason,
            advice=self.advice,
        )
        return (_rebuild_diverged, (fields,))


def _rebuild_diverged(fields: dict) -> SimulationDiverged:
    return SimulationDiverged(**fields)


class StageNotAvailable(MosivError):
    """A pipeline stage or command needs a component that is not installed or not built yet."""
