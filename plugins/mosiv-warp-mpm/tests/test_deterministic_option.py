"""The ``deterministic`` option: validated like every option, one setting per process (Warp
compiles a module one way), RUN_TO_RUN atomics for the plugin's kernels when on, and CPU
rollouts that repeat bit for bit either way.

The guard is process-wide, so a deterministic simulator is only ever built in a child process:
building one here would make every later simulator of the test session refuse to start."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
import torch
from mosiv_warp_mpm.options import WarpMPMOptions

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Simulator
from mosiv_framework.testing.parity import WORLD, standard_scenes
from mosiv_framework.testing.shapes import default_params


@pytest.mark.parametrize("bad", ["yes", 1, None])
def test_deterministic_must_be_a_bool(bad) -> None:
    with pytest.raises(ConfigError) as err:
        WarpMPMOptions(deterministic=bad)
    message = str(err.value)
    assert f"deterministic={bad!r}" in message
    assert "must be true or false" in message
    assert len(err.value.problems) == 1  # nothing else about the options is wrong


def test_deterministic_accepts_bools_and_defaults_off() -> None:
    assert WarpMPMOptions().deterministic is False
    assert WarpMPMOptions(deterministic=True).deterministic is True


def _run_child(code: str) -> str:
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, f"child process failed:\n{done.stdout}\n{done.stderr[-4000:]}"
    return done.stdout


def test_one_deterministic_setting_per_process() -> None:
    out = _run_child(
        """
        import warp as wp
        from mosiv_framework.errors import ConfigError
        from mosiv_warp_mpm import expression_kernels, kernels, laws, transfer_kernels
        from mosiv_warp_mpm.simulator import WarpMPMSimulator

        def build(on):
            return WarpMPMSimulator(grid=16, substeps=2, device="cpu", deterministic=on)

        first = build(True)
        second = build(True)  # the same setting again is fine
        assert first.deterministic and second.deterministic
        run_to_run = wp.DeterministicMode.RUN_TO_RUN
        for module in (kernels, laws, transfer_kernels, expression_kernels):
            mode = wp.get_module_options(module)["deterministic"]
            assert mode == run_to_run, (module.__name__, mode)
        looped = transfer_kernels.p2g_looped.module  # its own module (module="unique")
        assert looped.options["deterministic"] == run_to_run
        try:
            build(False)
        except ConfigError as e:
            message = str(e)
        else:
            raise AssertionError("deterministic=False after deterministic=True was accepted")
        assert "deterministic=False after deterministic=True" in message, message
        assert "give every warp-mpm simulator" in message, message
        assert "the same setting" in message, message
        # the refused simulator changed nothing: the kernels stay deterministic
        assert wp.get_module_options(kernels)["deterministic"] == run_to_run
        build(True)
        print("child ok")
        """
    )
    assert out.strip().endswith("child ok")


def test_non_deterministic_first_refuses_a_deterministic_one() -> None:
    out = _run_child(
        """
        import warp as wp
        from mosiv_framework.errors import ConfigError
        from mosiv_warp_mpm import kernels
        from mosiv_warp_mpm.simulator import WarpMPMSimulator

        WarpMPMSimulator(grid=16, substeps=2, device="cpu")
        WarpMPMSimulator(grid=16, substeps=2, device="cpu", deterministic=False)
        mode = wp.get_module_options(kernels)["deterministic"]
        assert mode != wp.DeterministicMode.RUN_TO_RUN, mode
        try:
            WarpMPMSimulator(grid=16, substeps=2, device="cpu", deterministic=True)
        except ConfigError as e:
            message = str(e)
        else:
            raise AssertionError("deterministic=True after deterministic=False was accepted")
        assert "deterministic=True after deterministic=False" in message, message
        assert "give every warp-mpm simulator" in message, message
        print("child ok")
        """
    )
    assert out.strip().endswith("child ok")


def _collision_rollout(sim, frames: int):
    particles, velocities = standard_scenes()["collision"]
    params = default_params(particles, velocities=velocities)
    with torch.no_grad():
        traj = sim.rollout(particles, params, world=WORLD, frames=frames)
    return traj.positions, traj.velocities


def test_cpu_rollouts_repeat_bit_for_bit() -> None:
    # default setting (deterministic=False), so it may run in this process; CPU explicitly,
    # whatever MOSIV_TEST_DEVICE says, since only the CPU promises it without the option
    from mosiv_warp_mpm.simulator import WarpMPMSimulator

    sim = WarpMPMSimulator(grid=32, substeps=20, device="cpu")
    assert sim.options.deterministic is False
    assert sim.deterministic is True  # the CPU runs its atomics in order
    first = _collision_rollout(sim, frames=3)
    again = _collision_rollout(sim, frames=3)  # the same run, its buffers reused
    fresh = _collision_rollout(WarpMPMSimulator(grid=32, substeps=20, device="cpu"), frames=3)
    for other in (again, fresh):
        for got, expected in zip(other, first):
            assert torch.equal(got, expected)
    positions = first[0]
    assert positions.shape[0] == 4 and torch.isfinite(positions).all()
    assert (positions[-1] - positions[0]).abs().max() > 1e-3  # the bodies did move


def test_simulator_interface_is_not_deterministic_by_default() -> None:
    class Minimal(Simulator):
        # only to make the abstract class constructible: the test reads a property and never
        # rolls out
        def rollout(self, particles, params, *, world, frames):
            raise NotImplementedError

    assert Minimal().deterministic is False
