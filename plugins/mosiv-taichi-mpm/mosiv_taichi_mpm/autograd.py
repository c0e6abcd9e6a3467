"""Bounded-memory reverse mode of a rollout, as a ``torch.autograd.Function``.

Forward keeps only the particle state at video-frame boundaries (checkpoints, torch tensors).
Backward walks the frames from last to first: it reloads a frame's checkpoint, re-simulates that
frame's substeps into the per-substep buffers, then runs the kernels' adjoints substep by
substep in reverse (recomputing that substep's grid first), carrying the state adjoint to the
previous frame. Memory is O(frames x particles) + O(substeps x particles) for one frame.
A rollout that nothing differentiates runs ``RolloutRun.forward`` alone on a forward-only engine
and keeps no checkpoints: O(particles) besides the positions and velocities it returns.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

STATE_NAMES = ("x", "v", "C", "F", "U", "V", "sig", "Jp")
_STATE_SHAPES = {"x": (3,), "v": (3,), "C": (3, 3), "F": (3, 3), "U": (3, 3), "V": (3, 3),
                 "sig": (3,), "Jp": ()}  # fmt: skip


def empty_state(n: int, device: torch.device) -> dict[str, torch.Tensor]:
    """Zero-filled flat arrays for one particle state (float32, contiguous)."""
    return {k: torch.zeros((n, *_STATE_SHAPES[k]), dtype=torch.float32, device=device)
            for k in STATE_NAMES}  # fmt: skip


@dataclass
class RolloutRun:
    """One rollout's forward results and what its backward needs.

    ``engine`` is the simulator's problem object providing ``step``, ``export``, ``load``,
    ``start`` and the adjoint helpers (engine.py ``Engine``). ``keep_checkpoints``: keep each
    frame's starting state for ``backward`` (false for a rollout nothing differentiates).
    """

    engine: object
    frames: int
    n: int
    device: torch.device
    keep_checkpoints: bool = True
    checkpoints: list[dict[str, torch.Tensor]] = field(default_factory=list)
    positions: torch.Tensor | None = None
    velocities: torch.Tensor | None = None
    contact: torch.Tensor | None = None
    #: loads this rollout's particles and parameters into the engine again before the
    #: backward re-simulates: rollouts of one layout share the engine, so a rollout made
    #: between this one's forward and backward (rollout_batch's default loop) replaced them
    prepare: Callable[[], None] | None = None

    def forward(self) -> None:
        eng = self.engine
        S = eng.substeps
        eng.start()
        pos, vel, contact = [], [], []
        state = eng.export(0, grads=False)
        pos.append(state["x"].clone())
        vel.append(state["v"].clone())
        contact.append(eng.empty_contact())
        for f in range(self.frames):
            if f > 0:
                eng.load(0, state, grads=False)
            if self.keep_checkpoints:
                self.checkpoints.append(state)
            eng.reset_frame_diagnostics()
            eng.set_frame(f)
            for s in range(S):
                eng.step(s, diagnostics=True)
            eng.raise_if_diverged(frame=f + 1)
            state = eng.export(S, grads=False)
            pos.append(state["x"].clone())
            vel.append(state["v"].clone())
            contact.append(eng.frame_contact())
        self.positions = torch.stack(pos)
        self.velocities = torch.stack(vel)
        self.contact = None if contact[0] is None else torch.stack(contact)

    def checkpoint_bytes(self) -> int:
        return sum(t.numel() * t.element_size() for c in self.checkpoints for t in c.values())

    def backward(self, grad_positions: torch.Tensor) -> None:
        """Accumulate d(loss)/d(parameters) into the engine's parameter adjoints."""
        eng = self.engine
        S = eng.substeps
        grad_positions = grad_positions.to(self.device, torch.float32).contiguous()
        if self.prepare is not None:
            self.prepare()
        eng.zero_param_grads()
        carry = None
        for f in reversed(range(self.frames)):
            eng.load(0, self.checkpoints[f], grads=False)
            eng.set_frame(f)
            for s in range(S):
                eng.step(s, diagnostics=False)
            eng.zero_state_grads()
            if carry is not None:
                eng.load(S, carry, grads=True)
            eng.add_position_grad(S, grad_positions[f + 1])
            for s in reversed(range(S)):
                eng.step_adjoint(s)
            carry = eng.export(0, grads=True)
        eng.rollout_start_adjoint()


class RolloutFunction(torch.autograd.Function):
    """positions [T, N, 3] = rollout(*parameter tensors); gradients via RolloutRun.backward."""

    @staticmethod
    def forward(ctx, run: RolloutRun, grads_of: object, *tensors: torch.Tensor):
        run.forward()
        ctx.run = run
        ctx.grads_of = grads_of
        ctx.tensors = tensors
        return run.positions

    @staticmethod
    def backward(ctx, grad_positions: torch.Tensor):
        run: RolloutRun = ctx.run
        run.backward(grad_positions)
        grads = ctx.grads_of()  # list aligned with the input tensors
        out = []
        for t, g in zip(ctx.tensors, grads):
            out.append(None if g is None else g.to(t.device, t.dtype).reshape(t.shape))
        return (None, None, *out)
