"""Stage III: identify initial velocities, then per-object parameters, through the simulator.

Paper section 3.5: Adam on the initial velocity first, then on the continuous parameters of each
object's known family, minimising the recipe's losses over the observed frames with a horizon
curriculum, optionally interleaving the parameter steps with re-fits of the initial velocities
(``identify.resync_every``: the paper's alternating updates with re-synchronisation of the
particle state).

``identify`` runs the phases of ``mosiv_framework.pipeline.phases`` one after the other and
owns what they share: the history, checkpoints (every few iterations, so an interrupted run
resumes where it stopped), each phase's best iterate (its start included: a phase never returns
something worse than it was given), stepping back from diverged rollouts, and the
``stopped_early`` records of phases cut short. Before the parameter phase, the global stage
(``mosiv_framework.pipeline.global_search``, ``identify.global_candidates`` rollouts) picks
where the descent starts; a checkpoint after it means a resumed run does not redo it. After
the phases, ``identify.intervals`` adds a 95 % interval per identified parameter
(``mosiv_framework.pipeline.uncertainty``) as a history record of phase ``intervals``.

Which iterate a parameter phase returns: the curriculum optimises frames ``1..h`` with ``h``
growing, and only losses over the whole window compare, so the phase keeps the best iterate of
every horizon and, at its end, scores those and its last iterate on the whole window too. Before
that, a phase that overshot the truth on a short horizon (Adam's momentum carries a stiffness a
decade past it, where the ceiling clamps it) and came back only under the decayed learning rate
returned its start, because no full-window iterate happened to beat it; the best short-horizon
iterates, which sat next to the truth, were never compared. Adam's first moment is also zeroed
where a bound clamps a coordinate, so momentum does not hold a parameter against its bound for
many steps after the gradient has turned.
"""

from __future__ import annotations

import logging
import math
import re
from collections import deque
from dataclasses import dataclass, field

import torch
from tqdm import tqdm

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.contact import ContactModes, choose_contact, restore_choice
from mosiv_framework.pipeline.global_search import coordinate_polish, global_search
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.pipeline.phases import (
    BestIterate,
    Fit,
    ParameterPhase,
    Phase,
    build_phases,
    geometry,
    gradients_finite,
    horizon,
    resync_velocities,
)
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.types import ParticleSet, World

# re-exported: other modules import the phases' helpers from here
__all__ = [
    "CHECKPOINT",
    "MAX_BACKOFFS",
    "Phase",
    "geometry",
    "gradients_finite",
    "horizon",
    "identify",
    "resync_velocities",
]

log = logging.getLogger(__name__)

CHECKPOINT = "identify/checkpoint.pt"
#: the history's phase name of the brief fits that compare contact modes
CONTACT_FIT = "contact_fit"
#: consecutive diverged rollouts tolerated, each stepping one accepted iterate further back and
#: halving the step size, before the phase stops at its best iterate
MAX_BACKOFFS = 6


@dataclass
class IdentifyState:
    """What the phases share and the checkpoint holds: the vector being optimised in place, the
    per-iteration history, and where checkpoints go (written under ``config_hash``)."""

    vector: ParameterVector
    run_dir: RunDir
    config_hash: str
    history: list[dict] = field(default_factory=list)
    #: whether the global stage has run (a resumed run does not redo it)
    global_done: bool = False

    def save_checkpoint(self, phase: int, iteration: int, optimizer: dict | None) -> None:
        """Resume at ``phase``'s ``iteration`` with ``optimizer`` (None: start that phase)."""
        vector = self.vector
        self.run_dir.save_torch(
            CHECKPOINT,
            {
                "config": self.config_hash,
                "phase": phase,
                "iteration": iteration,
                "history": self.history,
                "global_done": self.global_done,
                "optimizer": optimizer,
                "velocity": {k: v.detach().clone() for k, v in vector.velocity.items()},
                "normalized": {k: u.detach().clone() for k, u in vector.normalized.items()},
            },
        )

    def resume(self) -> tuple[int, int, dict | None]:
        """Restore the checkpoint if it was written under the same ``config_hash`` (the
        fingerprint of everything identification depends on); returns (phase, iteration,
        optimizer state), (0, 0, None) when starting afresh."""
        path = self.run_dir.path(CHECKPOINT)
        ckpt = self.run_dir.load_torch(CHECKPOINT) if path.is_file() else None
        if ckpt is None or ckpt.get("config") != self.config_hash:
            return 0, 0, None
        self.history = ckpt["history"]
        self.global_done = bool(ckpt.get("global_done", False))
        with torch.no_grad():
            for k, v in ckpt["velocity"].items():
                self.vector.velocity[k].copy_(v)
            for key, u in ckpt["normalized"].items():
                self.vector.normalized[key].copy_(u)
        return ckpt["phase"], ckpt["iteration"], ckpt["optimizer"]


