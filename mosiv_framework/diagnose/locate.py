"""Step 1 of a diagnosis: where do the fitted model and the recording disagree?

For every object and frame it measures the residual between the identified model's rollout and
the run's target points (Chamfer, centroid path, silhouettes per view where the scene has
masks), labels each frame's regime from the simulated state (free flight, object-object
contact, ground contact, rest), estimates the noise floor from the data, finds the onset of the
unexplained error by change-point detection and splits the residual by direction (along the
velocity, vertical, tangential, internal deformation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from mosiv_framework.diagnose.changepoint import hinge_change_point
from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.types import Trajectory

REGIMES = ("free_flight", "object_contact", "ground_contact", "rest")
#: a residual counts as significant when its RMS exceeds this many noise floors (an effect
#: worth looking for is at least 3x the noise floor; docs/DIAGNOSIS.md)
SIGNIFICANCE = 3.0


# --------------------------------------------------------------------------------------------
# regimes


def particle_spacing(volumes: torch.Tensor) -> float:
    """Typical particle spacing (m): the cube root of the median rest volume."""
    return float(volumes.median()) ** (1.0 / 3.0)


def label_regimes(
    positions: torch.Tensor,
    object_ids: torch.Tensor,
    *,
    fps: float,
    ground_height: float | None,
    contact_distance: float,
    rest_speed: float,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> dict[int, list[str]]:
    """Object id -> one regime per frame from simulated positions [T, N, 3] (m).

    ground_contact: the object's lowest particle is within ``contact_distance`` of the ground;
    object_contact: a particle of another object lies within ``contact_distance``, or the two
    bodies met unseen since the previous frame: apart there, but by less than the distance their
    centroids had closed over the interval before it (a 1-2 m/s impact of soft bodies can begin
    and end between two frames, and its effect first shows on the frame after it); rest: ground
    contact and a centroid speed (central difference) below ``rest_speed`` (m/s); otherwise free
    flight. Ground takes precedence over object contact (a resting stack is on the table).
    """
    pos = positions.detach().cpu().double().numpy()
    ids = object_ids.cpu().numpy()
    up_v = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    objects = sorted(int(k) for k in np.unique(ids))
    n_frames = pos.shape[0]
    centroids = {k: pos[:, ids == k].mean(axis=1) for k in objects}
    labels: dict[int, list[str]] = {k: [] for k in objects}

    gaps = []  # per frame: [k, j] smallest particle distance between objects k and j (m)
    for t in range(n_frames):
        trees = {k: cKDTree(pos[t, ids == k]) for k in objects}
        gap = {}
        for k in objects:
            for j in objects:
                if j != k:
                    gap[k, j] = float(trees[j].query(pos[t, ids == k], k=1)[0].min())
        gaps.append(gap)

    def met_unseen(k: int, j: int, t: int) -> bool:
        if t < 2 or gaps[t - 1][k, j] < contact_distance:
            return False  # seen in contact at t - 1 (or too early to tell)
        d = [float(np.linalg.norm(centroids[k][s] - centroids[j][s])) for s in (t - 2, t - 1)]
        return gaps[t - 1][k, j] < contact_distance + max(0.0, d[0] - d[1])

    for t in range(n_frames):
        for k in objects:
            pts = pos[t, ids == k]
            on_ground = False
            if ground_height is not None:
                on_ground = float((pts @ up_v).min() - ground_height) < contact_distance
            touching = any(
                gaps[t][k, j] < contact_distance or met_unseen(k, j, t) for j in objects if j != k
            )
            lo, hi = max(0, t - 1), min(n_frames - 1, t + 1)
            speed = np.linalg.norm(centroids[k][hi] - centroids[k][lo]) * fps / max(1, hi - lo)
            if on_ground and speed < rest_speed:
                labels[k].append("rest")
            elif on_ground:
                labels[k].append("ground_contact")
            elif touching:
                labels[k].append("object_contact")
            else:
                labels[k].append("free_flight")
    return labels


# --------------------------------------------------------------------------------------------
# residual direction


def decompose_direction(
    residual: np.ndarray, velocity: np.ndarray, *, up: np.ndarray, min_speed: float
) -> dict[str, float]:
    """Squared residual (m^2, summed over frames) split into orthogonal parts.

    along_velocity: projection on the simulated velocity direction (frames moving faster than
    ``min_speed``); vertical: the rest's component along ``up``; tangential: what remains.
    """
    up = up / np.linalg.norm(up)
    parts = {"along_velocity": 0.0, "vertical": 0.0, "tangential": 0.0}
    for r, v in zip(residual, velocity):
        speed = np.linalg.norm(v)
        along = (r @ v / speed**2) * v if speed > min_speed else np.zeros(3)
        rest = r - along
        vertical = (rest @ up) * up
        parts["along_velocity"] += float(along @ along)
        parts["vertical"] += float(vertical @ vertical)
        parts["tangential"] += float((rest - vertical) @ (rest - vertical))
    return parts


# --------------------------------------------------------------------------------------------
# residuals


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer of squared distances (m^2), the run's loss without subsampling."""
    da, _ = cKDTree(b).query(a, k=1)
    db, _ = cKDTree(a).query(b, k=1)
    return float((da**2).mean() + (db**2).mean())


