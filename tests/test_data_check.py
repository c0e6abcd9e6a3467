"""`mosiv data check`: every problem of a scene, each with its file and reason."""

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from mosiv_framework.scene import check_scene, read_scene, run_check, summary, write_example_scene


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return write_example_scene(tmp_path_factory.mktemp("check") / "scene")


@pytest.fixture
def scene(pristine, tmp_path) -> Path:
    return Path(shutil.copytree(pristine, tmp_path / "scene"))


def edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))  # json.dumps writes NaN literally, as a buggy tool would


def problems_of(root: Path) -> list[tuple[str, str]]:
    return [(p.file, p.reason) for p in check_scene(root)]


def has(problems, file, *words) -> bool:
    return any(f == file and all(w in r for w in words) for f, r in problems)


def test_valid_scene_has_no_problems(pristine):
    assert check_scene(pristine) == []
    lines = []
    assert run_check(pristine, out=lines.append) == 0
    assert lines == [f"ok: {summary(read_scene(pristine))}"]
    assert "example-two-spheres-0000: 2 objects" in lines[0] and "4 cameras at 32x32" in lines[0]


def test_done_when_three_problems_are_all_reported(scene):
    """The acceptance test: a removed frame, a mask id 7 not declared and a non-rigid
    extrinsic are reported together, each with its file, and the exit code is 1."""
    (scene / "rgb" / "cam_01" / "0002.png").unlink()
    mask = iio.imread(scene / "masks" / "cam_00" / "0001.png")
    mask[0, 0] = 7
    iio.imwrite(scene / "masks" / "cam_00" / "0001.png", mask)
    edit_json(
        scene / "cameras.json",
        lambda d: d["cameras"][2]["world_to_camera"][0].__setitem__(0, 1.5),
    )
    problems = problems_of(scene)
    assert len(problems) == 3, problems
    assert has(problems, "rgb/cam_01/0002.png", "missing frame")
    assert has(problems, "masks/cam_00/0001.png", "[7]", "not declared")
    assert has(problems, "cameras.json", "cameras[2] (cam_02).world_to_camera", "not a rigid")
    lines = []
    assert run_check(scene, out=lines.append) == 1
    text = "\n".join(lines)
    for file in ("rgb/cam_01/0002.png", "masks/cam_00/0001.png", "cameras.json"):
        assert file in text
    assert "3 problem(s)" in lines[-1]


def truncate_png(root):
    path = root / "rgb" / "cam_03" / "0001.png"
    path.write_bytes(path.read_bytes()[:60])


def resize_rgb(root):
    iio.imwrite(root / "rgb" / "cam_02" / "0003.png", np.zeros((16, 32, 3), np.uint8))


def rgba_rgb(root):
    iio.imwrite(root / "rgb" / "cam_00" / "0000.png", np.zeros((32, 32, 4), np.uint8))


def rgb_mask(root):
    iio.imwrite(root / "masks" / "cam_01" / "0000.png", np.zeros((32, 32, 3), np.uint8))


def jpeg_named_png(root):
    iio.imwrite(
        root / "rgb" / "cam_00" / "0002.png", np.zeros((32, 32, 3), np.uint8), extension=".jpg"
    )


def extra_frame(root):
    shutil.copy(root / "rgb" / "cam_00" / "0000.png", root / "rgb" / "cam_00" / "0004.png")


def stray_file(root):
    (root / "masks" / "cam_00" / "notes.txt").write_text("hi")


def unknown_camera_folder(root):
    shutil.copytree(root / "rgb" / "cam_00", root / "rgb" / "cam_99")


def missing_camera_folder(root):
    shutil.rmtree(root / "masks" / "cam_03")


def unknown_material(root):
    edit_json(root / "scene.json", lambda d: d["objects"][1].__setitem__("material", "jelly"))


def nan_in_json(root):
    edit_json(root / "scene.json", lambda d: d["gravity"].__setitem__(2, float("nan")))


def inf_in_cameras(root):
    edit_json(root / "cameras.json", lambda d: d["cameras"][0].__setitem__("cx", float("inf")))


def wrong_format(root):
    edit_json(root / "scene.json", lambda d: d.__setitem__("format", "mosiv-scene/0"))


def missing_field(root):
    edit_json(root / "scene.json", lambda d: d.pop("fps"))


def wrong_type(root):
    edit_json(root / "scene.json", lambda d: d.__setitem__("n_frames", "four"))


def observed_too_many(root):
    edit_json(root / "scene.json", lambda d: d.__setitem__("observed_frames", 9))


