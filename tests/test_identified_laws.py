"""``identify.laws``: a scene material identified with another law of the same parameters (the
corotated stress of Genesis's Elastic and ElastoPlastic), checked at load and carried through
identification into identified.json and the parameter errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mosiv_framework.errors import ConfigError
from mosiv_framework.pipeline import run_pipeline
from mosiv_framework.pipeline.run import with_identified_laws
from mosiv_framework.recipes import load_recipe
from mosiv_framework.types import ParticleSet

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "genesis_oracle.yaml"
TINY = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "tiny_scene"


@pytest.mark.parametrize(
    "override, message",
    [
        ("identify.laws.jelly=elastic", "'jelly' is not a scene material; valid: elastic"),
        ("identify.laws.elastic=rubber", "unknown law; valid: elastic, plasticine"),
        ("identify.laws.elastic=plasticine_corotated", "differ from elastic's"),
        ("identify.laws.sand=elastic", "differ from sand's"),
    ],
)
def test_a_law_that_is_not_a_variant_of_the_material_is_refused(override, message):
    with pytest.raises(ConfigError, match=message):
        load_recipe(RECIPE, [override])


def test_the_mapping_replaces_only_the_named_materials():
    import torch

    particles = ParticleSet(
        positions=torch.zeros(3, 3),
        object_ids=torch.tensor([1, 2, 3]),
        volumes=torch.ones(3),
        materials={1: "elastic", 2: "sand", 3: "plasticine"},
    )
    laws = {"elastic": "elastic_corotated", "plasticine": "plasticine_corotated"}
    mapped = with_identified_laws(particles, laws)
    assert mapped.materials == {1: "elastic_corotated", 2: "sand", 3: "plasticine_corotated"}
    assert particles.materials[1] == "elastic"  # the lifted particles are not changed
    assert with_identified_laws(particles, {}) is particles


def test_identification_with_the_corotated_law_on_a_genesis_scene(tmp_path):
    """The elastic body of a Genesis recording identified with the corotated stress: the run
    records the law it used, evaluates with it and scores E against the truth."""
    sets = [
        f"scene.path={TINY}",
        f"output.dir={tmp_path}",
        "identify.laws.elastic=elastic_corotated",
        "identify.law_choice=fixed",  # the law named above, not chosen
        "simulator.device=cpu",
        "simulator.grid=16",
        "simulator.substeps=20",
        "identify.velocity_iterations=2",
        "identify.param_iterations=2",
        "identify.global_candidates=0",
        "identify.contact=fixed",
        "identify.intervals=false",
        "losses.chamfer.max_points=256",
        "evaluate.emd_samples=128",
        "evaluate.render_videos=false",
    ]
    metrics = run_pipeline(load_recipe(RECIPE, sets), run_dir=tmp_path)
    identified = json.loads((tmp_path / "identified.json").read_text())
    families = {k: o["family"] for k, o in identified["objects"].items()}
    assert families == {"1": "elastic_corotated", "2": "sand"}
    assert metrics["param_error"]["1"]["E"]["true"] > 0
    assert metrics["params"]["objects"]["1"]["family"] == "elastic_corotated"