@dataclass
class ObjectResiduals:
    """Per-frame residuals of one object (frames 0..T-1).

    chamfer, internal: m^2 (internal = Chamfer after centring both point sets: shape error);
    centroid: [T, 3] m, target centroid minus simulated centroid, relative to frame 0 (the
    lifted particles' centroid may differ from the targets' by a constant offset).
    """

    chamfer: np.ndarray
    internal: np.ndarray
    centroid: np.ndarray
    sim_velocity: np.ndarray
    target_centroid: np.ndarray
    sim_centroid: np.ndarray


def object_residuals(ctx: RunContext, traj: Trajectory, frames: int) -> dict[int, ObjectResiduals]:
    """Residuals of ``traj`` against the run's targets over frames 0..frames-1."""
    out = {}
    for k in ctx.object_ids:
        sim = traj.object_positions(k)[:frames].detach().cpu().double().numpy()
        tgt = ctx.targets[k][:frames].double().numpy()
        c_sim, c_tgt = sim.mean(axis=1), tgt.mean(axis=1)
        chamfer = np.array([_chamfer(sim[t], tgt[t]) for t in range(frames)])
        internal = np.array([_chamfer(sim[t] - c_sim[t], tgt[t] - c_tgt[t]) for t in range(frames)])
        r = (c_tgt - c_sim) - (c_tgt[0] - c_sim[0])
        if traj.velocities is not None:
            vel = traj.velocities[:frames, traj.object_ids == k].detach().cpu().double()
            v = vel.mean(dim=1).numpy()
        else:
            v = np.gradient(c_sim, axis=0) * ctx.fps
        out[k] = ObjectResiduals(chamfer, internal, r, v, c_tgt, c_sim)
    return out


def silhouette_residuals(
    ctx: RunContext, traj: Trajectory, frames: int, *, max_views: int = 4
) -> dict | None:
    """Per object, frame and view: 1 - IoU between the scene mask and the projected rollout.

    The same rasterisation applied to the target points gives each view's floor (what the
    point-to-mask comparison scores even for a perfect model). None if the scene has no masks.
    """
    window = range(frames)  # views of cameras that recorded the whole window
    cams = [c for c in ctx.scene.camera_ids if all(ctx.scene.records(c, t) for t in window)]
    cams = cams[:max_views]
    try:
        masks = ctx.scene.load_mask_ids(frames=range(frames), cameras=cams).numpy()
    except Exception:  # masks are optional for a diagnosis: point residuals suffice
        return None
    spacing = particle_spacing(ctx.particles.volumes)
    residual = {k: np.zeros((frames, len(cams))) for k in ctx.object_ids}
    floor = {k: np.zeros((frames, len(cams))) for k in ctx.object_ids}
    for c, cam_id in enumerate(cams):
        cam = ctx.scene.camera(cam_id)
        for k in ctx.object_ids:
            sim = traj.object_positions(k)[:frames].detach().cpu().double()
            for t in range(frames):
                truth = masks[t, c] == k
                pred = _raster(cam, sim[t], spacing)
                target = _raster(cam, ctx.targets[k][t].double(), spacing)
                residual[k][t, c] = 1.0 - _iou(pred, truth)
                floor[k][t, c] = 1.0 - _iou(target, truth)
    return {"views": list(cams), "residual": residual, "floor": floor}


