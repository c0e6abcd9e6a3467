"""Data types that cross component interfaces.

Every tensor is a ``torch.Tensor`` in SI units (metres, seconds, kilograms, pascals); object ids
are the integers 1..K of ``scene.json``. Backends convert to their own arrays internally.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:  # the scene module is heavier (image I/O); only its Camera type is needed here
    from mosiv_framework.scene import Camera

Tensor = torch.Tensor


@dataclass(frozen=True)
class World:
    """The physical setting a simulator runs in, read from ``scene.json``.

    ``domain_lower``/``domain_upper`` bound the simulation box (m); ``gravity`` is an
    acceleration (m/s^2); ``ground_height`` is the z of the table plane (m), or None for no
    ground; ``fps`` is the video frame rate (1/s): one simulated frame lasts ``1/fps`` seconds.
    """

    domain_lower: tuple[float, float, float]
    domain_upper: tuple[float, float, float]
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
    ground_height: float | None = 0.0
    fps: float = 24.0

    @property
    def frame_dt(self) -> float:
        """Duration of one video frame in seconds."""
        return 1.0 / self.fps

    @property
    def extent(self) -> float:
        """Largest side of the domain box (m); the scale that tolerances are stated against."""
        return max(u - lo for lo, u in zip(self.domain_lower, self.domain_upper))


@dataclass
class ParticleSet:
    """Simulation particles of all objects at rest (frame 0).

    positions: [N, 3] m; volumes: [N] m^3 (rest volume of each particle); object_ids: [N] int64
    in 1..K; materials maps object id -> material family name (``elastic``, ``sand``, ...).
    ``appearance`` optionally carries whatever a renderer needs to draw the particles (for
    example Gaussians bound to them); simulators ignore it.
    """

    positions: Tensor
    volumes: Tensor
    object_ids: Tensor
    materials: dict[int, str]
    appearance: object | None = None

    def __post_init__(self) -> None:
        n = self.positions.shape[0]
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise ValueError(
                f"ParticleSet.positions must be [N, 3], got {tuple(self.positions.shape)}"
            )
        if self.volumes.shape != (n,) or self.object_ids.shape != (n,):
            raise ValueError(
                f"ParticleSet.volumes and object_ids must be [N={n}], got "
                f"{tuple(self.volumes.shape)} and {tuple(self.object_ids.shape)}"
            )
        missing = sorted(set(self.object_ids.unique().tolist()) - set(self.materials))
        if missing:
            raise ValueError(f"ParticleSet.materials lacks a family for object ids {missing}")
        # a NaN position passes every "inside the domain" comparison, so it is caught here,
        # where it enters, rather than as a diverged rollout frames later
        bad = ~torch.isfinite(self.positions.detach()).all(dim=1)
        if bool(bad.any()):
            raise ValueError(
                f"ParticleSet.positions: {int(bad.sum())} of {n} particles have a non-finite "
                f"coordinate (first of object {int(self.object_ids[bad][0])}); positions must "
                "be finite (m)"
            )
        volumes = self.volumes.detach()
        bad = ~(torch.isfinite(volumes) & (volumes > 0))
        if bool(bad.any()):
            raise ValueError(
                f"ParticleSet.volumes: {int(bad.sum())} of {n} particles have a volume that is "
                f"not finite and > 0 (first of object {int(self.object_ids[bad][0])}: "
                f"{float(volumes[bad][0])}); rest volumes must be positive (m^3)"
            )

    @property
    def object_list(self) -> list[int]:
        """Object ids present, ascending."""
        return sorted(self.materials)

    def __len__(self) -> int:
        return self.positions.shape[0]

    def to(self, device: torch.device | str) -> ParticleSet:
        return replace(
            self,
            positions=self.positions.to(device),
            volumes=self.volumes.to(device),
            object_ids=self.object_ids.to(device),
        )


@dataclass
class ObjectParams:
    """One object's physical parameters: its material family and a value per parameter.

    ``values`` holds 0-d tensors keyed by the law's parameter names plus the common object
    parameters ``rho`` (kg/m^3) and ``friction`` (Coulomb coefficient, dimensionless).
    """

    family: str
    values: dict[str, Tensor]

    def __getitem__(self, name: str) -> Tensor:
        return self.values[name]


@dataclass
class SimulationParams:
    """Everything a rollout is differentiable with respect to.

    objects: object id -> ObjectParams; initial_velocity: object id -> [3] m/s;
    ground_friction: 0-d Coulomb coefficient of the table; terms: physics-term name -> its
    parameters (0-d or small tensors), for the optional PhysicsTerm effects switched on.
    """

    objects: dict[int, ObjectParams]
    initial_velocity: dict[int, Tensor]
    ground_friction: Tensor
    terms: dict[str, dict[str, Tensor]] = field(default_factory=dict)

    def named_tensors(self) -> Iterator[tuple[str, Tensor]]:
        """All tensors in a fixed order with dotted names (``obj1.E``, ``v0.obj2``, ...).

        The order is what a torch.autograd.Function flattens its inputs by, so it must be
        deterministic: objects ascending, parameter names sorted.
        """
        for k in sorted(self.objects):
            for name in sorted(self.objects[k].values):
                yield f"obj{k}.{name}", self.objects[k].values[name]
        for k in sorted(self.initial_velocity):
            yield f"v0.obj{k}", self.initial_velocity[k]
        yield "ground_friction", self.ground_friction
        for term in sorted(self.terms):
            for name in sorted(self.terms[term]):
                yield f"term.{term}.{name}", self.terms[term][name]

    def with_tensors(self, tensors: Mapping[str, Tensor]) -> SimulationParams:
        """A copy whose tensors are replaced by those named in ``tensors`` (others kept)."""
        objects = {
            k: ObjectParams(
                p.family, {n: tensors.get(f"obj{k}.{n}", v) for n, v in p.values.items()}
            )
            for k, p in self.objects.items()
        }
        v0 = {k: tensors.get(f"v0.obj{k}", v) for k, v in self.initial_velocity.items()}
        terms = {
            t: {n: tensors.get(f"term.{t}.{n}", v) for n, v in ps.items()}
            for t, ps in self.terms.items()
        }
        return SimulationParams(
            objects, v0, tensors.get("ground_friction", self.ground_friction), terms
        )

    def detached(self) -> SimulationParams:
        return self.with_tensors({n: t.detach() for n, t in self.named_tensors()})


@dataclass
class Trajectory:
    """A simulated (or recorded) motion: particle positions at every video frame.

    positions: [T, N, 3] m, frame 0 is the initial state; object_ids: [N]; fps: frames per
    second. ``contact`` optionally holds [T, K, K+1] booleans from the simulator (object-object
    contact in the first K columns, ground contact in the last), used to label regimes.
    """

    positions: Tensor
    object_ids: Tensor
    fps: float
    velocities: Tensor | None = None
    contact: Tensor | None = None

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    def object_positions(self, object_id: int) -> Tensor:
        """[T, N_k, 3] positions of one object's particles."""
        return self.positions[:, self.object_ids == object_id]

    def centroids(self) -> dict[int, Tensor]:
        """Object id -> [T, 3] mean particle position per frame."""
        return {
            int(k): self.object_positions(int(k)).mean(dim=1)
            for k in self.object_ids.unique().tolist()
        }


