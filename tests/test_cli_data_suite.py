"""``mosiv data synth`` flags and ``mosiv data suite``: flags map onto a source's options, the
suite covers the paper's material pairs, writes suite.json, and resumes after an interruption.

A small in-test scene source (registered into a private registry) stands in for the real
generators, so these tests exercise the command line alone and run in well under a second each.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import mosiv_framework.registry as registry_module
from mosiv_framework.cli import data as data_cli
from mosiv_framework.cli.main import main
from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import SceneSource
from mosiv_framework.registry import Component, Registry, hookimpl
from mosiv_framework.scene import read_scene
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.scene.io import SceneObject, write_scene


@dataclass
class PairOptions:
    materials: str = "elastic,sand"
    n_objects: int = 2
    seed: int = 0
    resolution: int = 8
    n_cameras: int = 1
    n_frames: int = 2
    observed_frames: int = 1
    scene_name: str = ""
    ranges: str = "paper"


class PairSource(SceneSource):
    """Writes a blank scene that declares the requested materials; counts its calls."""

    calls: list[str] = []
    ranges: list[str] = []  # the ranges option of each generated scene
    crash_on = ""  # materials whose generation crashes half-way (an interrupted run)

    def __init__(self, **options):
        self.o = PairOptions(**options)

    def generate(self, out_dir: Path) -> Path:
        PairSource.calls.append(self.o.materials)
        PairSource.ranges.append(self.o.ranges)
        materials = self.o.materials.split(",")
        if len(materials) != self.o.n_objects:
            raise ConfigError(f"{len(materials)} materials for n_objects={self.o.n_objects}")
        if self.o.materials == PairSource.crash_on:
            Path(out_dir).mkdir(parents=True)
            (Path(out_dir) / "cameras.json").write_text("{}")  # a half-written scene
            raise RuntimeError("generator crashed")
        r, t = self.o.resolution, self.o.n_frames
        cams = [
            Camera.look_at((1.0, 0.2 * i, 1.0), (0, 0, 0), id=f"cam_{i:02d}", width=r, height=r,
                           fov_deg=40.0)
            for i in range(self.o.n_cameras)
        ]  # fmt: skip
        blank = np.zeros((t, r, r, 3), np.uint8)
        return write_scene(
            out_dir,
            name=self.o.scene_name or f"pair-{self.o.seed}",
            fps=24.0,
            objects=[SceneObject(k, f"o{k}", m) for k, m in enumerate(materials, start=1)],
            cameras=cams,
            rgb={c.id: blank for c in cams},
            masks={c.id: blank[..., 0] for c in cams},
            observed_frames=self.o.observed_frames,
            domain_lower=(-1, -1, 0),
            domain_upper=(1, 1, 1),
        )


class _Plugin:
    @hookimpl
    def mosiv_scene_sources(self, register):
        register(Component("scene_source", "pairs", factory=PairSource, options=PairOptions))


@pytest.fixture
def pairs_registry(monkeypatch):
    reg = Registry()
    reg.add_plugin(_Plugin(), name="pairs-test")
    monkeypatch.setattr(registry_module, "get_registry", lambda **_: reg)
    PairSource.calls, PairSource.ranges = [], []
    return reg


def test_flags_map_onto_source_options(pairs_registry):
    opts = data_cli.source_options(
        "pairs",
        {"materials": "elastic,sand,snow", "seed": 4, "frames": 9, "cameras": 3},
        ["resolution=12"],
    )
    assert opts == {
        "materials": "elastic,sand,snow",
        "n_objects": 3,  # from --materials
        "seed": 4,
        "n_frames": 9,
        "observed_frames": 4,  # half of --frames
        "n_cameras": 3,
        "resolution": 12,
    }
    with pytest.raises(ConfigError, match="--seed and seed=... both given"):
        data_cli.source_options("pairs", {"seed": 1}, ["seed=2"])
    with pytest.raises(ConfigError, match="has no option 'conceal'"):
        data_cli.source_options("pairs", {"conceal": ["wind"]}, [])
    assert data_cli.source_options("pairs", {"ranges": "wide"}, []) == {"ranges": "wide"}


def test_ranges_flag_reaches_every_suite_scene_and_pins_the_suite(pairs_registry, tmp_path, capsys):
    argv = ["data", "suite", str(tmp_path), "--source", "pairs", "--only", "E-P,S-S"]
    assert main([*argv, "--ranges", "wide"]) == 0
    assert PairSource.ranges == ["wide", "wide"]
    assert json.loads((tmp_path / "suite.json").read_text())["settings"]["ranges"] == "wide"
    # the paper ranges are another protocol: resuming the wide suite with them is refused
    assert main(argv) == 2
    assert "resume with the same settings" in capsys.readouterr().err
    # a value argparse does not know is a usage error
    with pytest.raises(SystemExit):
        main([*argv, "--ranges", "huge"])


def test_synth_command_with_flags_and_key_values_after_them(pairs_registry, tmp_path):
    out = tmp_path / "s"
    argv = ["data", "synth", str(out), "--source", "pairs", "--materials", "plasticine,sand",
            "--frames", "4", "--cameras", "2", "--seed", "7", "resolution=10"]  # fmt: skip
    assert main(argv) == 0
    scene = read_scene(out)
    assert [o.material for o in scene.objects] == ["plasticine", "sand"]
    assert scene.n_frames == 4 and scene.observed_frames == 2 and len(scene.cameras) == 2
    assert scene.cameras[0].width == 10 and scene.name == "pair-7"


def test_synth_flag_a_source_lacks_is_an_error_naming_it(capsys, tmp_path):
    # the core's example source has no "resolution" option (it calls it "size")
    code = main(["data", "synth", str(tmp_path / "e"), "--source", "example", "--resolution", "8"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--resolution" in err and "size" in err


def test_suite_covers_the_paper_pairs_and_indexes_them(pairs_registry, tmp_path, capsys):
    assert main(["data", "suite", str(tmp_path), "--source", "pairs", "--seed", "2"]) == 0
    index = json.loads((tmp_path / "suite.json").read_text())
    pairs = {"E-P", "E-F", "E-S", "P-F", "P-S", "F-S", "E-E", "P-P", "F-F", "S-S"}
    assert pairs <= set(index["scenes"])
    assert any(len(s["materials"]) == 3 for s in index["scenes"].values())
    abbreviation = {"E": "elastic", "P": "plasticine", "F": "newtonian", "S": "sand"}
    for code, entry in index["scenes"].items():
        scene = read_scene(tmp_path / entry["path"])
        assert [o.material for o in scene.objects] == entry["materials"]
        assert entry["materials"] == [abbreviation[c] for c in code.split("-")]
    seeds = [s["seed"] for s in index["scenes"].values()]
    assert len(set(seeds)) == len(seeds)  # every scene its own seed
    progress = capsys.readouterr().err  # progress is logged to stderr; stdout holds results
    assert f"[1/{len(data_cli.SUITE_SCENES)}] E-P" in progress and "done in" in progress


def test_suite_resumes_after_a_crash_without_redoing_finished_scenes(
    pairs_registry, tmp_path, capsys
):
    argv = ["data", "suite", str(tmp_path), "--source", "pairs", "--only", "E-P,P-F,S-S"]
    PairSource.crash_on = "plasticine,newtonian"
    assert main(argv) == 70  # an unexpected error: the internal-error status (docs/CLI.md)
    assert "internal error: RuntimeError: generator crashed" in capsys.readouterr().err
    assert (tmp_path / "E-P" / "scene.json").is_file()
    assert not (tmp_path / "P-F").exists()  # the half-written scene stays in the scratch area
    assert (tmp_path / ".partial" / "P-F").is_dir()
    PairSource.crash_on, PairSource.calls = "", []
    assert main(argv) == 0
    assert PairSource.calls == ["plasticine,newtonian", "sand,sand"]  # E-P was skipped
    assert not (tmp_path / ".partial").exists()
    index = json.loads((tmp_path / "suite.json").read_text())
    assert set(index["scenes"]) == {"E-P", "P-F", "S-S"}
    # resuming with other settings is refused: the suite would mix two protocols
    capsys.readouterr()
    assert main([*argv, "--seed", "5"]) == 2
    assert "resume with the same settings" in capsys.readouterr().err


def test_suite_refuses_an_incomplete_scene_it_did_not_write(pairs_registry, tmp_path, capsys):
    (tmp_path / "E-P").mkdir()
    (tmp_path / "E-P" / "notes.txt").write_text("mine")
    assert main(["data", "suite", str(tmp_path), "--source", "pairs", "--only", "E-P"]) == 2
    assert "not a complete scene" in capsys.readouterr().err
    assert (tmp_path / "E-P" / "notes.txt").read_text() == "mine"


def test_suite_only_rejects_unknown_codes(pairs_registry, tmp_path):
    with pytest.raises(ConfigError, match="valid: E-P"):
        data_cli.suite_plan("E-X")
    assert data_cli.suite_plan("s-s,e-p") == [
        ("E-P", ["elastic", "plasticine"]),
        ("S-S", ["sand", "sand"]),
    ]