def _raster(cam, points: torch.Tensor, spacing: float) -> np.ndarray:
    """Boolean [H, W] footprint of points, each a disc of its projected half-spacing."""
    uv, z = cam.project(points)
    keep = z > 0
    uv, z = uv[keep].numpy(), z[keep].numpy()
    image = np.zeros((cam.height, cam.width), dtype=bool)
    radius = np.maximum(1, np.ceil(0.75 * spacing * cam.fx / np.maximum(z, 1e-6))).astype(int)
    for (u, v), r in zip(uv, radius):
        u0, v0 = int(u), int(v)
        image[max(0, v0 - r + 1) : max(0, v0 + r), max(0, u0 - r + 1) : max(0, u0 + r)] = True
    return image


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


# --------------------------------------------------------------------------------------------
# the location


@dataclass
class Location:
    """Where the fitted model misses; ``summary`` is the JSON-ready digest of the rest."""

    residuals: dict[int, ObjectResiduals]
    regimes: dict[int, list[str]]
    noise_floor: dict[int, float]
    onset: dict[int, int]
    significant: bool
    flagged_object: int
    flagged_regimes: list[str]
    silhouettes: dict | None
    summary: dict = field(default_factory=dict)


def difference_variance_factor(order: int) -> int:
    """Variance of the ``order``-th difference of unit white noise: the sum of the squared
    binomial coefficients, C(2k, k) (second differences: 6, third differences: 20)."""
    return math.comb(2 * order, order)


def difference_noise_std(path: np.ndarray, *, order: int = 3) -> float:
    """3D noise std (m) of a path [T, 3] of white noise plus a smooth signal.

    The ``order``-th difference removes any polynomial of lower degree (third differences of a
    ballistic path, constant acceleration, are zero), so what remains is the noise, amplified
    by sqrt(C(2k, k)). Per axis the std is read robustly as median |difference| / 0.6745 (a
    kink at a contact spoils a few differences, not the median); the axes add in quadrature,
    giving the RMS length of the per-frame noise vector. 0 if the path has <= ``order`` frames.
    """
    if path.shape[0] <= order:
        return 0.0
    diff = np.diff(path, n=order, axis=0)
    per_axis = (
        np.median(np.abs(diff), axis=0) / 0.6745 / math.sqrt(difference_variance_factor(order))
    )
    return float(np.sqrt((per_axis**2).sum()))


def points_are_tracked(points: np.ndarray) -> bool:
    """Whether index i of a [T, N, 3] point sequence is the same material point every frame.

    Tracked points move with their neighbours: after removing the centroid motion, a point's
    frame-to-frame displacement is small against the gap between neighbouring points. Points
    drawn afresh each frame land anywhere on the body, so the same index jumps by about the
    body's size. The test: the median displacement relative to the centroid's is below the
    median nearest-neighbour distance. A sequence with one frame counts as tracked (there is
    no second sample to differ).
    """
    if points.shape[0] < 2:
        return True
    step = np.diff(points, axis=0)
    relative = step - step.mean(axis=1, keepdims=True)
    jump = float(np.median(np.linalg.norm(relative, axis=-1)))
    gap, _ = cKDTree(points[0]).query(points[0], k=2)
    return jump < float(np.median(gap[:, 1]))


@dataclass(frozen=True)
class NoiseEstimate:
    """One object's noise floor (m): the RMS length of the noise in its centroid residual.

    jitter: per-frame noise std from third differences of the residual path; sampling: the
    per-frame std of the target centroid from drawing N of the body's points (0 when the points
    are tracked: the same points every frame give the same error every frame, which removing
    the frame-0 offset cancels); floor: sqrt(2) x the larger of the two, because the residual is
    relative to frame 0 and so carries frame 0's noise as well as its own.
    """

    floor: float
    jitter: float
    sampling: float
    tracked: bool

    def to_json(self) -> dict:
        return {
            "noise_floor_m": self.floor,
            "jitter_m": self.jitter,
            "sampling_m": self.sampling,
            "targets_tracked": self.tracked,
        }


