"""Evaluation: roll the identified model over observed and future frames and score it.

Writes ``metrics.json`` in the layout docs/ARCHITECTURE.md gives ("metrics.json") and plots a
person would rather look at than read: per-object centroid paths (prediction vs reference) and
the loss curve.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import torch

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.metrics import chamfer_floor_mm2, chamfer_mm2, frame_metrics
from mosiv_framework.pipeline.appearance import can_render, rollout_images
from mosiv_framework.pipeline.formats import METRICS, stamped
from mosiv_framework.pipeline.memory import comparable_peaks, peak_memory_gb, run_peak_gb
from mosiv_framework.pipeline.uncertainty import mark_coverage
from mosiv_framework.pipeline.video import pick_camera, save_rollout_npz, write_comparison_video
from mosiv_framework.types import SimulationParams, Trajectory

log = logging.getLogger(__name__)


def parameter_errors(identified: SimulationParams, gt_params: dict) -> dict:
    """Per object and parameter: identified value, true value, relative (or absolute) error.

    Angles are compared in degrees (absolute error); every other parameter by relative error.
    Motion only determines stresses relative to density (scaling every density and stress-like
    parameter by one factor changes nothing, see ``params.GAUGE_PARAM``), so parameters in Pa,
    Pa*s and kg/m^3 also get ``rel_error_gauge_free``: the error after rescaling by
    true / identified density of the gauge object (the lowest id), the error of what the
    recording can tell.
    """
    from mosiv_framework.laws import get_law

    gauge = _gauge_factor(identified, gt_params)
    out: dict[str, dict] = {}
    for obj in gt_params.get("objects", []):
        k = int(obj["id"])
        if k not in identified.objects:
            continue
        errors = {}
        for name, true in obj.get("params", {}).items():
            if name not in identified.objects[k].values:
                continue
            value = float(identified.objects[k].values[name])
            if name == "friction_angle":
                errors[name] = {"value": value, "true": true, "abs_error_deg": abs(value - true)}
            else:
                errors[name] = {
                    "value": value,
                    "true": true,
                    "rel_error": abs(value - true) / max(abs(true), 1e-12),
                }
                family = identified.objects[k].family
                unit = "kg/m^3" if name == "rho" else _unit(get_law(family), name)
                if gauge is not None and unit in ("Pa", "Pa*s", "kg/m^3"):
                    errors[name]["rel_error_gauge_free"] = abs(value * gauge - true) / max(
                        abs(true), 1e-12
                    )
        if "initial_velocity" in obj and k in identified.initial_velocity:
            v = identified.initial_velocity[k].detach().float()
            t = torch.tensor(obj["initial_velocity"], dtype=torch.float32)
            errors["initial_velocity"] = {
                "value": v.tolist(),
                "true": t.tolist(),
                "rel_error": float((v - t).norm() / max(float(t.norm()), 1e-12)),
            }
        out[str(k)] = errors
    return out


def _unit(law, name: str) -> str:
    try:
        return law.param(name).unit
    except (KeyError, ValueError):
        return ""


def _gauge_factor(identified: SimulationParams, gt_params: dict) -> float | None:
    """True / identified density of the lowest-id object (None if either is unknown)."""
    objects = {int(o["id"]): o for o in gt_params.get("objects", [])}
    k = min(identified.objects, default=None)
    if k is None or k not in objects or "rho" not in identified.objects[k].values:
        return None
    true = objects[k].get("params", {}).get("rho")
    value = float(identified.objects[k].values["rho"])
    return None if true is None or value <= 0 else float(true) / value


def score(
    traj: Trajectory,
    reference: dict[int, torch.Tensor],
    *,
    observed_frames: int,
    n_samples: int,
    seed: int,
    images: tuple[list, list, list] | None = None,
) -> dict:
    """``observed`` and ``future`` metric blocks of a rollout against reference points.

    ``images``: (predicted, recorded, object regions) per frame
    (``appearance.rollout_images``); when given, each block also gets PSNR and SSIM over its
    frames and the PSNR over the object regions, else they stay None."""
    predicted = {k: traj.object_positions(k).detach().cpu() for k in reference}
    n = min(traj.n_frames, min(r.shape[0] for r in reference.values()))
    blocks = {}
    for name, frames in (
        ("observed", range(0, min(observed_frames, n))),
        ("future", range(observed_frames, n)),
    ):
        frames = list(frames)
        if not frames:
            blocks[name] = None
            continue
        blocks[name] = frame_metrics(
            {k: [p[f] for f in range(n)] for k, p in predicted.items()},
            {k: [r[f] for f in range(n)] for k, r in reference.items()},
            frames=frames,
            n_samples=n_samples,
            seed=seed,
            predicted_images=None if images is None else [images[0][f] for f in frames],
            target_images=None if images is None else [images[1][f] for f in frames],
            image_regions=None if images is None else [images[2][f] for f in frames],
        )
    return blocks


def plot_centroids(
    traj: Trajectory, reference: dict[int, torch.Tensor], *, fps: float, observed_frames: int, path
) -> None:
    """Centroid x, y, z over time per object: prediction (solid) vs reference (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), sharex=True)
    t_pred = torch.arange(traj.n_frames) / fps
    for k, ref in sorted(reference.items()):
        pred_c = traj.object_positions(k).detach().cpu().mean(1)
        ref_c = ref.mean(1)
        t_ref = torch.arange(ref.shape[0]) / fps
        for axis, ax in enumerate(axes):
            (line,) = ax.plot(t_pred, pred_c[:, axis], label=f"object {k} simulated")
            ax.plot(
                t_ref, ref_c[:, axis], "--", color=line.get_color(), label=f"object {k} reference"
            )
    for axis, ax in enumerate(axes):
        ax.axvline((observed_frames - 0.5) / fps, color="grey", lw=0.8)
        ax.set_title(f"centroid {'xyz'[axis]} (m)")
        ax.set_xlabel("time (s)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_history(history: list[dict], path) -> None:
    """Identification loss per iteration (log scale), phases separated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.4))
    history = [h for h in history if "loss" in h]  # diverged, stepped-back iterations have none
    losses = [h["loss"] for h in history]
    ax.semilogy(range(len(losses)), [max(v, 1e-20) for v in losses])
    changes = [i for i in range(1, len(history)) if history[i]["phase"] != history[i - 1]["phase"]]
    for i in changes:
        ax.axvline(i, color="grey", lw=0.8)
    ax.set_xlabel("iteration (velocity phase, then parameter phase)")
    ax.set_ylabel("loss")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_parameters(history: list[dict], path) -> None:
    """Per iteration: every identified quantity (relative to its first value, so parameters of
    different units share an axis) and the gradient norm of each optimised leaf."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    history = [h for h in history if "loss" in h]
    fig, (ax_v, ax_g) = plt.subplots(1, 2, figsize=(12, 3.6))
    if history:
        series: dict[str, list[float]] = {}
        for h in history:
            for k, obj in h["values"]["objects"].items():
                for name, value in obj["params"].items():
                    series.setdefault(f"obj{k}.{name}", []).append(value)
                speed = sum(x * x for x in obj["initial_velocity"]) ** 0.5
                series.setdefault(f"|v0.obj{k}|", []).append(speed)
            series.setdefault("ground_friction", []).append(h["values"]["ground_friction"])
            for term, values in h["values"].get("terms", {}).items():
                for name, value in values.items():
                    # vectors (a wind's acceleration) are plotted by their magnitude
                    size = sum(x * x for x in value) ** 0.5 if isinstance(value, list) else value
                    series.setdefault(f"{term}.{name}", []).append(size)
        for name, values in series.items():
            if max(values) - min(values) > 1e-9 * max(1.0, abs(values[0])):  # only what moved
                first = values[0] if values[0] != 0 else 1.0
                ax_v.plot([v / first for v in values], label=name)
        names = sorted({n for h in history for n in h.get("grads", {})})
        for name in names:
            ax_g.semilogy(
                [max(h.get("grads", {}).get(name, float("nan")), 1e-30) for h in history],
                label=name,
            )
    ax_v.set_title("identified values / their first value")
    ax_g.set_title("gradient norm per leaf (unscaled loss)")
    for ax in (ax_v, ax_g):
        ax.set_xlabel("iteration (velocity phase, then parameter phase)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: how many times evaluation may double the simulator's substeps after a divergence
EVALUATION_REFINEMENTS = 2


def _evaluation_rollout(simulator, particles, identified, *, world, frames, refine):
    """The identified model rolled over ``frames``; returns (trajectory, simulator, note).

    Identification only ever rolled the observed window. A model that diverges after it (a
    fluid hitting the table faster than the recipe's substeps resolve) is
    a time-step problem, not a wrong model, so the rollout is retried with 2x, then 4x the
    substeps, and the note in metrics.json says so; the run is not lost."""
    factor, note = 1, None
    while True:
        try:
            with torch.no_grad():
                traj = simulator.rollout(particles, identified, world=world, frames=frames)
            return traj, simulator, note
        except SimulationDiverged as exc:
            if refine is None or factor >= 2**EVALUATION_REFINEMENTS:
                raise
            factor *= 2
            substeps, simulator = refine(factor)
            note = (
                f"the rollout diverged in object {exc.object_id} at frame {exc.frame}, substep "
                f"{exc.substep} ({exc.reason}); evaluated with {substeps} substeps per frame"
            )
            log.info(
                "evaluation rollout diverged (%s); retrying with %d substeps", exc.reason, substeps
            )


def evaluate_run(
    *,
    recipe,
    scene,
    particles,
    reconstruction,
    identified,
    simulator,
    run_dir,
    started=None,
    refine=None,
    stage_times=None,
    stage_peaks=None,
) -> dict:
    """Roll ``identified`` over every frame, score it, write metrics.json, plots and videos.

    ``refine`` (see ``simulator_refiner``) lets a diverging rollout retry with more substeps.
    ``stage_times``: seconds each earlier stage took (``Progress.stage_times``); metrics.json
    records them beside the evaluation's own (its rollout and scores, before plots and videos).
    ``stage_peaks``: each earlier stage's recorded peak memory (``Progress.stage_peaks``);
    metrics.json's ``peak_memory_gb`` is the largest of those and this process's own, so a run
    that resumed or copied its first stages still reports what they needed.
    """
    t_evaluate = time.perf_counter()
    t_start = t_evaluate if started is None else started
    rd = run_dir
    world = scene.world
    # the identified families may differ from the lifted ones (library baseline, scope "all")
    particles = replace(particles, materials={k: p.family for k, p in identified.objects.items()})
    traj, simulator, note = _evaluation_rollout(
        simulator, particles, identified, world=world, frames=scene.n_frames - 1, refine=refine
    )
    reference = scene.gt_points() if scene.has_gt else reconstruction.points
    # PSNR/SSIM need images of the prediction: only particles with bound Gaussians (the
    # gaussians lifter) can be rendered against the recorded videos
    images = rollout_images(traj, particles, scene) if can_render(particles) else None
    blocks = score(
        traj,
        reference,
        observed_frames=scene.observed_frames,
        n_samples=recipe.evaluate.emd_samples,
        seed=recipe.evaluate.seed,
        images=images,
    )
    metrics = {
        "observed": blocks["observed"],
        "future": blocks["future"],
        "reference": "gt/points.npz" if scene.has_gt else "reconstruction",
        "params": rd.load_json("identified.json"),
        "param_error": parameter_errors(identified, scene.gt_params()) if scene.has_gt else None,
        "time_s": time.perf_counter() - t_start,
        "peak_memory_gb": run_peak_gb(peak_memory_gb(simulator), stage_peaks or {}),
    }
    if stage_peaks:
        metrics["stage_peak_memory_gb"] = comparable_peaks(stage_peaks)
    if stage_times is not None:
        metrics["stage_times_s"] = {
            **stage_times,
            "evaluate": round(time.perf_counter() - t_evaluate, 3),
        }
    if note is not None:
        metrics["evaluation_note"] = note
    if reconstruction.gaussians is not None and scene.has_gt:
        metrics["reconstruction"] = reconstruction_scores(reconstruction, scene)
    mark_coverage(metrics["param_error"], metrics["params"])  # intervals holding the truth
    metrics = stamped(METRICS, metrics)
    rd.save_json("metrics.json", metrics)
    _save_rollout_views(recipe, scene, traj, reference, rd)
    return metrics


def _save_rollout_views(recipe, scene, traj, reference, rd) -> None:
    """The evaluated rollout beside its numbers: the centroid plot, the rollout (rollout.pt,
    rollout.npz) and, when the recipe asks, the prediction-against-reference video."""
    plot_centroids(
        traj,
        reference,
        fps=scene.fps,
        observed_frames=scene.observed_frames,
        path=rd.path("trajectories.png"),
    )
    rd.save_torch(
        "rollout.pt",
        {"positions": traj.positions.detach().cpu(), "object_ids": traj.object_ids.cpu()},
    )
    save_rollout_npz(traj, rd.path("rollout.npz"))
    if recipe.evaluate.render_videos:
        write_comparison_video(
            traj,
            reference,
            camera=pick_camera(scene, recipe.evaluate.video_camera),
            path=rd.path(f"videos/prediction_vs_reference.{recipe.evaluate.video_format}"),
            size=recipe.evaluate.video_size,
            fps=recipe.evaluate.video_fps or scene.fps,
            observed_frames=scene.observed_frames,
        )


def gt_particle_spacing(gt_params: dict) -> float | None:
    """The spacing (m) of the generator's particles from gt/params.json: mosiv-synth records
    ``particle_spacing``, Genesis ``particle_size``; None when neither is there."""
    generator = gt_params.get("generator_params") or {}
    value = generator.get("particle_spacing", generator.get("particle_size"))
    return float(value) if isinstance(value, (int, float)) and value > 0 else None


def reconstruction_scores(reconstruction, scene) -> dict:
    """Stage I's Gaussians against the ground truth, per object: the Chamfer (mm^2) of the
    Gaussian centres to the true particles per frame, its worst frame and that frame's multiple
    of the scene's floor (``metrics.chamfer_floor_mm2``, the worst object and frame of a perfect
    dense reconstruction on the particles' spacing), and the mask IoU per frame and its worst
    frame where the reconstructor scored its own fit (gauss-dynamic's ``extras["training"]``),
    and the optimisation steps it skipped for a non-finite loss or gradient where it reports them
    (``extras["skipped_steps"]``; None where it does not). Identification fits these centres,
    so a run's accuracy is bounded by them."""
    gt = scene.gt_points()
    spacing = gt_particle_spacing(scene.gt_params())
    floor = chamfer_floor_mm2(gt, spacing=spacing) if spacing is not None else None
    training = (reconstruction.extras or {}).get("training") or {}
    per_object = {}
    for k, truth in sorted(gt.items()):
        points = reconstruction.points.get(k)
        cd = []
        if points is not None:
            n = min(points.shape[0], truth.shape[0])
            cd = [chamfer_mm2(points[t], truth[t]) for t in range(n)]
        iou = (training.get("iou") or {}).get(str(k)) or []
        defined = [v for v in iou if v is not None]
        worst = max(cd) if cd else None
        per_object[str(k)] = {
            "cd_mm2_per_frame": cd,
            "cd_mm2_max": worst,
            "cd_floor_multiple": worst / floor if worst is not None and floor else None,
            "iou_per_frame": iou,
            "iou_min": min(defined) if defined else None,
        }
    return {
        "chamfer_floor_mm2": floor,
        "particle_spacing_m": spacing,
        "skipped_steps": (reconstruction.extras or {}).get("skipped_steps"),
        "per_object": per_object,
    }
