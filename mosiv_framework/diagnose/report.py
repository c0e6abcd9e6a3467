"""Step 5 of a diagnosis: say it in words and numbers, in the run folder.

Writes ``diagnosis.json`` (everything, machine-readable), ``diagnosis.md`` (for a person) and
two plots under ``diagnose/``: the located residuals and the centroid paths before and after
modelling. The recipe change is a YAML snippet to paste into the run's recipe: the whole
``physics_terms`` section (the run's own terms at their refitted values plus the accepted term at
its fitted value, ``identify: true``; format in ``mosiv_framework.recipes.terms``), or the
``identify`` switch that frees a friction coefficient.
"""

from __future__ import annotations

import numpy as np
import yaml
from omegaconf import OmegaConf

from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.diagnose.decide import finite_or_none
from mosiv_framework.diagnose.floor import summarise_floor
from mosiv_framework.diagnose.formats import DIAGNOSIS_FORMAT
from mosiv_framework.diagnose.grid_stability import grid_lines, grid_summary
from mosiv_framework.diagnose.locate import Location, plot_location
from mosiv_framework.diagnose.model import is_refit_divergence
from mosiv_framework.recipes.terms import IDENTIFY_KEY

MM2 = 1e6  # m^2 -> mm^2, the unit metrics.json reports Chamfer errors in


def _block_means(errors: np.ndarray, observed: int) -> dict:
    """Mean Chamfer (mm^2) over objects and the observed / future frames of a [K, T] table;
    None where there is none, or where a prediction diverged (an infinite error)."""
    future = errors[:, observed:]
    return {
        "observed_cd_mm2": finite_or_none(errors[:, :observed].mean() * MM2),
        "future_cd_mm2": finite_or_none(future.mean() * MM2) if future.size else None,
    }


def saved_table(errors: np.ndarray) -> list[list[float | None]]:
    """A [K, T] error table (m^2) as diagnosis.json holds it: mm^2, and null for a frame a
    diverged prediction did not reach (its infinite error, ``decide.frame_errors``; read back
    by ``replay``)."""
    return [[finite_or_none(x) for x in row] for row in (errors * MM2).tolist()]


def loaded_table(rows: list) -> np.ndarray:
    """The inverse of ``saved_table`` (still in mm^2): a null entry, a frame a diverged
    prediction did not reach, is the infinite error the decision counted it as."""
    return np.asarray([[np.inf if x is None else x for x in row] for row in rows], dtype=float)


def _effect_cell(evidence: dict) -> str:
    """An evidence row's own effect (``effect.summarise_effect``) for the report's table."""
    effect = evidence.get("effect")
    if not effect:
        return "-"
    cell = f"{_fmt(effect['fit'])} (moves up to {effect['max_displacement_mm']:.3g} mm)"
    return cell if evidence.get("passes_effect", True) else cell + ", below the floor"


def _param_shift(before, after) -> dict:
    """Per object: each parameter and initial velocity before and after, with relative change."""
    out = {}
    for k, p in sorted(before.objects.items()):
        rows = {}
        for name, value in sorted(p.values.items()):
            b, a = float(value), float(after.objects[k].values[name])
            rows[name] = {"before": b, "after": a, "rel_change": (a - b) / max(abs(b), 1e-12)}
        vb = before.initial_velocity[k].detach().float()
        va = after.initial_velocity[k].detach().float()
        rows["initial_velocity"] = {
            "before": vb.tolist(),
            "after": va.tolist(),
            "rel_change": float((va - vb).norm() / max(float(vb.norm()), 1e-12)),
        }
        out[str(k)] = rows
    gb, ga = float(before.ground_friction), float(after.ground_friction)
    out["ground_friction"] = {"before": gb, "after": ga}
    return out


def _rounded(value):
    """6 significant digits: what the fit resolves, and readable in a recipe."""
    if isinstance(value, list):
        return [_rounded(x) for x in value]
    return float(f"{float(value):.6g}")


