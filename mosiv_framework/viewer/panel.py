"""The viewer's side panel as Markdown, and the per-frame numbers it shows: plain text, no
viser, so what a person reads is tested without a server."""

from __future__ import annotations

import math

import numpy as np

from mosiv_framework.pipeline.video import PALETTE
from mosiv_framework.viewer.data import ObjectSummary, ParamComparison, ViewerData

#: how much of an object's colour the reference points keep (the rest is white)
REFERENCE_TINT = 0.45


def object_rgb(k: int, *, reference: bool = False) -> tuple[int, int, int]:
    """Object ``k``'s colour (the palette of the run's videos, cycled by id) as 0-255 RGB;
    the reference points are a paler shade of it."""
    colour = PALETTE[(k - 1) % len(PALETTE)]
    if reference:
        colour = REFERENCE_TINT * colour + (1 - REFERENCE_TINT)
    return tuple(int(round(255 * c)) for c in colour)


def _num(x: float | None) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return f"{x:.4g}"


def _error(c: ParamComparison) -> str:
    if c.unit == "deg":
        return f"{c.error:.3g} deg"
    text = f"{100 * c.error:.3g} %"
    return text if c.gauge_free is None else f"{text} ({100 * c.gauge_free:.3g} % gauge-free)"


def _true(value) -> str:
    if isinstance(value, list):
        return "(" + ", ".join(f"{v:.3g}" for v in value) + ")"
    return _num(float(value))


def object_markdown(obj: ObjectSummary) -> str:
    """One object's identified parameters: value, and true value and error when the scene has
    ground truth (metrics.json ``param_error``)."""
    hex_colour = "#{:02x}{:02x}{:02x}".format(*object_rgb(obj.id))
    lines = [
        f"**<span style='color:{hex_colour}'>&#9632;</span> object {obj.id}: {obj.name}** "
        f"({obj.family})",
        "",
    ]
    truth = bool(obj.truth)
    lines += (
        ["| parameter | identified | true | error |", "| --- | --- | --- | --- |"]
        if truth
        else ["| parameter | identified |", "| --- | --- |"]
    )
    rows = [(name, _num(value)) for name, value in sorted(obj.params.items())]
    rows.append(("v0 (m/s)", _true(obj.initial_velocity)))
    for name, value in rows:
        key = "initial_velocity" if name.startswith("v0") else name
        if truth and key in obj.truth:
            c = obj.truth[key]
            lines.append(f"| {name} | {value} | {_true(c.true)} | {_error(c)} |")
        elif truth:
            lines.append(f"| {name} | {value} | | |")
        else:
            lines.append(f"| {name} | {value} |")
    return "\n".join(lines)


def chamfer_markdown(data: ViewerData) -> str:
    """Per object: the Chamfer distance (mm^2) over the observed and the future frames."""
    lines = ["| object | observed CD (mm²) | future CD (mm²) |", "| --- | --- | --- |"]
    for k, obj in sorted(data.objects.items()):
        lines.append(
            f"| {k} {obj.name} | {_num(obj.cd_observed_mm2)} | {_num(obj.cd_future_mm2)} |"
        )
    source = data.reference_source or "no reference"
    lines += ["", f"against {source}; frames 0-{data.observed_frames - 1} were observed"]
    return "\n".join(lines)


def frame_text(data: ViewerData, frame: int) -> str:
    """The status line of a frame: its number, time and whether it was observed."""
    return (
        f"frame {frame} / {data.n_frames - 1}, t = {frame / data.fps:.3f} s: "
        f"**{data.phase(frame)}**"
    )


def diagnosis_markdown(data: ViewerData) -> str:
    """The diagnosis verdict and, per object, its noise floor and where its residual starts."""
    res = data.residuals
    if res is None:
        return "no diagnosis.json: run `mosiv diagnose RUN` to see residuals here"
    lines = [f"verdict: **{res.verdict}**" + (f" ({res.accepted})" if res.accepted else ""), ""]
    for k in sorted(res.centroid_mm):
        lines.append(
            f"- object {k}: noise floor {_num(res.noise_floor_mm.get(k))} mm, residual from "
            f"frame {res.onset_frame.get(k, 0)}"
        )
    return "\n".join(lines)


def residual_at(data: ViewerData, k: int, frame: int) -> float | None:
    """Object ``k``'s Chamfer residual (mm^2) at ``frame`` from diagnosis.json, None when the
    diagnosis has no value there."""
    if data.residuals is None or k not in data.residuals.chamfer_mm2:
        return None
    row = data.residuals.chamfer_mm2[k]
    if frame >= len(row) or not np.isfinite(row[frame]):
        return None
    return float(row[frame])


def residual_rgb(value: float | None, scale: float) -> tuple[int, int, int]:
    """Marker colour of a residual: green at 0, through yellow, red at ``scale`` and above;
    grey when there is none."""
    if value is None or scale <= 0:
        return (150, 150, 150)
    x = min(max(value / scale, 0.0), 1.0)
    red = min(1.0, 2 * x)
    green = min(1.0, 2 * (1 - x))
    return (int(255 * red), int(200 * green), 40)
