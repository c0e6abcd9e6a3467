"""One allocated problem: fields + kernels + the substep sequence and its adjoint.

``Engine`` is what ``autograd.RolloutRun`` drives; the simulator builds one per problem size and
material set and re-uses it across rollouts: a differentiable one for rollouts that autograd
will differentiate, a forward-only one (no adjoints, two particle-state buffers) for the rest.
"""

from __future__ import annotations

import numpy as np
import torch

from mosiv_framework.errors import SimulationDiverged
from mosiv_taichi_mpm.autograd import STATE_NAMES, empty_state
from mosiv_taichi_mpm.fields import NO_DIVERGENCE, Layout, SimFields
from mosiv_taichi_mpm.forward_kernels import FusedForwardKernels
from mosiv_taichi_mpm.kernels import REASON_LEFT_DOMAIN, REASON_NONFINITE, STENCIL_PLANES


class Engine:
    """Fields and kernels for one Layout and set of law ids, plus per-rollout settings.

    ``differentiable=False`` allocates forward-only fields (fields.py): the forward methods work
    as on a differentiable engine, with the same results; the adjoint ones must not be called.
    """

    def __init__(
        self,
        layout: Layout,
        present_laws: tuple[int, ...],
        device: torch.device,
        *,
        fused_forward: bool = True,
        differentiable: bool = True,
    ):
        self.layout = layout
        self.differentiable = differentiable
        self.fields = SimFields(layout, differentiable=differentiable)
        self.kernels = FusedForwardKernels(self.fields, present_laws)
        #: forward substeps through the fused kernels (forward_kernels.py) or the split ones
        self.fused_forward = fused_forward
        self.device = device
        self.substeps = layout.substeps
        self.n = 0
        self.dt = 0.0
        self.ground_z = 0.0
        self.has_ground = 0
        self.clock = 0.0  # s: the start time of the frame being simulated (``set_frame``)
        self.object_ids: list[int] = []
        self.advice_info: dict[int, str] = {}
        self._x0: torch.Tensor | None = None

    # ------------------------------------------------------------------ setup
    def configure(self, *, positions, volumes, obj_index, object_ids, dt, ground_z, advice_info):
        """Per-rollout data: particles (torch, on self.device), time step (s), ground (m)."""
        self.n = positions.shape[0]
        self.dt = float(dt)
        self.has_ground = 0 if ground_z is None else 1
        self.ground_z = 0.0 if ground_z is None else float(ground_z)
        self.object_ids = list(object_ids)
        self.advice_info = advice_info
        self._x0 = positions
        self.kernels.set_particles(self.n, obj_index, volumes)

    def set_params(self, arrays: dict[str, np.ndarray]) -> None:
        """Copy packed parameter arrays (numpy float32/int32) into their fields, and on a
        differentiable engine into each particle's copy (after ``configure``, which set the
        particles' objects)."""
        f = self.fields
        f.law_id.from_numpy(arrays["law_id"])
        f.expr_on[None] = int(arrays["expr_on"])
        f.up.from_numpy(arrays["up"])
        for name, fld in f.param_fields().items():
            fld.from_numpy(arrays[name])
        if self.differentiable:
            self.kernels.spread_params(self.n)

    def set_frame(self, frame: int) -> None:
        """Substeps run next belong to ``frame`` (0-based: the one from frame to frame + 1);
        the expression term's time feature reads its start time."""
        self.clock = frame * self.substeps * self.dt

    # ------------------------------------------------------------------ forward
    def start(self) -> None:
        """Frame 0 as the state at substep boundary 0: rest shape, v = v0 of each object."""
        self.kernels.rest_state(self.n, self._x0)
        self.kernels.initial_velocity(self.n)

    def step(self, s: int, *, diagnostics: bool) -> None:
        """One substep from the state at substep boundary s to that at s + 1."""
        k, n, dt = self.kernels, self.n, self.dt
        if self.fused_forward:
            _, time, ground_h = self._force_args(s)
            k.substep(
                s, n, dt, self._pm_level(), time, ground_h, self.ground_z, self.has_ground,
                diagnostics,
            )  # fmt: skip
            return
        self._grid(s)
        if diagnostics and k.multi:
            k.detect_contact(self.ground_z, self.has_ground)
        k.clear_particle_velocity(s, n)
        k.g2p(s, n)
        k.advect(s, n, dt)
        if k.needs_svd:
            k.svd(s, n)
        else:
            k.copy_identity_svd(s, n)
        k.plasticity(s, n, dt)
        if diagnostics:
            k.check(s + 1, n, s)

    def _grid(self, s: int) -> None:
        """The grid of substep s through the split kernels, whose adjoints the reverse pass
        runs: P2G, then the grid forces and contact."""
        k = self.kernels
        k.clear_grid()
        k.stress(s, self.n, self.dt)
        for i in STENCIL_PLANES:
            k.p2g(s, self.n, i, self._pm_level())
        k.grid_forces(*self._force_args(s))
        k.grid_contact(self.ground_z, self.has_ground)

    def _force_args(self, s: int) -> tuple[float, float, float]:
        """grid_forces' arguments at substep s: dt, the time (s), the ground's height (m)."""
        return self.dt, self.clock + s * self.dt, self.ground_z if self.has_ground else 0.0

    def _pm_level(self) -> float:
        """Height (m) up to which p2g records the arriving momentum: the ground's, or none."""
        return self.ground_z if self.has_ground else -1.0e30

    def export(self, s: int, *, grads: bool) -> dict[str, torch.Tensor]:
        out = empty_state(self.n, self.device)
        self.kernels.transfer_state(s, self.n, False, grads, *(out[k] for k in STATE_NAMES))
        return out

    def load(self, s: int, state: dict[str, torch.Tensor], *, grads: bool) -> None:
        self.kernels.transfer_state(s, self.n, True, grads, *(state[k] for k in STATE_NAMES))

    # ------------------------------------------------------------------ diagnostics
    def reset_frame_diagnostics(self) -> None:
        self.fields.div_code.fill(NO_DIVERGENCE)
        self.fields.contact.fill(0)

    def empty_contact(self) -> torch.Tensor | None:
        if not self.kernels.multi:
            return None
        K = self.layout.n_objects
        return torch.zeros((K, K + 1), dtype=torch.bool, device=self.device)

    def frame_contact(self) -> torch.Tensor | None:
        if not self.kernels.multi:
            return None
        return torch.from_numpy(self.fields.contact.to_numpy() != 0).to(self.device)

    def raise_if_diverged(self, *, frame: int) -> None:
        """Read the per-object flags once per frame and raise SimulationDiverged if set."""
        codes = self.fields.div_code.to_numpy()[: len(self.object_ids)]
        flagged = [(int(c), i) for i, c in enumerate(codes) if c < NO_DIVERGENCE]
        if not flagged:
            return
        code, idx = min(flagged)
        substep, reason = code // 4, code % 4
        oid = self.object_ids[idx]
        if reason == REASON_NONFINITE:
            why = "position, velocity or deformation gradient became non-finite (NaN/inf)"
        elif reason == REASON_LEFT_DOMAIN:
            why = "particles reached the edge of the simulation grid (left the scene domain)"
        else:
            why = f"unknown divergence code {reason}"
        advice = (
            f"Use more substeps (now {self.substeps}) or a softer material "
            f"({self.advice_info.get(oid, 'lower stiffness')}); if the object is resolved by "
            "few cells, a finer grid helps, if cells are much smaller than particle spacing, a "
            "coarser one; check that the scene domain contains the whole motion."
        )
        raise SimulationDiverged(
            object_id=oid, frame=frame, substep=substep, reason=why, advice=advice
        )

    # ------------------------------------------------------------------ adjoint
    def zero_param_grads(self) -> None:
        if not self.differentiable:  # the first adjoint call of a backward (autograd.py)
            raise RuntimeError("a forward-only taichi-mpm engine has no adjoints to run")
        for fld in self.fields.param_fields().values():
            fld.grad.fill(0)
        self.fields.p_law.grad.fill(0)
        self.fields.p_rho.grad.fill(0)

    def zero_state_grads(self) -> None:
        f = self.fields
        for fld in (f.x, f.v, f.C, f.F, f.U, f.V, f.sig, f.Jp, f.F_trial, f.sig_trial):
            fld.grad.fill(0)

    def add_position_grad(self, s: int, g: torch.Tensor) -> None:
        self.kernels.add_position_grad(s, self.n, g.contiguous())

    def step_adjoint(self, s: int) -> None:
        """Adjoint of substep s: recompute its grid (one call with the fused kernels, else the
        split ones), then run the split kernels' adjoints in reverse."""
        k, n, dt = self.kernels, self.n, self.dt
        if self.fused_forward:
            _, time, ground_h = self._force_args(s)
            k.grid_of_substep(
                s, n, dt, self._pm_level(), time, ground_h, self.ground_z, self.has_ground
            )
        else:
            self._grid(s)
        k.clear_adjoints(n)
        k.plasticity.grad(s, n, dt)
        if k.needs_svd:
            k.svd_backward(s, n)
        k.advect.grad(s, n, dt)
        k.g2p.grad(s, n)
        k.grid_contact.grad(self.ground_z, self.has_ground)
        k.grid_forces.grad(*self._force_args(s))
        for i in STENCIL_PLANES:
            k.p2g.grad(s, n, i, self._pm_level())
        k.stress.grad(s, n, dt)

    def rollout_start_adjoint(self) -> None:
        """Adjoints of what a rollout runs once before its substeps: the initial velocities
        and the per-particle parameter copies (their sums reach the objects' rows here)."""
        self.kernels.initial_velocity.grad(self.n)
        self.kernels.spread_params.grad(self.n)

    def param_grads(self) -> dict[str, np.ndarray]:
        return {name: fld.grad.to_numpy() for name, fld in self.fields.param_fields().items()}

    def destroy(self) -> None:
        self.fields.destroy()
