"""How much a diagnosis may compute (``Budget``): the named budgets ``mosiv diagnose --budget``
offers (``BUDGETS``) and the recipe's ``diagnose`` section's changes to them
(``resolve_budget``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from mosiv_framework.diagnose.model import RefitOptions
from mosiv_framework.errors import ConfigError


@dataclass(frozen=True)
class Budget:
    """How much a diagnosis may compute: candidates refitted, refit iterations and starts,
    bootstrap resamples, the fraction of the observed window held out, the steps a
    regression start settles the shared parameters first (``RefitOptions.settle``),
    which models are also identified afresh with the run's schedule (``reidentify``: every,
    null-model or none, ``recipes.schema.REIDENTIFY``; the better of that and its refit is
    kept), the backtracking steps that end every refit (``RefitOptions.polish``), the
    refit's initial-velocity step (m/s per step) and whether contact and material
    candidates get a start at the far end of the screening's walk
    (``diagnosis.refit_starts``), whether a named effect must be stable across grid
    resolution (``grid_stability``), and whether the models' descents run in lockstep
    (``together``, ``diagnose.descent``). A recipe's ``diagnose`` section may set
    max_candidates, bootstrap, starts, iterations, polish, far_start, grid_check, together,
    reidentify and (as ``refit_velocity_lr``) velocity_lr."""

    max_candidates: int
    iterations: int
    starts: int
    bootstrap: int
    heldout_fraction: float = 0.25
    settle: int = 0
    reidentify: str = "none"
    polish: int = 0
    velocity_lr: float = RefitOptions.velocity_lr
    far_start: bool = False
    grid_check: bool = False
    together: bool = True


BUDGETS = {
    # the small budget fits the whole observed window (as the run did) and judges on the
    # future frames only: short windows leave too few fitted frames to tell effects apart
    "small": Budget(max_candidates=3, iterations=6, starts=2, bootstrap=200, heldout_fraction=0.0),
    # four candidates: wind ranked fourth in the screen of wind-1 of the full suite and was
    # never refitted with three
    "full": Budget(
        max_candidates=4,
        iterations=20,
        starts=3,
        bootstrap=1000,
        settle=20,
        reidentify="every",
        polish=10,
        grid_check=True,  # the null's refit and one per named effect, beside 5 fresh fits
    ),
}


def reidentifies(budget: Budget, model: str | None) -> bool:
    """Whether ``budget`` identifies ``model`` afresh: the null (None) or a candidate's name."""
    if budget.reidentify == "every":
        return True
    return budget.reidentify == "null-model" and model is None


def resolve_budget(budget: str | Budget, section=None) -> Budget:
    """The budget named (or given), with what the recipe's ``diagnose`` ``section`` sets."""
    if isinstance(budget, str):
        if budget not in BUDGETS:
            raise ConfigError(f"budget {budget!r} is unknown; valid: {sorted(BUDGETS)}")
        budget = BUDGETS[budget]
    if section is None:
        return budget
    keys = {  # recipe key: (budget field, type)
        "max_candidates": ("max_candidates", int),
        "bootstrap": ("bootstrap", int),
        "starts": ("starts", int),
        "iterations": ("iterations", int),
        "polish": ("polish", int),
        "refit_velocity_lr": ("velocity_lr", float),
        "far_start": ("far_start", bool),
        "grid_check": ("grid_check", bool),
        "together": ("together", bool),
        "reidentify": ("reidentify", str),
    }
    return replace(
        budget,
        **{
            field: kind(section[key])
            for key, (field, kind) in keys.items()
            if section.get(key) is not None
        },
    )