@dataclass
class GeometryFrames:
    """Per-object geometry at a list of frames, the common currency of losses and metrics.

    points: object id -> list (one per frame) of [N_k, 3] point sets in m;
    silhouettes: object id -> [F, C, H, W] alpha in [0, 1] over frames and cameras, or None.
    """

    frames: list[int]
    points: dict[int, list[Tensor]]
    silhouettes: dict[int, Tensor] | None = None

    @property
    def object_list(self) -> list[int]:
        return sorted(self.points)


@dataclass
class GaussianFrames:
    """Isotropic 3D Gaussians over time, each belonging to one object.

    means: [T, G, 3] m; radii: [T, G] m (standard deviation); colors: [G, 3] RGB in [0, 1], in
    the images' own (sRGB) values, blended as they are; opacities: [G] in [0, 1]; object_ids:
    [G] int64 in 1..K.
    """

    means: Tensor
    radii: Tensor
    colors: Tensor
    opacities: Tensor
    object_ids: Tensor

    @property
    def n_frames(self) -> int:
        return self.means.shape[0]


@dataclass
class Reconstruction:
    """What Stage I produces: object-aware dynamic Gaussians over all frames of a scene.

    ``gaussians`` may be None for reconstructors that only provide points (the oracle);
    ``points`` maps object id -> [T, N_k, 3] surface or volume samples per frame, the targets of
    the Chamfer loss. ``background`` optionally maps camera id -> [H, W, 3] static background.
    """

    points: dict[int, Tensor]
    gaussians: GaussianFrames | None = None
    background: dict[str, Tensor] | None = None
    extras: dict[str, object] = field(default_factory=dict)

    @property
    def object_list(self) -> list[int]:
        return sorted(self.points)


@dataclass
class Frames:
    """Multi-view video handed to a Segmenter (real recordings or rendered scenes).

    rgb: camera id -> uint8 [T, H, W, 3], all cameras with the same T; cameras: camera id ->
    ``Camera`` (world-to-camera, metres, z up) for the same ids; n_objects: how many objects the
    scene holds, if known; domain: ((x0, y0, z0), (x1, y1, z1)) box (m) that holds the objects
    over the whole clip, if known (segmenters that carve a visual hull need it); backgrounds:
    camera id -> uint8 [H, W, 3] image of the empty scene (a rig's clean plate), if recorded;
    camera_frames: camera id -> (first, last) frames a camera recorded where it did not record
    them all (a late start): its other frames hold no image (zeros) and a segmenter leaves
    them out (``recorded``).
    """

    rgb: dict[str, np.ndarray]
    cameras: dict[str, Camera]
    n_objects: int | None = None
    domain: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    backgrounds: dict[str, np.ndarray] | None = None
    camera_frames: dict[str, tuple[int, int]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if set(self.rgb) != set(self.cameras):
            raise ValueError(
                f"frames and cameras name different cameras: {sorted(self.rgb)} vs "
                f"{sorted(self.cameras)}"
            )
        lengths = {cam: np.shape(video)[0] for cam, video in self.rgb.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"cameras have different frame counts: {lengths}")
        for cam, video in self.rgb.items():
            if np.ndim(video) != 4 or np.shape(video)[-1] != 3:
                raise ValueError(
                    f"camera {cam!r}: rgb must be [T, H, W, 3], got {list(np.shape(video))}"
                )
        for cam, plate in (self.backgrounds or {}).items():
            if cam not in self.rgb or np.shape(plate) != np.shape(self.rgb[cam])[1:]:
                raise ValueError(
                    f"background of camera {cam!r}: {list(np.shape(plate))} does not match "
                    f"its frames ({list(np.shape(self.rgb.get(cam, [])))[1:]})"
                )

    @property
    def camera_ids(self) -> list[str]:
        return sorted(self.rgb)

    def recorded(self, camera_id: str) -> range:
        """The frames camera ``camera_id`` recorded."""
        first, last = self.camera_frames.get(camera_id, (0, self.n_frames - 1))
        return range(first, last + 1)

    @property
    def n_frames(self) -> int:
        return int(next(iter(self.rgb.values())).shape[0]) if self.rgb else 0
