"""Malformed recipes, generated from the quickstart recipe: every one is refused by the loader
and by ``mosiv recipe validate`` with a message naming the key or the file, exit code 2 (the
CLI's code for a MosivError), no traceback, and the recipe file left as it was.

Regressions for three settings that were once accepted and silently changed or broke a run:
``simulator.substeps=8`` (capped E at 4,800 Pa, the truth is 5e4), ``identify.horizon_full_at=-1``
and ``evaluate.emd_samples=0`` (failed only after the whole identification).
"""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from mosiv_framework.cli.main import main
from mosiv_framework.errors import ConfigError
from mosiv_framework.laws import get_law
from mosiv_framework.recipes import check_recipe, check_stiffness, load_recipe
from mosiv_framework.types import World

QUICKSTART = Path(__file__).parents[1] / "recipes" / "quickstart.yaml"
SECRET = "s3cret-token-7f2a"


def base_recipe(tmp_path: Path) -> dict:
    """The quickstart recipe with its scene and run folders moved under ``tmp_path``."""
    recipe = yaml.safe_load(QUICKSTART.read_text())
    recipe["scene"]["path"] = str(tmp_path / "scene")
    recipe["output"]["dir"] = str(tmp_path / "run")
    return recipe


def with_value(recipe: dict, dotted: str, value) -> dict:
    """A copy of ``recipe`` with ``dotted`` set to ``value`` (sections created as needed)."""
    out = copy.deepcopy(recipe)
    *parents, last = dotted.split(".")
    node = out
    for key in parents:
        node = node.setdefault(key, {})
    node[last] = value
    return out


#: (case, dotted key, value, text every message must contain)
VALUE_CASES = [
    ("int-as-word", "identify.param_iterations", "lots", "identify.param_iterations='lots'"),
    ("int-as-bool", "identify.velocity_iterations", True, "identify.velocity_iterations"),
    ("int-as-float", "identify.horizon_start", 2.5, "identify.horizon_start"),
    ("float-as-word", "identify.param_lr", "fast", "identify.param_lr='fast'"),
    ("bool-as-list", "evaluate.render_videos", [1, 2], "evaluate.render_videos"),
    ("horizon-negative", "identify.horizon_full_at", -1, "identify.horizon_full_at=-1"),
    ("horizon-above-one", "identify.horizon_full_at", 1.5, "in [0.0, 1.0]"),
    ("emd-zero", "evaluate.emd_samples", 0, "evaluate.emd_samples=0"),
    ("emd-huge", "evaluate.emd_samples", 10**6, "evaluate.emd_samples=1000000"),
    ("lr-nan", "identify.velocity_lr", float("nan"), "must be a finite number"),
    ("lr-zero", "identify.param_lr", 0.0, "identify.param_lr=0.0: must be > 0"),
    ("checkpoint-zero", "identify.checkpoint_every", 0, "identify.checkpoint_every=0"),
    ("cfl-above-one", "identify.stiffness_cfl", 2.0, "identify.stiffness_cfl=2.0"),
    ("seed-negative", "evaluate.seed", -1, "evaluate.seed=-1"),
    ("video-tiny", "evaluate.video_size", 2, "evaluate.video_size=2"),
    ("method-unknown", "identify.method", "guess", "identify.method='guess'"),
    ("substeps-cfl", "simulator.substeps", 8, "simulator.substeps=8 caps E"),
    ("substeps-zero", "simulator.substeps", 0, "substeps=0"),
    ("grid-tiny", "simulator.grid", 2, "grid=2"),
    ("unknown-section", "extra_section", 1, "unknown recipe section 'extra_section'"),
    ("unknown-key", "identify.learning_rate", 0.1, "unknown key identify.learning_rate"),
    ("unknown-option", "simulator.grdi", 3, "no option 'grdi'"),
    ("unknown-simulator", "simulator.name", "nope", "unknown simulator 'nope'"),
    ("unknown-loss", "losses.nope", {"weight": 1.0}, "unknown loss 'nope'"),
    ("unknown-term", "physics_terms.levitation", {}, "physics_terms.levitation"),
    ("no-loss-weight", "losses.chamfer.weight", 0.0, "nothing to minimise"),
    ("component-without-name", "simulator", {"grid": 32}, "'name' key"),
    ("section-not-mapping", "identify", 5, "section 'identify' must be a mapping"),
    ("section-null", "evaluate", None, "section 'evaluate' must be a mapping"),
    ("missing-value", "output.dir", "???", "output.dir"),
    ("interpolation-key", "output.dir", "${nope.x}", "output.dir='${nope.x}'"),
    ("interpolation-resolver", "output.dir", "${foo:bar}", "unknown resolver 'foo'"),
    ("interpolation-syntax", "output.dir", "runs/${nope", "not a valid interpolation"),
    ("interpolation-loop", "identify.seed", "${identify.seed}", "identify.seed"),
    ("env-resolver", "output.dir", "runs/${oc.env:MOSIV_FUZZ_SECRET}", "'oc.env' resolver"),
    ("env-nested", "scene.path", "${oc.select:x,${oc.env:MOSIV_FUZZ_SECRET}}", "'oc.env'"),
    ("decode-resolver", "output.dir", "${oc.decode:'\\${oc.env:HOME}'}", "'oc.decode'"),
]

