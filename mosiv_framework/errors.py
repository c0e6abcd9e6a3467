"""Exceptions raised by MOSIV with messages meant for users, not only developers.

Each kind of error carries the exit status the ``mosiv`` command line ends with when it stops
on one (``exit_code``); ``EXIT_CODES`` lists every status the command line uses, documented in
docs/CLI.md.
"""

from __future__ import annotations

#: the command finished; for ``mosiv data check``: the scene has no problem
EXIT_OK = 0
#: the command ran and its answer is negative (``data check`` found problems)
EXIT_FINDING = 1
#: the command line, a recipe or an option is invalid (argparse's own usage status too)
EXIT_USAGE = 2
#: the scene folder does not follow ``mosiv-scene/1``
EXIT_SCENE = 3
#: a simulation diverged (non-finite values, particles outside the domain)
EXIT_DIVERGED = 4
#: a component or stage the command needs is not installed or not built
EXIT_UNAVAILABLE = 5
#: a file or folder could not be written or read, or an output folder was refused
EXIT_OUTPUT = 6
#: an unexpected error inside MOSIV (a bug): ``mosiv -v ...`` shows the traceback
EXIT_INTERNAL = 70
#: stopped by Ctrl-C (SIGINT); 128 + 2, as shells report it
EXIT_INTERRUPTED = 130

#: every exit status of the ``mosiv`` command line and what it means
EXIT_CODES: dict[int, str] = {
    EXIT_OK: "success",
    EXIT_FINDING: "the command ran and reports a negative finding (data check: problems found)",
    EXIT_USAGE: "invalid command line, recipe, option or run folder argument",
    EXIT_SCENE: "the scene folder does not follow mosiv-scene/1",
    EXIT_DIVERGED: "a simulation or a reconstruction diverged",
    EXIT_UNAVAILABLE: "a component or stage is not installed or not available",
    EXIT_OUTPUT: "a file or folder could not be written or read, or an output folder was refused",
    EXIT_INTERNAL: "internal error (a bug); rerun with -v for the traceback",
    EXIT_INTERRUPTED: "interrupted (Ctrl-C); rerun the same command to resume",
}


class MosivError(Exception):
    """Base class of every error MOSIV raises on purpose."""

    #: the ``mosiv`` command line's exit status when it stops on this error
    exit_code: int = EXIT_USAGE


class ConfigError(MosivError):
    """A recipe or component option is invalid. ``problems`` lists every problem found."""

    exit_code = EXIT_USAGE

    def __init__(self, problems: list[str] | str):
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(f"- {p}" for p in self.problems))


class SceneFormatError(MosivError):
    """A scene folder does not follow ``mosiv-scene/1``. ``problems`` lists every problem."""

    exit_code = EXIT_SCENE

    def __init__(self, problems: list[str] | str):
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("\n".join(f"- {p}" for p in self.problems))


class SimulationDiverged(MosivError):
    """A simulation produced non-finite values or particles left the domain.

    Carries where it happened so the user can act on it.
    """

    exit_code = EXIT_DIVERGED

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


class ReconstructionDiverged(MosivError):
    """A reconstructor's optimisation kept producing non-finite losses or gradients.

    Names the stage, the step, and what was not finite, so the user can act on it.
    """

    exit_code = EXIT_DIVERGED

    def __init__(self, *, stage: str, step: int, what: str, advice: str):
        self.stage, self.step, self.what, self.advice = stage, step, what, advice
        super().__init__(f"{stage} diverged at step {step}: {what}. {advice}")

    def __reduce__(self):
        fields = dict(stage=self.stage, step=self.step, what=self.what, advice=self.advice)
        return (_rebuild_reconstruction_diverged, (fields,))


def _rebuild_reconstruction_diverged(fields: dict) -> ReconstructionDiverged:
    return ReconstructionDiverged(**fields)


class StageNotAvailable(MosivError):
    """A pipeline stage or command needs a component that is not installed or not built yet."""

    exit_code = EXIT_UNAVAILABLE


class OutputError(MosivError):
    """A folder or file a command must write cannot be written (not writable, a file where a
    folder is needed, ...) or an output folder was refused (e.g. a non-empty folder that is not
    a run folder). The message names the path and what would be accepted."""

    exit_code = EXIT_OUTPUT
