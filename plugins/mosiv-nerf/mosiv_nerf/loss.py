"""Loss ``nerf-photometric``: simulated particles rendered through the recorded cameras and
compared with the recorded images and masks, the CoupNeRF* objective of identification.

At every compared frame f the simulated positions of each object's particles (the order of
``GeometryFrames.points`` is the particle set's, object by object) are splatted and rendered
with the ``nerf-grid`` renderer, composited over the reconstruction's static backgrounds, and

    L = 1/(F C) sum_f sum_c [ rgb_weight mean_px |I - I_rec| + mask_weight sum_k mean_px
        |alpha_k - M_k| ]

(per-pixel L1 like the core's silhouette loss, so weights do not depend on resolution). The
loss is a registered Loss and reaches its inputs through its options: ``scene`` (the recorded
images and masks) and ``run_dir``, whose particles.pt (written by the lift stage before
identification) holds the particles' colours and densities. A recipe passes
``scene: ${scene.path}`` and ``run_dir: ${output.dir}``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Loss
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GeometryFrames
from mosiv_nerf.options import NerfPhotometricOptions
from mosiv_nerf.renderer import NerfGridRenderer

Tensor = torch.Tensor


def resized_camera(camera: Camera, size: int) -> Camera:
    """``camera`` with its image resampled to size x size pixels (intrinsics scaled)."""
    su, sv = size / camera.width, size / camera.height
    return Camera(
        camera.id,
        size,
        size,
        camera.fx * su,
        camera.fy * sv,
        camera.cx * su,
        camera.cy * sv,
        camera.world_to_camera,
    )


def area_resize(image: Tensor, size: int) -> Tensor:
    """[H, W, C] -> [size, size, C] by area averaging (as the silhouette path resamples)."""
    return F.interpolate(image.permute(2, 0, 1)[None], size=(size, size), mode="area")[0].permute(
        1, 2, 0
    )


class NerfPhotometricLoss(Loss):
    """Loss ``nerf-photometric``; keyword options are those of NerfPhotometricOptions."""

    def __init__(self, **options):
        self.options = NerfPhotometricOptions(**options)
        self.weight = self.options.weight
        self.renderer = NerfGridRenderer(**dict(self.options.renderer_options))
        self._scene = None
        self._appearance = None
        self._targets: dict[int, tuple] = {}
        self._generator = torch.Generator().manual_seed(self.options.seed)

    # ---------------------------------------------------------------------------- inputs
    def _load(self):
        if self._scene is not None:
            return
        from mosiv_framework.pipeline.rundir import RunDir
        from mosiv_framework.scene import read_scene

        self._scene = read_scene(self.options.scene)
        path = RunDir(self.options.run_dir).path("particles.pt")
        if not path.is_file():
            raise ConfigError(
                f"loss nerf-photometric: {path} is missing; it is written by the lift stage "
                "of the run in run_dir (set run_dir: ${output.dir})"
            )
        particles = torch.load(path, weights_only=False)
        appearance = particles.appearance
        if getattr(appearance, "binding", None) is None or not hasattr(
            appearance.binding, "colors"
        ):
            raise ConfigError(
                "loss nerf-photometric needs particles lifted by nerf-particles (colours and "
                "densities per particle)"
            )
        self._appearance = appearance
        self._object_ids = particles.object_ids
        size = self.options.size
        self._cameras = [resized_camera(c, size) if size else c for c in self._scene.cameras]

    def _target(self, frame: int, device) -> tuple[Tensor, Tensor, Tensor]:
        """(rgb [C, h, w, 3], masks [C, K, h, w], background [C, h, w, 3]) at ``frame``."""
        if frame not in self._targets:
            scene, size = self._scene, self.options.size
            # views not recorded are black and empty here, and never compared (_cameras_now)
            rgb = scene.load_rgb_tensor(frames=[frame], missing="zeros")[0]  # [C, H, W, 3]
            masks = scene.load_masks(frames=[frame], missing="zeros")[0]  # [C, K, H, W]
            bg = torch.stack([self._appearance.background[c.id].float() for c in scene.cameras])
            if size:
                rgb = torch.stack([area_resize(x, size) for x in rgb])
                bg = torch.stack([area_resize(x, size) for x in bg])
                masks = F.interpolate(masks, size=(size, size), mode="area")
            self._targets[frame] = (rgb, masks, bg)
        return tuple(t.to(device) for t in self._targets[frame])

    # ------------------------------------------------------------------------------ loss
    def _cameras_now(self, frame: int) -> list[int]:
        """Indices of the cameras compared at ``frame``: ``cameras_per_call`` of those that
        recorded it, drawn at random (all of them with 0)."""
        scene = self._scene
        recorded = [i for i, c in enumerate(scene.cameras) if scene.records(c.id, frame)]
        take = self.options.cameras_per_call
        if take == 0 or take >= len(recorded):
            return recorded
        pick = torch.randperm(len(recorded), generator=self._generator)[:take]
        return sorted(recorded[i] for i in pick.tolist())

    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> Tensor:
        self._load()
        objects = predicted.object_list
        binding = self._appearance.binding
        ids = self._object_ids
        order = torch.cat([torch.nonzero(ids == k).flatten() for k in objects])
        n_objects = int(max(self._scene.object_ids))
        total, count = None, 0
        for i, frame in enumerate(predicted.frames):
            positions = torch.cat([predicted.points[k][i] for k in objects])
            device = positions.device
            if positions.shape[0] != order.shape[0]:
                raise ValueError(
                    f"nerf-photometric: {positions.shape[0]} simulated points for "
                    f"{order.shape[0]} lifted particles"
                )
            frames = binding.gaussian_frames(torch.zeros_like(positions))
            frames.means = positions[None]
            frames.colors, frames.opacities = frames.colors[order], frames.opacities[order]
            frames.radii, frames.object_ids = frames.radii[:, order], frames.object_ids[order]
            rgb_rec, masks, bg = self._target(frame, device)
            for c in self._cameras_now(frame):
                out = self.renderer.render(
                    frames, self._cameras[c], n_objects=n_objects, background=bg[c]
                )
                value = self.options.rgb_weight * (out.rgb - rgb_rec[c]).abs().mean()
                alpha = out.object_alpha[[k - 1 for k in objects]]
                value = value + self.options.mask_weight * (
                    (alpha - masks[c][[k - 1 for k in objects]]).abs().mean(dim=(1, 2)).sum()
                )
                total = value if total is None else total + value
                count += 1
        return total / count