#: (case, file bytes, text the message must contain); the file's path is named too
TEXT_CASES = [
    ("yaml-syntax", b"simulator: {name: warp-mpm\n", "not valid YAML"),
    ("yaml-tab", b"identify:\n\tseed: 1\n", "not valid YAML"),
    ("yaml-duplicate", b"identify: {seed: 1}\nidentify: {seed: 2}\n", "duplicate key"),
    ("a-list", b"- scene\n- simulator\n", "got a YAML list"),
    ("a-scalar", b"just some words\n", "got a YAML single value"),
    ("empty", b"", "the recipe file is empty"),
    ("only-comments", b"# a recipe\n# nothing else\n", "the recipe file is empty"),
    ("null", b"null\n", "the recipe file is empty"),
    ("binary", bytes(range(256)) * 4, "not a text file"),
    ("control-chars", b"scene: \x00\x01\n", "not valid YAML"),
]


def _cases(tmp_path: Path):
    base = base_recipe(tmp_path)
    for case, key, value, needle in VALUE_CASES:
        data = yaml.safe_dump(with_value(base, key, value), sort_keys=False).encode()
        yield case, data, needle
    yield from TEXT_CASES


def test_the_generated_set_is_large_enough(tmp_path):
    assert len(list(_cases(tmp_path))) >= 20


@pytest.mark.parametrize("case", [c[0] for c in VALUE_CASES + TEXT_CASES])
def test_malformed_recipe_is_refused_clearly(case, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("MOSIV_FUZZ_SECRET", SECRET)
    data, needle = next((d, n) for c, d, n in _cases(tmp_path) if c == case)
    path = tmp_path / f"{case}.yaml"
    path.write_bytes(data)
    before = (path.read_bytes(), path.stat().st_mtime_ns)

    with pytest.raises(ConfigError) as err:
        load_recipe(path)
    text = "\n".join(err.value.problems)
    assert needle in text, text
    assert str(path) in text  # every problem names the file it is in
    assert SECRET not in text

    code = main(["recipe", "validate", str(path)])
    out, errtext = capsys.readouterr()
    assert code == 2, (out, errtext)
    assert needle in errtext and "Traceback" not in out + errtext
    assert SECRET not in out + errtext
    assert "valid" not in out
    assert (path.read_bytes(), path.stat().st_mtime_ns) == before


def test_every_problem_of_one_recipe_is_reported_at_once(tmp_path):
    recipe = base_recipe(tmp_path)
    for key, value, _ in (
        ("identify.horizon_full_at", -1, None),
        ("evaluate.emd_samples", 0, None),
        ("identify.checkpoint_every", 0, None),
        ("output.dir", "${nope.x}", None),
    ):
        recipe = with_value(recipe, key, value)
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    with pytest.raises(ConfigError) as err:
        load_recipe(path)
    # interpolations are resolved before the schema is checked: that problem comes alone
    assert len(err.value.problems) == 1 and "output.dir='${nope.x}'" in err.value.problems[0]
    path.write_text(yaml.safe_dump(with_value(recipe, "output.dir", str(tmp_path / "run"))))
    with pytest.raises(ConfigError) as err:
        load_recipe(path)
    text = "\n".join(err.value.problems)
    assert len(err.value.problems) == 3, text
    for needle in ("horizon_full_at=-1", "emd_samples=0", "checkpoint_every=0"):
        assert needle in text


def test_bad_overrides_are_each_named(tmp_path, capsys):
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(base_recipe(tmp_path)))
    overrides = ["identify.seed", "identify.seed=${oops", "a=[1,2"]
    with pytest.raises(ConfigError) as err:
        load_recipe(path, overrides)
    assert len(err.value.problems) == 3
    for override, problem in zip(overrides, err.value.problems):
        assert repr(override) in problem
    assert main(["recipe", "validate", str(path), "identify.seed=${oc.env:HOME}"]) == 2
    assert "'oc.env' resolver is off" in capsys.readouterr().err


def test_recipe_interpolations_and_recipe_resolvers_still_work(tmp_path):
    recipe = with_value(base_recipe(tmp_path), "identify.seed", 7)
    recipe = with_value(recipe, "evaluate.seed", "${identify.seed}")
    recipe = with_value(recipe, "output.dir", str(tmp_path / "run-${oc.select:identify.seed,0}"))
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    loaded = load_recipe(path)
    assert loaded.evaluate.seed == 7 and loaded.output.dir.endswith("run-7")


