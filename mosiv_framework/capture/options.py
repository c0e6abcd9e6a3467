"""The choices the capture commands offer, in a module without heavy imports: the CLI builds
its parser from these (``mosiv --help`` must not load pycolmap, imageio or torch)."""

from __future__ import annotations

#: metres per unit of the unit names ``--units`` accepts (a positive number works too)
METRES_PER_UNIT: dict[str, float] = {
    "m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048,
}  # fmt: skip
#: the up axes ``--up`` accepts, by their index
AXES = {"x": 0, "y": 1, "z": 2}
#: COLMAP camera models the writer can write (each holds the lens it names: RADIAL needs fx = fy
#: and only k1, k2; OPENCV k1, k2, p1, p2; FULL_OPENCV the rational model; OPENCV_FISHEYE a
#: fisheye lens)
WRITE_MODELS = ("OPENCV", "RADIAL", "FULL_OPENCV", "OPENCV_FISHEYE")
#: H.264 constant rate factor: 0 lossless .. 51 worst; 18 is visually lossless for most content
DEFAULT_CRF = 18
