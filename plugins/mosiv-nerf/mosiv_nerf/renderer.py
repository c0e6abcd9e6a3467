"""Renderer ``nerf-grid``: simulated particles back to a voxel field, then volume rendering.

This is how the CoupNeRF* baseline sees a later frame: every particle carries the density
sigma_p and colour c_p the frame-0 field had where it was sampled. Its density, per object, and
its density-weighted colour are splatted onto a grid around the particles (``mosiv_nerf.splat``,
the MPM's quadratic B-spline by default), with v_p = sigma_p V_p / cell^3 so that a block of
particles on a lattice of the grid's spacing reproduces its density. The node colour is
sum sigma c / sum sigma. The grid is then rendered like the frame-0 field (``mosiv_nerf.volume``):
differentiable with respect to the particle positions, which is what lets photometric and
mask losses reach the physical parameters through the simulator.

Particles arrive as GaussianFrames (the Renderer interface): ``means`` the positions,
``radii`` half the particle spacing (V_p = (2 r)^3), ``colors`` the colours (sRGB as the field
fitted them), ``opacities`` o_p = 1 - exp(-sigma_p 2 r), the opacity of one particle spacing
(so sigma_p = -log(1 - o_p) / (2 r)).
"""

from __future__ import annotations

import torch

from mosiv_framework.interfaces import Renderer, RenderOutput
from mosiv_framework.types import GaussianFrames
from mosiv_nerf.field import render_image
from mosiv_nerf.options import NerfGridOptions
from mosiv_nerf.splat import kernel_reach, splat
from mosiv_nerf.volume import GridBox, trilinear

Tensor = torch.Tensor

#: most opacity one particle may have: keeps sigma = -log(1 - o) finite
MAX_OPACITY = 1.0 - 1e-6


def particle_density(opacities: Tensor, radii: Tensor) -> Tensor:
    """sigma_p (1/m) from a particle's opacity over one spacing 2 r."""
    return -torch.log1p(-opacities.clamp(0.0, MAX_OPACITY)) / (2.0 * radii)


def particle_opacity(sigma: Tensor, spacing: float | Tensor) -> Tensor:
    """The inverse of ``particle_density``: opacity 1 - exp(-sigma spacing)."""
    return 1.0 - torch.exp(-sigma * spacing)


class ParticleGrid:
    """Particles splatted onto a grid: a sampler for ``mosiv_nerf.volume.march``."""

    def __init__(self, box: GridBox, nodes: Tensor, n_objects: int):
        self.box, self.nodes, self.n_objects = box, nodes, n_objects

    def sample(self, points: Tensor) -> tuple[Tensor, Tensor]:
        values = trilinear(self.nodes, self.box, points)
        sigma_k = values[: self.n_objects].clamp(min=0.0)
        sigma = sigma_k.sum(dim=0)
        rgb = (values[self.n_objects :] / sigma.clamp(min=1e-6)[None]).movedim(0, -1)
        return sigma_k, rgb.clamp(0.0, 1.0)


def particle_grid(
    positions: Tensor,
    sigma: Tensor,
    colors: Tensor,
    object_ids: Tensor,
    *,
    n_objects: int,
    cell: float,
    volumes: Tensor,
    kernel: str = "bspline",
) -> ParticleGrid:
    """P2G of particles (positions [N, 3] m, sigma [N] 1/m, colors [N, 3], object_ids [N] in
    1..n_objects, volumes [N] m^3) onto a grid of spacing ``cell`` around them."""
    with torch.no_grad():
        # the box follows the particles but snaps to a world-fixed lattice of spacing cell, so
        # it is piecewise constant in the positions and their gradient is the whole story
        lower = torch.floor(positions.min(dim=0).values / cell) * cell
        upper = torch.ceil(positions.max(dim=0).values / cell) * cell
    box = GridBox.around(lower.detach(), upper.detach(), cell, margin=kernel_reach(kernel) + 1)
    weight = sigma * volumes / cell**3  # [N]
    onehot = torch.nn.functional.one_hot(object_ids.long() - 1, n_objects).to(positions)
    values = torch.cat([onehot * weight[:, None], colors * weight[:, None]], dim=1)
    return ParticleGrid(box, splat(positions, values, box, kernel=kernel), n_objects)


class NerfGridRenderer(Renderer):
    """Renderer ``nerf-grid``; keyword options are those of NerfGridOptions."""

    def __init__(self, **options):
        self.options = NerfGridOptions(**options)

    def grid(self, gaussians: GaussianFrames, frame: int, n_objects: int) -> ParticleGrid:
        """The splatted grid of ``gaussians`` at ``frame``."""
        radii = gaussians.radii[frame]
        cell = self.options.cell or float(2.0 * radii.detach().median())
        return particle_grid(
            gaussians.means[frame],
            particle_density(gaussians.opacities, radii),
            gaussians.colors,
            gaussians.object_ids,
            n_objects=n_objects,
            cell=cell,
            volumes=(2.0 * radii) ** 3,
            kernel=self.options.kernel,
        )

    def render(
        self,
        gaussians: GaussianFrames,
        camera,
        *,
        frame: int = 0,
        n_objects: int,
        background: Tensor | None = None,
    ) -> RenderOutput:
        grid = self.grid(gaussians, frame, n_objects)
        return render_image(
            grid.sample,
            grid.box,
            camera,
            n_objects=n_objects,
            step=self.options.step_ratio * grid.box.cell,
            background=background,
            max_samples=self.options.max_samples,
        )