def recipe_change(fit, run_terms: dict | None = None) -> str:
    """The YAML a recipe needs to include the accepted effect.

    ``run_terms`` is the run's resolved ``physics_terms`` section: its terms are carried into
    the snippet at their values in the fit (which refitted the identified ones), so the
    snippet replaces the recipe's section as a whole and is pasted, not merged.
    """
    c = fit.candidate
    if c.kind == "ground_friction":
        snippet = {"identify": {"identify_ground_friction": True}}
    elif c.kind == "object_friction":
        snippet = {"identify": {"identify_friction": True}}
    elif c.kind == "plasticity":
        # a family is declared by the scene, not the recipe: say which declaration to change
        value = c.physical(fit.theta)
        k = value["object"]
        return (
            f"# in the scene's scene.json, declare object {k} as material: plasticine; the next "
            f"run identifies its yield_stress (this fit: {_rounded(value['yield_stress'])} Pa)\n"
        )
    else:
        section = {}
        for name, entry in (run_terms or {}).items():
            values = fit.params.terms.get(name, {})
            section[name] = {
                **{p: _rounded(v.tolist()) for p, v in sorted(values.items())},
                IDENTIFY_KEY: bool(entry.get(IDENTIFY_KEY, False)),
            }
        fitted = {p: _rounded(v) for p, v in c.physical(fit.theta).items()}
        section[c.name] = {**fitted, IDENTIFY_KEY: True}  # the next run refines it
        snippet = {"physics_terms": section}
    return yaml.safe_dump(snippet, sort_keys=False, default_flow_style=None)


