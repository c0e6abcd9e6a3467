"""Recipes: schema, overrides, component names and options, every error reported at once."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from mosiv_framework.errors import ConfigError
from mosiv_framework.recipes import load_recipe
from mosiv_framework.registry import Component, Registry, hookimpl

RECIPES = Path(__file__).parents[1] / "recipes"


@dataclass
class ToySimOptions:
    grid: int = 64
    substeps: int = 100


class ToyPlugin:
    @hookimpl
    def mosiv_simulators(self, register):
        register(Component("simulator", "toy-sim", factory=dict, options=ToySimOptions))
        register(Component("simulator", "other-sim", factory=dict, options=ToySimOptions))

    @hookimpl
    def mosiv_lifters(self, register):
        register(Component("lifter", "gt-points", factory=dict))


@pytest.fixture
def registry() -> Registry:
    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss", "lift"])
    reg.add_plugin(ToyPlugin(), name="toy")
    return reg


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "recipe.yaml"
    path.write_text(text)
    return path


def test_resolves_defaults_and_component_options(tmp_path, registry):
    path = write(tmp_path, "simulator: {name: toy-sim, grid: 32}\nscene: {path: somewhere}\n")
    recipe = load_recipe(path, ["identify.param_iterations=7"], registry=registry)
    assert recipe.simulator == {"name": "toy-sim", "grid": 32, "substeps": 100}
    assert recipe.identify.param_iterations == 7
    assert recipe.identify.velocity_iterations == 80  # paper default filled in
    assert recipe.scene.path == "somewhere"
    assert recipe.losses.chamfer.weight == 1.0 and recipe.losses.chamfer.max_points == 4096


def test_override_selects_another_component(tmp_path, registry):
    path = write(tmp_path, "simulator: {name: toy-sim}\n")
    recipe = load_recipe(
        path, ["simulator.name=other-sim", "simulator.substeps=5"], registry=registry
    )
    assert recipe.simulator.name == "other-sim" and recipe.simulator.substeps == 5


def test_unknown_simulator_lists_valid_names(tmp_path, registry):
    path = write(tmp_path, "simulator: {name: toy-sim}\n")
    with pytest.raises(ConfigError, match="valid simulator names: other-sim, toy-sim"):
        load_recipe(path, ["simulator.name=nope"], registry=registry)


def test_every_problem_is_reported_at_once(tmp_path, registry):
    path = write(
        tmp_path,
        "simulator: {name: toy-sim, grdi: 3, substeps: many}\n"
        "identify: {velocity_iterations: lots, learning_rate: 1}\n"
        "losses: {chamfer: {weight: -1}, nonexistent: {}}\n"
        "lifter: {name: magic}\n"
        "extra_section: 1\n",
    )
    with pytest.raises(ConfigError) as err:
        load_recipe(path, registry=registry)
    problems = "\n".join(err.value.problems)
    assert len(err.value.problems) == 8, problems
    for needle in (
        "unknown recipe section 'extra_section'",
        "no option 'grdi'; valid options: grid, substeps",
        "substeps='many'",
        "identify.velocity_iterations='lots'",
        "unknown key identify.learning_rate",
        "chamfer.weight must be",
        "unknown loss 'nonexistent'",
        "unknown lifter 'magic'; valid lifter names: gt-points",
    ):
        assert needle in problems


def test_bad_yaml_and_missing_file_name_the_file(tmp_path, registry):
    with pytest.raises(ConfigError, match="does not exist"):
        load_recipe(tmp_path / "nope.yaml", registry=registry)
    bad = write(tmp_path, "simulator: {name: toy-sim\n")
    with pytest.raises(ConfigError, match="recipe.yaml: not valid YAML") as err:
        load_recipe(bad, registry=registry)
    assert f"in {bad}, line" in str(err.value) and "<unicode string>" not in str(err.value)
    with pytest.raises(ConfigError, match="key=value"):
        load_recipe(write(tmp_path, "{}\n"), ["simulator.name"], registry=registry)


def test_a_typo_in_an_override_is_the_overrides_not_the_files(tmp_path, registry):
    path = write(tmp_path, "simulator: {name: toy-sim}\nidentify: {learning_rate: 1}\n")
    overrides = ["identfy.param_iterations=3", "identify.param_iteratons=4", "identify.seed=2"]
    with pytest.raises(ConfigError) as err:
        load_recipe(path, overrides, registry=registry)
    problems = err.value.problems
    assert any(
        p.startswith("override 'identfy.param_iterations=3': unknown recipe section 'identfy'")
        for p in problems
    ), problems
    assert any(p.startswith("override 'identify.param_iteratons=4': unknown key") for p in problems)
    # the file's own mistake stays the file's, although an override names its section
    assert any(p.startswith(f"{path}: unknown key identify.learning_rate") for p in problems)
    # an override's key that is the tail of the file's (learning_rate in identify.learning_rate)
    with pytest.raises(ConfigError) as err:
        load_recipe(path, ["learning_rate=3"], registry=registry)
    problems = err.value.problems
    assert any(p.startswith(f"{path}: unknown key identify.learning_rate") for p in problems)
    assert any(p.startswith("override 'learning_rate=3': unknown recipe section") for p in problems)


def test_a_bad_plugin_option_from_the_command_line_is_the_overrides(tmp_path):
    """A plugin checks its own options and names the option, not the dotted key: the problem is
    still the override's when the override set that option, and the file's when the file did
    (though an override names another option of the same plugin)."""
    pytest.importorskip("mosiv_warp_mpm")
    quickstart = RECIPES / "quickstart.yaml"
    for override, said in [
        ("simulator.substeps=0", "simulator: simulator warp-mpm option substeps=0"),
        ("simulator.grid_window=5", "simulator: simulator warp-mpm option grid_window='5'"),
        ("simulator.foo=1", "simulator: simulator 'warp-mpm' has no option 'foo'"),
        ("simulator.name=nosuch", "simulator.name: unknown simulator 'nosuch'"),
        ("losses.chamfer.weight=-1", "losses.chamfer: chamfer.weight must be"),
        ("lifter.voxel_size=-1", "lifter: lifter 'gt-points': voxel_size must be"),
        ("lifter.renderer_options.x=0", "has no option 'renderer_options'"),
    ]:
        with pytest.raises(ConfigError) as err:
            load_recipe(quickstart, [override])
        (problem,) = err.value.problems
        assert problem.startswith(f"override {override!r}: ") and said in problem, problem
    # a word of the message that is an option's name ("name") does not make it that option's
    pytest.importorskip("mosiv_lift")
    lines = quickstart.read_text().splitlines()
    lifter = [i for i, line in enumerate(lines) if line.startswith("lifter:")]
    lines[lifter[0]] = "lifter: {name: gaussians, renderer: ''}"
    bad_renderer = write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(ConfigError) as err:
        load_recipe(bad_renderer, ["lifter.name=gaussians"])
    (problem,) = err.value.problems
    assert problem.startswith(f"{bad_renderer}: lifter: ") and "renderer name" in problem
    text = quickstart.read_text().replace("name: warp-mpm", "name: warp-mpm, foo: 1")
    assert text != quickstart.read_text()
    own = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_recipe(own, ["simulator.grid=32"])  # grid is among the valid options listed
    (problem,) = err.value.problems
    assert problem.startswith(f"{own}: simulator: ") and "no option 'foo'" in problem


@pytest.mark.parametrize("name", sorted(p.name for p in RECIPES.glob("*.yaml")))
def test_shipped_recipes_are_valid(name):
    recipe = load_recipe(RECIPES / name)
    assert OmegaConf.select(recipe, "simulator.name")


def test_recipe_show_cli_names_valid_simulators(capsys):
    from mosiv_framework.cli.main import main

    code = main(["recipe", "show", str(RECIPES / "quickstart.yaml"), "simulator.name=nope"])
    err = capsys.readouterr().err
    assert code != 0
    assert "unknown simulator 'nope'" in err and "warp-mpm" in err


def test_recipe_show_prints_resolved_recipe(capsys):
    from mosiv_framework.cli.main import main

    assert main(["recipe", "show", str(RECIPES / "quickstart.yaml"), "identify.seed=3"]) == 0
    shown = OmegaConf.create(capsys.readouterr().out)
    assert shown.identify.seed == 3 and shown.simulator.name == "warp-mpm"


def test_stiffness_cap_reads_an_existing_scene_before_its_source(tmp_path):
    """scene.json, when present, gives the frame rate, domain and families the cap is checked
    against; at twice the quickstart's 24 fps the 8-substep cap is four times lower still."""
    import json

    from mosiv_framework.recipes import check_recipe

    scene = tmp_path / "scene"
    scene.mkdir()
    objects = [{"id": 1, "name": "a", "material": "elastic"}]
    domain = {"lower": [-0.4, -0.4, 0.0], "upper": [0.4, 0.4, 0.6]}
    (scene / "scene.json").write_text(json.dumps({"fps": 48, "domain": domain, "objects": objects}))
    overrides = [f"scene.path={scene}", "simulator.substeps=8"]
    with pytest.raises(ConfigError) as err:
        check_recipe(RECIPES / "quickstart.yaml", overrides)
    (problem,) = err.value.problems
    assert "caps E of object 1 (elastic) at 19,200 Pa" in problem  # 4,800 Pa x (48/24)^2
    assert "48 fps" in problem


def test_random_families_make_the_cap_a_warning(tmp_path):
    """A source that draws the families at random: a low cap is reported per family as a
    warning, since the scene may hold none of them."""
    from mosiv_framework.recipes import check_recipe

    overrides = [
        f"scene.path={tmp_path / 'scene'}",
        "scene.source.materials=random",
        "simulator.substeps=8",
    ]
    _, warnings = check_recipe(RECIPES / "quickstart.yaml", overrides)
    assert any(
        "elastic or plasticine or snow objects (drawn at random) at 4,800 Pa" in w for w in warnings
    ), warnings