def inverted_domain(root):
    edit_json(root / "scene.json", lambda d: d["domain"]["lower"].__setitem__(2, 1.0))


def ids_not_1_to_k(root):
    edit_json(root / "scene.json", lambda d: d["objects"][1].__setitem__("id", 3))


def duplicate_ids(root):
    edit_json(root / "scene.json", lambda d: d["objects"][1].__setitem__("id", 1))


def duplicate_cameras(root):
    edit_json(root / "cameras.json", lambda d: d["cameras"][1].__setitem__("id", "cam_00"))


def negative_focal(root):
    edit_json(root / "cameras.json", lambda d: d["cameras"][3].__setitem__("fy", -10.0))


def reflection(root):
    def flip(d):
        d["cameras"][1]["world_to_camera"][0] = [-x for x in d["cameras"][1]["world_to_camera"][0]]

    edit_json(root / "cameras.json", flip)


def broken_json(root):
    (root / "cameras.json").write_text('{"convention": "opencv", ')


def gt_wrong_dtype(root):
    with np.load(root / "gt" / "points.npz") as npz:
        arrays = dict(npz)
    arrays["obj_2"] = arrays["obj_2"].astype(np.float64)
    arrays["obj_1"] = arrays["obj_1"][:3]
    arrays["obj_9"] = arrays["obj_2"]
    np.savez(root / "gt" / "points.npz", **arrays)


def gt_nan(root):
    with np.load(root / "gt" / "points.npz") as npz:
        arrays = dict(npz)
    arrays["obj_1"][1, 5, 2] = np.nan
    np.savez(root / "gt" / "points.npz", **arrays)


def gt_params_mismatch(root):
    def edit(d):
        d["objects"][0]["material"] = "sand"
        d["objects"][1]["params"]["stiffness"] = 3.0

    edit_json(root / "gt" / "params.json", edit)


def null_field(root):
    edit_json(root / "scene.json", lambda d: d.__setitem__("fps", None))


def bool_in_matrix(root):
    edit_json(
        root / "cameras.json", lambda d: d["cameras"][1]["world_to_camera"][3].__setitem__(3, True)
    )


def gt_param_out_of_range(root):
    edit_json(
        root / "gt" / "params.json", lambda d: d["objects"][0]["params"].__setitem__("nu", 0.7)
    )


CASES = [
    (null_field, "scene.json", ("fps: must be a number, got None",)),
    (bool_in_matrix, "cameras.json", ("cam_01).world_to_camera: must be 4 rows of 4 numbers",)),
    (gt_param_out_of_range, "gt/params.json", ("params.nu: 0.7 is not in (-1, 0.5)",)),
    (truncate_png, "rgb/cam_03/0001.png", ("broken PNG",)),
    (resize_rgb, "rgb/cam_02/0003.png", ("32x16 pixels", "32x32")),
    (rgba_rgb, "rgb/cam_00/0000.png", ("4 channel", "expected 3")),
    (rgb_mask, "masks/cam_01/0000.png", ("3 channel", "expected 1")),
    (jpeg_named_png, "rgb/cam_00/0002.png", ("not a PNG",)),
    (extra_frame, "rgb/cam_00/0004.png", ("extra frame", "0000..0003")),
    (stray_file, "masks/cam_00/notes.txt", ("unexpected file",)),
    (unknown_camera_folder, "rgb/cam_99", ("does not declare",)),
    (missing_camera_folder, "masks/cam_03", ("missing folder",)),
    (unknown_material, "scene.json", ("objects[1].material", "'jelly'", "plasticine")),
    (nan_in_json, "scene.json", ("gravity[2] = nan", "finite")),
    (inf_in_cameras, "cameras.json", ("cameras[0].cx = inf",)),
    (wrong_format, "scene.json", ("format", "mosiv-scene/1")),
    (missing_field, "scene.json", ("fps: missing",)),
    (wrong_type, "scene.json", ("n_frames: must be an integer",)),
    (observed_too_many, "scene.json", ("observed_frames: 9 exceeds n_frames = 4",)),
    (inverted_domain, "scene.json", ("domain.lower", "z = 1.0 must be below")),
    (ids_not_1_to_k, "scene.json", ("1..K",)),
    (duplicate_ids, "scene.json", ("duplicate object id(s) [1]",)),
    (duplicate_cameras, "cameras.json", ("duplicate camera id 'cam_00'",)),
    (negative_focal, "cameras.json", ("cam_03).fy: must be positive",)),
    (reflection, "cameras.json", ("determinant", "reflection")),
    (broken_json, "cameras.json", ("not valid JSON",)),
    (gt_wrong_dtype, "gt/points.npz", ("obj_2: dtype float64",)),
    (gt_wrong_dtype, "gt/points.npz", ("obj_1: 3 frames", "n_frames = 4")),
    (gt_wrong_dtype, "gt/points.npz", ("obj_9: not an object",)),
    (gt_nan, "gt/points.npz", ("obj_1: contains 1 non-finite",)),
    (gt_params_mismatch, "gt/params.json", ("objects[0].material", "'sand'", "'elastic'")),
    (gt_params_mismatch, "gt/params.json", ("params.stiffness", "unknown parameter")),
]


