"""The genesis source's parameter presets and the substeps it runs Genesis with (no engine)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mosiv_genesis import plan as P
from mosiv_genesis.options import GenesisOptions

from mosiv_framework.errors import ConfigError

# The paper preset's draws for seed 7 as the source drew them before the wide preset existed.
PAPER_SEED_7 = {
    "elastic": {"E": 50625.477333, "nu": 0.289721380097, "rho": 1110.2742761},
    "plasticine": {"E": 50625.477333, "nu": 0.289721380097, "rho": 1110.2742761,
                   "yield_stress": 2675.62156997},
    "sand": {"E": 50625.477333, "nu": 0.289721380097, "rho": 1110.2742761,
             "friction_angle": 28.3781078499},
    "newtonian": {"E": 50625.477333, "nu": 0.289721380097, "rho": 1110.2742761},
    "snow": {"E": 50625.477333, "nu": 0.289721380097, "rho": 1110.2742761,
             "yield_lower": 0.0295041437998, "yield_higher": 0.00540049885473},
}  # fmt: skip


@pytest.mark.parametrize("family", P.GENESIS_FAMILIES)
def test_paper_preset_draws_what_it_drew_before(family):
    values = P.sample_params(family, np.random.default_rng(7), "paper")
    assert values == pytest.approx(PAPER_SEED_7[family], rel=1e-10)


@pytest.mark.parametrize("family", P.GENESIS_FAMILIES)
def test_wide_draws_fall_inside_the_declared_ranges(family):
    ranges = P.preset_ranges(family, "wide")
    rng = np.random.default_rng(2)
    draws = [P.sample_params(family, rng, "wide") for _ in range(400)]
    for name, (lo, hi) in ranges.items():
        values = np.array([d[name] for d in draws])
        assert np.all((values >= lo) & (values <= hi)), f"{family}.{name}"
        log = name in P.WIDE_LOG
        f = np.log(values / lo) / math.log(hi / lo) if log else (values - lo) / (hi - lo)
        assert f.min() < 0.2 and f.max() > 0.8, f"{family}.{name} not spread"
    assert ranges["E"] == (1.0e4, 1.0e6) and ranges["nu"] == (0.15, 0.4)
    assert ranges["rho"] == (500.0, 2000.0)


def test_wide_table_matches_the_ranges_drawn_from():
    table = P.range_table("wide")
    assert table["sand"]["friction_angle"] == {"lower": 20.0, "upper": 45.0, "log": False}
    assert table["plasticine"]["yield_stress"]["log"] is True
    lo, hi = P.WIDE_EXTRA["plasticine"]["yield_stress"]
    assert hi / lo >= 10.0  # a decade or more of yield stress


def test_substeps_keep_the_stiffest_draw_below_the_cfl_bound():
    stiff = {"E": 1.0e6, "nu": 0.4, "rho": 500.0}  # the wide preset's stiffest corner
    lam, mu = 1.0e6 * 0.4 / (1.4 * 0.2), 1.0e6 / 2.8
    assert P.p_wave_speed(stiff) == pytest.approx(math.sqrt((lam + 2 * mu) / 500.0))
    s = P.required_substeps([stiff], grid_density=64.0, fps=24.0, requested=140)
    assert P.cfl_number([stiff], grid_density=64.0, dt=1 / (24.0 * 140)) > P.CFL_BOUND
    assert P.cfl_number([stiff], grid_density=64.0, dt=1 / (24.0 * s)) < P.CFL_BOUND
    assert P.cfl_number([stiff], grid_density=64.0, dt=1 / (24.0 * (s - 1))) > P.CFL_TARGET
    # the paper's stiffest corner needs nothing beyond the default 140 substeps
    paper = {"E": 5.25e4, "nu": 0.3, "rho": 800.0}
    assert P.required_substeps([paper], grid_density=64.0, fps=24.0, requested=140) == 140


def test_planned_substeps_keep_every_wide_draw_below_the_cfl_bound():
    from mosiv_genesis.source import _plan

    for seed in range(6):
        opts = GenesisOptions(materials="elastic,sand", ranges="wide", seed=seed)
        plan = _plan(opts, np.random.default_rng(seed))
        dt = 1.0 / (opts.fps * plan.substeps)
        assert plan.substeps >= opts.substeps
        assert P.cfl_number(plan.params, grid_density=opts.grid_density, dt=dt) < P.CFL_BOUND


def test_unknown_preset_is_refused():
    with pytest.raises(ConfigError, match="ranges='huge'"):
        GenesisOptions(ranges="huge")


def test_substeps_keep_to_genesis_step_hint():
    soft = {"E": 1.0e4, "nu": 0.2, "rho": 2000.0}  # CFL alone would allow a few substeps
    s = P.required_substeps([soft], grid_density=32.0, fps=24.0, requested=10)
    assert 1.0 / (24.0 * s) <= P.GENESIS_DT_HINT / 32.0 < 1.0 / (24.0 * (s - 1))
