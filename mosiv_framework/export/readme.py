"""The README.md of an export folder: what each file is and which tools open it."""

from __future__ import annotations

from pathlib import Path

from mosiv_framework.export.axes import DESCRIPTION
from mosiv_framework.export.meshes import SIGMA_PER_SPACING

_SECTIONS = {
    "particles": (
        "Simulated particles, one PLY per frame (binary little-endian). Vertex properties: "
        "`x y z` (m), `vx vy vz` (m/s, finite differences of the positions) and "
        "`object_id` (1..K). Opens in MeshLab, CloudCompare, Blender (PLY import) and Open3D "
        "(`o3d.io.read_point_cloud`; the extra properties with `plyfile`)."
    ),
    "gaussians": (
        "The lifted 3D Gaussians carried by the simulated particles, one PLY per frame, in the "
        "layout of the reference 3D Gaussian splatting code: `x y z nx ny nz f_dc_0..2 "
        "f_rest_0..44 opacity scale_0..2 rot_0..3`. `f_dc = (rgb - 0.5) / 0.28209479`, "
        "`f_rest` zero, `opacity` a logit, `scale_*` the log of the standard deviation (m), "
        "`rot` the identity quaternion (w x y z). Opens in SuperSplat "
        "(https://playcanvas.com/supersplat/editor) and the antimatter15 or gsplat.js web "
        "viewers; those made for COLMAP captures expect y down (`mosiv export --up=-y`). "
        "`object_ids.npy` gives each Gaussian's object."
    ),
    "reconstruction_gaussians": (
        "The dynamic Gaussians of the reconstruction (Stage I, fitted to the videos) at the "
        "frames it covers, in the same 3DGS layout as `gaussians/`."
    ),
    "meshes": (
        "Surface meshes, one glTF binary per frame with one mesh node `object_<k>` per object, "
        "y up as glTF requires (the file's (x, y, z) is MOSIV's (x, z, -y)) and coloured in "
        "linear RGB: "
        "the particles splatted into a density grid (each particle its rest volume, blurred by "
        f"{SIGMA_PER_SPACING} particle spacings) cut at density 0.5 by marching cubes. Opens in "
        "Blender (glTF import), https://gltf-viewer.donmccurdy.com, three.js and trimesh."
    ),
}


def readme_text(run, frames: list[int], counts: dict[str, int], out: Path, up: str = "z") -> str:
    """README.md for an export of ``run`` (RunData) over ``frames`` with ``counts`` files per
    folder written into ``out``, the PLY files' world with ``up`` up."""
    first, last = frames[0], frames[-1]
    lines = [
        "# MOSIV export",
        "",
        f"Run `{run.root}`: {len(run.object_list)} objects, {len(run.object_ids)} particles, "
        f"frames {first}..{last} of {run.n_frames} at {run.fps:g} fps. Files are named by "
        "frame number (`frame_0007` is frame 7, time 7 / fps). Units: metres, seconds. The PLY "
        f"files are {DESCRIPTION[up]} (`mosiv export --up`); the glTF meshes are y up.",
        "",
    ]
    for folder, text in _SECTIONS.items():
        if counts.get(folder):
            lines += [f"## `{folder}/` ({counts[folder]} frames)", "", text, ""]
    files = [
        ("identified.json", "the identified parameters per object (SI units), initial "
         "velocities and ground friction, as the run wrote them"),
        ("metrics_summary.json", "the scores of the run: Chamfer distance, EMD and image "
         "metrics over observed and future frames, and parameter errors when the scene had "
         "ground truth"),
    ]  # fmt: skip
    present = [(name, what) for name, what in files if (out / name).is_file()]
    if present:
        lines += ["## Parameters", ""]
        lines += [f"- `{name}`: {what}." for name, what in present]
        lines.append("")
    lines += [
        "`.mosiv-export.json` marks this folder as written by `mosiv export`; running the "
        "command again replaces the files above.",
        "",
    ]
    return "\n".join(lines)
