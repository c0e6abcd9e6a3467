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