def plot_paths(ctx: RunContext, trajectories: dict, path) -> None:
    """Centroid x, y, z per object: targets (black) and each model's rollout."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        len(ctx.object_ids), 3, figsize=(12, 2.8 * len(ctx.object_ids)), squeeze=False
    )
    t = np.arange(ctx.n_frames) / ctx.fps
    for row, k in enumerate(ctx.object_ids):
        target = ctx.targets[k][: ctx.n_frames].mean(1).numpy()
        for axis in range(3):
            ax = axes[row, axis]
            ax.plot(t, target[:, axis], "k.-", lw=1.5, label="recording")
            for name, traj in trajectories.items():
                c = traj.object_positions(k)[: ctx.n_frames].detach().cpu().mean(1).numpy()
                ax.plot(t[: len(c)], c[:, axis], label=name)  # shorter if it diverged
            ax.axvline((ctx.observed_frames - 0.5) / ctx.fps, color="grey", lw=0.8)
            ax.set_title(f"object {k} centroid {'xyz'[axis]} (m)", fontsize=9)
    axes[0, 0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time (s); grey line: end of the observed window")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _frame_ranges(frames: list[int]) -> str:
    """[1, 2, 3, 6, 7, 9] -> "1-3, 6-7, 9"."""
    runs: list[list[int]] = []
    for t in frames:
        if runs and t == runs[-1][-1] + 1:
            runs[-1].append(t)
        else:
            runs.append([t])
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else f"{r[0]}" for r in runs)


#: the flagged object's location entries the summary's ``where`` repeats
WHERE_KEYS = (
    "window",
    "onset_frame",
    "signal_to_noise",
    "noise_floor_m",
    "jitter_m",
    "sampling_m",
    "targets_tracked",
    "direction_fraction",
)


def write_report(ctx: RunContext, location: Location, result: dict) -> dict:
    """Write diagnosis.json, diagnosis.md and the plots; returns the JSON-ready summary."""
    rd = ctx.run_dir
    rd.path("diagnose").mkdir(exist_ok=True)
    plot_location(location, fps=ctx.fps, path=rd.path("diagnose/residuals.png"))
    summary = _summary(location, result, ctx.observed_frames)
    trajectories = _null_trajectories(ctx, result.get("null"))
    fit = result["accepted"]
    if fit is not None:
        summary["accepted"] = _accepted_record(ctx, fit, result["interval"])
        trajectories[f"with {fit.name}"] = fit.trajectory
    plot_paths(ctx, trajectories, rd.path("diagnose/paths.png"))
    rd.save_json("diagnosis.json", summary)
    rd.write_bytes("diagnosis.md", _markdown(summary).encode())
    return summary


def _summary(location: Location, result: dict, observed: int) -> dict:
    """diagnosis.json without the accepted term (``accepted`` None)."""
    errors = result["errors"]
    null = result.get("null")
    flagged = location.summary["objects"][str(location.flagged_object)]
    return {
        "format": DIAGNOSIS_FORMAT,
        "verdict": result["verdict"],
        "where": {
            "object": location.flagged_object,
            "regimes": location.flagged_regimes,
            "significant": location.significant,
            **{key: flagged[key] for key in WHERE_KEYS},
        },
        "location": location.summary,
        "frames": result["frames"],
        "budget": result["budget"],
        "skipped_candidates": result.get("skipped_candidates", []),
        "screening": result["screening"],
        "evidence": result["evidence"],
        "errors": {name: _block_means(e, observed) for name, e in errors.items()},
        # the [object, frame] tables themselves, so another decision rule can be replayed on
        # a finished diagnosis without refitting anything
        "frame_errors_mm2": {name: saved_table(e) for name, e in errors.items()},
        "null_parameters": null.n_params if null is not None else None,
        # the decision rule (``DecideOptions``) the evidence was judged by, for a replay
        "rule": result.get("rule"),
        # a candidate's name where the null was refitted again from its switched-off parameters
        "null_started_from": null.started_from if null is not None else None,
        # whether the null kept was identified afresh (``reidentify``) rather than refitted
        "null_reidentified": null.reidentified if null is not None else False,
        # where the null's prediction over all frames diverged (``model.Fit.diverged``)
        "null_diverged": null.diverged if null is not None else None,
        # how far the null's prediction moves on resampled particles (``floor.py``): the unit
        # of the own-effect test, recorded so that a replay can apply it
        "resolution_floor_mm2": summarise_floor(result.get("resolution_floor"), result["frames"]),
        "accepted": None,
        # terms the data cannot tell apart from the best candidate, the uniform acceleration
        # or drag exponent they pin down (``equivalence.equivalents``)
        "equivalent": result.get("equivalent") or {},
        # the open-form law of what no candidate explains (``discover``), where run
        "discovered": result.get("discovered"),
        # that law tested as a model (``formula``): the law, its refit with intervals
        "formula": result.get("formula"),
        # the check at a second grid (``grid_stability``): who was checked, why one was not named
        "grid_stability": grid_summary(result["evidence"]),
        # time of this attempt; the steps it took from an earlier, cut-off one (``steps.py``)
        "time_s": result["time_s"],
        "resumed_steps": result.get("resumed_steps", []),
    }


def _null_trajectories(ctx: RunContext, null) -> dict:
    """The paths plot's rollouts before the accepted term: the identified model and the null
    refit (drawn up to where it diverged, if it did)."""
    trajectories = {"identified": ctx.identified_rollout()}
    if null is not None and null.trajectory is not None:
        trajectories["refit without new physics"] = null.trajectory
    elif null is not None and null.reached is not None:
        trajectories["refit without new physics (diverged)"] = null.reached
    return trajectories


def _accepted_record(ctx: RunContext, fit, interval) -> dict:
    """diagnosis.json's ``accepted``: the term, its coefficients with their 95 % interval
    (``interval``: lower and upper per coefficient), the shift of the run's parameters and
    the recipe change that adds it."""
    names = fit.candidate.coefficient_names
    lower, upper = interval
    return {
        "name": fit.name,
        "description": fit.candidate.description,
        "coefficients": dict(zip(names, fit.theta.tolist())),
        "interval_95": {n: [lo, hi] for n, lo, hi in zip(names, lower, upper)},
        "units": dict(zip(names, fit.candidate.units)),
        "value": fit.candidate.physical(fit.theta),
        "starts": [{"theta": th, "fit_loss_m2": loss} for th, loss in fit.starts],
        "param_shift": _param_shift(ctx.identified, fit.params),
        "recipe_change": recipe_change(
            fit, OmegaConf.to_container(ctx.recipe, resolve=True).get("physics_terms")
        ),
    }


def _fmt(x, spec: str = ".4g") -> str:
    return "n/a" if x is None else format(x, spec)


def _pct(x) -> str:
    return _fmt(x, ".2%")


def _markdown(s: dict) -> str:
    """diagnosis.md: where the model misses, what was left out (if a term was accepted), the
    errors, the evidence and the screening."""
    lines = _where_lines(s["where"], s["verdict"])
    if s["verdict"] == "discrepancy":
        lines += [
            "The model differs from the recording, but no physical effect explains it: a "
            "per-object smooth correction predicts as well as every candidate that improved "
            "the model, or the candidate's coefficient differs between objects, or it is "
            "not stable across grid resolution.",
            "",
        ]
    if s["accepted"] is not None:
        lines += _accepted_lines(s["accepted"])
    lines += _equivalent_lines(s.get("equivalent") or {})
    if s.get("discovered"):
        lines += _discovered_lines(s["discovered"])
    if s.get("formula"):
        lines += _formula_lines(s["formula"])
    lines += _error_lines(s["errors"])
    if s["evidence"]:
        lines += _evidence_lines(s) + grid_lines(s["evidence"])
    if s["screening"]:
        lines += _screening_lines(s["screening"])
    return "\n".join(lines)


def _where_lines(where: dict, verdict: str) -> list[str]:
    sampling = (
        "none, targets tracked"
        if where["targets_tracked"]
        else f"{where['sampling_m'] * 1e3:.3g} mm"
    )
    directions = ", ".join(f"{d} {100 * f:.0f} %" for d, f in where["direction_fraction"].items())
    return [
        "# Diagnosis",
        "",
        f"**Verdict: {verdict}.**",
        "",
        "## Where",
        f"Object {where['object']} carries the largest unexplained error: centroid residual "
        f"{where['signal_to_noise']:.3g} x its noise floor ({where['noise_floor_m'] * 1e3:.3g} mm: "
        f"frame jitter {where['jitter_m'] * 1e3:.3g} mm, centroid sampling {sampling}), "
        f"from frame {where['onset_frame']} (change point) to {where['window'][1]}, in regimes "
        f"{', '.join(where['regimes'])}. Residual by direction: {directions}.",
        "",
        "![residuals](diagnose/residuals.png)",
        "",
    ]


def _accepted_lines(acc: dict) -> list[str]:
    lines = [
        "## What was left out",
        f"{acc['description']} (`{acc['name']}`):",
        "",
        "| coefficient | value | 95 % interval | unit |",
        "|---|---|---|---|",
    ]
    for name, value in acc["coefficients"].items():
        lo, hi = acc["interval_95"][name]
        lines.append(f"| {name} | {value:.4g} | [{lo:.4g}, {hi:.4g}] | {acc['units'][name]} |")
    lines += ["", "Shift of the original parameters when refitted with it:", ""]
    lines += [
        "| object | parameter | before | after | relative change |",
        "|---|---|---|---|---|",
    ]
    for k, rows in acc["param_shift"].items():
        if k == "ground_friction":
            continue
        for name, row in rows.items():
            if name == "initial_velocity":
                b = ", ".join(f"{x:.3g}" for x in row["before"])
                a = ", ".join(f"{x:.3g}" for x in row["after"])
                lines.append(f"| {k} | v0 (m/s) | {b} | {a} | {row['rel_change']:.2%} |")
            else:
                lines.append(
                    f"| {k} | {name} | {row['before']:.4g} | {row['after']:.4g} "
                    f"| {row['rel_change']:.2%} |"
                )
    return lines + [
        "",
        "Recipe change that adds it:",
        "",
        "```yaml",
        acc["recipe_change"].rstrip(),
        "```",
        "",
    ]


def _equivalent_lines(eq: dict) -> list[str]:
    """The quantity the data pin down and the terms they cannot tell apart."""
    if not eq:
        return []
    lines = ["## Equivalent forms", ""]
    uniform = eq.get("uniform_acceleration")
    if uniform:
        a = ", ".join(f"{x:.3g}" for x in uniform["acceleration"])
        g = ", ".join(f"{x:.3g}" for x in uniform["gravity"])
        lines.append(
            f"A uniform extra acceleration ({a}) m/s^2: equivalently a gravity of ({g}) m/s^2, "
            f"magnitude {uniform['gravity_magnitude']:.4g} m/s^2"
            + (
                " (95 %: {:.4g} to {:.4g})".format(*uniform["gravity_magnitude_interval"])
                if uniform.get("gravity_magnitude_interval")
                else ""
            )
            + "."
        )
    drag = eq.get("drag")
    if drag:
        lo, hi = drag["interval"]
        lines.append(
            f"Drag a = -c |v|^(p-1) v fitted to the residual accelerations: p = "
            f"{drag['exponent']:.2f} (95 %: {lo:.2f} to {hi:.2f}), c = {drag['coefficient']:.3g}: "
            f"{drag['form']}."
        )
    if eq.get("equivalent"):
        lines.append(
            f"Cannot be told apart from {eq['best']} on these data: "
            + ", ".join(f"`{n}`" for n in eq["equivalent"])
            + "."
        )
    return lines + [""]


def _discovered_lines(found: dict) -> list[str]:
    """The discovered law per axis with its coefficients' intervals."""
    lines = [
        "## Discovered law (sparse regression of the residual accelerations)",
        "",
        f"From {found['samples']} samples"
        + ("" if found["node_local"] else " (uses other objects or contact: not node-local)")
        + ":",
        "",
    ]
    for axis in found["axes"].values():
        terms = "; ".join(
            f"{t['feature']}: {t['coefficient']:.3g} [{t['interval'][0]:.3g}, "
            f"{t['interval'][1]:.3g}]"
            for t in axis["terms"]
        )
        lines.append(f"- `{axis['formula']}`" + (f" ({terms})" if terms else ""))
    return lines + [""]


