"""benchmarks/plan_param_errors.py: errors recomputed from the generator's plan equal those the
pipeline wrote into metrics.json for the same run (a saved from-video run)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
RUN = BENCHMARKS / "data" / "video_ablation" / "scene-03-plasticine-newtonian" / "scene-cd-sil"


def test_errors_from_the_plan_match_the_runs_own_metrics():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        from identify_suite import errors_of
        from plan_param_errors import plan_errors
    finally:
        sys.path.remove(str(BENCHMARKS))
    metrics = json.loads((RUN / "metrics.json").read_text())
    identified = json.loads((RUN / "identified.json").read_text())
    recomputed = plan_errors(identified, materials="plasticine,newtonian", seed=3)
    saved = {k: v for k, v in errors_of(metrics).items() if v}
    assert recomputed.keys() == saved.keys()
    for kind, values in saved.items():
        assert recomputed[kind] == pytest.approx(values, rel=1e-9), kind
    # the wrong seed draws another scene, whose truth the same model does not match
    assert plan_errors(identified, materials="plasticine,newtonian", seed=4) != recomputed