@pytest.mark.parametrize(
    ("corrupt", "file", "words"), CASES, ids=lambda c: getattr(c, "__name__", None)
)
def test_each_problem_is_reported_with_its_file(scene, corrupt, file, words):
    corrupt(scene)
    problems = problems_of(scene)
    assert has(problems, file, *words), problems
    assert run_check(scene, out=lambda line: None) == 1


def test_ids_shift_also_flags_masks(scene):
    """Renumbering object 2 as 3 makes every mask pixel of object 2 undeclared: reported per file."""
    ids_not_1_to_k(scene)
    problems = problems_of(scene)
    assert has(problems, "masks/cam_00/0000.png", "[2] not declared", "declared: [1, 3]")
    assert has(problems, "gt/points.npz", "obj_3: missing")


def test_runs_of_missing_frames_and_leftovers(scene):
    for t in (1, 2, 3):
        (scene / "masks" / "cam_02" / f"000{t}.png").unlink()
    (scene / "rgb" / "cam_00" / ".0003.png.123.abcd.tmp").write_bytes(b"half")
    (scene / "rgb" / "cam_00" / "00001.png").write_bytes(b"")
    problems = problems_of(scene)
    assert has(problems, "masks/cam_02", "missing frames 0001..0003", "3 files")
    assert has(problems, "rgb/cam_00/.0003.png.123.abcd.tmp", "interrupted write")
    assert has(problems, "rgb/cam_00/00001.png", "unexpected file")
    assert len(problems) == 3, problems


def test_huge_n_frames_is_reported_compactly(scene):
    edit_json(scene / "scene.json", lambda d: d.__setitem__("n_frames", 10**9))
    problems = problems_of(scene)
    # one problem per camera folder (4 cameras x rgb, masks) and per gt array, not 10^9
    assert len(problems) == 10, problems
    assert has(problems, "gt/points.npz", "obj_2: 4 frames")
    assert has(problems, "rgb/cam_00", "missing frames 0004..999999999")


def test_missing_scene_folder(tmp_path):
    problems = check_scene(tmp_path / "nowhere")
    assert len(problems) == 1 and "does not exist" in problems[0].reason
    lines = []
    assert run_check(tmp_path / "nowhere", out=lines.append) == 1


def test_scene_path_is_a_file(tmp_path):
    """scene.path naming a file gets one clear line, and nothing is created beside it."""
    a_file = tmp_path / "scene.json"
    a_file.write_text("{}")
    lines = []
    assert run_check(a_file, out=lines.append) == 1
    assert "is a file, not a scene folder" in lines[0] and str(a_file) in lines[0]
    assert [p.name for p in tmp_path.iterdir()] == ["scene.json"]


def test_cli_reports_gt_and_frame_problems_without_traceback(scene, capsys):
    """`mosiv data check` runs validate_scene's rules: a frame that is a folder, a pickled
    gt array and an object with 3 of 4 gt frames are each listed, with exit code 1."""
    from mosiv_framework.cli.main import main

    frame = scene / "rgb" / "cam_02" / "0001.png"
    frame.unlink()
    frame.mkdir()
    with np.load(scene / "gt" / "points.npz") as npz:
        arrays = dict(npz)
    arrays["obj_1"] = np.array([{"x": 1}], dtype=object)
    arrays["obj_2"] = arrays["obj_2"][:3]
    np.savez(scene / "gt" / "points.npz", **arrays)
    assert main(["data", "check", str(scene)]) == 1
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err
    assert "rgb/cam_02/0001.png: is a folder; expected a PNG file" in out.out
    assert "gt/points.npz: obj_1: dtype object holds Python objects" in out.out
    assert "gt/points.npz: obj_2: 3 frames, scene.json has n_frames = 4" in out.out