def _formula_lines(record: dict) -> list[str]:
    """The discovered law tested as a model (an ``expression`` candidate): the law, whether
    it was accepted, and its refitted coefficients with their 95 % intervals."""
    lines = ["## Discovered law tested as a model", ""]
    if not record.get("tested"):
        return lines + [f"Not tested: {'; '.join(record.get('skipped') or ['no law'])}.", ""]
    outcome = "accepted" if record["accepted"] else "not accepted"
    if record.get("failed"):
        outcome += f" (failed: {', '.join(record['failed'])})"
    if record.get("refitted") is None:  # its refit diverged (``model.diverged_refit``)
        return lines + [
            f"`{record['tested']}` was applied by the simulator on its grid nodes (the "
            f"`expression` term): {outcome}; {record.get('diverged') or 'no refit'}.",
            "",
        ]
    lines += [
        f"`{record['tested']}` was applied by the simulator on its grid nodes (the "
        "`expression` term), refitted with the run's free parameters and judged like the "
        f"library terms (Evidence, row `expression`): {outcome}. Refitted, with 95 % intervals:",
        "",
    ]
    for axis in record["refitted"]["axes"].values():
        terms = "; ".join(
            f"{t['feature']}: {t['coefficient']:.3g} "
            + ("[-]" if t["interval"] is None else "[{:.3g}, {:.3g}]".format(*t["interval"]))
            for t in axis["terms"]
        )
        lines.append(f"- `{axis['formula']}`" + (f" ({terms})" if terms else ""))
    terms = [t for axis in record["refitted"]["axes"].values() for t in axis["terms"]]
    if any(t["interval"] is None for t in terms):  # computed only after held-out and BIC
        lines += ["", "[-]: no interval (the law failed the tests before it)."]
    return lines + [""]