def identify(
    *,
    simulator,
    particles: ParticleSet,
    world: World,
    targets: dict[int, torch.Tensor],
    observed_frames: int,
    objective: WeightedSum,
    vector: ParameterVector,
    section,
    run_dir: RunDir,
    config_hash: str = "",
    velocity_frames: int | None = None,
    contact: ContactModes | None = None,
) -> tuple[ParameterVector, list[dict]]:
    """Optimise ``vector`` in place; returns it and the per-iteration history.

    The velocity phase fits frames ``1..velocity_frames - 1`` (the free flight before any
    contact, whose motion does not depend on the unknown materials; default: all observed
    frames); the parameter phase fits every observed frame, its curriculum starting at the first
    frame after that free flight (earlier frames do not depend on any material parameter, so
    their gradients are round-off that Adam, being scale-free, would follow with full-size
    steps). A parameter whose gradient is exactly zero in a step (friction before any contact,
    a yield stress above every stress reached) holds still rather than coasting on Adam's
    momentum, and a non-finite gradient is treated like a diverged rollout: the step is taken
    back (one more accepted iterate back for each consecutive failure) and the learning rate
    halved; when ``MAX_BACKOFFS`` steps back all fail, the phase ends at its best iterate with a
    ``stopped_early`` record in the history. Each phase minimises its loss
    divided by the phase's first loss, so Adam's step sizes are the recipe's learning rates
    whatever the loss's unit or magnitude (Adam is invariant to a constant factor except for
    its epsilon, which would otherwise swamp gradients of m^2-sized Chamfer losses).
    A checkpoint is resumed only if it was written under the same ``config_hash`` (the
    fingerprint of everything identification depends on); otherwise it starts afresh.
    With ``contact`` (``identify.contact: auto``) the contact between objects is chosen from
    the data before the parameter phase (``mosiv_framework.pipeline.contact``), even where that
    phase does not run (the library baseline), and everything after uses the chosen mode.
    """
    if observed_frames < 2:
        raise ConfigError(f"identification needs at least 2 observed frames, got {observed_frames}")
    # the targets move once to where the rollouts come back (the particles' device)
    device = particles.positions.device
    fit = Fit(simulator, particles, world, {k: t.to(device) for k, t in targets.items()}, objective)
    phases = build_phases(section, observed_frames=observed_frames, velocity_frames=velocity_frames)
    state = IdentifyState(vector, run_dir, config_hash)
    start_phase, start_iter, carried = state.resume()
    if contact is not None:
        restore_choice(contact, fit, state.history, vector)
    holdout = int(getattr(section, "holdout_frames", 0) or 0)
    for index, phase in enumerate(phases):
        runs = phase.iterations > 0 and bool(phase.leaves(vector))
        if index < start_phase or not (runs or isinstance(phase, ParameterPhase)):
            continue
        resumed = carried if index == start_phase else None
        global_result = None
        if isinstance(phase, ParameterPhase) and resumed is None and not state.global_done:
            if runs or contact is not None:
                _global_stage(section, fit, state, phase, search=runs, contact=contact)
                state.save_checkpoint(index, 0, None)
            if holdout:  # the global stage's result competes with the descent's at the end
                global_result = BestIterate.snapshot(vector)
        if not runs:
            continue
        run = _PhaseRun(phase, index, fit, state, section.checkpoint_every, resumed)
        run.iterate(first=start_iter if resumed is not None else 0, full_at=section.horizon_full_at)
        if isinstance(phase, ParameterPhase):
            run.polish()
        # end of phase (also when its last iteration diverged): keep the best iterate
        run.best.apply(vector)
        if isinstance(phase, ParameterPhase) and holdout:
            candidates = {"descent": run.best, "global": global_result}
            _choose_on_holdout(fit, vector, candidates, observed_frames - 1, state.history)
        state.save_checkpoint(index + 1, 0, None)
    if getattr(section, "intervals", False) and _parameters_fitted(phases, vector):
        method = getattr(section, "interval_method", "laplace")
        _interval_stage(fit, vector, observed_frames - 1, state.history, method)
    return vector, state.history