def estimate_noise(centroid_residual: np.ndarray, target_points: np.ndarray) -> NoiseEstimate:
    """Noise floor of one object's centroid residual [T, 3] (m) from its targets [T, N, 3].

    The jitter estimate already contains resampling noise (it is white across frames), so the
    two parts are not added; the sampling std, known in closed form (point spread / sqrt(N)),
    is a lower bound on the white noise when points are resampled, which steadies the jitter
    estimate on short windows. A floor of float32 rounding of the coordinates keeps the
    signal-to-noise ratio finite on noise-free data.
    """
    tracked = points_are_tracked(target_points)
    sampling = 0.0
    if not tracked:
        spread = np.sqrt(target_points.var(axis=1).sum(axis=-1))  # per frame, m
        sampling = float(spread.mean() / math.sqrt(target_points.shape[1]))
    jitter = difference_noise_std(centroid_residual, order=3)
    rounding = float(np.finfo(np.float32).eps * np.abs(target_points).max())
    floor = math.sqrt(2.0) * max(jitter, sampling, rounding)
    return NoiseEstimate(floor, jitter, sampling, tracked)


def locate(
    ctx: RunContext, *, frames: int | None = None, traj: Trajectory | None = None
) -> Location:
    """Residuals, regimes, noise floor, onset and direction over the first ``frames`` frames
    (default: the observed window, the frames the run fitted)."""
    frames = ctx.observed_frames if frames is None else frames
    traj = ctx.identified_rollout() if traj is None else traj
    residuals = object_residuals(ctx, traj, frames)
    spacing = particle_spacing(ctx.particles.volumes)
    gravity = np.asarray(ctx.world.gravity, dtype=np.float64)
    up = (
        -gravity / np.linalg.norm(gravity) if np.linalg.norm(gravity) > 0 else np.array([0, 0, 1.0])
    )
    regimes = _regimes(ctx, traj, frames, spacing=spacing, up=up)
    floors, onsets, per_object = {}, {}, {}
    for k, res in residuals.items():
        targets = ctx.targets[k][:frames].double().numpy()
        per_object[str(k)], floors[k], onsets[k] = _object_summary(
            res, targets, regimes[k], frames=frames, min_speed=0.5 * spacing * ctx.fps, up=up
        )
    snr = {k: per_object[str(k)]["signal_to_noise"] for k in residuals}
    flagged = max(snr, key=snr.get)
    significant = snr[flagged] > SIGNIFICANCE
    # an effect acts in the interval before the frame where its residual first shows, so the
    # regime of the frame before an onset counts too (an impact's friction or dent shows on the
    # frames after it, when the bodies fly apart)
    flagged_regimes = sorted(
        {r for k in residuals if snr[k] > SIGNIFICANCE for r in regimes[k][max(onsets[k] - 1, 0) :]}
    ) or sorted(set(regimes[flagged][max(onsets[flagged] - 1, 0) :]))
    silhouettes = silhouette_residuals(ctx, traj, frames)
    summary = {
        "frames": frames,
        "significant": significant,
        "significance_threshold": SIGNIFICANCE,
        "flagged_object": flagged,
        "flagged_regimes": flagged_regimes,
        "objects": per_object,
    }
    if silhouettes is not None:
        summary["silhouette"] = _silhouette_summary(silhouettes, residuals)
    return Location(
        residuals,
        regimes,
        floors,
        onsets,
        significant,
        flagged,
        flagged_regimes,
        silhouettes,
        summary,
    )


def _regimes(
    ctx: RunContext, traj: Trajectory, frames: int, *, spacing: float, up: np.ndarray
) -> dict[int, list[str]]:
    """``label_regimes`` of the rollout's first ``frames`` frames, with contact closer than the
    larger of 1.5 particle spacings and a grid cell, and rest below half a spacing per frame."""
    grid = ctx.recipe.simulator.get("grid", None)
    dx = ctx.world.extent / float(grid) if grid else spacing
    return label_regimes(
        traj.positions[:frames],
        traj.object_ids,
        fps=ctx.fps,
        ground_height=ctx.world.ground_height,
        contact_distance=max(1.5 * spacing, dx),
        rest_speed=0.5 * spacing * ctx.fps,
        up=tuple(up),
    )


