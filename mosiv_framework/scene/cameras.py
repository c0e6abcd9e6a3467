"""Pinhole cameras in the OpenCV convention of ``mosiv-scene/1`` (docs/SCENE_FORMAT.md,
cameras.json).

Camera frame: x right, y down, z forward. ``world_to_camera`` is a rigid 4x4 transform taking
world points (m) to camera coordinates. A camera point (x, y, z) lands on the continuous pixel
coordinate ``(u, v) = (fx * x / z + cx, fy * y / z + cy)``, in which the pixel in column ``i`` and
row ``j`` covers ``[i, i + 1) x [j, j + 1)`` and has its centre at ``(i + 0.5, j + 0.5)``. So a
principal point ``cx = width / 2`` sits exactly between the two middle columns of an even image.

All geometry is torch so renderers and losses can differentiate through it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

Tensor = torch.Tensor

#: default tolerance of the rigidity test: |R^T R - I| and |det R - 1| entries, last row entries
RIGID_ATOL = 1e-4


def rigidity_problems(matrix: object, *, atol: float = RIGID_ATOL) -> list[str]:
    """Reasons why ``matrix`` is not a rigid 4x4 transform (empty list when it is).

    Rigid means: shape 4x4, finite, rotation block orthonormal (``R^T R = I``) with ``det R = +1``
    and last row ``0 0 0 1``, each within ``atol``. Reflections (det -1) and scaled rotations are
    rejected because they would silently mirror or resize the reconstructed world.
    """
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an int beyond float range
        return ["is not a 4x4 array of numbers"]
    if m.shape != (4, 4):
        return [f"has shape {list(m.shape)}, expected 4x4"]
    if not np.all(np.isfinite(m)):
        return ["contains non-finite numbers"]
    reasons = []
    if np.max(np.abs(m[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > atol:
        reasons.append(f"last row is {m[3].tolist()}, expected [0, 0, 0, 1]")
    rot = m[:3, :3]
    ortho_err = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
    if ortho_err > atol:
        reasons.append(
            f"rotation block is not orthonormal (max |R^T R - I| = {ortho_err:.3g} > {atol:g})"
        )
    det = float(np.linalg.det(rot))
    if abs(det - 1.0) > atol and ortho_err <= atol:
        # orthonormal but det -1: a reflection, which no physical camera produces
        reasons.append(f"rotation block has determinant {det:.6g}, expected +1 (a reflection)")
    return reasons


def is_rigid(matrix: object, *, atol: float = RIGID_ATOL) -> bool:
    """True when ``matrix`` is a rigid 4x4 transform (see ``rigidity_problems``)."""
    return not rigidity_problems(matrix, atol=atol)


@dataclass(eq=False)  # tensors make field-wise == ambiguous; compare to_dict() instead
class Camera:
    """One pinhole camera: intrinsics in pixels, extrinsic ``world_to_camera`` (4x4, metres).

    ``world_to_camera`` is stored as a float64 CPU tensor; methods cast it to the dtype and
    device of their inputs so they stay differentiable with respect to those inputs.
    """

    id: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: Tensor

    def __post_init__(self) -> None:
        m = self.world_to_camera
        if isinstance(m, torch.Tensor):
            m = m.detach().to(device="cpu", dtype=torch.float64).clone()
        else:
            m = torch.as_tensor(np.asarray(m, dtype=np.float64))
        if m.shape != (4, 4):
            raise ValueError(
                f"camera {self.id!r}: world_to_camera must be 4x4, got {list(m.shape)}"
            )
        self.world_to_camera = m
        self.width, self.height = int(self.width), int(self.height)
        self.fx, self.fy, self.cx, self.cy = (
            float(self.fx),
            float(self.fy),
            float(self.cx),
            float(self.cy),
        )

    # ----------------------------------------------------------------------------- matrices
    @property
    def rotation(self) -> Tensor:
        """World-to-camera rotation R, [3, 3] float64."""
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> Tensor:
        """World-to-camera translation t (m), [3] float64: x_cam = R x_world + t."""
        return self.world_to_camera[:3, 3]

    @property
    def intrinsics(self) -> Tensor:
        """The 3x3 matrix K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels), float64."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=torch.float64,
        )

    @property
    def camera_to_world(self) -> Tensor:
        """Inverse of the rigid extrinsic, [4, 4] float64: [[R^T, -R^T t], [0, 1]]."""
        out = torch.eye(4, dtype=torch.float64)
        rt = self.rotation.T
        out[:3, :3] = rt
        out[:3, 3] = -rt @ self.translation
        return out

    @property
    def camera_center(self) -> Tensor:
        """Optical centre in world coordinates (m), [3] float64: c = -R^T t."""
        return -self.rotation.T @ self.translation

    @property
    def is_rigid(self) -> bool:
        return is_rigid(self.world_to_camera)

    # --------------------------------------------------------------------------- projection
    def world_to_camera_points(self, points: Tensor) -> Tensor:
        """World points [N, 3] (m) -> camera-frame points [N, 3] (m)."""
        r = self.rotation.to(points)
        t = self.translation.to(points)
        return points @ r.T + t

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """World points [N, 3] (m) -> pixel coordinates uv [N, 2] and depth z [N] (m).

        ``uv`` is continuous with pixel centres at integer + 0.5. Points with ``depth <= 0`` are
        behind the camera; their uv is meaningless (inf at depth 0) and callers mask them out.
        Differentiable with respect to ``points``.
        """
        pc = self.world_to_camera_points(points)
        z = pc[:, 2]
        u = self.fx * pc[:, 0] / z + self.cx
        v = self.fy * pc[:, 1] / z + self.cy
        return torch.stack([u, v], dim=-1), z

    def unproject(self, uv: Tensor, depth: Tensor) -> Tensor:
        """Pixel coordinates uv [N, 2] and depths z [N] (m, along the optical axis) -> world
        points [N, 3]; the inverse of ``project`` for points in front of the camera."""
        x = (uv[:, 0] - self.cx) / self.fx * depth
        y = (uv[:, 1] - self.cy) / self.fy * depth
        pc = torch.stack([x, y, depth], dim=-1)
        r = self.rotation.to(pc)
        t = self.translation.to(pc)
        return (pc - t) @ r  # R^T (x_cam - t), written row-wise

    def pixel_centers(self, *, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
        """[H, W, 2] continuous (u, v) of every pixel centre: (column + 0.5, row + 0.5)."""
        u = torch.arange(self.width, dtype=dtype, device=device) + 0.5
        v = torch.arange(self.height, dtype=dtype, device=device) + 0.5
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        return torch.stack([uu, vv], dim=-1)

    def rays(
        self,
        uv: Tensor | None = None,
        *,
        dtype: torch.dtype = torch.float32,
        device=None,
    ) -> tuple[Tensor, Tensor]:
        """World-frame rays through pixels: (origins, unit directions), each [..., 3].

        Without ``uv`` the rays pass through every pixel centre and have shape [H, W, 3];
        otherwise through the given continuous pixel coordinates ``uv`` [..., 2].
        """
        if uv is None:
            uv = self.pixel_centers(dtype=dtype, device=device)
        dtype, device = uv.dtype, uv.device
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
        d_world = d_cam @ self.rotation.to(dtype=dtype, device=device)  # R^T d, row-wise
        d_world = d_world / d_world.norm(dim=-1, keepdim=True)
        origins = self.camera_center.to(dtype=dtype, device=device).expand_as(d_world)
        return origins, d_world

    # ------------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        """The cameras.json entry of this camera (plain Python numbers)."""
        return {
            "id": self.id,
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "world_to_camera": self.world_to_camera.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict) -> Camera:
        """Build from a cameras.json entry; field validation lives in ``scene.check``."""
        missing = [
            k
            for k in ("id", "width", "height", "fx", "fy", "cx", "cy", "world_to_camera")
            if k not in data
        ]
        if missing:
            raise ValueError(f"camera entry {data.get('id', '?')!r} lacks field(s) {missing}")
        return cls(
            id=str(data["id"]),
            width=data["width"],
            height=data["height"],
            fx=data["fx"],
            fy=data["fy"],
            cx=data["cx"],
            cy=data["cy"],
            world_to_camera=data["world_to_camera"],
        )

    @classmethod
    def look_at(
        cls,
        eye: Sequence[float],
        target: Sequence[float],
        up: Sequence[float] = (0.0, 0.0, 1.0),
        *,
        id: str = "cam_00",
        width: int,
        height: int,
        fov_deg: float | None = None,
        fx: float | None = None,
        fy: float | None = None,
    ) -> Camera:
        """A camera at ``eye`` (m) looking at ``target`` (m), with world ``up`` pointing up in
        the image (towards smaller v).

        Give either ``fov_deg`` (horizontal field of view, degrees) or ``fx`` (pixels; ``fy``
        defaults to ``fx``). The principal point is the image centre (width/2, height/2).
        """
        eye_v = np.asarray(eye, dtype=np.float64)
        forward = np.asarray(target, dtype=np.float64) - eye_v
        if np.linalg.norm(forward) < 1e-12:
            raise ValueError("look_at: eye and target coincide; the viewing direction is undefined")
        forward /= np.linalg.norm(forward)
        # OpenCV axes: z forward, x right = forward x up, y down = forward x right
        right = np.cross(forward, np.asarray(up, dtype=np.float64))
        if np.linalg.norm(right) < 1e-9:
            raise ValueError(
                f"look_at: up {list(up)} is parallel to the viewing direction "
                f"{forward.tolist()}; choose another up vector"
            )
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rot = np.stack([right, down, forward])  # rows: camera axes in world coordinates
        m = np.eye(4)
        m[:3, :3] = rot
        m[:3, 3] = -rot @ eye_v
        if (fov_deg is None) == (fx is None):
            raise ValueError("look_at: give exactly one of fov_deg (degrees) or fx (pixels)")
        if fov_deg is not None:
            if not 0.0 < fov_deg < 180.0:
                raise ValueError(f"look_at: fov_deg={fov_deg} must lie in (0, 180) degrees")
            fx = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
        return cls(
            id=id,
            width=width,
            height=height,
            fx=fx,
            fy=fx if fy is None else fy,
            cx=width / 2.0,
            cy=height / 2.0,
            world_to_camera=m,
        )