def _global_stage(
    section, fit: Fit, state: IdentifyState, phase: Phase, *, search: bool, contact
) -> None:
    """The global stage before the parameter phase (``identify.global_candidates`` Sobol
    candidates over frames ``1..identify.global_frames``, 0: the phase's whole window; only
    where ``search``, i.e. the parameter phase runs). With ``contact`` it runs in every contact
    mode, each followed by a brief fit (``identify.contact_iterations`` parameter steps over
    the phase's whole window), and the mode that fits best is chosen (``choose_contact``)."""
    candidates = int(getattr(section, "global_candidates", 0) or 0) if search else 0
    frames = int(getattr(section, "global_frames", 0) or 0)
    frames = phase.last if frames <= 0 else min(frames, phase.last)
    brief = int(getattr(section, "contact_iterations", 0) or 0) if search else 0
    # the sweep belongs to the global stage: it starts from the stage's best candidate
    polish = int(getattr(section, "global_polish", 0) or 0) if candidates > 0 else 0

    def stage(fit_in_mode: Fit) -> None:
        if candidates > 0:
            log.info("global stage: %d candidates over frames 1..%d", candidates, frames)
            global_search(
                fit_in_mode,
                state.vector,
                candidates=candidates,
                frames=frames,
                seed=int(getattr(section, "seed", 0) or 0),
                history=state.history,
            )
        if polish > 0:
            log.info("global polish: %d values per parameter", polish)
            coordinate_polish(
                fit_in_mode, state.vector, points=polish, frames=frames, history=state.history
            )
        if contact is not None and brief > 0:
            brief_fit(fit_in_mode, brief)

    def brief_fit(fit_in_mode: Fit, steps: int) -> None:
        # the brief fit of a contact mode: the whole window from the first step, no
        # checkpoints (a resumed run redoes the choice), the best iterate kept
        trial = ParameterPhase(CONTACT_FIT, steps, phase.lr, phase.last, phase.last)
        run = _PhaseRun(trial, -1, fit_in_mode, state, steps, None)
        run.iterate(first=0, full_at=section.horizon_full_at)
        run.polish()  # the last step's iterate competes too
        run.best.apply(state.vector)

    if contact is None:
        stage(fit)
    else:
        choose_contact(
            contact, fit, state.vector, frames=phase.last, search=stage, history=state.history,
            extend=brief_fit if search else None,
        )  # fmt: skip
    state.global_done = True


