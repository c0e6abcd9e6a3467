"""The fused forward kernels (forward_kernels.py) against the split ones whose adjoints the
reverse pass runs: the same equations, so the same rollout up to the order of float additions.

The scene exercises every branch the fusion touches: two objects of SVD laws (plasticine, sand)
in multi-field contact, thrown onto the table, with wind, drag, material damping and ground
restitution on, and the expression term in the other case. The gradient tests of this folder
run with the fused forward (the default), so its re-simulated frames feed their adjoints there.
"""

import pytest
import torch

from mosiv_framework.errors import ConfigError

#: metres; the two paths sum the particles' P2G contributions in another order (float32), which
#: moves positions by about 1e-6 m over these frames; a wrong weight, node or stress moves them
#: by millimetres
POSITION_TOLERANCE = 2e-5
FRAMES = 6


def _terms(expression: bool) -> dict:
    """Every library term the fused kernel applies, or an expression term."""
    if expression:  # a sideways push, a drag in v_x and a spring in the height
        return {"expression": {"a_y:1": 0.4, "a_x:v_x": -0.5, "a_z:h": -2.0}}
    return {
        "wind": {"acceleration": [0.5, -0.2, 0.0]},
        "linear_drag": {"coefficient": 0.3},
        "quadratic_drag": {"coefficient": 0.2},
        "material_damping": {"viscosity": 0.5},
        "ground_restitution": {"coefficient": 0.3},
    }


@pytest.mark.parametrize("expression", [False, True], ids=["library_terms", "expression"])
def test_fused_forward_rolls_out_as_the_split_kernels(
    simulator_factory, thrown_spheres, expression
):
    particles, params, world = thrown_spheres(_terms(expression))
    fused = simulator_factory(grid=16, substeps=30)
    split = simulator_factory(grid=16, substeps=30, fused_forward=False)
    assert fused.options.fused_forward and not split.options.fused_forward
    a = fused.rollout(particles, params, world=world, frames=FRAMES)
    b = split.rollout(particles, params, world=world, frames=FRAMES)
    moved = (a.positions[-1] - a.positions[0]).norm(dim=-1).max().item()
    assert moved > 0.05, "the scene barely moved: it tests nothing"
    assert (a.positions - b.positions).abs().max().item() <= POSITION_TOLERANCE
    assert (a.velocities - b.velocities).abs().max().item() <= POSITION_TOLERANCE * 24 * 30
    assert torch.equal(a.contact, b.contact)
    assert a.contact[:, 0, 1].any(), "the bodies never touched: contact is not exercised"


def test_fused_forward_option_is_checked():
    from mosiv_taichi_mpm.plugin import make_simulator

    with pytest.raises(ConfigError, match="fused_forward='yes'"):
        make_simulator(device="cpu", fused_forward="yes")


#: relative gradient agreement of the fused and the split grid recomputation: the two sum the
#: particles' P2G adds in another order (float32); a grid recomputed without the stored mass
#: and affine term, or from another substep, moves the gradients by tens of percent
GRADIENT_RTOL = 2e-3


def test_fused_grid_recompute_gives_the_split_kernels_gradients(simulator_factory, thrown_spheres):
    """The reverse pass recomputes each substep's grid in one call (``grid_of_substep``) or with
    the split kernels; every parameter's gradient agrees."""
    grads = []
    for fused in (True, False):
        particles, params, world = thrown_spheres(_terms(False), requires_grad=True)
        simulator = simulator_factory(grid=16, substeps=30, fused_forward=fused)
        trajectory = simulator.rollout(particles, params, world=world, frames=2)
        # a loss every parameter reaches: the last frame's positions, weighted per axis
        weights = torch.tensor([1.0, -0.5, 2.0])
        loss = (trajectory.positions[-1] * weights).sum()
        named = [(n, t) for n, t in params.named_tensors() if t.requires_grad]
        values = torch.autograd.grad(loss, [t for _, t in named])
        grads.append({n: g for (n, _), g in zip(named, values)})
    fused, split = grads
    checked = 0
    for name, g in fused.items():
        scale = max(g.abs().max().item(), split[name].abs().max().item())
        if scale == 0.0:
            continue
        checked += 1
        assert (g - split[name]).abs().max().item() <= GRADIENT_RTOL * scale, name
    assert checked >= 10, f"only {checked} parameters have a gradient: the test checks little"
