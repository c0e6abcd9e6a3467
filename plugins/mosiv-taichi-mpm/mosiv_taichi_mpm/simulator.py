"""The ``taichi-mpm`` Simulator: validation, parameter packing and the rollout entry point.

Physics lives in kernels.py / laws.py, the reverse mode in autograd.py; this module turns the
framework's torch-level ParticleSet / SimulationParams / World into field contents and back.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.expression import NAME as EXPRESSION_TERM
from mosiv_framework.expression import (
    NODE_FEATURES,
    RELATIVE_FEATURES,
    coefficient_problems,
    parse_coefficient,
    up_vector,
)
from mosiv_framework.interfaces import Simulator
from mosiv_framework.particle_order import scatter_ordered
from mosiv_framework.types import ParticleSet, SimulationParams, Trajectory, World
from mosiv_taichi_mpm import runtime
from mosiv_taichi_mpm.autograd import RolloutFunction, RolloutRun
from mosiv_taichi_mpm.engine import Engine
from mosiv_taichi_mpm.fields import make_layout
from mosiv_taichi_mpm.laws import LAW_IDS, LAW_PARAMS, MAX_LAW_PARAMS
from mosiv_taichi_mpm.options import TaichiMPMOptions

#: term name -> {parameter name: shape}
TERMS: dict[str, dict[str, tuple[int, ...]]] = {
    "linear_drag": {"coefficient": ()},
    "quadratic_drag": {"coefficient": ()},
    "wind": {"acceleration": (3,)},
    "gravity": {"acceleration": (3,)},
    "material_damping": {"viscosity": ()},
    "ground_restitution": {"coefficient": ()},
}
#: term parameter -> the field that carries it
_TERM_FIELD = {
    ("linear_drag", "coefficient"): "lin_drag",
    ("quadratic_drag", "coefficient"): "quad_drag",
    ("wind", "acceleration"): "wind",
    ("gravity", "acceleration"): "gravity",
    ("material_damping", "viscosity"): "damping",
    ("ground_restitution", "coefficient"): "ground_e",
}
#: what to lower when an object of a family diverges
_STIFFNESS_ADVICE = {
    "elastic": "lower E",
    "plasticine": "lower E",
    "sand": "lower E",
    "newtonian": "lower bulk_modulus or viscosity",
    "non_newtonian": "lower bulk_modulus or shear_modulus",
    "snow": "lower E or hardening",
    "elastic_corotated": "lower E",
    "plasticine_corotated": "lower E",
}


class TaichiMPMSimulator(Simulator):
    """Differentiable multi-object MLS-MPM on Taichi (docs/PHYSICS.md, MLS-MPM scheme)."""

    supported_laws = frozenset(LAW_IDS)
    supported_terms = frozenset(TERMS) | {EXPRESSION_TERM}
    expression_features = NODE_FEATURES

    def __init__(self, options: TaichiMPMOptions | None = None, **kwargs):
        self.options = options if options is not None else TaichiMPMOptions(**kwargs)
        self.device_name = runtime.resolve_device(self.options.device)
        #: engines of the current layout, by whether they are differentiable
        self._engines: dict[bool, Engine] = {}
        self._engine_key: tuple | None = None
        self._peak_field_bytes = 0
        self._peak_bytes = 0

    @property
    def torch_device(self) -> torch.device:
        return torch.device("cuda" if self.device_name == "cuda" else "cpu")

    # ------------------------------------------------------------------ memory
    def reset_peak_memory(self) -> None:
        self._peak_bytes = 0
        self._peak_field_bytes = 0
        if self.device_name == "cuda":
            torch.cuda.reset_peak_memory_stats()

    def peak_memory_bytes(self) -> int | None:
        """The largest of the rollouts since ``reset_peak_memory``: the Taichi field bytes of the
        engine it ran on (values, and adjoints where differentiable) plus its torch checkpoints
        (on CUDA: plus torch's own peak allocation, which holds the checkpoints)."""
        if self._peak_bytes == 0:
            return None
        if self.device_name == "cuda":
            return self._peak_field_bytes + int(torch.cuda.max_memory_allocated())
        return self._peak_bytes

    def evaluate_law(self, family, F, values, *, plastic_J=None, velocity_gradient=None, dt=1e-3):
        """The backend's own stress and return map of ``family`` on a batch of F (parity suite):
        returns (tau [N, 3, 3] Pa, F_new [N, 3, 3], plastic_J_new [N])."""
        if family not in LAW_IDS:
            raise ConfigError(f"unknown family {family!r}; taichi-mpm supports {sorted(LAW_IDS)}")
        runtime.ensure(self.device_name)
        from mosiv_taichi_mpm.law_eval import evaluate_law

        return evaluate_law(
            family, F, values, plastic_J=plastic_J, velocity_gradient=velocity_gradient, dt=dt
        )

    # ------------------------------------------------------------------ rollout
    def rollout(
        self, particles: ParticleSet, params: SimulationParams, *, world: World, frames: int
    ) -> Trajectory:
        if not isinstance(frames, int) or frames < 1:
            raise ConfigError(f"rollout frames={frames!r} must be an integer >= 1")
        object_ids = particles.object_list
        self._validate(particles, params, object_ids)
        dev = self.torch_device
        families = [params.objects[k].family for k in object_ids]
        names, tensors = zip(*params.named_tensors())
        # only a rollout autograd will differentiate needs the per-substep buffers and adjoints
        differentiable = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
        engine = self.engine_for(len(particles), families, world, differentiable=differentiable)

        self._check_inside(particles, world)
        # the engine keeps its particles in scatter order; the outputs go back to the caller's
        lay = engine.layout
        ordered = scatter_ordered(
            particles, object_ids, origin=lay.origin, dx=lay.dx, nodes=lay.nodes, device=dev
        )
        setup = {
            "positions": ordered.positions.detach().contiguous(),
            "volumes": ordered.volumes.detach().to(torch.float32).contiguous(),
            "obj_index": ordered.obj_index.to(torch.int32).contiguous(),
            "object_ids": object_ids,
            "dt": 1.0 / (world.fps * self.options.substeps),
            "ground_z": world.ground_height,
            "advice_info": {k: self._advice(params, k) for k in object_ids},
        }
        packed = self._pack(params, object_ids, world)

        def load_rollout() -> None:
            # the engine is this simulator's for every rollout of its layout: another rollout
            # between this one's forward and its backward loads its own particles and
            # parameters, so the backward loads this rollout's again (RolloutRun.prepare)
            engine.configure(**setup)
            engine.set_params(packed)

        load_rollout()
        run = RolloutRun(
            engine, frames, len(particles), dev, keep_checkpoints=differentiable,
            prepare=load_rollout,
        )  # fmt: skip

        def grads_of():
            return self._unpack_grads(engine.param_grads(), names, params, object_ids)

        if differentiable:
            positions = RolloutFunction.apply(run, grads_of, *tensors)
        else:
            run.forward()
            positions = run.positions
        field_bytes = engine.fields.nbytes()
        self._peak_field_bytes = max(self._peak_field_bytes, field_bytes)
        self._peak_bytes = max(self._peak_bytes, field_bytes + run.checkpoint_bytes())
        out_device = particles.positions.device
        return Trajectory(
            positions=ordered.to_caller(positions).to(out_device),
            object_ids=particles.object_ids,
            fps=world.fps,
            velocities=ordered.to_caller(run.velocities).to(out_device),
            contact=None if run.contact is None else run.contact.to(out_device),
        )

    def _advice(self, params: SimulationParams, k: int) -> str:
        """What to lower when object k diverges: its stiffness, and the damping viscosity."""
        advice = _STIFFNESS_ADVICE[params.objects[k].family]
        if "material_damping" in params.terms:
            eta = float(params.terms["material_damping"]["viscosity"].detach())
            if eta > 0:  # explicit viscous stability: dt < rho dx^2 / (6 eta)
                advice += f" or the material_damping viscosity ({eta:g} Pa s)"
        return advice

    def engine_for(
        self, n_particles: int, families: list[str], world: World, *, differentiable: bool = True
    ) -> Engine:
        """The compiled engine for ``n_particles`` particles of objects with ``families`` (one
        per object, in object order) in ``world``'s domain; reused while the layout holds.
        ``differentiable=False``: the forward-only engine of that layout (fields.py)."""
        generation = runtime.ensure(self.device_name)
        layout = make_layout(
            n_particles=n_particles,
            n_objects=len(families),
            single_field=self.options.contact == "single_field",
            grid=self.options.grid,
            substeps=self.options.substeps,
            domain_lower=tuple(world.domain_lower),
            domain_upper=tuple(world.domain_upper),
        )
        present = tuple(sorted({LAW_IDS[f] for f in families}))
        return self._get_engine(layout, present, generation, differentiable)

    def _get_engine(self, layout, present, generation, differentiable: bool) -> Engine:
        """Each kind is built on first use; both are freed when the layout changes (their
        fields are already gone when the runtime's generation did)."""
        key = (layout, present, generation)
        if self._engine_key != key:
            if self._engine_key is not None and self._engine_key[2] == generation:
                for engine in self._engines.values():
                    engine.destroy()
            self._engines = {}
            self._engine_key = key
        if differentiable not in self._engines:
            self._engines[differentiable] = Engine(
                layout,
                present,
                self.torch_device,
                fused_forward=self.options.fused_forward,
                differentiable=differentiable,
            )
        return self._engines[differentiable]

    # ------------------------------------------------------------------ validation
    def _validate(self, particles, params: SimulationParams, object_ids: list[int]) -> None:
        problems = []
        for k in object_ids:
            if k not in params.objects:
                problems.append(f"params.objects has no entry for object {k}")
                continue
            fam = params.objects[k].family
            if fam not in LAW_IDS:
                problems.append(
                    f"object {k}: material family {fam!r} not supported by taichi-mpm; "
                    f"valid: {sorted(LAW_IDS)}"
                )
                continue
            if particles.materials.get(k, fam) != fam:
                problems.append(
                    f"object {k}: particles say {particles.materials[k]!r} but params say {fam!r}"
                )
            missing = [
                p
                for p in (*LAW_PARAMS[fam], "rho", "friction")
                if p not in params.objects[k].values
            ]
            if missing:
                problems.append(f"object {k} ({fam}): missing parameter(s) {missing}")
            v0 = params.initial_velocity.get(k)
            if v0 is None or tuple(v0.shape) != (3,):
                problems.append(f"params.initial_velocity[{k}] must be a [3] tensor (m/s)")
        for term, values in params.terms.items():
            if term == EXPRESSION_TERM:
                problems += _expression_problems(values)
                continue
            if term not in TERMS:
                valid = sorted(self.supported_terms)
                problems.append(
                    f"physics term {term!r} not supported by taichi-mpm; valid: {valid}"
                )
                continue
            for pname, shape in TERMS[term].items():
                t = values.get(pname)
                if t is None or t.numel() != math.prod(shape):
                    problems.append(f"term {term!r} needs {pname!r} with shape {shape}")
            extra = sorted(set(values) - set(TERMS[term]))
            if extra:
                problems.append(f"term {term!r} has unknown parameter(s) {extra}")
        if problems:
            raise ConfigError(problems)

    def _check_inside(self, particles: ParticleSet, world: World) -> None:
        pos = particles.positions.detach()
        lo = torch.tensor(world.domain_lower, dtype=pos.dtype, device=pos.device)
        hi = torch.tensor(world.domain_upper, dtype=pos.dtype, device=pos.device)
        outside = ((pos < lo) | (pos > hi)).any(dim=1)
        if bool(outside.any()):
            k = int(particles.object_ids[outside][0])
            raise ConfigError(
                f"{int(outside.sum())} particles (e.g. of object {k}) start outside the world "
                f"domain lower={world.domain_lower} upper={world.domain_upper}"
            )

    # ------------------------------------------------------------------ packing
    def _pack(self, params: SimulationParams, object_ids, world: World) -> dict[str, np.ndarray]:
        K = len(object_ids)
        law_id = np.zeros(K, np.int32)
        law_p = np.zeros((K, MAX_LAW_PARAMS), np.float32)
        rho, fric = np.zeros(K, np.float32), np.zeros(K, np.float32)
        v0 = np.zeros((K, 3), np.float32)
        for i, k in enumerate(object_ids):
            p = params.objects[k]
            law_id[i] = LAW_IDS[p.family]
            for j, name in enumerate(LAW_PARAMS[p.family]):
                law_p[i, j] = float(p.values[name].detach())
            rho[i] = float(p.values["rho"].detach())
            fric[i] = float(p.values["friction"].detach())
            v0[i] = params.initial_velocity[k].detach().cpu().numpy()
        out = {"law_id": law_id, "law_p": law_p, "rho": rho, "friction": fric, "v0": v0}
        out["ground_mu"] = np.array(float(params.ground_friction.detach()), np.float32)
        out["gravity"] = np.array(world.gravity, np.float32)
        out["wind"] = np.zeros(3, np.float32)
        out["lin_drag"] = np.array(0.0, np.float32)
        out["quad_drag"] = np.array(0.0, np.float32)
        # absent material_damping / ground_restitution pack as 0, their "off" value
        out["damping"] = np.array(0.0, np.float32)
        out["ground_e"] = np.array(0.0, np.float32)
        for (term, pname), fld in _TERM_FIELD.items():
            if term in params.terms:
                t = params.terms[term][pname].detach().cpu().numpy().astype(np.float32)
                out[fld] = t.reshape(out[fld].shape)
        expression = params.terms.get(EXPRESSION_TERM, {})
        out["expr_on"] = np.array(1 if expression else 0, np.int32)
        out["expr_coef"] = np.zeros((len(NODE_FEATURES), 3), np.float32)
        for name, value in expression.items():
            axis, feature = parse_coefficient(name)
            out["expr_coef"][NODE_FEATURES.index(feature), axis] = float(value.detach())
        out["up"] = up_vector(world.gravity).numpy().astype(np.float32)
        return out

    def _unpack_grads(self, g: dict[str, np.ndarray], names, params, object_ids):
        """Field adjoints -> one torch tensor per named parameter tensor (same order)."""
        index_of = {k: i for i, k in enumerate(object_ids)}
        by_name: dict[str, np.ndarray] = {}
        for k in object_ids:
            i, fam = index_of[k], params.objects[k].family
            for j, pname in enumerate(LAW_PARAMS[fam]):
                by_name[f"obj{k}.{pname}"] = g["law_p"][i, j]
            by_name[f"obj{k}.rho"] = g["rho"][i]
            by_name[f"obj{k}.friction"] = g["friction"][i]
            by_name[f"v0.obj{k}"] = g["v0"][i]
        by_name["ground_friction"] = g["ground_mu"]
        for (term, pname), fld in _TERM_FIELD.items():
            if term in params.terms:
                by_name[f"term.{term}.{pname}"] = g[fld]
        for name in params.terms.get(EXPRESSION_TERM, {}):
            axis, feature = parse_coefficient(name)
            by_name[f"term.{EXPRESSION_TERM}.{name}"] = g["expr_coef"][
                NODE_FEATURES.index(feature), axis
            ]
        out = []
        for name in names:
            arr = by_name.get(name)
            out.append(None if arr is None else torch.as_tensor(np.array(arr, np.float32)))
        return out


def _expression_problems(values: dict[str, torch.Tensor]) -> list[str]:
    """What taichi-mpm cannot apply of an expression: what no backend can
    (``coefficient_problems``), and the other objects' features."""
    problems = coefficient_problems(values)
    if problems:
        return problems
    return [
        f"expression parameter {name!r}: the other objects' features (dp_*, dv_*) are applied "
        "by the warp-mpm simulator only (set simulator.name: warp-mpm); taichi-mpm applies "
        f"{', '.join(NODE_FEATURES)}"
        for name in values
        if parse_coefficient(name)[1] in RELATIVE_FEATURES
    ]