def _choose_on_holdout(
    fit: Fit, vector: ParameterVector, candidates: dict, last: int, history: list
) -> None:
    """Apply whichever of ``candidates`` (name -> BestIterate; None: not available, as after a
    resumed run) fits frames ``1..last`` best, the held-out frames of ``identify.
    holdout_frames`` included; a ``holdout`` record in ``history`` gives each one's loss.

    Each candidate was fitted without the held-out frames, so what tells them apart there is
    how they extrapolate: on data the model cannot match exactly (another engine's, a
    recording) the descent's closer fit of the fitted frames can be the worse prediction."""
    losses = {}
    for name, candidate in candidates.items():
        if candidate is None or candidate.leaves is None:
            continue
        candidate.apply(vector)
        try:
            loss = fit.window_loss(vector, last)
        except SimulationDiverged:
            continue
        if math.isfinite(loss):
            losses[name] = loss
    if not losses:  # nothing could be scored: keep the descent's result
        candidates["descent"].apply(vector)
        history.append({"phase": "holdout", "losses": {}, "chosen": "descent"})
        return
    chosen = min(losses, key=losses.get)
    candidates[chosen].apply(vector)
    log.info(
        "identification: %s kept on the whole window 1..%d (%s)",
        chosen,
        last,
        ", ".join(f"{n} {v:.4g}" for n, v in losses.items()),
    )
    history.append(
        {
            "phase": "holdout",
            "frames": last,
            "losses": losses,
            "chosen": chosen,
            "values": vector.to_json(),
        }
    )


def _parameters_fitted(phases: list[Phase], vector: ParameterVector) -> bool:
    """Whether a parameter phase ran over at least one leaf (intervals are about its result)."""
    return any(
        isinstance(p, ParameterPhase) and p.iterations > 0 and p.leaves(vector) for p in phases
    )


def _interval_stage(fit: Fit, vector: ParameterVector, last: int, history: list, method) -> None:
    """A 95 % interval per identified parameter (``identify.interval_method``), recorded in
    the history."""
    from mosiv_framework.pipeline.uncertainty import interval_record

    history.append(interval_record(fit, vector, last=last, method=method))


