"""What the viewer shows, read from a finished run folder into plain arrays and numbers.

Nothing here imports viser: the loading is tested without a server, and the UI
(``viewer.app``) only draws a ``ViewerData``. A run folder holds (pipeline/evaluate.py):
``rollout.npz`` (the identified model over every frame, ``obj_<k>`` [T, N_k, 3]),
``identified.json``, ``metrics.json`` and ``recipe.yaml`` naming the scene; ``diagnosis.json``
when ``mosiv diagnose`` ran (diagnose/report.py).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from mosiv_framework.errors import ConfigError, OutputError
from mosiv_framework.pipeline.formats import FILE_FORMATS, check_format

log = logging.getLogger(__name__)

#: files a run folder must hold for the viewer; rollout.npz is written by the evaluation
REQUIRED = ("recipe.yaml", "identified.json", "metrics.json")


@dataclass
class CameraView:
    """One scene camera as a frustum: pose in world coordinates, OpenCV axes (x right, y down,
    z forward), the convention of ``scene.cameras.Camera`` and of viser's frustums."""

    id: str
    position: np.ndarray  # [3] optical centre (m)
    rotation: np.ndarray  # [3, 3] camera-to-world rotation
    fov_y: float  # vertical field of view (rad)
    aspect: float  # width / height


@dataclass
class ParamComparison:
    """An identified parameter against the scene's true value (metrics.json ``param_error``)."""

    true: float | list[float]
    error: float  # relative (fraction) or, for angles, absolute in degrees
    unit: str  # "rel" or "deg"
    gauge_free: float | None = None  # relative error after the density gauge (evaluate.py)


@dataclass
class ObjectSummary:
    """One object's identified model and scores."""

    id: int
    name: str
    family: str
    params: dict[str, float]
    initial_velocity: list[float]
    truth: dict[str, ParamComparison] = field(default_factory=dict)
    cd_observed_mm2: float | None = None
    cd_future_mm2: float | None = None


@dataclass
class Residuals:
    """diagnosis.json's per-object, per-frame residuals of the identified model.

    chamfer_mm2: object -> [T] Chamfer error per frame (NaN where a prediction did not reach);
    centroid_mm: object -> [F] length of the centroid residual over the diagnosed frames;
    noise_floor_mm and onset_frame: the location step's noise floor and change point."""

    verdict: str
    accepted: str | None
    chamfer_mm2: dict[int, np.ndarray]
    centroid_mm: dict[int, np.ndarray]
    noise_floor_mm: dict[int, float]
    onset_frame: dict[int, int]


@dataclass
class ViewerData:
    """Everything ``mosiv view`` draws, for frames 0..n_frames-1."""

    run_dir: Path
    scene_name: str
    fps: float
    n_frames: int
    observed_frames: int
    up: tuple[float, float, float]
    domain: tuple[tuple[float, float, float], tuple[float, float, float]]
    ground_height: float | None
    predicted: dict[int, np.ndarray]  # object -> [T, N_k, 3]
    reference: dict[int, np.ndarray]  # object -> [T', N_k, 3]; empty when the run has none
    reference_source: str | None  # "gt/points.npz", "reconstruction" or None
    cameras: list[CameraView]
    objects: dict[int, ObjectSummary]
    ground_friction: float | None = None
    residuals: Residuals | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def object_ids(self) -> list[int]:
        return sorted(self.predicted)

    def phase(self, frame: int) -> str:
        """``"observed"`` for a frame the identification saw, else ``"future"``."""
        return "observed" if frame < self.observed_frames else "future"


