"""Parameter errors of an identified model against the generator's plan of its scene, when the
run's own ``metrics.json`` is missing (a device lease that ended during evaluation).

The generator draws every random choice of a scene from its seed (``mosiv_synth.generate.
plan_scene``), so the ground-truth parameters can be recomputed without simulating or rendering;
the errors are those ``metrics.json`` would hold (``param_error``), summarised per kind as in
``identify_suite.errors_of`` (stress-like parameters gauge-free).

    python benchmarks/plan_param_errors.py RUN/identified.json --materials newtonian,sand --seed 5
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from identify_suite import errors_of

from mosiv_framework.pipeline.evaluate import parameter_errors
from mosiv_framework.pipeline.params import ParameterVector


def plan_errors(identified: dict, *, materials: str, seed: int, n_objects: int = 2) -> dict:
    """``{kind: [error per object]}`` of ``identified`` (an ``identified.json`` document) against
    the scene that ``mosiv data synth`` draws for ``materials`` and ``seed``."""
    from mosiv_synth.generate import gt_params_document, plan_scene
    from mosiv_synth.options import SynthOptions

    options = SynthOptions(materials=materials, seed=seed, n_objects=n_objects, progress=False)
    truth = gt_params_document(plan_scene(options), options)
    errors = parameter_errors(ParameterVector.from_json(identified), truth)
    return {k: v for k, v in errors_of({"params": identified, "param_error": errors}).items() if v}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("identified", type=Path, help="a run's identified.json")
    parser.add_argument(
        "--materials", required=True, help="the scene's materials, e.g. elastic,sand"
    )
    parser.add_argument("--seed", type=int, required=True, help="the scene's generator seed")
    parser.add_argument("--objects", type=int, default=2)
    args = parser.parse_args(argv)
    identified = json.loads(args.identified.read_text())
    errors = plan_errors(
        identified, materials=args.materials, seed=args.seed, n_objects=args.objects
    )
    print(json.dumps({k: [round(x, 3) for x in v] for k, v in errors.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
