"""validate_scene on malformed scenes: every mutation of a valid example scene gives a problem
naming the offending file or field, nothing raises, nothing is written, and the readers the
pipeline uses refuse the same inputs with SceneFormatError (never a numpy, OSError, zipfile or
ValueError traceback)."""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import zipfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from mosiv_framework.errors import SceneFormatError
from mosiv_framework.scene import (
    read_scene,
    require_valid_scene,
    run_check,
    validate_scene,
    write_example_scene,
)

N_FRAMES = 10
PICKLE_MARKER = "pickle_ran"  # made next to the scene if a pickle in gt/points.npz is ever run


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return write_example_scene(
        tmp_path_factory.mktemp("validation") / "scene", n_frames=N_FRAMES, n_cameras=2, size=16
    )


@pytest.fixture
def scene(pristine, tmp_path) -> Path:
    return Path(shutil.copytree(pristine, tmp_path / "scene", symlinks=True))


def snapshot(root: Path) -> dict[str, str]:
    """Every path under ``root`` (links not followed) -> sha256 of a file, the target of a link
    or "folder": any write, new folder or removal while validating changes it."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath, name)
            rel = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[rel] = "link -> " + os.readlink(p)
            elif p.is_dir():
                out[rel] = "folder"
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


# ------------------------------------------------------------------------------ mutations
def edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))  # json.dumps writes NaN literally, as a buggy tool would


def set_scene(key, value):
    return lambda root: edit_json(root / "scene.json", lambda d: d.__setitem__(key, value))


def set_object(i, key, value):
    return lambda root: edit_json(
        root / "scene.json", lambda d: d["objects"][i].__setitem__(key, value)
    )


def set_camera(i, key, value):
    return lambda root: edit_json(
        root / "cameras.json", lambda d: d["cameras"][i].__setitem__(key, value)
    )


def write_text(rel: str, text: str | bytes):
    def mutate(root):
        path = root / rel
        path.write_bytes(text if isinstance(text, bytes) else text.encode())

    return mutate


def remove(rel: str):
    def mutate(root):
        path = root / rel
        shutil.rmtree(path) if path.is_dir() else path.unlink()

    return mutate


def replace_with_folder(rel: str):
    def mutate(root):
        remove(rel)(root)
        (root / rel).mkdir()
        (root / rel / "inner.txt").write_text("x")

    return mutate


def replace_with_link(rel: str, target: str):
    """``target`` relative to the link's folder; a link to itself is a loop."""

    def mutate(root):
        remove(rel)(root)
        os.symlink(target, root / rel)

    return mutate


def truncate(rel: str, keep: float):
    def mutate(root):
        data = (root / rel).read_bytes()
        (root / rel).write_bytes(data[: int(len(data) * keep)])

    return mutate


def edit_points(edit):
    def mutate(root):
        with np.load(root / "gt" / "points.npz") as npz:
            arrays = dict(npz)
        edit(arrays)
        np.savez(root / "gt" / "points.npz", **arrays)

    return mutate


def poke(arr, value):
    arr = arr.copy()
    arr[3, 7, 1] = value
    return arr