def _object_summary(
    res: ObjectResiduals,
    targets: np.ndarray,
    regimes: list[str],
    *,
    frames: int,
    min_speed: float,
    up: np.ndarray,
) -> tuple[dict, float, int]:
    """(the location summary's entry for one object, its noise floor, its onset frame): the
    residual against the noise floor, the change point where it begins, the regimes after it
    and the residual's split by direction."""
    noise = estimate_noise(res.centroid, targets)
    magnitude = np.linalg.norm(res.centroid, axis=1)
    onset = hinge_change_point(magnitude)[0]
    window = list(range(onset, frames))
    rms = float(np.sqrt((magnitude[1:] ** 2).mean())) if frames > 1 else 0.0
    directions = decompose_direction(
        res.centroid[window], res.sim_velocity[window], up=up, min_speed=min_speed
    )
    directions["internal"] = float(np.clip(res.internal[window] - res.internal[0], 0.0, None).sum())
    total = sum(directions.values()) or 1.0
    counts = {r: regimes[onset:].count(r) for r in REGIMES}
    entry = {
        "centroid_rms_m": rms,
        **noise.to_json(),
        "signal_to_noise": rms / max(noise.floor, 1e-12),
        "chamfer_m2": res.chamfer.tolist(),
        "centroid_residual_m": res.centroid.tolist(),
        "onset_frame": onset,
        "window": [onset, frames - 1],
        "regimes": regimes,
        "window_regimes": {r: n for r, n in counts.items() if n},
        "direction_fraction": {d: e / total for d, e in directions.items()},
    }
    return entry, noise.floor, onset


def _silhouette_summary(silhouettes: dict, residuals: dict) -> dict:
    """The silhouettes' excess over their floor per view, and its spread across views."""
    return {
        "views": silhouettes["views"],
        "per_view_excess": {
            str(k): (silhouettes["residual"][k] - silhouettes["floor"][k]).mean(0).tolist()
            for k in residuals
        },
        "spread_across_views": {
            str(k): float((silhouettes["residual"][k] - silhouettes["floor"][k]).std(1).mean())
            for k in residuals
        },
    }


def plot_location(location: Location, *, fps: float, path) -> None:
    """Centroid residual magnitude per object over time, regimes shaded, onset and floor marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {
        "free_flight": "white",
        "object_contact": "#fde0c5",
        "ground_contact": "#d6e6f4",
        "rest": "#e0e0e0",
    }
    objects = sorted(location.residuals)
    fig, axes = plt.subplots(len(objects), 2, figsize=(11, 2.8 * len(objects)), squeeze=False)
    for row, k in enumerate(objects):
        res = location.residuals[k]
        t = np.arange(res.centroid.shape[0]) / fps
        ax = axes[row, 0]
        for i, regime in enumerate(location.regimes[k]):
            ax.axvspan((i - 0.5) / fps, (i + 0.5) / fps, color=colors[regime], lw=0)
        ax.plot(
            t, 1e3 * np.linalg.norm(res.centroid, axis=1), "k-o", ms=3, label="|centroid residual|"
        )
        ax.axhline(
            1e3 * SIGNIFICANCE * location.noise_floor[k],
            color="r",
            ls="--",
            lw=0.8,
            label=f"{SIGNIFICANCE:g} x noise floor",
        )
        ax.axvline(location.onset[k] / fps, color="purple", lw=1, label="onset")
        ax.set_ylabel(f"object {k} (mm)")
        ax.legend(fontsize=7)
        ax = axes[row, 1]
        for axis, name in enumerate("xyz"):
            ax.plot(t, 1e3 * res.centroid[:, axis], label=name)
        ax.set_ylabel("residual components (mm)")
        ax.legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel(
            "time (s); shading: white flight, orange object contact, blue ground, grey rest"
        )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
