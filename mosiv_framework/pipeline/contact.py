"""Which contact between objects a recording's world has, chosen from its observed frames.

MOSIV's simulators model objects that touch in two ways (``simulator.contact``, docs/PHYSICS.md
"Contact between objects"): ``multi_field``, one velocity field per object with Coulomb
friction between them, where bodies part after an impact, and ``single_field``, one field for
all objects, where bodies that touch share velocities with no friction between them (classic
MPM, and how Genesis solves its scenes; plastic bodies stay together, elastic ones can spring
apart). A
recording does not say which of the two its world has, so ``identify.contact: auto`` lets the
data decide:

1. After the velocity phase (which fits the free flight before any contact, the same in both
   modes), each mode in turn starts from the same parameters, runs the global stage when it is
   on (``identify.global_candidates``) and then ``identify.contact_iterations`` steps of the
   parameter phase over every observed frame, in that mode: each mode is scored with the
   materials that suit it, not with the start's. On four tiny two-body scenes, each made in
   both modes and identified from a recipe naming the other, the choice scored at the start
   alone was wrong in two of the eight runs (the start's materials were as far off as the
   contact); after three steps per mode it was right in all eight, the chosen mode's loss 1.2
   to 160 times lower.
2. Each mode's objective is evaluated over every observed frame, both on the same random
   subsets of points (the Chamfer losses subsample afresh on every call; without common draws
   the two scores would differ by the draw alone).
3. The recipe's ``simulator.contact`` is kept unless the other mode's loss is lower than
   ``(1 - identify.contact_margin)`` times the kept mode's loss. Where the bodies never touch
   in the observed frames both modes roll out the same motion and the recipe decides.
   With ``identify.contact_tie_iterations`` the variants the rule cannot tell apart (within
   the margin of the lowest loss, ``tied``) first continue their brief fits by that many
   steps, and the rule decides on their new losses (a tie after a few steps may be one mode
   still converging from farther away).
4. A choice that about half or twice the margin would have made otherwise, or one between
   variants that are not the recipe's and lie within the margin of each other, is a close call
   (``close_call``): decided by the margin's exact value more than by the data. It is recorded
   and warned about, not changed: on the capture of a paper-size scene (docs/RESULTS.md, "A
   recording through a rig and back") single_field won by 5.4 % against the 5 % margin and
   predicted the future 20x worse than the runs that kept multi_field.

The same brief fits also choose the stress (``identify.law_choice: auto``): each contact mode is
tried with the recipe's laws (``identify.laws``) and with those laws overridden by
``identify.law_alternatives`` (by default the fixed-corotated stress, which Genesis's Elastic
and ElastoPlastic use, for elastic and plasticine bodies). The alternative laws have the same
parameters, so starts, bounds and errors mean the same. The rule is the one above over every
variant: the lowest loss wins where it beats the recipe's variant (its contact mode with its
laws) by the margin, so an alternative can win although, in the same contact mode, it fits
only a little better than the recipe's laws. A scene whose materials have no alternative tries
only its own laws. Each combination is a "variant", named by its mode, followed by
`` + alternatives`` where it uses the alternative laws.

The choice is recorded in the history (phase ``contact``; the brief fits are phase
``contact_fit``, the global stage's records tagged with their ``contact`` mode), in
identified.json under ``contact`` (``choice``, ``mode``, and for ``auto`` the
``recipe_mode``, each variant's ``losses``, the ``margin`` and the last of the ``frames``
scored, ``close_call`` naming the rival of a close call, after a tie the ``brief_losses``
before it was continued and the ``tie_iterations``, and with the law choice the chosen
``laws`` set and its ``law_map``, object id -> law) and in the log. With ``identify.contact: fixed`` identified.json records the recipe's mode.
The parameter phase continues from the chosen mode's brief fit, and it, the intervals,
evaluation and every later rollout of the run (``mosiv eval``, ``mosiv simulate``, ``mosiv
diagnose``) use the chosen mode (``simulator_section``). The cost: per mode, the global
stage's rollouts and ``contact_iterations`` parameter steps. Nothing here reads the scene's
ground truth.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import torch
from omegaconf import DictConfig, OmegaConf

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.phases import BestIterate, Fit
from mosiv_framework.simulation import CONTACT_MODES

log = logging.getLogger(__name__)

#: the history's phase name of the contact choice
PHASE = "contact"


@dataclass
class ContactModes:
    """The simulators identification may choose between, one per contact mode; ``default`` is
    the recipe's ``simulator.contact`` (kept unless the other mode fits better by more than
    ``margin``, a fraction of its loss)."""

    simulators: dict[str, object]
    default: str
    margin: float
    #: law set name -> object id -> the law the object is rolled out with; the first set is
    #: the recipe's (kept unless another fits better by more than ``margin``); empty: the laws
    #: are not chosen
    law_sets: dict[str, dict[int, str]] = field(default_factory=dict)
    #: parameter steps that continue the brief fits of variants tied within ``margin``
    #: (``identify.contact_tie_iterations``; 0: a tie keeps the recipe's variant at once)
    tie_iterations: int = 0

    @property
    def order(self) -> list[str]:
        """The modes, the recipe's first."""
        return [self.default] + [m for m in self.simulators if m != self.default]

    def variants(self) -> list[tuple[str, str | None]]:
        """Every (contact mode, law set) to try, the recipe's first (law set None: not chosen)."""
        sets = list(self.law_sets) or [None]
        return [(mode, laws) for mode in self.order for laws in sets]

    def label(self, mode: str, laws: str | None) -> str:
        """A variant's name in records and logs: its mode, with `` + SET`` after it where it
        uses another law set than the recipe's."""
        if laws is None or laws == next(iter(self.law_sets)):
            return mode
        return f"{mode} + {laws}"


