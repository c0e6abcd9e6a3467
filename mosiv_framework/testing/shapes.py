"""Backend-agnostic helpers that build small ParticleSets and SimulationParams for tests.

Particles sit on a regular lattice of the given spacing (m); each carries the lattice cell volume
spacing^3 (m^3) as its rest volume.
"""

from __future__ import annotations

import torch

from mosiv_framework.laws import get_law
from mosiv_framework.types import ObjectParams, ParticleSet, SimulationParams


def _lattice(lower, upper, spacing: float) -> torch.Tensor:
    axes = []
    for lo, hi in zip(lower, upper):
        n = max(1, round((hi - lo) / spacing))
        # cell centres of n cells filling [lo, hi]
        axes.append(lo + (torch.arange(n, dtype=torch.float32) + 0.5) * (hi - lo) / n)
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)


def block(
    lower, upper, *, spacing: float, object_id: int, material: str = "elastic"
) -> ParticleSet:
    """Particles filling the axis-aligned box [lower, upper] (m)."""
    x = _lattice(lower, upper, spacing)
    n = x.shape[0]
    volume = torch.prod(torch.tensor(upper) - torch.tensor(lower)).item() / n
    return ParticleSet(
        x,
        torch.full((n,), volume),
        torch.full((n,), object_id, dtype=torch.long),
        {object_id: material},
    )


def sphere(
    center, radius: float, *, spacing: float, object_id: int, material: str = "elastic"
) -> ParticleSet:
    """Particles of the lattice (spacing m) that fall inside the ball of ``radius`` (m)."""
    c = torch.tensor(center, dtype=torch.float32)
    x = _lattice([v - radius for v in center], [v + radius for v in center], spacing)
    cell = (2.0 * radius / max(1, round(2.0 * radius / spacing))) ** 3
    x = x[(x - c).norm(dim=1) <= radius]
    n = x.shape[0]
    return ParticleSet(
        x,
        torch.full((n,), cell),
        torch.full((n,), object_id, dtype=torch.long),
        {object_id: material},
    )


def combine(parts: list[ParticleSet], materials: dict[int, str] | None = None) -> ParticleSet:
    """One ParticleSet of several objects; ``materials`` (object id -> family) overrides the
    families the parts were made with."""
    mats: dict[int, str] = {}
    for p in parts:
        mats.update(p.materials)
    mats.update(materials or {})
    return ParticleSet(
        torch.cat([p.positions for p in parts]),
        torch.cat([p.volumes for p in parts]),
        torch.cat([p.object_ids for p in parts]),
        mats,
    )


def default_params(
    particles: ParticleSet,
    *,
    overrides: dict[int, dict[str, float]] | None = None,
    velocities: dict[int, tuple[float, float, float]] | None = None,
    ground_friction: float = 0.3,
    terms: dict[str, dict[str, float | list[float]]] | None = None,
    requires_grad: bool = False,
) -> SimulationParams:
    """SimulationParams from each law's ParamSpec defaults (plus rho and friction).

    overrides: object id -> {parameter: value}; velocities: object id -> initial velocity (m/s);
    terms: physics-term name -> {parameter: value}. With ``requires_grad`` every tensor is a leaf
    that collects gradients.
    """
    overrides = overrides or {}
    velocities = velocities or {}

    def leaf(v) -> torch.Tensor:
        return torch.tensor(v, dtype=torch.float32, requires_grad=requires_grad)

    objects = {}
    for k, family in sorted(particles.materials.items()):
        values = get_law(family).defaults()
        unknown = sorted(set(overrides.get(k, {})) - set(values))
        if unknown:
            raise ValueError(
                f"object {k} ({family}): unknown parameter(s) {unknown}; valid {sorted(values)}"
            )
        values.update(overrides.get(k, {}))
        objects[k] = ObjectParams(family, {n: leaf(v) for n, v in values.items()})
    v0 = {k: leaf(list(velocities.get(k, (0.0, 0.0, 0.0)))) for k in sorted(particles.materials)}
    term_tensors = {t: {n: leaf(v) for n, v in ps.items()} for t, ps in (terms or {}).items()}
    return SimulationParams(objects, v0, leaf(ground_friction), term_tensors)
