"""Reading and writing ``mosiv-scene/1`` folders (docs/SCENE_FORMAT.md).

``read_scene`` validates the JSON files and the frame layout (``check.check_layout``) and
returns a ``Scene`` whose images load lazily. ``SceneWriter`` / ``write_scene`` write a scene
file by file, each atomically (temporary name, then ``os.replace``), so an interrupted generator
never leaves a truncated file under a final name; scene.json is written last, so a scene without
it is visibly unfinished.
"""

from __future__ import annotations

import io
import json
import os
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mosiv_framework.errors import SceneFormatError
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.scene.check import FORMAT, check_layout, frame_name
from mosiv_framework.scene.check_common import Meta, Report, load_json, path_kind
from mosiv_framework.scene.check_gt import (
    EFFECTS,
    PARAMS,
    check_gt_effects,
    check_gt_params,
    read_points,
)
from mosiv_framework.types import World


@dataclass(frozen=True)
class SceneObject:
    """One object of scene.json: id in 1..K, a display name, and its material family."""

    id: int
    name: str
    material: str


@dataclass
class Scene:
    """A scene folder: its declarations (scene.json, cameras.json) and lazy image access.

    Distances in metres, ``gravity`` in m/s^2, ``fps`` in frames per second. ``ground_height``
    is None when the scene has no ground plane. ``camera_frames`` maps the id of a camera that
    did not record every frame (one that started late or stopped early) to the (first, last)
    frames it did record; ``records`` and ``view_mask`` say which views exist.
    """

    root: Path
    name: str
    fps: float
    n_frames: int
    observed_frames: int
    gravity: tuple[float, float, float]
    domain_lower: tuple[float, float, float]
    domain_upper: tuple[float, float, float]
    ground_height: float | None
    objects: list[SceneObject]
    cameras: list[Camera]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    camera_frames: dict[str, tuple[int, int]] = field(default_factory=dict)
    _camera_index: dict[str, Camera] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        self._camera_index = {c.id: c for c in self.cameras}

    # ------------------------------------------------------------------------ declarations
    @property
    def domain(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(lower, upper) corners of the simulation box (m)."""
        return self.domain_lower, self.domain_upper

    @property
    def world(self) -> World:
        return World(
            domain_lower=self.domain_lower,
            domain_upper=self.domain_upper,
            gravity=self.gravity,
            ground_height=self.ground_height,
            fps=self.fps,
        )

    @property
    def object_ids(self) -> list[int]:
        return [o.id for o in self.objects]

    @property
    def materials(self) -> dict[int, str]:
        """Object id -> material family."""
        return {o.id: o.material for o in self.objects}

    @property
    def camera_ids(self) -> list[str]:
        return [c.id for c in self.cameras]

    def camera(self, camera_id: str) -> Camera:
        try:
            return self._camera_index[camera_id]
        except KeyError:
            raise KeyError(
                f"scene {self.name!r} has no camera {camera_id!r}; cameras: {self.camera_ids}"
            ) from None

    # ------------------------------------------------------------------------------- views
    @property
    def every_view_recorded(self) -> bool:
        """Whether every camera recorded every frame (no camera has a ``frames`` range)."""
        return not self.camera_frames

    def recorded_frames(self, camera_id: str) -> range:
        """The frames camera ``camera_id`` recorded."""
        self.camera(camera_id)  # raises a KeyError naming the valid cameras
        first, last = self.camera_frames.get(camera_id, (0, self.n_frames - 1))
        return range(first, last + 1)

    def records(self, camera_id: str, frame: int) -> bool:
        """Whether camera ``camera_id`` has an image (and a mask) at ``frame``."""
        return frame in self.recorded_frames(camera_id)

    def cameras_at(self, frame: int) -> list[Camera]:
        """The cameras that recorded ``frame``, in cameras.json order."""
        return [c for c in self.cameras if self.records(c.id, frame)]

    def view_mask(
        self, *, frames: Iterable[int] | None = None, cameras: Sequence[str] | None = None
    ) -> torch.Tensor:
        """bool [F, C]: which (frame, camera) views exist; defaults as ``load_rgb_tensor``."""
        frames = list(range(self.n_frames)) if frames is None else list(frames)
        cameras = self.camera_ids if cameras is None else list(cameras)
        return torch.tensor([[self.records(c, t) for c in cameras] for t in frames], dtype=bool)

    # ------------------------------------------------------------------------------ images
    def _frame_path(self, kind: str, camera_id: str, frame: int) -> Path:
        self.camera(camera_id)  # raises a KeyError naming the valid cameras
        if not 0 <= frame < self.n_frames:
            raise IndexError(f"frame {frame} outside 0..{self.n_frames - 1} of scene {self.name!r}")
        if not self.records(camera_id, frame):
            span = self.recorded_frames(camera_id)
            raise SceneFormatError(
                f"scene {self.name!r}: camera {camera_id!r} recorded frames "
                f"{span.start}..{span.stop - 1} only (cameras.json), not frame {frame}; "
                "this step needs every camera at every frame, or must skip the missing views "
                "(Scene.records, Scene.view_mask)"
            )
        return self.root / kind / camera_id / frame_name(frame)

    def rgb_path(self, camera_id: str, frame: int) -> Path:
        return self._frame_path("rgb", camera_id, frame)

    def mask_path(self, camera_id: str, frame: int) -> Path:
        return self._frame_path("masks", camera_id, frame)

    def _read_png(self, path: Path, camera_id: str, channels: int) -> np.ndarray:
        import imageio.v3 as iio  # lazy: image I/O is only needed once pixels are read

        rel = path.relative_to(self.root).as_posix()
        try:
            img = np.asarray(iio.imread(path, extension=".png"))
        except Exception as exc:  # any decoder failure means the file is broken
            raise SceneFormatError(f"{rel}: cannot be decoded as PNG ({exc})") from exc
        cam = self.camera(camera_id)
        want = (cam.height, cam.width) + ((channels,) if channels > 1 else ())
        if img.shape != want or img.dtype != np.uint8:
            raise SceneFormatError(
                f"{rel}: is {img.dtype} {list(img.shape)}, expected uint8 {list(want)} "
                "(run `mosiv data check` on the scene to list every problem)"
            )
        return img

    def rgb(self, camera_id: str, frame: int) -> np.ndarray:
        """One frame's colour image, uint8 [H, W, 3] (sRGB)."""
        return self._read_png(self.rgb_path(camera_id, frame), camera_id, 3)

    def mask(self, camera_id: str, frame: int) -> np.ndarray:
        """One frame's instance mask, uint8 [H, W]: 0 background, k object id."""
        return self._read_png(self.mask_path(camera_id, frame), camera_id, 1)

    def _stack(self, read, frames, cameras, missing: str, channels: int) -> np.ndarray:
        frames = list(range(self.n_frames)) if frames is None else list(frames)
        cameras = self.camera_ids if cameras is None else list(cameras)
        if missing not in ("error", "zeros"):
            raise ValueError(f"missing={missing!r}: valid values are 'error' and 'zeros'")
        sizes = {(self.camera(c).width, self.camera(c).height) for c in cameras}
        if len(sizes) > 1:
            raise SceneFormatError(
                f"cameras {cameras} have different resolutions {sorted(sizes)}; "
                "load them separately (cameras=[one id])"
            )

        def view(c: str, f: int) -> np.ndarray:
            if missing == "zeros" and not self.records(c, f):
                cam = self.camera(c)
                shape = (cam.height, cam.width) + ((channels,) if channels > 1 else ())
                return np.zeros(shape, dtype=np.uint8)
            return read(c, f)

        return np.stack([np.stack([view(c, f) for c in cameras]) for f in frames])

    def load_rgb_tensor(
        self,
        *,
        frames: Iterable[int] | None = None,
        cameras: Sequence[str] | None = None,
        device: torch.device | str = "cpu",
        missing: str = "error",
    ) -> torch.Tensor:
        """Colour frames as float32 [F, C, H, W, 3] in [0, 1] (sRGB values, not linearised).

        Defaults to every frame and every camera, in cameras.json order. A view the camera did
        not record raises SceneFormatError (``missing="error"``) or is black
        (``missing="zeros"``: the caller then weighs views by ``view_mask``).
        """
        arr = self._stack(self.rgb, frames, cameras, missing, 3)
        return torch.from_numpy(arr).to(device=device, dtype=torch.float32) / 255.0

    def load_masks(
        self,
        *,
        frames: Iterable[int] | None = None,
        cameras: Sequence[str] | None = None,
        device: torch.device | str = "cpu",
        missing: str = "error",
    ) -> torch.Tensor:
        """Per-object masks as float32 [F, C, K, H, W] in {0, 1}; channel k-1 is object k.
        ``missing`` as ``load_rgb_tensor`` (a view not recorded is all background)."""
        ids_t = self.load_mask_ids(frames=frames, cameras=cameras, device=device, missing=missing)
        object_ids = torch.arange(1, len(self.objects) + 1, device=device)
        return (ids_t[:, :, None] == object_ids[:, None, None]).to(torch.float32)

    def load_mask_ids(
        self,
        *,
        frames: Iterable[int] | None = None,
        cameras: Sequence[str] | None = None,
        device: torch.device | str = "cpu",
        missing: str = "error",
    ) -> torch.Tensor:
        """Instance ids as int64 [F, C, H, W] (0 background, k object id); ``missing`` as
        ``load_rgb_tensor`` (a view not recorded is all background)."""
        ids = self._stack(self.mask, frames, cameras, missing, 1)
        return torch.from_numpy(ids.astype(np.int64)).to(device)

    # ------------------------------------------------------------- ground truth (evaluation)
    @property
    def has_gt(self) -> bool:
        return (self.root / "gt" / "points.npz").is_file()

    def _meta(self) -> Meta:
        """What scene.json declares, for the ground-truth rules of ``check_gt``."""
        return Meta(
            n_frames=self.n_frames,
            object_ids=set(self.object_ids),
            materials=self.materials,
            names={o.id: o.name for o in self.objects},
        )

    def _refuse(self, report: Report) -> None:
        if report.problems:
            raise SceneFormatError([f"{self.root / p.file}: {p.reason}" for p in report.problems])

    def gt_points(self) -> dict[int, torch.Tensor]:
        """Object id -> float32 [T, N_k, 3] true particle positions (m). Evaluation only.

        Raises SceneFormatError naming gt/points.npz unless it holds, for every object, a
        finite float32 array with a position for each of the scene's n_frames frames (read
        without pickle: an object array is refused, never loaded).
        """
        report = Report()
        arrays = read_points(self.root, report, self._meta())
        self._refuse(report)
        return {k: torch.from_numpy(arrays[f"obj_{k}"]) for k in self.object_ids}

    def _gt_json(self, rel: str, check) -> dict | None:
        """The parsed, checked gt JSON file ``rel``; None when absent."""
        if path_kind(self.root / rel) == "missing":
            return None
        report = Report()
        data = load_json(self.root, rel, report)
        if data is not None:
            check(report, data)
        self._refuse(report)
        return data

    def gt_params(self) -> dict[str, Any]:
        """The parsed gt/params.json (``generator``, ``objects`` with true parameters).
        Evaluation only. Raises SceneFormatError when it is missing or breaks a rule."""
        data = self._gt_json(PARAMS, lambda report, d: check_gt_params(report, d, self._meta()))
        if data is None:
            raise SceneFormatError(
                f"{self.root / PARAMS}: missing; scene {self.name!r} has no ground truth"
            )
        return data

    def gt_effects(self) -> list[dict[str, Any]]:
        """Effects of gt/effects.json (``kind``, ``params``); [] when the file is absent.
        Only the evaluation of discrepancy diagnosis may read this."""
        data = self._gt_json(EFFECTS, check_gt_effects)
        return [] if data is None else list(data["effects"])


def read_scene(path: str | Path) -> Scene:
    """Load a scene folder; raise SceneFormatError listing every problem of its layout.

    Images are not decoded here (``mosiv data check`` does that); they load on access.
    """
    root = Path(path)
    problems = check_layout(root)
    if problems:
        raise SceneFormatError(
            [str(p) if p.file == "." else f"{root / p.file}: {p.reason}" for p in problems]
        )
    try:
        return _build_scene(root)
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        # the layout check passed, so the files changed under us; still name them, no traceback
        raise SceneFormatError(
            f"{root / 'scene.json'}, {root / 'cameras.json'}: changed while being read "
            f"({type(exc).__name__}: {exc}); run `mosiv data check {root}`"
        ) from exc


def _build_scene(root: Path) -> Scene:
    """The Scene of a folder whose layout has been checked."""
    scene = json.loads((root / "scene.json").read_text(encoding="utf-8"))
    cams = json.loads((root / "cameras.json").read_text(encoding="utf-8"))
    ground = scene.get("ground")
    return Scene(
        root=root,
        name=scene["name"],
        fps=float(scene["fps"]),
        n_frames=int(scene["n_frames"]),
        observed_frames=int(scene["observed_frames"]),
        gravity=tuple(float(x) for x in scene["gravity"]),
        domain_lower=tuple(float(x) for x in scene["domain"]["lower"]),
        domain_upper=tuple(float(x) for x in scene["domain"]["upper"]),
        ground_height=None if ground is None else float(ground["height"]),
        objects=[
            SceneObject(int(o["id"]), str(o["name"]), str(o["material"]))
            for o in sorted(scene["objects"], key=lambda o: o["id"])
        ],
        cameras=[Camera.from_dict(c) for c in cams["cameras"]],
        up=tuple(float(x) for x in scene.get("up", (0.0, 0.0, 1.0))),
        camera_frames={
            str(c["id"]): (int(c["frames"][0]), int(c["frames"][1]))
            for c in cams["cameras"]
            if "frames" in c
        },
    )


# ---------------------------------------------------------------------------------- writing
def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that ``path`` is either absent/old or complete.

    Writes a hidden temporary file in the same folder (same file system, so ``os.replace`` is an
    atomic rename) and removes it if anything fails.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # open(..., "xb") rather than mkstemp: mkstemp makes 0600 files, this respects the umask
    tmp = path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    try:
        with open(tmp, "xb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_json(path: str | Path, data: Any) -> None:
    """JSON with ``allow_nan=False``: a NaN is a bug of the writer, not something to store."""
    text = json.dumps(data, indent=2, allow_nan=False) + "\n"
    atomic_write_bytes(path, text.encode("utf-8"))


def encode_png(image: np.ndarray) -> bytes:
    """uint8 [H, W] or [H, W, 3] -> PNG bytes."""
    import imageio.v3 as iio

    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"PNG frames must be uint8, got {image.dtype}")
    return iio.imwrite("<bytes>", image, extension=".png")


class SceneWriter:
    """Writes one scene folder piece by piece (frames as they are rendered), atomically.

    Usage: create it with the declarations (``camera_frames``: the (first, last) frames of a
    camera that did not record every frame), call ``write_frame`` for every recorded view,
    optionally ``write_gt``, then ``finish()``, which writes scene.json only if every frame is
    there. Materials must be valid families and ids 1..K (checked by ``finish`` via the layout
    check, which raises SceneFormatError naming each problem).
    """

    def __init__(
        self,
        out_dir: str | Path,
        *,
        name: str,
        fps: float,
        n_frames: int,
        observed_frames: int,
        objects: Sequence[SceneObject],
        cameras: Sequence[Camera],
        domain_lower: Sequence[float],
        domain_upper: Sequence[float],
        gravity: Sequence[float] = (0.0, 0.0, -9.8),
        ground_height: float | None = 0.0,
        camera_frames: Mapping[str, tuple[int, int]] | None = None,
    ) -> None:
        self.root = Path(out_dir)
        self.n_frames = n_frames
        self.cameras = {c.id: c for c in cameras}
        #: camera id -> (first, last) frames of a camera that did not record every frame
        self.camera_frames = {c: (int(a), int(b)) for c, (a, b) in (camera_frames or {}).items()}
        unknown = sorted(set(self.camera_frames) - set(self.cameras))
        if unknown:
            raise KeyError(f"camera_frames names unknown camera(s) {unknown}")
        self._scene_json = {
            "format": FORMAT,
            "name": name,
            "fps": fps,
            "n_frames": n_frames,
            "observed_frames": observed_frames,
            "units": "m",
            "up": [0.0, 0.0, 1.0],
            "gravity": [float(g) for g in gravity],
            "domain": {
                "lower": [float(x) for x in domain_lower],
                "upper": [float(x) for x in domain_upper],
            },
            "objects": [{"id": o.id, "name": o.name, "material": o.material} for o in objects],
        }
        if ground_height is not None:
            self._scene_json["ground"] = {"height": float(ground_height)}
        self.root.mkdir(parents=True, exist_ok=True)
        atomic_write_json(
            self.root / "cameras.json",
            {"convention": "opencv", "cameras": [self._camera_entry(c) for c in cameras]},
        )

    def _camera_entry(self, camera: Camera) -> dict:
        entry = camera.to_dict()
        if camera.id in self.camera_frames:
            entry["frames"] = list(self.camera_frames[camera.id])
        return entry

    def write_frame(self, camera_id: str, frame: int, *, rgb: np.ndarray, mask: np.ndarray) -> None:
        """Write rgb uint8 [H, W, 3] and mask uint8 [H, W] of one camera at one frame."""
        cam = self.cameras.get(camera_id)
        if cam is None:
            raise KeyError(f"unknown camera {camera_id!r}; cameras: {list(self.cameras)}")
        first, last = self.camera_frames.get(camera_id, (0, self.n_frames - 1))
        if not first <= frame <= last:
            raise IndexError(f"frame {frame} of camera {camera_id!r} outside {first}..{last}")
        for what, img, shape in (
            ("rgb", rgb, (cam.height, cam.width, 3)),
            ("mask", mask, (cam.height, cam.width)),
        ):
            if np.shape(img) != shape:
                raise ValueError(
                    f"{what} of camera {camera_id!r} frame {frame} has shape "
                    f"{list(np.shape(img))}, expected {list(shape)}"
                )
        atomic_write_bytes(self.root / "rgb" / camera_id / frame_name(frame), encode_png(rgb))
        atomic_write_bytes(self.root / "masks" / camera_id / frame_name(frame), encode_png(mask))

    def write_gt(
        self,
        *,
        points: Mapping[int, np.ndarray | torch.Tensor] | None = None,
        params: Mapping[str, Any] | None = None,
        effects: Sequence[Mapping[str, Any]] | None = None,
    ) -> None:
        """gt/points.npz (object id -> [T, N_k, 3] m, stored float32), gt/params.json (the
        whole document: ``generator``, ``objects``) and gt/effects.json (list of effects)."""
        gt = self.root / "gt"
        if points is not None:
            arrays = {
                f"obj_{int(k)}": np.asarray(
                    v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else v, np.float32
                )
                for k, v in points.items()
            }
            buf = io.BytesIO()
            np.savez_compressed(buf, **arrays)
            atomic_write_bytes(gt / "points.npz", buf.getvalue())
        if params is not None:
            atomic_write_json(gt / "params.json", dict(params))
        if effects is not None:
            atomic_write_json(gt / "effects.json", {"effects": [dict(e) for e in effects]})

    def finish(self) -> Path:
        """Write scene.json (last, as the completion marker) and validate the layout."""
        atomic_write_json(self.root / "scene.json", self._scene_json)
        problems = check_layout(self.root)
        if problems:
            raise SceneFormatError([str(p) for p in problems])
        return self.root


def write_scene(
    out_dir: str | Path,
    *,
    name: str,
    fps: float,
    objects: Sequence[SceneObject],
    cameras: Sequence[Camera],
    rgb: Mapping[str, np.ndarray],
    masks: Mapping[str, np.ndarray],
    domain_lower: Sequence[float],
    domain_upper: Sequence[float],
    observed_frames: int | None = None,
    gravity: Sequence[float] = (0.0, 0.0, -9.8),
    ground_height: float | None = 0.0,
    gt_points: Mapping[int, np.ndarray | torch.Tensor] | None = None,
    gt_params: Mapping[str, Any] | None = None,
    gt_effects: Sequence[Mapping[str, Any]] | None = None,
) -> Path:
    """Write a whole scene at once. ``rgb``: camera id -> uint8 [T, H, W, 3];
    ``masks``: camera id -> uint8 [T, H, W]; ``observed_frames`` defaults to all T frames."""
    lengths = {len(v) for v in rgb.values()} | {len(v) for v in masks.values()}
    if len(lengths) != 1:
        raise ValueError(
            f"rgb and masks must hold the same number of frames, got {sorted(lengths)}"
        )
    n_frames = lengths.pop()
    writer = SceneWriter(
        out_dir,
        name=name,
        fps=fps,
        n_frames=n_frames,
        observed_frames=n_frames if observed_frames is None else observed_frames,
        objects=objects,
        cameras=cameras,
        domain_lower=domain_lower,
        domain_upper=domain_upper,
        gravity=gravity,
        ground_height=ground_height,
    )
    for cam in cameras:
        for t in range(n_frames):
            writer.write_frame(cam.id, t, rgb=rgb[cam.id][t], mask=masks[cam.id][t])
    writer.write_gt(points=gt_points, params=gt_params, effects=gt_effects)
    return writer.finish()
