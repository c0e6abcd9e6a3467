"""``mosiv run``: scene -> reconstruct -> lift -> identify -> evaluate, each stage resumable.

The stages live in modules named by what they do: ``run`` (the stage sequence and resuming),
``identification`` (the identification stage around ``identify``, the phase runner, and
``phases``), ``evaluate`` (scoring, plots, metrics.json), ``rundir`` (the run folder) and
``formats`` (the format versions of the JSON files a run writes). This package re-exports what
the CLI, the diagnosis, the benchmarks and the tests use.
"""

from __future__ import annotations

from mosiv_framework.pipeline.evaluate import EVALUATION_REFINEMENTS, evaluate_run
from mosiv_framework.pipeline.identification import (
    build_objective,
    check_terms_supported,
    identify_stage,
    start_vector,
)
from mosiv_framework.pipeline.run import (
    build_simulator,
    component,
    ensure_scene,
    run_pipeline,
    simulator_refiner,
)

#: the name the benchmarks import
_component = component

__all__ = [
    "EVALUATION_REFINEMENTS",
    "build_objective",
    "build_simulator",
    "check_terms_supported",
    "component",
    "ensure_scene",
    "evaluate_run",
    "identify_stage",
    "run_pipeline",
    "simulator_refiner",
    "start_vector",
]