def contact_modes(
    simulator_section,
    simulator,
    *,
    margin: float,
    tie_iterations: int = 0,
    every_mode: bool = True,
    law_sets: dict[str, dict[int, str]] | None = None,
) -> ContactModes:
    """A ContactModes of ``simulator`` (built from ``simulator_section``, the recipe's) and, with
    ``every_mode``, the same simulator in every other mode of ``CONTACT_MODES``; ``law_sets``
    as ``ContactModes.law_sets`` (see ``law_sets``)."""
    from mosiv_framework.registry import get_registry

    options = dict(OmegaConf.to_container(simulator_section, resolve=True))
    name, default = options.pop("name"), options.get("contact", "none")
    simulators = {default: simulator}
    for mode in CONTACT_MODES if every_mode else ():
        if mode != default:
            simulators[mode] = get_registry().create(
                "simulator", name, {**options, "contact": mode}
            )
    return ContactModes(simulators, default, margin, dict(law_sets or {}), int(tie_iterations))


def law_sets(
    materials: Mapping[int, str], laws: Mapping[str, str], alternatives: Mapping[str, str]
) -> dict[str, dict[int, str]]:
    """The law sets ``identify.law_choice: auto`` tries, object id -> law: ``recipe`` (each
    scene material's law in ``laws``, else its own) and ``alternatives`` (``laws`` overridden by
    ``alternatives``), the latter only where it changes some object's law."""
    recipe = {k: laws.get(m, m) for k, m in materials.items()}
    other = {k: {**laws, **alternatives}.get(m, m) for k, m in materials.items()}
    return {"recipe": recipe} if other == recipe else {"recipe": recipe, "alternatives": other}


def pick(losses: dict[str, float], default: str, margin: float) -> str:
    """The rule: ``default`` unless another mode's loss is below ``(1 - margin)`` times its
    loss (an infinite loss, a diverged rollout, loses to any finite one)."""
    kept = losses[default]
    best = min(losses, key=lambda m: (losses[m], m != default))
    if best == default or not math.isfinite(losses[best]):
        return default
    if not math.isfinite(kept) or losses[best] < (1.0 - margin) * kept:
        return best
    return default


def close_call(losses: dict[str, float], default: str, margin: float) -> str | None:
    """The rival of a choice decided by the margin's exact value more than by the data, else
    None: the variant the rule would choose with about half or twice the margin (the factor
    ``1 - margin`` a rival's loss must beat, taken to its square root or its square, which stay
    margins below 1 for any margin), or, where a variant other than the recipe's won, another
    such variant it does not beat by the margin (between those the lower loss decides alone).
    A margin of 0 has no close calls: the lower loss decides."""
    chosen = pick(losses, default, margin)
    factor = 1.0 - margin
    for other_factor in (math.sqrt(factor), factor**2):
        other = pick(losses, default, 1.0 - other_factor)
        if other != chosen:
            return other
    if chosen != default:
        for label, loss in losses.items():
            unbeaten = not losses[chosen] < factor * loss
            if label not in (chosen, default) and math.isfinite(loss) and unbeaten:
                return label
    return None


def tied(losses: dict[str, float], margin: float) -> list[str]:
    """The variants the rule cannot tell apart: those whose loss the lowest one does not beat
    by more than ``margin`` (a fraction of their loss); empty unless there are two or more."""
    finite = {m: v for m, v in losses.items() if math.isfinite(v)}
    if not finite:
        return []
    lowest = min(finite.values())
    close = [m for m, v in finite.items() if not lowest < (1.0 - margin) * v]
    return close if len(close) > 1 else []


