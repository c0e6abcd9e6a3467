"""The ``expression`` term (a discovered force law on grid nodes) is implemented by warp-mpm
only: taichi-mpm does not list it and refuses a rollout with it, naming the term and the
backend that has it, before compiling anything."""

import pytest
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.testing.shapes import block, default_params
from mosiv_framework.types import World


def test_expression_is_refused_naming_the_backend_that_supports_it(simulator_factory):
    sim = simulator_factory(grid=16, substeps=10)
    assert "expression" not in sim.supported_terms
    p = block((0.4, 0.4, 0.4), (0.5, 0.5, 0.5), spacing=0.025, object_id=1)
    params = default_params(p)
    params.terms["expression"] = {"a_x:v_x": torch.tensor(-1.0)}
    with pytest.raises(ConfigError, match="'expression'.*implemented by the warp-mpm simulator"):
        sim.rollout(p, params, world=World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), frames=1)
