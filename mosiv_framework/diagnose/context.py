"""What a diagnosis works on: a finished ``mosiv run`` folder, loaded once.

The run folder (see ``mosiv_framework.pipeline``) holds the recipe it ran, the lifted particles,
the reconstruction whose points were the identification targets, and the identified parameters.
The diagnosis compares the identified model's rollout with those same targets: it never reads
the scene's ground truth (``gt/``), which only the suite's scoring may use.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.interfaces import Simulator
from mosiv_framework.losses import chamfer_m2
from mosiv_framework.pipeline.contact import simulator_section
from mosiv_framework.pipeline.params import ParameterVector, wave_speed_limit
from mosiv_framework.pipeline.phases import batched_losses
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.recipes.terms import identified_terms
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import Scene, read_scene
from mosiv_framework.types import ParticleSet, SimulationParams, Trajectory, World

#: files a run folder must hold before it can be diagnosed
REQUIRED = ("recipe.yaml", "particles.pt", "reconstruction.pt", "identified.json")


@dataclass
class RunContext:
    """A loaded run: recipe, scene, particles, targets, identified model and its simulator.

    ``targets`` maps object id -> [T, N_k, 3] points (m) over every frame the reconstruction
    covers; frames ``< observed_frames`` were fitted by the run, the rest are its future.

    Rollouts compute on the simulator's ``torch_device``: differentiable ones (``simulate``)
    stay there, so the losses of screening and refits run beside the simulator, while
    ``rollout`` (no gradient) brings its trajectory back to the CPU, where the location, the
    regression and the reports read it with numpy.
    """

    run_dir: RunDir
    recipe: DictConfig
    scene: Scene
    particles: ParticleSet
    targets: dict[int, torch.Tensor]
    identified: SimulationParams
    identified_json: dict
    simulator: Simulator
    simulator_name: str
    observed_frames: int
    n_frames: int
    loss_points: int = 1024
    _rollout_cache: dict = field(default_factory=dict, repr=False)

    @property
    def world(self) -> World:
        return self.scene.world

    @property
    def object_ids(self) -> list[int]:
        return sorted(self.targets)

    @property
    def fps(self) -> float:
        return self.scene.fps

    @property
    def device(self) -> torch.device:
        """Where the simulator computes (``Simulator.torch_device``)."""
        return torch.device(getattr(self.simulator, "torch_device", "cpu"))

    def simulate(self, params: SimulationParams, *, frames: int) -> Trajectory:
        """A differentiable rollout of ``params`` over ``frames`` frames, on ``device``.

        The particles take each object's family from ``params``, so a candidate may change a
        family (an elastic body that yields becomes plasticine)."""
        return self.simulator.rollout(
            self.particles_for(params), params, world=self.world, frames=frames
        )

    def simulate_batch(
        self, params_list: list[SimulationParams], *, frames: int
    ) -> list[Trajectory | SimulationDiverged]:
        """Differentiable rollouts of independent parameter sets together
        (``Simulator.rollout_batch``: one simulation on backends that batch, e.g. warp-mpm),
        each as ``simulate`` would give it alone; a set whose rollout diverged gets its
        SimulationDiverged (object, frame, substep) and the others go on."""
        return self.simulator.rollout_batch(
            self._device_particles(), params_list, world=self.world, frames=frames
        )

    def rollout(self, params: SimulationParams, *, frames: int | None = None) -> Trajectory:
        """A rollout of ``params`` (no gradient) over ``frames`` frames (default: all)."""
        frames = self.n_frames - 1 if frames is None else frames
        with torch.no_grad():
            traj = self.simulate(params.detached(), frames=frames)
        return _on_cpu(traj)

    def rollout_losses(
        self, params_list: list[SimulationParams], fit_frames: list[int]
    ) -> list[float]:
        """The fit-frame loss (``loss``) of each parameter set's rollout, without a tape.

        The sets are independent probes of the same scene, so they go through
        ``Simulator.rollout_batch`` together (``pipeline.phases.batched_losses``, 16 a call: one
        simulation on backends that batch, e.g. warp-mpm). Each loss is that of ``rollout``
        of the set alone followed by ``loss`` (bit for bit on warp-mpm's CPU path): the
        trajectories are brought to the CPU first, as ``rollout`` does.

        Args:
            params_list: the parameter sets (members); each member's particles take their
                families from it, as in ``simulate``.
            fit_frames: the frames the loss averages over; each rollout runs to the last.

        Returns:
            One loss (m^2) per set, in order: ``inf`` for a set whose rollout diverged (the
            others still run) or whose loss is not finite.
        """
        return batched_losses(
            self.simulator,
            self._device_particles(),
            [p.detached() for p in params_list],
            world=self.world,
            frames=max(fit_frames),
            loss=lambda result: self.loss(_on_cpu(result), fit_frames),
        )

    def _device_particles(self) -> ParticleSet:
        """The run's particles on ``device`` (moved once, not per rollout)."""
        key = ("particles", self.device)
        if key not in self._rollout_cache:
            self._rollout_cache[key] = self.particles.to(self.device)
        return self._rollout_cache[key]

    def particles_for(self, params: SimulationParams) -> ParticleSet:
        """The run's particles on ``device``, labelled with the families ``params`` simulate
        them as."""
        particles = self._device_particles()
        families = {k: p.family for k, p in params.objects.items()}
        if families == particles.materials:
            return particles
        return replace(particles, materials=families)

    def identified_rollout(self) -> Trajectory:
        """The run's own prediction over all frames (computed once)."""
        if "identified" not in self._rollout_cache:
            self._rollout_cache["identified"] = self.rollout(self.identified)
        return self._rollout_cache["identified"]

    def loss(self, traj: Trajectory, frames: list[int]) -> torch.Tensor:
        """Object-wise Chamfer (m^2) at ``frames``, summed over objects, mean over frames.

        The run's Chamfer loss, but on a fixed point subset per object (drawn once, of the
        recipe's ``losses.chamfer.max_points``), so that every model the diagnosis compares is
        scored on the same points: a random subset per call would add noise to the comparison.
        Differentiable with respect to the trajectory.
        """
        per_frame = []
        for t in frames:
            total = 0.0
            for k in self.object_ids:
                sim = traj.object_positions(k)[t]
                tgt = self._targets_on(k, sim.device)[t]
                total = total + chamfer_m2(
                    sim[self._subset("sim", k, sim.shape[0])],
                    tgt[self._subset("tgt", k, tgt.shape[0])],
                )
            per_frame.append(total)
        return torch.stack(per_frame).mean()

    def _targets_on(self, k: int, device: torch.device) -> torch.Tensor:
        """Object ``k``'s targets on ``device`` (moved once per device)."""
        key = ("targets", k, device)
        if key not in self._rollout_cache:
            self._rollout_cache[key] = self.targets[k].to(device)
        return self._rollout_cache[key]

    def _subset(self, side: str, k: int, n: int) -> torch.Tensor:
        key = ("subset", side, k, n)
        if key not in self._rollout_cache:
            generator = torch.Generator().manual_seed(1000 * k + (side == "tgt"))
            m = self.loss_points if self.loss_points > 0 else n
            perm = torch.randperm(n, generator=generator)
            self._rollout_cache[key] = perm[: min(m, n)].sort().values
        return self._rollout_cache[key]

    def parameter_vector(
        self, params: SimulationParams | None = None, *, ceilings: dict | None = None
    ) -> ParameterVector:
        """Optimisable leaves for the run's free parameters, started at ``params``.

        Which parameters are free follows the run's recipe (identify_friction,
        identify_ground_friction, and physics terms marked ``identify``), so a refit changes
        exactly what the run identified; the run's other physics terms stay on, fixed.
        ``ceilings`` lowers upper bounds as identification did (``ParameterVector.create``);
        the vector holds the simulator's stability limit as identification's does
        (``ParameterVector.keep_stable``).
        """
        params = self.identified if params is None else params
        section = self.recipe.identify
        ground = None if self.world.ground_height is None else float(params.ground_friction)
        return ParameterVector.create(
            {k: p.family for k, p in params.objects.items()},
            {k: v.detach().clone() for k, v in params.initial_velocity.items()},
            values={
                k: {n: float(v) for n, v in p.values.items()} for k, p in params.objects.items()
            },
            ground_friction=ground,
            identify_friction=bool(section.identify_friction),
            identify_ground_friction=bool(section.identify_ground_friction),
            terms={n: dict(v) for n, v in params.terms.items()},
            identify_terms=tuple(n for n in self.identified_term_names if n in params.terms),
            ceilings=ceilings,
            wave_speed_limit=wave_speed_limit(
                float(getattr(section, "stiffness_cfl", 0.0)),  # absent: no limit
                self.world,
                getattr(getattr(self.simulator, "options", None), "grid", None),
                getattr(getattr(self.simulator, "options", None), "substeps", None),
            ),
        )

    @property
    def identified_term_names(self) -> tuple[str, ...]:
        """The physics terms the run's recipe switched on with ``identify: true``."""
        section = OmegaConf.to_container(self.recipe, resolve=True).get("physics_terms") or {}
        return identified_terms(section)


def _on_cpu(traj: Trajectory) -> Trajectory:
    """``traj``'s positions on the CPU, where the diagnosis reads them with numpy."""
    if traj.positions.device.type == "cpu":
        return traj
    return Trajectory(traj.positions.cpu(), traj.object_ids.cpu(), traj.fps)


def load_run(
    run_dir: str | Path,
    *,
    simulator_overrides: dict | None = None,
    scene_path: str | Path | None = None,
) -> RunContext:
    """Load a finished run folder; raises ConfigError naming what is missing.

    ``simulator_overrides`` replaces simulator options of the recipe (e.g. ``device``);
    ``scene_path`` reads the scene from there instead of the recipe's ``scene.path`` (a run
    folder copied from another machine).
    """
    rd = RunDir(run_dir)
    missing = [name for name in REQUIRED if not rd.path(name).is_file()]
    if missing:
        raise ConfigError(
            f"{rd.root} is not a finished run folder: it lacks {missing}; run "
            f"`mosiv run RECIPE output.dir={rd.root}` first"
        )
    recipe = OmegaConf.load(rd.path("recipe.yaml"))
    identified_json = rd.load_json("identified.json")
    return build_context(
        rd,
        recipe,
        read_scene(recipe.scene.path if scene_path is None else scene_path),
        rd.load_torch("reconstruction.pt"),
        rd.load_torch("particles.pt"),
        ParameterVector.from_json(identified_json),
        identified_json,
        simulator_overrides=simulator_overrides,
    )


def build_context(
    rd: RunDir,
    recipe: DictConfig,
    scene: Scene,
    reconstruction,
    particles: ParticleSet,
    identified: SimulationParams | None,
    identified_json: dict,
    *,
    simulator_overrides: dict | None = None,
) -> RunContext:
    """A RunContext from a run's parts: the recipe's simulator (with ``simulator_overrides``)
    and the reconstruction's points as targets, over the frames both the scene and the
    reconstruction cover."""
    # the contact identification used (identify.contact: auto may have chosen it)
    section = simulator_section(recipe.simulator, identified_json)
    sim_options = dict(OmegaConf.to_container(section, resolve=True))
    sim_name = sim_options.pop("name")
    sim_options.update(simulator_overrides or {})
    simulator = get_registry().create("simulator", sim_name, sim_options)
    losses = OmegaConf.to_container(recipe.losses, resolve=True)
    targets = {int(k): v.detach().float().cpu() for k, v in reconstruction.points.items()}
    n_frames = min(scene.n_frames, min(t.shape[0] for t in targets.values()))
    return RunContext(
        run_dir=rd,
        recipe=recipe,
        scene=scene,
        particles=particles,
        targets=targets,
        identified=identified,
        identified_json=identified_json,
        simulator=simulator,
        simulator_name=sim_name,
        observed_frames=min(scene.observed_frames, n_frames),
        n_frames=n_frames,
        loss_points=int(losses.get("chamfer", {}).get("max_points", 1024)),
    )
