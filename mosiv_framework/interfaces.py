"""The component kinds of MOSIV (docs/ARCHITECTURE.md, Interfaces), as small abstract base classes.

A plugin implements one of these and registers a factory for it through the registry. The core
only ever talks to these interfaces; it never imports a plugin.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.laws.base import ConstitutiveLaw, ParamSpec
from mosiv_framework.types import (
    Frames,
    GaussianFrames,
    GeometryFrames,
    ParticleSet,
    Reconstruction,
    SimulationParams,
    Trajectory,
    World,
)

if TYPE_CHECKING:  # the scene module is heavier (image I/O); only its types are needed here
    from mosiv_framework.bench_peer import PeerTiming, PeerWorkload
    from mosiv_framework.scene import Camera, Scene

__all__ = [
    "BenchPeer",
    "ConstitutiveLaw",
    "Lifter",
    "Loss",
    "PhysicsTerm",
    "Reconstructor",
    "RenderOutput",
    "Renderer",
    "SceneSource",
    "Segmenter",
    "Simulator",
]


class Reconstructor(ABC):
    """Multi-view video + masks -> per-object dynamic Gaussians over all frames."""

    @abstractmethod
    def fit(self, scene: Scene, *, run_dir: Path | None = None) -> Reconstruction: ...


class Lifter(ABC):
    """Reconstruction at frame 0 -> simulation particles tagged with object and material."""

    @abstractmethod
    def lift(self, reconstruction: Reconstruction, scene: Scene) -> ParticleSet: ...


class Simulator(ABC):
    """Particles + per-object parameters -> trajectory, differentiable in torch.

    ``rollout`` must be differentiable with respect to every tensor of ``params`` (through a
    torch.autograd.Function) and must raise ``SimulationDiverged`` instead of returning NaN.
    """

    #: material families this backend implements natively
    supported_laws: frozenset[str] = frozenset()
    #: physics-term names this backend implements
    supported_terms: frozenset[str] = frozenset()
    #: with the ``expression`` term: the features (mosiv_framework.expression.FEATURES) it
    #: applies; None means all of them
    expression_features: tuple[str, ...] | None = None

    @property
    def torch_device(self) -> torch.device:
        """Where rollouts compute. Callers that evaluate losses on many rollouts (identification)
        hand over particles on this device, so trajectories and losses stay there; the
        default is the CPU, GPU backends override it."""
        return torch.device("cpu")

    @property
    def deterministic(self) -> bool:
        """Whether two rollouts of the same inputs give bit-identical states and gradients.
        The pipeline then asks torch for its deterministic algorithms as well, so a whole
        identification repeats exactly. Backends that cannot promise it keep this default."""
        return False

    @abstractmethod
    def rollout(
        self,
        particles: ParticleSet,
        params: SimulationParams,
        *,
        world: World,
        frames: int,
    ) -> Trajectory:
        """Simulate ``frames`` video frames after frame 0; returns frames+1 states."""

    def rollout_batch(
        self,
        particles: ParticleSet,
        params_list: Sequence[SimulationParams],
        *,
        world: World,
        frames: int,
    ) -> list[Trajectory | SimulationDiverged]:
        """Roll out one scene under several parameter sets ("members"); one result per member.

        Member b's object families are those of ``params_list[b]`` (the particles' materials
        are replaced for it, as the law screening does), so members may try different laws.
        A member that diverges does not stop the others: its entry is the SimulationDiverged
        (object_id, frame, substep) instead of a Trajectory. Input errors (ConfigError) are
        raised for the whole call. Each Trajectory equals ``rollout`` of that member alone up
        to float32 round-off.

        This default loops over ``rollout`` (differentiable where ``rollout`` is); backends
        override it to advance all members in one simulation (docs/BENCHMARKS.md, Batched
        rollouts).
        """
        results: list[Trajectory | SimulationDiverged] = []
        for params in params_list:
            member = member_particles(particles, params)
            try:
                results.append(self.rollout(member, params, world=world, frames=frames))
            except SimulationDiverged as err:
                results.append(err)
        return results

    def evaluate_law(
        self,
        family: str,
        F: torch.Tensor,
        values: dict[str, torch.Tensor],
        *,
        plastic_J: torch.Tensor,
        velocity_gradient: torch.Tensor,
        dt: float,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """Run the backend's own implementation of a law on given inputs.

        Returns (Kirchhoff stress [N,3,3], return-mapped F [N,3,3], plastic_J [N]) so the parity
        suite can compare it with the core's torch reference; None if the backend cannot expose
        its law kernels (then the suite reports the law check as failed, not skipped).
        """
        return None

    def reset_peak_memory(self) -> None:
        """Start a new peak-memory measurement (backends that track their own memory)."""

    def peak_memory_bytes(self) -> int | None:
        """Peak device memory (bytes) used by the backend since the last reset, if known."""
        return None


def member_particles(particles: ParticleSet, params: SimulationParams) -> ParticleSet:
    """``particles`` with each object's family taken from ``params`` (objects that ``params``
    does not name keep theirs): the particle set one member of ``rollout_batch`` simulates."""
    materials = {
        k: params.objects[k].family if k in params.objects else family
        for k, family in particles.materials.items()
    }
    if materials == particles.materials:
        return particles
    return replace(particles, materials=materials)


class Loss(ABC):
    """Compares simulated and target geometry at observed frames; returns a scalar tensor."""

    @abstractmethod
    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> torch.Tensor: ...


@dataclass
class RenderOutput:
    """One camera's render: rgb [H, W, 3], alpha [H, W], depth [H, W] (m, along the optical
    axis; 0 where empty) and object_alpha [K, H, W] (one channel per object id 1..K)."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    object_alpha: torch.Tensor