def choose_contact(
    modes: ContactModes,
    fit: Fit,
    vector,
    *,
    frames: int,
    search: Callable[[Fit], None],
    history: list[dict],
    extend: Callable[[Fit, int], None] | None = None,
) -> dict:
    """Score every mode (see the module docstring), leave ``fit.simulator`` in the chosen one
    and ``vector`` at that mode's start; returns the choice's history record (also appended).

    Args:
        modes: the simulators to choose between.
        fit: the identification's Fit; its ``simulator`` is replaced by the chosen one.
        vector: the ParameterVector, changed in place (by ``search``, and to the chosen
            mode's start).
        frames: the last frame scored (the observed window).
        search: the global stage and brief fit, run in each mode before it is scored (it
            moves ``vector``; a SimulationDiverged from it scores the mode ``inf``).
        history: the identification history; the global stage's records of each mode are
            tagged with ``contact``.
        extend: continues a variant's brief fit by the given number of parameter steps; with
            ``modes.tie_iterations`` it is run on each variant of a tie (``tied``) from where
            its brief fit left it, and the variants are scored again.
    """
    start = BestIterate.snapshot(vector)
    draws = _draw_states(fit.objective)
    losses, leaves, variants = {}, {}, {}

    def fit_and_score(label: str, run: Callable[[Fit], None], what: str) -> None:
        """Run ``run`` in variant ``label`` from where ``vector`` is and score it; the records
        it appends are tagged with the variant, a divergence scores it inf (leaves kept)."""
        _use_variant(modes, fit, vector, *variants[label])
        first = len(history)
        try:
            run(fit)
        except SimulationDiverged as exc:  # not one rollout of this variant worked
            log.warning("contact %s%s: %s", label, what, exc)
            losses[label] = math.inf
            return
        finally:
            for record in history[first:]:
                record["contact"] = label
        _restore_draws(draws)
        losses[label] = _score(fit, vector, frames)
        leaves[label] = BestIterate.snapshot(vector)
        log.info("contact %s%s: loss %.6g over frames 1..%d", label, what, losses[label], frames)

    for mode, laws in modes.variants():
        label = modes.label(mode, laws)
        variants[label], leaves[label] = (mode, laws), start
        start.apply(vector)
        fit_and_score(label, search, "")
    default = modes.label(*modes.variants()[0])
    brief = dict(losses)
    close = tied(losses, modes.margin) if extend is not None and modes.tie_iterations > 0 else []
    steps = modes.tie_iterations
    for label in close:  # more evidence where the brief fits could not tell the variants apart
        leaves[label].apply(vector)
        fit_and_score(label, lambda f: extend(f, steps), f", continued by {steps} steps")
    chosen = pick(losses, default, modes.margin)
    mode, laws = variants[chosen]
    leaves[chosen].apply(vector)
    _use_variant(modes, fit, vector, mode, laws)
    record = _choice_record(modes, mode, laws, losses, brief if close else None, frames, vector)
    rival = close_call(losses, default, modes.margin)
    if rival is not None:
        record["close_call"] = rival
    history.append(record)
    _log_choice(chosen, default, losses, modes.margin, rival)
    return record


def _log_choice(chosen: str, default: str, losses: dict, margin: float, rival: str | None):
    """The log's line of the choice, and a warning where it was a close call."""
    log.info(
        "contact between objects: %s (%s; the recipe's %s is kept unless another is more "
        "than %g %% lower)",
        chosen,
        ", ".join(f"{m} {v:.6g}" for m, v in losses.items()),
        default,
        100 * margin,
    )
    if rival is not None:
        log.warning(close_call_warning(chosen, rival, margin))


def close_call_warning(chosen: str, rival: str, margin: float) -> str:
    """What a run says of a close call between ``chosen`` and ``rival`` (variant labels, see
    ``ContactModes.label``), with the settings of a run that holds the rival."""
    (mode, laws), (rival_mode, rival_laws) = _split_label(chosen), _split_label(rival)
    settings = []
    if rival_mode != mode:
        settings.append(f"identify.contact=fixed simulator.contact={rival_mode}")
    if rival_laws != laws:
        settings.append(
            "identify.law_choice=fixed"
            + (" with identify.laws as identify.law_alternatives sets them" if rival_laws else "")
        )
    return (
        f"contact between objects: {chosen} was a close call (with identify.contact_margin="
        f"{margin:g} about halved or doubled, or between variants the margin does not protect, "
        f"{rival} would do as well); the two can predict the future very differently: compare "
        f"a run that holds {rival} ({'; '.join(settings)})"
    )