class RunsCode:
    """An object whose unpickling makes a folder: proof that a pickle was (not) loaded."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def pickled_points(root):
    arr = np.empty(1, dtype=object)
    arr[0] = RunsCode(str(root.parent / PICKLE_MARKER))
    with np.load(root / "gt" / "points.npz") as npz:
        arrays = dict(npz)
    arrays["obj_1"] = arr
    np.savez(root / "gt" / "points.npz", **arrays)


def lying_header(root):
    """An uncompressed member whose header declares more frames than its bytes hold."""
    with np.load(root / "gt" / "points.npz") as npz:
        arrays = dict(npz)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for key, arr in arrays.items():
            member = io.BytesIO()
            np.save(member, arr)
            raw = member.getvalue()
            if key == "obj_2":
                raw = raw.replace(f"({N_FRAMES}, 256, 3)".encode(), b"(99, 256, 3)")
            zf.writestr(f"{key}.npy", raw)
    (root / "gt" / "points.npz").write_bytes(buf.getvalue())


def edit_mask(t: int, cam: str, edit):
    def mutate(root):
        path = root / "masks" / cam / f"{t:04d}.png"
        iio.imwrite(path, edit(iio.imread(path)))

    return mutate


def erase_object_from_masks(k: int):
    def mutate(root):
        for path in sorted((root / "masks").rglob("*.png")):
            mask = iio.imread(path)
            iio.imwrite(path, np.where(mask == k, 0, mask).astype(np.uint8))

    return mutate


def set_param(i, key, value):
    return lambda root: edit_json(
        root / "gt" / "params.json", lambda d: d["objects"][i].__setitem__(key, value)
    )


def cameras_text(edit):
    """Edit cameras.json as text, for JSON that json.dumps would not write."""

    def mutate(root):
        path = root / "cameras.json"
        path.write_text(edit(path.read_text()))

    return mutate


def first_matrix_entry(text: str, literal: str) -> str:
    data = json.loads(text)
    data["cameras"][0]["world_to_camera"][0][0] = "@@"
    return json.dumps(data).replace('"@@"', literal)


def rebuild(rel: str, key: str, value):
    return lambda root: edit_json(root / rel, lambda d: d.__setitem__(key, value))


def points_to(key, value_of):
    return edit_points(lambda a: a.__setitem__(key, value_of(a)))


def rgb_to_file(root):
    shutil.rmtree(root / "rgb")
    (root / "rgb").write_text("x")


def gt_to_file(root):
    shutil.rmtree(root / "gt")
    (root / "gt").write_text("x")


def plain_npy(root):
    np.save(root / "gt" / "plain.npy", np.zeros(3))
    os.replace(root / "gt" / "plain.npy", root / PTS)


R0, M1, PTS, PAR = "rgb/cam_00/0003.png", "masks/cam_01/0005.png", "gt/points.npz", "gt/params.json"
C0, C1 = "cameras.json: cameras[0] (cam_00).", "cameras.json: cameras[1] (cam_01)."
EYE = [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
MANY = [{"id": k, "name": f"o{k}", "material": "sand"} for k in range(1, 301)]
SAND = "objects[0].material: is 'sand' but scene.json says 'elastic'"


def C(case_id: str, mutate, expected: str):
    """One malformed scene: ``expected`` is ``"<file>: <text>"``; some problem must contain it
    (the file, the field, the value and what is valid where the rule has one)."""
    return pytest.param(mutate, expected, id=case_id)


CASES = [
    # ---- scene.json
    C("scene-json-missing", remove("scene.json"), "scene.json: missing"),
    C("scene-json-bad-json", write_text("scene.json", '{"a": '), "scene.json: is not valid JSON"),
    C("scene-json-not-utf8", write_text("scene.json", b"\xff{}"), "scene.json: is not valid JSON"),
    C("scene-json-a-list", write_text("scene.json", "[1]"), "scene.json: top level must be a JSON"),
    C("scene-json-nested", write_text("scene.json", "[" * 10**5), "scene.json: is not valid JSON"),
    C("scene-json-is-folder", replace_with_folder("scene.json"), "scene.json: is a folder"),
    C(
        "scene-json-link-loop",
        replace_with_link("scene.json", "scene.json"),
        "scene.json: is a sym",
    ),
    C("n-frames-string", set_scene("n_frames", "ten"), "scene.json: n_frames: must be an integer"),
    C("n-frames-float", set_scene("n_frames", 10.0), "scene.json: n_frames: must be an integer"),
    C("n-frames-zero", set_scene("n_frames", 0), "scene.json: n_frames: must be at least 1, got 0"),
    C("n-frames-negative", set_scene("n_frames", -3), "scene.json: n_frames: must be at least 1"),
    C("n-frames-fewer", set_scene("n_frames", 7), "rgb/cam_00/0007.png: extra frame (n_frames = 7"),
    C("n-frames-more", set_scene("n_frames", 12), "rgb/cam_01: missing frames 0010..0011"),
    C("observed-too-many", set_scene("observed_frames", 11), "scene.json: observed_frames: 11 exc"),
    C("fps-zero", set_scene("fps", 0), "scene.json: fps: must be positive, got 0"),
    C("fps-negative", set_scene("fps", -24.0), "scene.json: fps: must be positive, got -24.0"),
    C("fps-bool", set_scene("fps", True), "scene.json: fps: must be a number, got True"),
    C("fps-beyond-float", set_scene("fps", 10**400), "scene.json: non-finite number: fps = 1000"),
    C("fps-null", set_scene("fps", None), "scene.json: fps: must be a number, got None"),
    C("format-wrong", set_scene("format", "x/2"), "scene.json: format: is 'x/2', expected 'mosiv"),
    C("units-cm", set_scene("units", "cm"), "scene.json: units: is 'cm'; mosiv-scene/1 scenes are"),
    C("gravity-nan", set_scene("gravity", [0, 0, float("nan")]), "scene.json: non-finite number"),
    C("gravity-short", set_scene("gravity", [0, 1]), "scene.json: gravity: must be a list of 3"),
    C("up-zero", set_scene("up", [0, 0, 0]), "scene.json: up: must be a non-zero vector"),
    C(
        "domain-inverted",
        set_scene("domain", {"lower": [0, 0, 1], "upper": [1, 1, 0]}),
        "scene.json: domain.lower: z = 1.0 must be below upper z = 0.0",
    ),
    C("domain-a-list", set_scene("domain", [0, 1]), "scene.json: domain: must be a JSON object"),
    C("ground-below", set_scene("ground", {"height": -2.0}), "scene.json: ground.height: -2.0 lie"),
    C("objects-empty", set_scene("objects", []), "scene.json: objects: must be a non-empty list"),
    C("objects-a-dict", set_scene("objects", {"1": 2}), "scene.json: objects: must be a non-empty"),
    C("object-id-string", set_object(0, "id", "one"), "scene.json: objects[0].id: must be an int"),
    C("object-id-zero", set_object(1, "id", 0), "scene.json: objects[1].id: must be at least 1"),
    C("object-id-duplicate", set_object(1, "id", 1), "scene.json: objects: duplicate object id"),
    C("object-material", set_object(0, "material", "jelly"), "scene.json: objects[0].material: un"),
    C("object-name-empty", set_object(1, "name", ""), "scene.json: objects[1].name: must be a non"),
    C("objects-too-many", set_scene("objects", MANY), "scene.json: objects: 300 objects; masks ar"),
    # ---- cameras.json
    C("cameras-json-missing", remove("cameras.json"), "cameras.json: missing"),
    C("cameras-empty", rebuild("cameras.json", "cameras", []), "cameras.json: cameras: must be a"),
    C(
        "convention",
        rebuild("cameras.json", "convention", "gl"),
        "cameras.json: convention: is 'gl",
    ),
    C("width-zero", set_camera(0, "width", 0), C0 + "width: must be at least 1, got 0"),
    C("height-negative", set_camera(1, "height", -16), C1 + "height: must be at least 1, got -16"),
    C("width-float", set_camera(0, "width", 16.5), C0 + "width: must be an integer, got 16.5"),
    C("fx-zero", set_camera(0, "fx", 0.0), C0 + "fx: must be positive, got 0.0"),
    C("cx-string", set_camera(0, "cx", "8"), C0 + "cx: must be a number, got '8'"),
    C(
        "matrix-nan",
        cameras_text(lambda t: first_matrix_entry(t, "NaN")),
        "cameras.json: non-finite number: cameras[0].world_to_camera[0][0] = nan",
    ),
    C(
        "matrix-infinity",
        cameras_text(lambda t: first_matrix_entry(t, "-Infinity")),
        "cameras.json: non-finite number: cameras[0].world_to_camera[0][0] = -inf",
    ),
    C(
        "matrix-singular",
        set_camera(0, "world_to_camera", [[0.0] * 4] * 3 + [[0, 0, 0, 1]]),
        C0 + "world_to_camera: not a rigid transform",
    ),
    C("matrix-3x4", set_camera(0, "world_to_camera", EYE), C0 + "world_to_camera: must be 4 rows"),
    C(
        "matrix-huge",
        set_camera(0, "world_to_camera", [[10**400, 0, 0, 0], *EYE]),
        "cameras.json: non-finite number: cameras[0].world_to_camera[0][0] = 1000",
    ),
    C("camera-id-path", set_camera(1, "id", "../c"), "cameras.json: cameras[1] (../c).id: must be"),
    C("camera-id-duplicate", set_camera(1, "id", "cam_00"), "cameras.json: cameras[1] (cam_00).id"),
    C(
        "camera-frames-not-a-pair",
        set_camera(1, "frames", [2]),
        "cameras.json: cameras[1] (cam_01).frames: must be [first, last]",
    ),
    C(
        "camera-frames-past-the-end",
        set_camera(1, "frames", [2, 10]),
        "cameras.json: cameras[1] (cam_01).frames: must satisfy 0 <= first <= last <= 9",
    ),
    C(
        "camera-frames-extra-frame",
        set_camera(1, "frames", [2, 9]),
        "rgb/cam_01/0001.png: extra frame (cameras.json: camera 'cam_01' recorded frames 0002..",
    ),
    C(
        "camera-frames-no-camera",
        lambda root: (set_camera(0, "frames", [0, 4])(root), set_camera(1, "frames", [6, 9])(root)),
        "cameras.json: no camera records frame(s) 5",
    ),
    # ---- frames
    C("frame-missing", remove(R0), R0 + ": missing frame (n_frames = 10"),
    C("frame-is-folder", replace_with_folder(R0), R0 + ": is a folder; expected a PNG file"),
    C("frame-broken-link", replace_with_link(R0, "nowhere.png"), R0 + ": is a symbolic link whose"),
    C("frame-link-loop", replace_with_link(R0, "0003.png"), R0 + ": is a symbolic link loop"),
    C("frame-truncated", truncate(R0, 0.5), R0 + ": broken PNG, cannot be decoded"),
    C("frame-empty", write_text(R0, b""), R0 + ": is not a PNG file"),
    C(
        "frame-extra",
        lambda r: shutil.copy(r / R0, r / "rgb/cam_00/0010.png"),
        "rgb/cam_00/0010.png: extra frame",
    ),
    C(
        "frame-leftover",
        write_text("rgb/cam_00/.0003.png.1.ab.tmp", b"x"),
        "rgb/cam_00/.0003.png.1.ab.tmp: temporary file left by an interrupted write",
    ),
    C("rgb-is-file", rgb_to_file, "rgb: is a file; expected a folder"),
    C("camera-folder-missing", remove("masks/cam_01"), "masks/cam_01: missing folder"),
    C("camera-folder-loop", replace_with_link("masks/cam_01", "cam_01"), "masks/cam_01: is a sym"),
    C(
        "mask-undeclared-id",
        edit_mask(5, "cam_01", lambda m: np.where(m == 1, 9, m)),
        M1 + ": contains object id(s) [9] not declared in scene.json (declared: [1, 2])",
    ),
    C("mask-wrong-size", edit_mask(5, "cam_01", lambda m: m[:8]), M1 + ": is 16x8 pixels but"),
    C(
        "mask-three-channels",
        edit_mask(5, "cam_01", lambda m: np.stack([m] * 3, -1)),
        M1 + ": has 3 channel(s), expected 1",
    ),
    C("mask-16-bit", edit_mask(5, "cam_01", lambda m: m.astype(np.uint16)), M1 + ": has 16-bit"),
    C("object-in-no-mask", erase_object_from_masks(2), "masks: object 2 (blue_clay) of scene"),
    # ---- gt/points.npz
    C("points-missing", remove(PTS), PTS + ": missing"),
    C(
        "points-nan",
        points_to("obj_1", lambda a: poke(a["obj_1"], np.nan)),
        PTS + ": obj_1: contains 1 non-finite numbers",
    ),
    C(
        "points-inf",
        points_to("obj_2", lambda a: poke(a["obj_2"], -np.inf)),
        PTS + ": obj_2: contains 1 non-finite numbers",
    ),
    C(
        "points-float64",
        points_to("obj_1", lambda a: a["obj_1"].astype(np.float64)),
        PTS + ": obj_1: dtype float64, expected float32",
    ),
    C(
        "points-int",
        points_to("obj_2", lambda a: a["obj_2"].astype(np.int32)),
        PTS + ": obj_2: dtype int32, expected float32",
    ),
    C(
        "points-two-columns",
        points_to("obj_1", lambda a: a["obj_1"][..., :2]),
        PTS + ": obj_1: shape [10, 256, 2], expected [T, N, 3]",
    ),
    C(
        "points-flat",
        points_to("obj_1", lambda a: a["obj_1"].reshape(-1, 3)),
        PTS + ": obj_1: shape [2560, 3], expected [T, N, 3]",
    ),
    C(
        "points-no-points",
        points_to("obj_2", lambda a: a["obj_2"][:, :0]),
        PTS + ": obj_2: shape [10, 0, 3], expected [T, N, 3] with N >= 1",
    ),
    C(
        "points-7-of-10-frames",
        points_to("obj_2", lambda a: a["obj_2"][:7]),
        PTS + ": obj_2: 7 frames, scene.json has n_frames = 10",
    ),
    C(
        "points-extra-frames",
        points_to("obj_1", lambda a: np.concatenate([a["obj_1"]] * 2)),
        PTS + ": obj_1: 20 frames, scene.json has n_frames = 10",
    ),
    C("points-object-missing", edit_points(lambda a: a.pop("obj_2")), PTS + ": obj_2: missing"),
    C(
        "points-unknown-object",
        points_to("obj_3", lambda a: a["obj_1"]),
        PTS + ": obj_3: not an object of scene.json",
    ),
    C("points-truncated", truncate(PTS, 0.5), PTS + ": cannot be read as .npz"),
    C("points-empty-file", write_text(PTS, b""), PTS + ": cannot be read as .npz"),
    C("points-plain-npy", plain_npy, PTS + ": cannot be read as .npz (not a valid zip"),
    C("points-pickled", pickled_points, PTS + ": obj_1: dtype object holds Python objects"),
    C("points-lying-header", lying_header, PTS + ": obj_2: truncated"),
    C("points-is-folder", replace_with_folder(PTS), PTS + ": is a folder; expected a .npz file"),
    C("points-broken-link", replace_with_link(PTS, "x.npz"), PTS + ": is a symbolic link whose"),
    # ---- gt/params.json, gt/effects.json, gt/
    C("params-missing", remove(PAR), PAR + ": missing"),
    C("params-bad-json", write_text(PAR, "{'objects': []}"), PAR + ": is not valid JSON"),
    C("params-objects-dict", rebuild(PAR, "objects", {}), PAR + ": objects: must be a list"),
    C(
        "params-no-params",
        lambda r: edit_json(r / PAR, lambda d: d["objects"][0].pop("params")),
        PAR + ": objects[0].params: must be a JSON object",
    ),
    C("param-string", set_param(0, "params", {"E": "5"}), PAR + ": objects[0].params.E: must be"),
    C("param-nan", set_param(0, "params", {"E": float("nan")}), PAR + ": non-finite number"),
    C("param-negative", set_param(1, "params", {"rho": -1.0}), PAR + ": objects[1].params.rho: -1"),
    C("param-unknown", set_param(1, "params", {"k": 1.0}), PAR + ": objects[1].params.k: unknown"),
    C("params-material", set_param(0, "material", "sand"), PAR + ": " + SAND),
    C(
        "params-object-missing",
        lambda r: edit_json(r / PAR, lambda d: d["objects"].pop()),
        PAR + ": objects: no entry for object 2 of scene.json",
    ),
    C("params-id-duplicate", set_param(1, "id", 1), PAR + ": objects[1].id: duplicate entry"),
    C(
        "effects-not-list",
        write_text("gt/effects.json", '{"effects": 3}'),
        "gt/effects.json: effects: must be a list, got 3",
    ),
    C("gt-is-file", gt_to_file, "gt: is a file; expected the ground-truth folder"),
]


def names(problems: list[str], file: str) -> list[str]:
    return [p for p in problems if p.startswith(f"{file}: ")]


def exercise_readers(root: Path) -> None:
    """What the pipeline reads; each either works or raises SceneFormatError."""
    try:
        scene = read_scene(root)
    except SceneFormatError:
        return
    readers = (
        scene.gt_points,
        scene.gt_params,
        scene.gt_effects,
        scene.load_masks,
        scene.load_rgb_tensor,
    )
    for read in readers:
        try:
            read()
        except SceneFormatError:
            pass


@pytest.mark.parametrize(("mutate", "expected"), CASES)
def test_malformed_scene_is_reported_by_name(scene, mutate, expected):
    mutate(scene)
    before = snapshot(scene.parent)
    problems = validate_scene(scene)  # must not raise
    assert any(expected in p for p in problems), f"no {expected!r} in {problems}"
    file = expected.split(": ")[0]
    # a fault of the checker itself is reported as "could not be checked"; none may occur
    assert not [p for p in problems if "could not be checked" in p], problems
    with pytest.raises(SceneFormatError) as err:
        require_valid_scene(scene)
    assert any(str(scene / file) in p for p in err.value.problems)
    assert run_check(scene, out=lambda line: None) == 1
    exercise_readers(scene)
    assert snapshot(scene.parent) == before, "validation or reading changed the files"
    assert not (scene.parent / PICKLE_MARKER).exists(), "a pickle in gt/points.npz was loaded"


def test_enough_distinct_mutations():
    ids = [c.id for c in CASES]
    assert len(ids) == len(set(ids)) and len(ids) >= 40


def test_pristine_scene_is_valid_and_readable(pristine):
    before = snapshot(pristine)
    assert validate_scene(pristine) == []
    assert validate_scene(pristine, need_ground_truth=True) == []
    require_valid_scene(pristine, need_ground_truth=True)
    scene = read_scene(pristine)
    points = scene.gt_points()
    assert sorted(points) == [1, 2]
    for p in points.values():
        assert p.shape == (N_FRAMES, 256, 3) and p.numpy().flags.writeable
    assert snapshot(pristine) == before


def test_need_ground_truth(scene):
    shutil.rmtree(scene / "gt")
    assert validate_scene(scene) == []
    assert validate_scene(scene, need_ground_truth=False) == []
    problems = validate_scene(scene, need_ground_truth=True)
    assert len(problems) == 1 and problems[0].startswith("gt: missing folder"), problems


def test_broken_gt_is_skipped_when_not_needed(scene):
    truncate(PTS, 0.5)(scene)
    assert validate_scene(scene, need_ground_truth=False) == []
    assert names(validate_scene(scene), PTS)


def test_scene_path_is_a_file_or_missing(tmp_path):
    a_file = tmp_path / "scene.json"
    a_file.write_text("{}")
    missing = tmp_path / "nowhere" / "scene"
    for path, words in ((a_file, "is a file, not a scene folder"), (missing, "does not exist")):
        problems = validate_scene(path)
        assert len(problems) == 1 and str(path) in problems[0] and words in problems[0]
        with pytest.raises(SceneFormatError, match=words):
            require_valid_scene(path)
        with pytest.raises(SceneFormatError, match=words):
            read_scene(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.json"]  # nothing created


def test_scene_path_is_a_link_loop(tmp_path):
    os.symlink(tmp_path / "loop", tmp_path / "loop")
    problems = validate_scene(tmp_path / "loop")
    assert len(problems) == 1 and "symbolic link loop" in problems[0], problems


def test_every_problem_is_reported_together(scene):
    """Problems in several files do not hide each other."""
    mutations = {c.id: c.values[0] for c in CASES}
    for case in ("fps-zero", "width-zero", "frame-is-folder", "points-7-of-10-frames"):
        mutations[case](scene)
    mutations["param-negative"](scene)
    problems = validate_scene(scene)
    for file in ("scene.json", "cameras.json", R0, PTS, PAR):
        assert names(problems, file), (file, problems)


@pytest.mark.parametrize(
    "case", ["points-nan", "points-7-of-10-frames", "points-pickled", "points-truncated"]
)
def test_gt_readers_refuse_what_validation_reports(scene, case):
    """The layout is fine, so read_scene works; evaluation's gt_points then refuses the file by
    name instead of crashing or scoring against 7 of 10 frames."""
    {c.id: c.values[0] for c in CASES}[case](scene)
    loaded = read_scene(scene)
    with pytest.raises(SceneFormatError, match="gt/points.npz: obj_|gt/points.npz: cannot"):
        loaded.gt_points()
    assert not (scene.parent / PICKLE_MARKER).exists()


def test_gt_params_refused_by_name(scene):
    set_param(1, "params", {"rho": -1.0})(scene)
    with pytest.raises(SceneFormatError, match=r"gt/params.json: objects\[1\].params.rho"):
        read_scene(scene).gt_params()
