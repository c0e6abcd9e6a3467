"""The diagnosis's screening probes rolled out together (``RunContext.rollout_losses``, i.e.
``Simulator.rollout_batch``) on a real warp-mpm run: on the CPU the batched rollout gives each
member's one-by-one trajectory bit for bit, so the screen must come out exactly as it does when
every probe is rolled out alone, and a member that diverges is inf without touching the others.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import torch

from mosiv_framework.testing.shapes import default_params

# shared fakes of the diagnosis tests; --import-mode=importlib leaves this folder off sys.path
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from diagnose_fakes import spy_batches, windy_block_context  # noqa: E402

FIT = list(range(1, 8))
#: the screened candidates: by gradient with a walk out (wind), by a flat gradient's probes
#: (ground_restitution, where the loss may be flat at 0) and by a ladder (plasticity)
SCREENED = ("wind", "ground_restitution", "plasticity")


def _dropped_context():
    """The one-block windy scene of ``windy_block_context`` over the fit frames."""
    return windy_block_context(max(FIT) + 1)


def _one_by_one(monkeypatch, ctx) -> None:
    """Make ``ctx`` score its probes as the screen did before batching: ``rollout`` then
    ``loss`` per parameter set (inf where the rollout diverges), never ``rollout_batch``."""
    from mosiv_framework.errors import SimulationDiverged

    def alone(params_list, fit_frames):
        losses = []
        for params in params_list:
            try:
                traj = ctx.rollout(params, frames=max(fit_frames))
            except SimulationDiverged:
                losses.append(math.inf)
                continue
            losses.append(float(ctx.loss(traj, fit_frames)))
        return losses

    monkeypatch.setattr(ctx, "rollout_losses", alone)
    monkeypatch.setattr(ctx.simulator, "rollout_batch", None)  # any batched call fails


def _summary(screens) -> list[tuple]:
    return [
        (s.candidate.name, s.theta.tolist(), s.drop_fraction, s.score, s.note, s.gradient)
        for s in screens
    ]


def test_the_batched_screen_equals_the_screen_of_one_rollout_at_a_time(monkeypatch):
    """Every candidate's predicted coefficient, drop, score and note (which lists the ladder's
    losses) are the same whether the probes are rolled out together or one by one."""
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.hypothesise import screen

    ctx = _dropped_context()
    candidates = [c for c in build_candidates(ctx)[0] if c.name in SCREENED]
    assert sorted(c.name for c in candidates) == sorted(SCREENED)
    regimes = ["free_flight", "ground_contact", "rest", "object_contact"]

    sizes = spy_batches(monkeypatch, ctx.simulator)
    batched = screen(ctx, candidates, flagged_regimes=regimes, fit_frames=FIT)
    assert max(sizes) > 1, sizes  # the probes did go through rollout_batch together
    monkeypatch.undo()
    _one_by_one(monkeypatch, ctx)
    alone = screen(ctx, candidates, flagged_regimes=regimes, fit_frames=FIT)

    assert _summary(batched) == _summary(alone)
    assert [s.far is None for s in batched] == [s.far is None for s in alone]
    for a, b in zip(batched, alone):
        assert a.far is None or torch.equal(a.far, b.far)
    # the screen did probe something: the wind lowers the loss, the ladder lists its rungs
    by_name = {s.candidate.name: s for s in batched}
    assert by_name["wind"].drop_fraction > 0
    assert by_name["plasticity"].note.startswith("ladder 1: ")


def test_a_diverging_member_is_inf_and_the_others_keep_their_one_by_one_losses(monkeypatch):
    """Three parameter sets in chunks of two: the middle one leaves the grid in its first
    substep (60 m/s); the first and the last, one in each chunk, score exactly what their own
    rollout scores."""
    from mosiv_framework.pipeline import phases

    ctx = _dropped_context()
    windy = default_params(
        ctx.particles, velocities={1: (0.5, 0.0, -0.5)}, terms={"wind": {"acceleration": [0, 1, 0]}}
    )
    fast = default_params(ctx.particles, velocities={1: (60.0, 0.0, 0.0)})
    members = [ctx.identified, fast, windy]
    monkeypatch.setattr(phases, "BATCH_MEMBERS", 2)
    sizes = spy_batches(monkeypatch, ctx.simulator)
    losses = ctx.rollout_losses(members, FIT)
    assert sizes == [2, 1]
    expected = [float(ctx.loss(ctx.rollout(p, frames=max(FIT)), FIT)) for p in (members[0], windy)]
    assert losses[1] == math.inf
    assert [losses[0], losses[2]] == expected
    assert expected[0] != expected[1]  # the members are not all the same rollout
