"""The structured schema of a recipe: one dataclass per section.

Component sections (reconstructor, lifter, simulator) are mappings with a ``name`` key naming a
registered component and that component's options beside it::

    simulator: {name: warp-mpm, grid: 64, substeps: 200}

``losses`` maps registered loss names to their options (``losses.chamfer.weight=0`` switches the
Chamfer term off). ``physics_terms`` maps registered physics-term names to their initial values
and an ``identify`` flag (see ``mosiv_framework.recipes.terms``). Everything else is plain typed
fields with defaults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

#: recipe section -> component kind its ``name`` refers to
COMPONENT_SECTIONS: dict[str, str] = {
    "reconstructor": "reconstructor",
    "lifter": "lifter",
    "simulator": "simulator",
}

#: which sections hold a mapping of several components of one kind, keyed by name
MULTI_COMPONENT_SECTIONS: dict[str, str] = {"losses": "loss"}


@dataclass
class SceneSection:
    """Where the recording is. ``path`` is a ``mosiv-scene/1`` folder. ``generate``:
    "if-missing" generates the scene there first with ``source`` (a registered SceneSource and
    its options) when the folder holds no scene; "never" (the default) makes a missing scene an
    error, so that a mistyped path is reported rather than filled with a synthetic scene."""

    path: str = "scene"
    source: dict[str, Any] | None = None
    generate: str = "never"

    @staticmethod
    def value_problems(values: dict[str, Any]) -> list[str]:
        """Values the type check cannot catch, each naming the key and what is valid."""
        generate = values.get("generate", "never")
        if generate not in SCENE_GENERATE:
            return [f"scene.generate={generate!r}: valid values are {list(SCENE_GENERATE)}"]
        if generate == "if-missing" and not values.get("source"):
            return ["scene.generate='if-missing' needs scene.source (what generates the scene)"]
        return []


#: when ``mosiv run`` generates the scene with scene.source: only where none exists, or never
SCENE_GENERATE = ("if-missing", "never")


#: identification methods: continuous gradient refinement (the paper) or the discrete-library
#: baseline (each object's material picked from fixed prototypes, no refinement)
IDENTIFY_METHODS = ("gradient", "library")
#: which frames the velocity phase fits: the free flight before any contact, or all observed
VELOCITY_WINDOWS = ("free", "observed")
#: prototypes the library baseline may pick from: the object's known family, or every family
LIBRARY_SCOPES = ("family", "all")
#: where the parameters start: the law defaults, or the centre of each law's bounds
IDENTIFY_STARTS = ("defaults", "centre")
#: where the ground's coefficient starts: as ``start`` puts it, or read off the recorded
#: landings (``pipeline.landing``)
GROUND_FRICTION_STARTS = ("start", "landing")
#: how the intervals are estimated: the loss read as a Gaussian likelihood (right when the
#: model is), or the sandwich covariance over frame blocks (``pipeline.sandwich``)
INTERVAL_METHODS = ("laplace", "sandwich")
#: the contact between objects: the simulator's ``contact`` as the recipe gives it, or chosen
#: from the observed frames (``mosiv_framework.pipeline.contact``)
IDENTIFY_CONTACT = ("fixed", "auto")
#: the laws: ``identify.laws`` as the recipe gives them, or chosen from the observed frames
#: between them and ``identify.law_alternatives`` (``mosiv_framework.pipeline.contact``)
IDENTIFY_LAW_CHOICE = ("fixed", "auto")
#: the stresses ``law_choice: auto`` tries: Genesis's (and many graphics engines') fixed-
#: corotated stress beside MOSIV's neo-Hookean elastic and StVK-Hencky plasticine
DEFAULT_LAW_ALTERNATIVES = {"elastic": "elastic_corotated", "plasticine": "plasticine_corotated"}


@dataclass
class IdentifySection:
    """Stage III: initial velocity first, then per-object parameters (paper section 3.5).

    method: "gradient" (Adam through the simulator) or "library" (the discrete-library
    baseline: velocities as usual, then each object's material picked from fixed prototypes by
    the observed loss, see ``mosiv_framework.pipeline.library``);
    velocity_window: "free" fits initial velocities on the frames before any contact (detected
    from the targets with ``contact_gap``), "observed" on every observed frame;
    contact_gap (m): objects closer than this to each other or the ground are in contact
    (0: two cells of the simulator grid, or 2 cm when the simulator has no grid);
    ballistic_tolerance: free flight also ends at the first frame where an object's centroid
    leaves the gravity parabola through its earlier centroids by more than this fraction of
    the points' spacing (0: the contact gap alone); a recording's contact can act before its
    surfaces meet, which a gap set by a fine simulator grid misses (docs/PHYSICS.md, Free
    flight in the data);
    stiffness_cfl: cap stiffnesses so the P-wave speed stays below this fraction of one grid
    cell per substep (0: no cap; needs the simulator's ``grid`` and ``substeps`` options);
    silhouette_size: side (pixels) of the square images the silhouette losses compare, the
    recorded masks area-averaged down to it (capped at the cameras' own size);
    start: where the law parameters start: "defaults" (each law's default values) or "centre"
    (the centre of each law's bounds, geometric for scale parameters such as E, 1e5 Pa for
    1e3-1e7 Pa, and at most the stiffness ceiling: a start that knows nothing of the data);
    ground_friction_start: where the ground's Coulomb coefficient starts: "start" (as ``start``
    puts it: the default 0.3, or 1.0, the centre of 0-2) or "landing" (the largest ratio of
    tangential to normal impulse over the observed landings of bodies clear of the others,
    ``mosiv_framework.pipeline.landing``; the default where no landing can be read);
    global_candidates: before the parameter phase, roll out this many scrambled Sobol
    candidates over all objects' identified parameters jointly, in log space for scale
    parameters and within the law bounds and stiffness ceilings, and start the descent from
    the best of them and the start (0: off; see ``mosiv_framework.pipeline.global_search``);
    global_frames: the last frame those rollouts cover (0: the whole observed window);
    global_polish: after those candidates (only with them), scan each of the same parameters
    alone over this many values spread over its range, the others held, and keep the best (0:
    off): a joint design leaves each parameter few values, and a yield stress above every
    stress reached has no gradient to come back with (``global_search.coordinate_polish``);
    holdout_frames: the last this many observed frames are held out of the parameter phase
    (its global stage, sweep and descent fit the frames before them); the phase then keeps
    whichever of the global stage's result and the descent's best fits the whole observed
    window best, the held-out frames telling which extrapolates (0: off). For data a model
    cannot match exactly, where a closer fit of the observed frames can predict the future
    worse (``pipeline.identify._choose_on_holdout``);
    intervals: after identification, a 95 % interval per identified parameter (two-sided, or
    the one-sided bound the data support, or "unconstrained"), stored in identified.json under
    ``intervals`` (see ``mosiv_framework.pipeline.uncertainty``);
    interval_method: "laplace" reads the loss as a Gaussian likelihood of the model, right
    when the model made the data; "sandwich" (H^-1 J H^-1 with J from the disagreement
    between frames, never narrower than the Laplace one) stays honest when it did not, e.g.
    on data another engine made;
    contact: "fixed" identifies with the simulator's ``contact`` as given; "auto" chooses
    between multi_field and single_field from the observed frames after the velocity phase
    (each mode from the same start, after its own global stage and ``contact_iterations``
    parameter steps, scored on the whole observed window) and uses the choice for everything
    after (see ``mosiv_framework.pipeline.contact``); needs a simulator with a ``contact``
    option;
    contact_iterations: the parameter steps of each mode's brief fit (0: each mode is scored at
    the start, or after its global stage; the materials of the start then decide as much as
    the contact does);
    contact_margin: with contact "auto", the simulator's ``contact`` is kept unless the other
    mode's loss is lower by more than this fraction of its loss (ties, e.g. bodies that never
    touch in the observed frames, keep it);
    contact_tie_iterations: where the brief fits leave two or more variants within
    ``contact_margin`` of the lowest loss, each of those continues its brief fit by this many
    parameter steps and the rule is applied again to the new losses (0: the tie keeps the
    recipe's variant at once);
    laws: the law each scene material is identified with where it is not the family's own,
    e.g. ``{elastic: elastic_corotated, plasticine: plasticine_corotated}`` (the stress of
    Genesis's Elastic and ElastoPlastic); the two laws must have the same parameters, so
    starts, bounds and errors mean the same (empty: every material its own law);
    law_choice: "fixed" identifies with ``laws``; "auto" also tries ``laws`` overridden by
    ``law_alternatives`` and keeps the alternative only if it fits the observed frames better
    by more than ``contact_margin``, chosen together with the contact as the contact alone is
    (each combination after its own global stage and ``contact_iterations`` parameter steps;
    see ``mosiv_framework.pipeline.contact``); the choice is recorded in identified.json;
    law_alternatives: with law_choice "auto", the law each material is tried with (same
    parameters as the material's, as for ``laws``); a recipe's entries are merged with the
    defaults, so to try no alternative for a material map it to its own law
    (``law_alternatives.plasticine=plasticine``).
    """

    method: str = "gradient"
    velocity_iterations: int = 80
    param_iterations: int = 200
    velocity_lr: float = 0.05
    param_lr: float = 0.05
    #: horizon curriculum: fit the first ``horizon_start`` frames first, then lengthen the
    #: rollout linearly so the whole observed window is used from ``horizon_full_at`` (a
    #: fraction of each phase's iterations) on; after a free-flight velocity phase the
    #: parameter phase starts at the first frame after the free flight, if that is later
    horizon_start: int = 3
    horizon_full_at: float = 0.5
    #: alternating updates (paper section 3.5): every ``resync_every`` parameter iterations
    #: (0 = off) the initial velocities, the particle state every rollout starts from, are
    #: re-fitted to the current horizon under the current parameters for ``resync_iterations``
    #: steps, so a velocity error does not drift the trajectory while the materials change
    resync_every: int = 0
    resync_iterations: int = 5
    identify_friction: bool = True
    identify_ground_friction: bool = True
    seed: int = 0
    checkpoint_every: int = 10
    velocity_window: str = "free"
    contact_gap: float = 0.0
    ballistic_tolerance: float = 0.1
    stiffness_cfl: float = 0.5
    silhouette_size: int = 48
    #: library baseline: which prototypes are candidates, and how many coordinate sweeps over
    #: the objects (each sweep tries every candidate of one object with the others held fixed)
    library_scope: str = "family"
    library_sweeps: int = 2
    start: str = "defaults"
    ground_friction_start: str = "start"
    #: off by default: on the quickstart scene from the centre start, the best of 16 candidates
    #: (a yield stress of 4e5 Pa that no impact reaches, so its gradient is 0) led the descent
    #: to a future Chamfer distance of 2590 mm^2 against 265 without the stage (from the law
    #: defaults it kept the start: 132 either way); on a one-body drop with E 5x off it landed
    #: within 0.2 % of the truth. Use a power of two (16: one candidate in each sixteenth of
    #: every searched range, for E over 1e3-1e7 Pa one per factor of 1.8); N + 1 rollouts
    #: without a tape, the start included
    global_candidates: int = 0
    global_frames: int = 0
    global_polish: int = 0
    holdout_frames: int = 0
    intervals: bool = True
    interval_method: str = "laplace"
    contact: str = "fixed"
    contact_iterations: int = 20
    contact_margin: float = 0.05
    contact_tie_iterations: int = 0
    laws: dict[str, str] = field(default_factory=dict)
    law_choice: str = "fixed"
    law_alternatives: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_LAW_ALTERNATIVES))

    @staticmethod
    def value_problems(values: dict[str, Any]) -> list[str]:
        """Values the type check cannot catch, each naming the key and what is valid."""
        out = [
            f"identify.{key}={values.get(key)!r}: valid values are {list(valid)}"
            for key, valid in (
                ("method", IDENTIFY_METHODS),
                ("velocity_window", VELOCITY_WINDOWS),
                ("library_scope", LIBRARY_SCOPES),
                ("start", IDENTIFY_STARTS),
                ("ground_friction_start", GROUND_FRICTION_STARTS),
                ("interval_method", INTERVAL_METHODS),
                ("contact", IDENTIFY_CONTACT),
                ("law_choice", IDENTIFY_LAW_CHOICE),
            )
            if values.get(key) not in valid
        ]
        out += _range_problems("identify", values, IDENTIFY_RANGES)
        if values.get("resync_every", 0) > 0 and values.get("resync_iterations", 1) < 1:
            out.append(
                f"identify.resync_iterations={values['resync_iterations']!r}: must be >= 1 "
                "when resync_every > 0"
            )
        out += law_problems(values.get("laws") or {})
        alternatives = values.get("law_alternatives") or {}
        out += law_problems(alternatives, key="identify.law_alternatives")
        if values.get("method") == "library" and values.get("library_sweeps", 1) < 1:
            out.append(
                f"identify.library_sweeps={values['library_sweeps']!r}: must be >= 1 with "
                "method 'library' (each sweep tries every prototype of every object)"
            )
        return out


def law_problems(laws: dict[str, str], *, key: str = "identify.laws") -> list[str]:
    """``laws`` (the recipe's ``key``): each key a scene material, each value a law with the
    same parameters (a variant of its stress, not another material)."""
    from mosiv_framework.laws import FAMILIES, get_law
    from mosiv_framework.scene import MATERIAL_FAMILIES

    out = []
    for material, law in laws.items():
        where = f"{key}.{material}={law!r}"
        if material not in MATERIAL_FAMILIES:
            out.append(
                f"{where}: {material!r} is not a scene material; valid: "
                f"{', '.join(MATERIAL_FAMILIES)}"
            )
        elif law not in FAMILIES:
            out.append(f"{where}: unknown law; valid: {', '.join(FAMILIES)}")
        else:
            own, other = get_law(material).param_names(), get_law(law).param_names()
            if own != other:
                out.append(
                    f"{where}: its parameters {other} differ from {material}'s {own}; "
                    "name a law with the same parameters"
                )
    return out


#: (least, greatest, what the value is) of numeric identify settings; None: unbounded.
#: Iteration counts may be 0 (the phase is skipped); learning rates are Adam step sizes
IDENTIFY_RANGES: dict[str, tuple[float | None, float | None, str]] = {
    "velocity_iterations": (0, None, "Adam steps of the velocity phase (0 skips it)"),
    "param_iterations": (0, None, "Adam steps of the parameter phase (0 skips it)"),
    "velocity_lr": (0, None, "a positive learning rate (m/s per Adam step)"),
    "param_lr": (0, None, "a positive learning rate (normalised units per Adam step)"),
    "horizon_start": (1, None, "frames rolled out at the first iteration"),
    "horizon_full_at": (0.0, 1.0, "fraction of each phase until the whole window is used"),
    "resync_every": (0, None, "parameter iterations between velocity re-fits (0 = off)"),
    "resync_iterations": (0, None, "Adam steps of each velocity re-fit"),
    "seed": (0, None, "a random seed"),
    "checkpoint_every": (1, None, "iterations between checkpoints"),
    "contact_gap": (0.0, None, "a distance in m (0 = automatic)"),
    "ballistic_tolerance": (0.0, None, "a fraction of the points' spacing (0 = off)"),
    "stiffness_cfl": (0.0, 1.0, "cells a P-wave may cross per substep; 0 = no cap"),
    "silhouette_size": (8, 1024, "the side of the compared silhouettes in pixels"),
    "library_sweeps": (0, None, "coordinate sweeps of the library baseline"),
    "global_candidates": (0, None, "candidates of the global stage (0 = off)"),
    "global_frames": (0, None, "last frame of the global stage's rollouts (0 = all observed)"),
    "global_polish": (0, None, "values per parameter of the global stage's coordinate scan"),
    "holdout_frames": (0, None, "observed frames held out of the parameter phase (0 = off)"),
    "contact_iterations": (0, None, "parameter steps of each contact mode's brief fit"),
    "contact_margin": (0.0, 1.0, "the fraction by which the other contact mode must fit better"),
    "contact_tie_iterations": (0, None, "parameter steps that continue tied brief fits"),
}
#: rates are exclusive at 0: a zero learning rate never moves
_POSITIVE = ("velocity_lr", "param_lr")


def _range_problems(
    section: str, values: dict[str, Any], ranges: dict[str, tuple[Any, Any, str]]
) -> list[str]:
    """One problem per value outside its range (or not finite), naming key, value and range."""
    out = []
    for key, (least, greatest, what) in ranges.items():
        value = values.get(key)
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            continue  # a type problem, reported by the schema merge
        if not math.isfinite(value):
            out.append(f"{section}.{key}={value!r}: must be a finite number ({what})")
            continue
        low_ok = least is None or (value > least if key in _POSITIVE else value >= least)
        high_ok = greatest is None or value <= greatest
        if low_ok and high_ok:
            continue
        if key in _POSITIVE:
            valid = f"> {least}"
        elif greatest is None:
            valid = f">= {least}"
        else:
            valid = f"in [{least}, {greatest}]"
        out.append(f"{section}.{key}={value!r}: must be {valid} ({what})")
    return out


@dataclass
class EvaluateSection:
    """Evaluation over observed and future frames (metrics.json, videos, plots)."""

    emd_samples: int = 2048
    render_videos: bool = True
    seed: int = 0
    #: videos: the scene camera they are drawn from ("" = the first in cameras.json), their
    #: size in pixels and frame rate (0 = the scene's fps)
    video_camera: str = ""
    video_size: int = 256
    video_fps: float = 0.0
    #: "gif", or "mp4" (H.264 through imageio-ffmpeg, far smaller for long or large videos)
    video_format: str = "gif"

    @staticmethod
    def value_problems(values: dict[str, Any]) -> list[str]:
        """Values the type check cannot catch, each naming the key and what is valid."""
        problems = _range_problems("evaluate", values, EVALUATE_RANGES)
        video_format = values.get("video_format", "gif")
        if video_format not in VIDEO_FORMATS:
            problems.append(
                f"evaluate.video_format={video_format!r}: must be one of {', '.join(VIDEO_FORMATS)}"
            )
        return problems


VIDEO_FORMATS = ("gif", "mp4")


#: the exact EMD matches n sampled points by the Hungarian algorithm: n^2 distances in memory
#: (8192 samples: 0.5 GiB of float64) and n^3 time, so the cap keeps evaluation finishing
EMD_SAMPLES_MAX = 8192
EVALUATE_RANGES: dict[str, tuple[float | None, float | None, str]] = {
    "emd_samples": (1, EMD_SAMPLES_MAX, "points per set matched by the exact EMD"),
    "seed": (0, None, "a random seed"),
    "video_size": (16, 4096, "the video's side in pixels"),
    "video_fps": (0.0, None, "frames per second (0 = the scene's)"),
}


@dataclass
class DiagnoseSection:
    """Finding missing physics (docs/DIAGNOSIS.md)."""

    #: screen only these candidates (empty: every candidate the simulator supports)
    terms: list[str] = field(default_factory=list)
    #: never screen these (how the suite builds its out-of-library scenes)
    exclude: list[str] = field(default_factory=list)
    #: the budget's candidates, refit starts and bootstrap resamples, unless set here (None,
    #: not a number, so that a recipe never caps the full budget's 4 candidates unasked)
    max_candidates: int | None = None
    bootstrap: int | None = None
    starts: int | None = None
    #: the budget's Adam steps and backtracking steps per refit start, unless set here
    iterations: int | None = None
    polish: int | None = None
    #: refit step of the initial velocities, m/s per Adam step (default 0.02). Contact scenes
    #: may want far less: on ground_restitution-1 one 0.02 m/s step took the fit from 10 to
    #: 12,000 mm^2
    refit_velocity_lr: float | None = None
    #: a further refit start at the far end of the screening's walk for contact and material
    #: candidates (``diagnose.diagnosis.refit_starts``); default off
    far_start: bool | None = None
    #: before an effect is named, refit it and the null on a second grid and require the same
    #: evidence and coefficients there (``diagnose.grid_stability``); default: the budget's (on
    #: in full, off in small). grid_factor: the second grid over simulator.grid (default 0.75);
    #: grid_tolerance: the allowed difference in combined 95 % half-widths (default 1)
    grid_check: bool | None = None
    grid_factor: float | None = None
    grid_tolerance: float | None = None
    #: the refits' and fresh identifications' descents in lockstep, one batched rollout per
    #: step (``diagnose.descent``); false: one after another, the same results (bit for bit
    #: on warp-mpm's CPU path), for timing what the batch saves. Default on
    together: bool | None = None
    #: which models are also identified afresh with the run's schedule beside their refit,
    #: the better kept (``REIDENTIFY``): every, null-model or none; default:
    #: the budget's (every in full, none in small)
    reidentify: str | None = None

    @staticmethod
    def value_problems(values: dict[str, Any]) -> list[str]:
        """Values the type check cannot catch, each naming the key and what is valid."""
        out = []
        for key, least in (
            ("max_candidates", 1),
            ("bootstrap", 1),
            ("starts", 1),
            ("iterations", 1),
            ("polish", 0),
        ):
            if values.get(key) is not None and values[key] < least:
                out.append(f"diagnose.{key}={values[key]!r}: must be >= {least} (or null)")
        fresh = values.get("reidentify")
        if fresh is not None and fresh not in REIDENTIFY:
            out.append(
                f"diagnose.reidentify={fresh!r}: valid values are {', '.join(REIDENTIFY)} "
                "(or null: the budget's)"
            )
        lr = values.get("refit_velocity_lr")
        if lr is not None and not lr > 0:
            out.append(f"diagnose.refit_velocity_lr={lr!r}: must be a positive step in m/s")
        return out + grid_option_problems(values)


#: which models a diagnosis identifies afresh beside their refits (``diagnose.reidentify``)
REIDENTIFY = ("every", "null-model", "none")

#: the second grid over simulator.grid a recipe may ask the grid check for (besides 1)
GRID_FACTOR_RANGE = (0.25, 4.0)


def grid_option_problems(values: dict[str, Any]) -> list[str]:
    """What is wrong with a ``diagnose`` section's grid-check keys (None: the default), each
    problem naming the key, its value and the valid values."""
    out = []
    check = values.get("grid_check")
    if check is not None and not isinstance(check, bool):
        out.append(f"diagnose.grid_check={check!r}: valid values are true, false or null")
    factor, tolerance = values.get("grid_factor"), values.get("grid_tolerance")
    low, high = GRID_FACTOR_RANGE
    if factor is not None and not (_is_number(factor) and low <= factor <= high and factor != 1):
        out.append(
            f"diagnose.grid_factor={factor!r}: valid values are numbers from {low:g} to "
            f"{high:g} other than 1 (the second grid over simulator.grid, e.g. 0.75 or 1.5), "
            "or null"
        )
    if tolerance is not None and not (
        _is_number(tolerance) and tolerance > 0 and math.isfinite(tolerance)
    ):
        out.append(
            f"diagnose.grid_tolerance={tolerance!r}: valid values are positive numbers (the "
            "allowed difference in combined 95 % half-widths), or null"
        )
    return out


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@dataclass
class OutputSection:
    """The run folder and how to treat an existing one."""

    dir: str = "runs/default"
    resume: bool = True


@dataclass
class Recipe:
    scene: SceneSection = field(default_factory=SceneSection)
    reconstructor: dict[str, Any] = field(default_factory=lambda: {"name": "oracle"})
    lifter: dict[str, Any] = field(default_factory=lambda: {"name": "gt-points"})
    simulator: dict[str, Any] = field(default_factory=lambda: {"name": "warp-mpm"})
    losses: dict[str, Any] = field(
        default_factory=lambda: {"chamfer": {"weight": 1.0}, "silhouette": {"weight": 1.0}}
    )
    #: optional effects (drag, wind, ...) in every rollout: term name -> initial values and
    #: ``identify`` (whether the parameter phase fits them)
    physics_terms: dict[str, Any] = field(default_factory=dict)
    identify: IdentifySection = field(default_factory=IdentifySection)
    evaluate: EvaluateSection = field(default_factory=EvaluateSection)
    diagnose: DiagnoseSection = field(default_factory=DiagnoseSection)
    output: OutputSection = field(default_factory=OutputSection)