def recorded_close_call(modes: ContactModes, record: dict) -> str | None:
    """``close_call_warning`` of a recorded choice (the history's record, or identified.json's
    ``contact``), None where it was no close call."""
    if not record.get("close_call"):
        return None
    chosen = modes.label(record["mode"], record.get("laws"))
    return close_call_warning(chosen, record["close_call"], record["margin"])


def _split_label(label: str) -> tuple[str, str | None]:
    """A variant label's contact mode and law set (None: the recipe's laws)."""
    mode, _, laws = label.partition(" + ")
    return mode, laws or None


def _finite(losses: dict[str, float]) -> dict[str, float | None]:
    """Losses for JSON: a variant that diverged (inf) is None."""
    return {m: (v if math.isfinite(v) else None) for m, v in losses.items()}


def _choice_record(modes, mode, laws, losses, brief, frames: int, vector) -> dict:
    """The history record of the choice of ``mode`` (and the stress variant ``laws``);
    ``brief``: the brief fits' losses where tied variants were continued (``losses`` are then
    those after the continuation), else None."""
    record = {
        "phase": PHASE,
        "choice": "auto",
        "mode": mode,
        "recipe_mode": modes.default,
        "losses": _finite(losses),
        "margin": modes.margin,
        "frames": frames,
        "values": vector.to_json(),
    }
    if brief is not None:
        record["brief_losses"] = _finite(brief)
        record["tie_iterations"] = modes.tie_iterations
    if laws is not None:
        record["laws"] = laws
        record["law_map"] = {str(k): law for k, law in modes.law_sets[laws].items()}
    return record


def restore_choice(modes: ContactModes, fit: Fit, history: list[dict], vector=None) -> None:
    """After resuming from a checkpoint: put ``fit`` (and ``vector``'s laws) back in the
    variant the history chose."""
    record = choice_record(history)
    if record is not None and record["mode"] in modes.simulators:
        fit.simulator = modes.simulators[record["mode"]]
        if vector is not None and record.get("laws") in modes.law_sets:
            _use_variant(modes, fit, vector, record["mode"], record["laws"])
        warning = recorded_close_call(modes, record)
        if warning:  # said again: this process's log has not said it yet
            log.warning(warning)


def _use_variant(modes: ContactModes, fit: Fit, vector, mode: str, laws: str | None) -> None:
    """Roll out in ``mode`` with law set ``laws`` (None: the laws as they are): the simulator,
    and the laws in ``vector`` and in ``fit``'s particles."""
    fit.simulator = modes.simulators[mode]
    if laws is None:
        return
    families = modes.law_sets[laws]
    vector.families.update(families)
    fit.particles = replace(fit.particles, materials=dict(families))


def choice_record(history: list[dict]) -> dict | None:
    """The history's contact choice, if identification made one."""
    records = [h for h in history if h.get("phase") == PHASE]
    return records[-1] if records else None


def contact_json(history: list[dict], simulator_section) -> dict | None:
    """identified.json's ``contact``: the choice the history holds, else the recipe's fixed
    mode; None for a simulator without a ``contact`` option."""
    record = choice_record(history)
    if record is not None:
        keep = ("choice", "mode", "recipe_mode", "losses", "margin", "frames", "laws", "law_map",
                "brief_losses", "tie_iterations", "close_call")  # fmt: skip
        return {k: record[k] for k in keep if k in record}
    mode = simulator_section.get("contact", None)
    return None if mode is None else {"choice": "fixed", "mode": str(mode)}


def simulator_section(section, identified_json: dict | None) -> DictConfig:
    """The recipe's simulator section with the contact identification used (identified.json's
    ``contact.mode``); unchanged where identified.json records none (fixed contact, or a run
    made before the choice existed)."""
    section = OmegaConf.create(OmegaConf.to_container(section, resolve=True))
    mode = ((identified_json or {}).get("contact") or {}).get("mode")
    if mode is not None and "contact" in section:
        section.contact = mode
    return section


def _score(fit: Fit, vector, frames: int) -> float:
    """The objective over frames 1..frames; inf where the rollout diverges."""
    try:
        value = fit.window_loss(vector, frames)
    except SimulationDiverged:
        return math.inf
    return value if math.isfinite(value) else math.inf


def _draw_states(objective) -> list[tuple[torch.Generator, torch.Tensor]]:
    """The random generators of the objective's terms (point subsampling) and their states."""
    generators = [getattr(t, "generator", None) for t in objective.terms.values()]
    return [(g, g.get_state()) for g in generators if isinstance(g, torch.Generator)]


def _restore_draws(states: list[tuple[torch.Generator, torch.Tensor]]) -> None:
    for generator, state in states:
        generator.set_state(state)
