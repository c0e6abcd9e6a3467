"""Evaluation: roll the identified model over observed and future frames and score it.

Writes ``metrics.json`` in the shape of DESIGN.md section 5.4 and plots a person would rather
look at than read: per-object centroid paths (prediction vs reference) and the loss curve.
"""

from __future__ import annotations

import torch

from mosiv_framework.metrics import frame_metrics
from mosiv_framework.types import SimulationParams, Trajectory


def parameter_errors(identified: SimulationParams, gt_params: dict) -> dict:
    """Per object and parameter: identified value, true value, relative (or absolute) error.

    Angles are compared in degrees (absolute error); every other parameter by relative error.
    """
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


def score(
    traj: Trajectory,
    reference: dict[int, torch.Tensor],
    *,
    observed_frames: int,
    n_samples: int,
    seed: int,
) -> dict:
    """``observed`` and ``future`` metric blocks of a rollout against reference points."""
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