def load_run(run_dir: str | Path) -> ViewerData:
    """Read a finished run folder for the viewer.

    Raises:
        ConfigError: the folder is missing, is not a run folder, or has no rollout.npz yet.
        SceneFormatError: the scene recipe.yaml names cannot be read.
        OutputError, FormatError: a run file is unreadable or of an unknown format.
    """
    from mosiv_framework.scene import read_scene

    root = _require_run(run_dir)
    recipe = yaml.safe_load((root / "recipe.yaml").read_text(encoding="utf-8")) or {}
    scene = read_scene(scene_folder(root, recipe))
    identified = _json(root, "identified.json")
    metrics = _json(root, "metrics.json")
    predicted = _read_rollout(root / "rollout.npz")
    reference, source = _reference(root, scene, metrics)
    data = ViewerData(
        run_dir=root,
        scene_name=scene.name,
        fps=scene.fps,
        n_frames=min(p.shape[0] for p in predicted.values()),
        observed_frames=scene.observed_frames,
        up=tuple(scene.up),
        domain=scene.domain,
        ground_height=scene.ground_height,
        predicted=predicted,
        reference=reference,
        reference_source=source,
        cameras=[camera_view(c) for c in scene.cameras],
        objects=_objects(identified, metrics, {o.id: o.name for o in scene.objects}),
        ground_friction=identified.get("ground_friction"),
    )
    if metrics.get("evaluation_note"):
        data.notes.append(str(metrics["evaluation_note"]))
    if (root / "diagnosis.json").is_file():
        data.residuals = load_residuals(root / "diagnosis.json", data.object_ids)
    return data


def _require_run(run_dir: str | Path) -> Path:
    root = Path(run_dir)
    if not root.is_dir():
        state = "is a file, not a folder" if root.exists() else "does not exist"
        raise ConfigError(
            f"run folder {str(run_dir)!r} {state}; give a folder written by `mosiv run` "
            f"(its output.dir)"
        )
    missing = [name for name in REQUIRED if not (root / name).is_file()]
    if missing:
        raise ConfigError(
            f"{root} is not a finished run folder: it lacks {', '.join(missing)}; run "
            f"`mosiv run RECIPE output.dir={root}` first"
        )
    if not (root / "rollout.npz").is_file():
        raise ConfigError(
            f"{root / 'rollout.npz'}: missing; the run was evaluated before rollouts were saved "
            f"or its evaluation did not finish; write it with `mosiv eval {root}`"
        )
    return root


def scene_folder(root: Path, recipe: dict) -> Path:
    """The scene folder of a run's recipe.yaml. A relative ``scene.path`` is relative to the
    folder ``mosiv run`` was started in; when the viewer starts elsewhere, that folder is found
    from the run folder and the recipe's ``output.dir`` (runs/quickstart in /work -> /work)."""
    path = (recipe.get("scene") or {}).get("path")
    if not path:
        raise ConfigError(f"{root / 'recipe.yaml'}: names no scene.path; the run's scene is needed")
    scene = Path(path)
    if scene.is_absolute() or scene.is_dir():
        return scene
    out = Path(str((recipe.get("output") or {}).get("dir") or ""))
    parts = out.parts
    resolved = root.resolve()
    if parts and not out.is_absolute() and resolved.parts[-len(parts) :] == parts:
        started_in = Path(*resolved.parts[: -len(parts)])
        if (started_in / scene).is_dir():
            return started_in / scene
    return scene  # read_scene names it in its error


def _json(root: Path, name: str) -> dict:
    path = root / name
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise OutputError(
            f"{path}: not valid JSON ({exc}); rerun the stage that writes it"
        ) from None
    supported = FILE_FORMATS.get(name)
    return data if supported is None else check_format(data, supported, path=path)


def _read_rollout(path: Path) -> dict[int, np.ndarray]:
    """``obj_<k>`` arrays of a rollout.npz (video.save_rollout_npz), read without pickle."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {
                int(name[4:]): np.asarray(npz[name], dtype=np.float32)
                for name in npz.files
                if name.startswith("obj_")
            }
    except (OSError, ValueError) as exc:
        raise OutputError(f"{path}: cannot be read as a rollout ({exc})") from None
    bad = [k for k, a in arrays.items() if a.ndim != 3 or a.shape[-1] != 3 or not len(a)]
    if not arrays or bad:
        raise OutputError(
            f"{path}: expected obj_<k> arrays of shape [frames, points, 3]"
            + (f"; objects {bad} are not" if bad else "; it holds none")
        )
    return arrays


def _reference(root: Path, scene, metrics: dict) -> tuple[dict[int, np.ndarray], str | None]:
    """The points the run was scored against: the scene's ground truth, else the run's
    reconstruction (metrics.json ``reference``), else none."""
    if scene.has_gt:
        return {k: v.numpy() for k, v in scene.gt_points().items()}, "gt/points.npz"
    if metrics.get("reference") == "reconstruction" and (root / "reconstruction.pt").is_file():
        import torch

        # the run's own file, written by its reconstruct stage (a pickled Reconstruction)
        rec = torch.load(root / "reconstruction.pt", weights_only=False)
        return {int(k): v.detach().cpu().numpy() for k, v in rec.points.items()}, "reconstruction"
    return {}, None


def camera_view(camera) -> CameraView:
    """A ``scene.cameras.Camera`` as a frustum's pose and shape."""
    c2w = camera.camera_to_world.numpy()
    return CameraView(
        id=camera.id,
        position=c2w[:3, 3].copy(),
        rotation=c2w[:3, :3].copy(),
        fov_y=2.0 * math.atan(camera.height / (2.0 * camera.fy)),
        aspect=camera.width / camera.height,
    )