class Renderer(ABC):
    """Gaussians (one frame) -> images through a camera; differentiable."""

    @abstractmethod
    def render(
        self, gaussians: GaussianFrames, camera: Camera, *, frame: int = 0, n_objects: int
    ) -> RenderOutput: ...


class PhysicsTerm(ABC):
    """An optional physical effect (drag, wind, ...) that simulators can switch on.

    The core holds its schema and a torch reference of the extra acceleration it adds
    (for body-force terms); backends implement it natively and say so in
    ``Simulator.supported_terms``.
    """

    name: str
    params: tuple[ParamSpec, ...]
    #: regimes where it acts: any of "free_flight", "object_contact", "ground_contact", "rest"
    regimes: frozenset[str]
    description: str = ""
    #: False: a parameter a recipe leaves out starts at its default. True: only the parameters
    #: given act (and only those are identified); for terms with many optional coefficients
    #: such as ``expression``
    sparse: bool = False

    def parameter_names_text(self) -> str:
        """The valid parameter names, as error messages list them."""
        return ", ".join(spec.name for spec in self.params)

    def reference_acceleration(
        self, velocity: torch.Tensor, values: dict[str, torch.Tensor]
    ) -> torch.Tensor | None:
        """Extra acceleration [N, 3] (m/s^2) for body-force terms, None for boundary terms."""
        return None


class SceneSource(ABC):
    """Writes scenes in the ``mosiv-scene/1`` format (generators, converters)."""

    @abstractmethod
    def generate(self, out_dir: Path) -> Path:
        """Write one scene into ``out_dir`` and return its path."""


class Segmenter(ABC):
    """Multi-view video -> per-camera instance masks with identities shared by all cameras.

    Object k in one camera's masks is object k in every other camera and every frame, so the
    masks can stand in for the ``masks/`` of a ``mosiv-scene/1`` scene (docs/SCENE_FORMAT.md).
    """

    @abstractmethod
    def segment(self, frames: Frames) -> dict[str, np.ndarray]:
        """Instance-id masks: camera id -> uint8 array [T, H, W] (0 background, k = object k)."""


class BenchPeer(ABC):
    """Another simulator timed on the bench's workload (``mosiv bench sim --peer NAME``).

    It maps the workload (bench_peer.PeerWorkload: particles, law, grid, substeps, frames,
    device) onto its own engine, times the forward frames after an untimed warm-up, and says
    what it did not time (gradients) in its PeerTiming.
    """

    @abstractmethod
    def measure(self, workload: PeerWorkload) -> PeerTiming: ...
