"""``mosiv export``: a finished run as files other tools open (PLY, glTF, JSON).

The export folder is marked by ``MARKER`` (written first): a folder holding it is a previous
export of this command and may be written again; any other non-empty folder is refused. Frame
files are named by the scene's frame number, ``frame_0007.ply`` for frame 7.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np

from mosiv_framework.errors import ConfigError, OutputError
from mosiv_framework.export.axes import ROTATIONS, rotate
from mosiv_framework.export.meshes import object_mesh, particle_spacing, write_frame_glb
from mosiv_framework.export.ply import write_gaussians_ply, write_particles_ply
from mosiv_framework.export.run_data import RunData, load_run

log = logging.getLogger(__name__)

MARKER = ".mosiv-export.json"
EXPORT_FORMAT = "mosiv-export/1"
#: what an export writes; a new export of the same folder removes these first
PRODUCTS = (
    "particles",
    "gaussians",
    "reconstruction_gaussians",
    "meshes",
    "identified.json",
    "metrics_summary.json",
    "README.md",
)


def select_frames(spec: str, run: RunData) -> list[int]:
    """Frame numbers of ``spec``: ``all``, ``observed`` (the scene's observed frames) or
    ``N..M`` (N to M, both included; a single ``N`` is one frame)."""
    n = run.n_frames
    if spec == "all":
        return list(range(n))
    if spec == "observed":
        if run.observed_frames is None:
            raise ConfigError(
                f"--frames observed: the run's observed frames are unknown ({run.scene_note})"
            )
        return list(range(min(run.observed_frames, n)))
    first, sep, last = spec.partition("..")
    try:
        lo, hi = int(first), int(last if sep else first)
    except ValueError:
        raise ConfigError(f"--frames {spec!r}: give all, observed or N..M (e.g. 0..9)") from None
    if lo > hi:
        raise ConfigError(f"--frames {spec!r}: the first frame must not come after the last")
    if not 0 <= lo <= hi < n:
        raise ConfigError(f"--frames {spec!r}: the rollout has frames 0..{n - 1}")
    return list(range(lo, hi + 1))


def prepare_out(out: Path) -> None:
    """Refuse ``out`` unless new, empty, or a previous export (whose products are removed)."""
    if out.exists() and not out.is_dir():
        raise OutputError(f"export folder {str(out)!r} is a file; give a folder")
    if out.is_dir() and any(out.iterdir()):
        if not (out / MARKER).is_file():
            raise OutputError(
                f"export folder {str(out)!r} is not empty and not a previous `mosiv export` "
                f"(no {MARKER}); give a new or empty folder (nothing is overwritten)"
            )
        for name in PRODUCTS:
            target = out / name
            if target.is_dir():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()
    out.mkdir(parents=True, exist_ok=True)


def _frame(name: str, t: int, suffix: str) -> str:
    return f"{name}/frame_{t:04d}{suffix}"


def export_particles(run: RunData, out: Path, frames: list[int], up: str = "z") -> int:
    velocities = run.velocities()
    for t in frames:
        write_particles_ply(
            out / _frame("particles", t, ".ply"),
            rotate(run.positions[t], up),
            rotate(velocities[t], up),
            run.object_ids,
        )
    return len(frames)


def _write_gaussian_frames(folder: Path, gaussians, frames: list[int], up: str) -> int:
    """Frames of a GaussianFrames (means [T, G, 3]) that it has, their means in the world with
    ``up`` up (isotropic: the rotation stays the identity); returns how many."""
    written = 0
    for t in frames:
        if t >= gaussians.n_frames:
            continue
        write_gaussians_ply(
            folder / f"frame_{t:04d}.ply",
            rotate(gaussians.means[t].detach().cpu().numpy(), up),
            gaussians.radii[t].detach().cpu().numpy(),
            gaussians.colors.detach().cpu().numpy(),
            gaussians.opacities.detach().cpu().numpy(),
        )
        written += 1
    if written:
        np.save(folder / "object_ids.npy", gaussians.object_ids.detach().cpu().numpy())
    return written


def export_gaussians(run: RunData, out: Path, frames: list[int], up: str = "z") -> dict[str, int]:
    """Simulated Gaussians (bound to the particles) and reconstructed ones, where the run has
    them; returns folder -> frames written."""
    import torch

    written = {}
    binding = getattr(getattr(run.particles, "appearance", None), "binding", None)
    if binding is not None:
        moved = binding.gaussian_frames(torch.from_numpy(run.positions))
        written["gaussians"] = _write_gaussian_frames(out / "gaussians", moved, frames, up)
    recon = getattr(run.reconstruction, "gaussians", None)
    if recon is not None:
        folder = out / "reconstruction_gaussians"
        written["reconstruction_gaussians"] = _write_gaussian_frames(folder, recon, frames, up)
    return written


def export_meshes(run: RunData, out: Path, frames: list[int]) -> int:
    from mosiv_framework.pipeline.video import PALETTE

    if run.volumes is not None:
        volumes = run.volumes
    else:  # no particles.pt: each particle a cube of the median nearest-neighbour distance
        from scipy.spatial import cKDTree

        d, _ = cKDTree(run.positions[0]).query(run.positions[0], k=2)
        volumes = np.full(len(run.object_ids), float(np.median(d[:, 1])) ** 3)
    objects = run.object_list
    spacing = {k: particle_spacing(volumes[run.object_ids == k]) for k in objects}
    colors = {k: PALETTE[(k - 1) % len(PALETTE)] for k in objects}
    for t in frames:
        meshes = {
            k: object_mesh(
                run.positions[t][run.object_ids == k],
                volumes[run.object_ids == k],
                spacing=spacing[k],
            )
            for k in objects
        }
        write_frame_glb(out / _frame("meshes", t, ".glb"), meshes, colors)
    return len(frames)


def metrics_summary(metrics: dict | None) -> dict | None:
    """The scores of metrics.json without the parameters (those are identified.json)."""
    if metrics is None:
        return None
    keep = ("format", "observed", "future", "reference", "param_error", "evaluation_note")
    return {k: metrics[k] for k in keep if k in metrics}


def export_run(
    run_dir: str | Path, out: str | Path | None = None, frames: str = "all", up: str = "z"
) -> Path:
    """Export the run at ``run_dir`` into ``out`` (default RUN/export); returns ``out``. The
    PLY files' world has ``up`` up (``axes.ROTATIONS``: z, MOSIV's own; y; -y, OpenCV's); the
    glTF meshes are y up whatever ``up`` is, as glTF requires."""
    if up not in ROTATIONS:
        raise ConfigError(f"--up {up!r}: choose one of {', '.join(ROTATIONS)}")
    from mosiv_framework.export.readme import readme_text

    run = load_run(run_dir)
    selected = select_frames(frames, run)
    out = Path(out) if out is not None else run.root / "export"
    prepare_out(out)
    marker = {"format": EXPORT_FORMAT, "run": str(run.root.resolve()), "frames": frames, "up": up}
    (out / MARKER).write_text(json.dumps(marker, indent=2) + "\n")
    counts = {"particles": export_particles(run, out, selected, up)}
    counts.update(export_gaussians(run, out, selected, up))
    counts["meshes"] = export_meshes(run, out, selected)
    for name, data in (
        ("identified.json", run.identified),
        ("metrics_summary.json", metrics_summary(run.metrics)),
    ):
        if data is not None:
            (out / name).write_text(json.dumps(data, indent=2) + "\n")
    (out / "README.md").write_text(readme_text(run, selected, counts, out, up))
    log.info("exported %d frames of %s into %s", len(selected), run.root, out)
    return out