def _objects(identified: dict, metrics: dict, names: dict[int, str]) -> dict[int, ObjectSummary]:
    blocks = {b: metrics.get(b) or {} for b in ("observed", "future")}
    errors = metrics.get("param_error") or {}
    out = {}
    for key, obj in sorted(identified.get("objects", {}).items(), key=lambda kv: int(kv[0])):
        k = int(key)
        summary = ObjectSummary(
            id=k,
            name=names.get(k, f"object {k}"),
            family=obj["family"],
            params={n: float(v) for n, v in obj.get("params", {}).items()},
            initial_velocity=[float(x) for x in obj.get("initial_velocity", [])],
            truth={n: _comparison(e) for n, e in (errors.get(key) or {}).items()},
        )
        for block, attr in (("observed", "cd_observed_mm2"), ("future", "cd_future_mm2")):
            per_object = blocks[block].get("per_object") or {}
            entry = per_object.get(key, per_object.get(k))
            if entry is not None:
                setattr(summary, attr, float(entry["cd_mm2"]))
        out[k] = summary
    return out


def _comparison(entry: dict) -> ParamComparison:
    if "abs_error_deg" in entry:
        return ParamComparison(entry["true"], float(entry["abs_error_deg"]), "deg")
    gauge = entry.get("rel_error_gauge_free")
    return ParamComparison(
        entry["true"], float(entry["rel_error"]), "rel", None if gauge is None else float(gauge)
    )


def load_residuals(path: Path, object_ids: list[int]) -> Residuals:
    """The identified model's residuals from a diagnosis.json (diagnose/report.py).

    ``frame_errors_mm2["identified"]`` is a [K, T] table in the order of the sorted object ids,
    null where a prediction did not reach a frame; ``location.objects`` holds each object's
    centroid residual (m) over the diagnosed frames, its noise floor and onset frame."""
    from mosiv_framework.diagnose.formats import DIAGNOSIS_FORMAT, file_format

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise OutputError(f"{path}: not valid JSON ({exc}); rerun `mosiv diagnose`") from None
    file_format(data, path, (DIAGNOSIS_FORMAT,))
    table = (data.get("frame_errors_mm2") or {}).get("identified") or []
    ids = sorted(object_ids)
    chamfer = {
        k: np.array([np.nan if x is None else float(x) for x in row], dtype=float)
        for k, row in zip(ids, table)
    }
    centroid, floor, onset = {}, {}, {}
    for key, entry in ((data.get("location") or {}).get("objects") or {}).items():
        k = int(key)
        res = np.asarray(entry.get("centroid_residual_m") or [], dtype=float).reshape(-1, 3)
        centroid[k] = np.linalg.norm(res, axis=1) * 1e3
        floor[k] = float(entry.get("noise_floor_m", float("nan"))) * 1e3
        onset[k] = int(entry.get("onset_frame", 0))
    accepted = data.get("accepted")
    return Residuals(
        verdict=str(data.get("verdict", "")),
        accepted=accepted.get("name") if isinstance(accepted, dict) else None,
        chamfer_mm2=chamfer,
        centroid_mm=centroid,
        noise_floor_mm=floor,
        onset_frame=onset,
    )