class _PhaseRun:
    """One phase's optimisation: Adam over the phase's leaves on a cosine schedule, the loss
    scaled by the phase's first loss, stepping back from diverged rollouts, and the best
    full-horizon iterate, the start included."""

    def __init__(self, phase: Phase, index: int, fit: Fit, state, checkpoint_every, resumed):
        self.phase, self.index, self.fit, self.state = phase, index, fit, state
        self.checkpoint_every = max(1, checkpoint_every)
        self.named = phase.leaves(state.vector)
        self.optimizer = torch.optim.Adam(list(self.named.values()), lr=phase.lr)
        # cosine decay to a tenth of the rate: big steps early, settling at the end
        self.schedule = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer,
            lambda i, n=phase.iterations: 0.1 + 0.45 * (1 + math.cos(math.pi * i / n)),
        )
        # the iterates whose rollouts last succeeded, newest last: a divergence steps back one
        # of them per consecutive failure (the newest may itself diverge over the longer
        # horizon the curriculum has grown to since; a smaller step would not change that)
        self.trail: deque[BestIterate] = deque(maxlen=MAX_BACKOFFS)
        self.backoffs = 0
        if resumed is not None:
            self.optimizer.load_state_dict(resumed["optimizer"])
            self.schedule.load_state_dict(resumed["schedule"])
            self.best = BestIterate(resumed["best_loss"], resumed["best_leaves"])
            self.scale = resumed.get("scale")
            self.by_horizon = {
                int(h): BestIterate(loss, leaves)
                for h, (loss, leaves) in resumed.get("by_horizon", {}).items()
            }
        else:
            self.scale = None
            #: horizon -> the best iterate at that (shorter than the window) horizon
            self.by_horizon: dict[int, BestIterate] = {}
            # the start competes too: a phase never returns something worse than it was given
            # (Adam's first steps are about one learning rate long whatever the gradient, which
            # can throw an already good start, e.g. free-flight velocities, far off)
            self.best = BestIterate()
            state.vector.keep_stable()  # a phase starts inside the limit, whatever set its start
            self.best.offer(fit.window_loss(state.vector, phase.last), state.vector)

    def iterate(self, *, first: int, full_at: float) -> None:
        """Iterations ``first..`` of the phase; returns early when it stopped at its best."""
        phase, state = self.phase, self.state
        bar = tqdm(range(first, phase.iterations), desc=f"identify {phase.name}", unit="it")
        for it in bar:
            h = horizon(it, phase.iterations, start=phase.first, full_at=full_at, last=phase.last)
            phase.before_iteration(it, h, self.fit, state.vector, state.history)
            self.optimizer.zero_grad()
            try:
                loss_value, terms = self._loss_and_gradients(h)
            except SimulationDiverged as exc:
                if self._step_back(exc, it, h):
                    continue
                return
            self._step(it, h, loss_value, terms)
            bar.set_postfix(loss=f"{loss_value:.3e}", h=h)
            if (it + 1) % self.checkpoint_every == 0 and it + 1 < phase.iterations:
                state.save_checkpoint(self.index, it + 1, self._optimizer_state())

    def _loss_and_gradients(self, h: int) -> tuple[float, dict]:
        """The loss over frames 1..h and its scaled gradients on the leaves; raises
        SimulationDiverged for a diverged rollout or a non-finite gradient."""
        predicted, target = self.fit.rollout_geometry(self.state.vector, h)
        loss, terms = self.fit.objective.evaluate(predicted, target)
        loss_value = float(loss.detach())
        if self.scale is None:  # the phase's first loss sets its unit (see ``identify``)
            self.scale = 1.0 / max(loss_value, 1e-30)
        (loss * self.scale).backward()
        _check_gradients(self.named, phase=self.phase.name, horizon=h)
        return loss_value, terms

    def _step(self, it: int, h: int, loss_value: float, terms: dict) -> None:
        """One accepted Adam step, logged in the history."""
        vector = self.state.vector
        self.backoffs = 0
        self.trail.append(BestIterate.snapshot(vector))  # the leaves this step starts from
        # gradients of the unscaled loss, per leaf, for the log
        grads = {
            n: float(leaf.grad.norm()) / self.scale
            for n, leaf in self.named.items()
            if leaf.grad is not None
        }
        if h == self.phase.last:  # only losses over the phase's whole window are comparable
            self.best.offer(loss_value, vector)
        else:  # kept to be scored on the whole window at the end (``polish``)
            self.by_horizon.setdefault(h, BestIterate()).offer(loss_value, vector)
        for leaf in self.named.values():  # no evidence: Adam skips a leaf without a gradient
            if leaf.grad is not None and not bool(leaf.grad.any()):
                leaf.grad = None
        self.optimizer.step()
        self.schedule.step()
        self._clamp_to_bounds()
        self.state.history.append(
            {
                "phase": self.phase.name,
                "iteration": it,
                "horizon": h,
                "loss": loss_value,
                "terms": terms,
                "grad_norm": math.sqrt(sum(g * g for g in grads.values())),
                "grads": grads,
                "lr": self.optimizer.param_groups[0]["lr"],
                "values": vector.to_json(),
            }
        )

    def _clamp_to_bounds(self) -> None:
        """Keep normalised coordinates inside [0, 1] and every stiffness inside the
        simulator's stability limit at the current densities and Poisson ratios
        (``ParameterVector.keep_stable``), and forget Adam's momentum where a bound stopped a
        coordinate: otherwise the first moment, built up on the way there, holds it against
        the bound for many steps after the gradient has turned back."""
        vector = self.state.vector
        with torch.no_grad():
            for u in vector.normalized.values():
                at_bound = (u <= 0.0) | (u >= 1.0)
                u.clamp_(0.0, 1.0)
                moment = self.optimizer.state.get(u, {}).get("exp_avg")
                if moment is not None and bool(at_bound.any()):
                    moment[at_bound] = 0.0
            for key in vector.keep_stable():
                moment = self.optimizer.state.get(vector.normalized[key], {}).get("exp_avg")
                if moment is not None:
                    moment.zero_()

    def polish(self) -> None:
        """Score the last iterate and the best iterate of every shorter horizon over the whole
        window, so the phase returns the best of them if one beats its full-window best (the
        curriculum's short horizons often land nearest the truth; see the module docstring)."""
        last = self.phase.last
        candidates = [BestIterate.snapshot(self.state.vector)]
        candidates += [self.by_horizon[h] for h in sorted(self.by_horizon, reverse=True)]
        keep = BestIterate.snapshot(self.state.vector)
        for candidate in candidates:
            if candidate.leaves is None:
                continue
            candidate.apply(self.state.vector)
            try:
                loss = self.fit.window_loss(self.state.vector, last)
            except SimulationDiverged:
                continue
            if math.isfinite(loss) and loss < self.best.loss:
                log.info(
                    "identification %s: an iterate beat the best over frames 1..%d "
                    "(loss %.4g < %.4g)",
                    self.phase.name,
                    last,
                    loss,
                    self.best.loss,
                )
            if math.isfinite(loss):
                self.best.offer(loss, self.state.vector)
        keep.apply(self.state.vector)
        self.by_horizon = {}

    def _step_back(self, exc: SimulationDiverged, it: int, h: int) -> bool:
        """After a diverged step: back to an earlier iterate at half the rate (True), or, when
        every recent iterate fails at this horizon, a ``stopped_early`` record (False) so the
        phase ends at the best iterate found rather than losing the run."""
        # the last step went somewhere the simulator cannot follow (too stiff or too soft for
        # its substeps, or a gradient that overflowed): step back, take smaller steps from there
        phase, state = self.phase, self.state
        self.backoffs += 1
        where = f"{exc.reason} (identification, {phase.name} iteration {it})"
        if not self.trail and self.best.leaves is None:  # not one rollout of this phase worked
            raise SimulationDiverged(
                object_id=exc.object_id,
                frame=exc.frame,
                substep=exc.substep,
                reason=where,
                advice=f"{exc.advice} Or lower identify.{phase.name}_lr.",
            ) from exc
        record = {"phase": phase.name, "iteration": it, "horizon": h}
        if not self.trail:
            tried = self.backoffs - 1
            record["stopped_early"] = f"{exc} after {tried} steps back"
            state.history.append({**record, "values": state.vector.to_json()})
            log.warning(
                "identification %s phase stopped at iteration %d: %s; %d steps back did not "
                "help, keeping the best iterate",
                phase.name,
                it,
                where,
                tried,
            )
            return False
        self.trail.pop().apply(state.vector)
        self.optimizer.zero_grad()
        # halve the schedule's base rate too, or its next step would undo the halving
        self.schedule.base_lrs = [lr * 0.5 for lr in self.schedule.base_lrs]
        for group in self.optimizer.param_groups:
            group["lr"] *= 0.5
        state.history.append({**record, "diverged": str(exc), "values": state.vector.to_json()})
        return True

    def _optimizer_state(self) -> dict:
        return {
            "optimizer": self.optimizer.state_dict(),
            "schedule": self.schedule.state_dict(),
            "best_loss": self.best.loss,
            "best_leaves": self.best.leaves,
            "scale": self.scale,
            "by_horizon": {h: (b.loss, b.leaves) for h, b in self.by_horizon.items()},
        }


def _check_gradients(named: dict[str, torch.Tensor], *, phase: str, horizon: int) -> None:
    """Raise SimulationDiverged naming the leaves whose gradient is not finite (NaN or inf
    would otherwise enter Adam's state and every later step)."""
    bad = [name for name, leaf in named.items() if not gradients_finite([leaf])]
    if bad:
        owner = re.search(r"obj(\d+)", bad[0])
        raise SimulationDiverged(
            object_id=int(owner.group(1)) if owner else 0,
            frame=horizon,
            substep=0,
            reason=f"non-finite gradient of {', '.join(bad)} in the backward pass over frames "
            f"1..{horizon} ({phase})",
            advice="",
        )