def _error_lines(errors: dict) -> list[str]:
    lines = [
        "## Errors (mean Chamfer against the run's targets, mm^2)",
        "",
        "| model | observed | future |",
        "|---|---|---|",
    ]
    for name, e in errors.items():
        lines.append(f"| {name} | {_fmt(e['observed_cd_mm2'])} | {_fmt(e['future_cd_mm2'])} |")
    return lines + ["", "![paths](diagnose/paths.png)", ""]


def _evidence_lines(s: dict) -> list[str]:
    floor = s.get("resolution_floor_mm2")
    lines = ["## Evidence (against the null model refitted with the same budget)", ""]
    if floor:
        lines += [
            "Resolution floor (the null's prediction on resampled particles against its "
            f"own, in excess of frame 0): {_fmt(floor['fit'])} mm^2 on the fit frames, "
            f"{_fmt(floor['heldout'])} mm^2 on the held-out frames.",
            "",
        ]
    lines += [
        _how_judged(s),
        "",
        "| candidate | refitted coefficients | 95 % interval | held-out drop | bootstrap sd "
        "| dBIC | held-out | BIC | own effect, fit frames (mm^2) | accepted |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [_evidence_row(e) for e in s["evidence"]]
    lines.append("")
    lines += _physical_lines(s["evidence"])
    # why a candidate whose refit or prediction blew up was not accepted, in the simulator's
    # words
    diverged = [e for e in s["evidence"] if e.get("diverged")]
    lines += [f"- `{e['name']}` was not accepted: {_divergence(e['diverged'])}." for e in diverged]
    return lines + ([""] if diverged else [])


def _divergence(diverged: str) -> str:
    """A ``Fit.diverged`` message as the report says it: the refit's own
    (``model.diverged_refit``) as it is, a prediction's (the simulator's) introduced."""
    if is_refit_divergence(diverged):
        return diverged
    return f"its prediction diverged ({diverged})"


def _physical_lines(evidence: list[dict]) -> list[str]:
    """The physical-evidence tests of the candidates that improved the model."""
    tested = [e for e in evidence if e.get("nuisance_drop") is not None or e.get("consistency")]
    if not tested:
        return []
    lines = [
        "Physical evidence: the held-out drop against the nuisance model (the null with a "
        "smooth per-object correction) and the agreement of the coefficient across objects.",
        "",
        "| candidate | drop vs nuisance | bootstrap sd | beats nuisance | objects agree |",
        "|---|---|---|---|---|",
    ]
    for e in tested:
        c = e.get("consistency") or {}
        agree = {True: "yes", False: "no", None: "-"}[c.get("consistent")]
        lines.append(
            f"| {e['name']} | {_pct(e.get('nuisance_drop'))} | {_pct(e.get('nuisance_spread'))} "
            f"| {'pass' if e.get('passes_nuisance', True) else 'fail'} | {agree} |"
        )
    return lines + [""]


def _how_judged(s: dict) -> str:
    """Which frames the models were refitted and judged on, and which null was kept."""
    text = (
        f"Every model was refitted on frames {_frame_ranges(s['frames']['fit'])} and judged "
        f"on the held-out frames {_frame_ranges(s['frames']['heldout'])}."
    )
    if s.get("null_started_from"):
        text += (
            f" The null model was refitted again from {s['null_started_from']}'s refit "
            "with its effect switched off, which fitted better than the null's own refit."
        )
    elif s.get("null_reidentified"):
        text += (
            " The null model kept is the one identified afresh on the fit frames, which "
            "fitted better than its refit."
        )
    if s.get("null_diverged"):
        text += (
            f" The null model's prediction diverged ({s['null_diverged']}): the candidates "
            "are judged only on the held-out frames it reached."
        )
    return text


def _evidence_row(e: dict) -> str:
    theta = ", ".join(f"{x:.3g}" for x in e["theta"]) if e.get("theta") else "-"
    # a candidate refitted again from the best model's shared parameters (its own refit
    # fitted worse, see ``model.converge_candidates``)
    mark = f" (from {e['started_from']})" if e.get("started_from") else ""
    if e.get("reidentified") and not e.get("started_from"):
        mark = " (identified afresh)"  # see ``reidentify``
    interval = (
        ", ".join(f"[{lo:.3g}, {hi:.3g}]" for lo, hi in e["interval"]) if e.get("interval") else "-"
    )
    if not e.get("passes_interval", True):
        interval += " (includes zero)"
    held = "pass" if e["passes_heldout"] else "fail"
    if e.get("diverged"):
        held += (
            " (refit diverged)" if is_refit_divergence(e["diverged"]) else " (prediction diverged)"
        )
    return (
        f"| {e['name']}{mark} | {theta} | {interval} | {_pct(e['heldout_drop'])} | "
        f"{_pct(e['heldout_spread'])} | "
        f"{_fmt(e['delta_bic'], '.3g')} | {held} | "
        f"{'pass' if e['passes_bic'] else 'fail'} | {_effect_cell(e)} | "
        f"{'yes' if e['accepted'] else 'no'} |"
    )


def _screening_lines(screening: list[dict]) -> list[str]:
    lines = [
        "## Screening",
        "",
        "| candidate | allowed | predicted drop | score | note |",
        "|---|---|---|---|---|",
    ]
    for r in screening:
        lines.append(
            f"| {r['name']} | {'yes' if r['allowed'] else 'no'} "
            f"| {r['predicted_drop_fraction']:.2%} | {_fmt(r['score'])} | {r['note']} |"
        )
    return lines + [""]