def test_secrets_never_reach_the_stored_recipe_or_the_output(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("MOSIV_FUZZ_SECRET", SECRET)
    recipe = with_value(base_recipe(tmp_path), "output.dir", "${oc.env:MOSIV_FUZZ_SECRET}")
    path = tmp_path / "secret.yaml"
    path.write_text(yaml.safe_dump(recipe))
    for command in ("show", "validate"):
        assert main(["recipe", command, str(path)]) == 2
        out, err = capsys.readouterr()
        assert "output.dir" in err and "recipe.yaml" in err and SECRET not in out + err
    # ``mosiv run`` stops before writing anything: no scene, no run folder, no recipe.yaml
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(path)]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["secret.yaml"]
    assert SECRET not in "".join(capsys.readouterr())


def _analytic_e_cap(substeps: int, *, grid: int, extent: float, fps: float, cfl: float) -> float:
    """E at which the P-wave speed of an elastic body with the law's default density and
    Poisson ratio reaches ``cfl`` cells per substep: M = rho c^2, E = M (1+nu)(1-2nu)/(1-nu)."""
    law = get_law("elastic")
    rho, nu = law.param("rho").default, law.param("nu").default
    c = cfl * (extent / grid) * fps * substeps
    return rho * c * c * (1 + nu) * (1 - 2 * nu) / (1 - nu)


def test_few_substeps_are_an_error_naming_the_cap_and_the_fix(tmp_path):
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(base_recipe(tmp_path)))
    # the quickstart's synth scene: 24 fps on a 0.8 m domain, a 32-cell grid, cfl 0.5
    cap = _analytic_e_cap(8, grid=32, extent=0.8, fps=24.0, cfl=0.5)
    assert cap < get_law("elastic").param("E").default  # the truth, 5e4 Pa, is out of reach
    with pytest.raises(ConfigError) as err:
        load_recipe(path, ["simulator.substeps=8"])
    (problem,) = err.value.problems
    assert f"caps E of objects 1 (elastic), 2 (plasticine) at {cap:,.0f} Pa" in problem
    need = int(problem.split("simulator.substeps >= ")[1].split()[0])
    # the substeps the message asks for are the fewest that clear the starting value
    assert _analytic_e_cap(need, grid=32, extent=0.8, fps=24.0, cfl=0.5) >= 5e4
    assert _analytic_e_cap(need - 1, grid=32, extent=0.8, fps=24.0, cfl=0.5) < 5e4
    recipe, warnings = check_recipe(path, [f"simulator.substeps={need}"])
    assert recipe.simulator.substeps == need
    (warning,) = warnings  # valid, but E stays capped below the law's 1e7 Pa
    assert f"at {_analytic_e_cap(need, grid=32, extent=0.8, fps=24.0, cfl=0.5):,.0f} Pa" in warning
    # with the cap switched off there is nothing to report
    assert check_recipe(path, ["simulator.substeps=8", "identify.stiffness_cfl=0"])[1] == []


def test_pipeline_stiffness_check_uses_the_scene_it_read():
    recipe = OmegaConf.to_container(load_recipe(QUICKSTART))  # defaults filled in, as run
    world = World((-0.4, -0.4, 0.0), (0.4, 0.4, 0.6), fps=24.0)
    families = {1: "elastic", 2: "sand"}
    with pytest.raises(ConfigError, match="caps E of object 1 \\(elastic\\) at 4,800 Pa"):
        check_stiffness(with_value(recipe, "simulator.substeps", 8), world=world, families=families)
    warnings = check_stiffness(recipe, world=world, families=families)
    # sand's default Poisson ratio (0.3) gives it a lower cap than elastic's (0.25)
    caps = {w.split(" of ")[1].split(" at ")[0]: w for w in warnings}
    assert set(caps) == {"object 1 (elastic)", "object 2 (sand)"}
    nu = get_law("sand").param("nu").default
    m = get_law("sand").param("rho").default * (0.5 * 0.025 * 24 * 40) ** 2
    assert f"at {m * (1 + nu) * (1 - 2 * nu) / (1 - nu):,.0f} Pa" in caps["object 2 (sand)"]
    # a ten times finer grid needs ten times the substeps for the same cap
    finer = with_value(with_value(recipe, "simulator.grid", 320), "simulator.substeps", 400)

    def cap_texts(found: list[str]) -> list[str]:
        return [w.split(" at ")[1].split(" Pa")[0] for w in found]

    assert cap_texts(check_stiffness(finer, world=world, families=families)) == cap_texts(warnings)


def test_cli_exit_code_and_message_in_a_fresh_process(tmp_path):
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(with_value(base_recipe(tmp_path), "evaluate.emd_samples", 0)))
    done = subprocess.run(
        [sys.executable, "-m", "mosiv_framework.cli.main", "recipe", "validate", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert "evaluate.emd_samples=0: must be in [1, 8192]" in done.stderr
    assert "Traceback" not in done.stdout + done.stderr
