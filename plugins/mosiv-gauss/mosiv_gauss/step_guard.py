"""Steps of an optimisation whose loss or gradients are not finite: find, skip, and stop.

A Gaussian fit can meet a batch of views whose loss or gradients are not finite (a degenerate
Gaussian, a numerical corner of the rasterizer). Applying such a step would make every
parameter NaN for good and the rest of the fit silent nonsense, so the step is skipped instead;
if no step is finite any more the fit stops with an error that names the stage and the step.
"""

from __future__ import annotations

import torch
from torch import Tensor

from mosiv_framework.errors import ReconstructionDiverged

#: a step whose loss or gradients are not finite is skipped (the parameters keep their last
#: finite values); this many skipped in a row end the stage with ReconstructionDiverged, since
#: then no view gives a finite loss any more
MAX_SKIPPED_IN_A_ROW = 25


def non_finite_parts(loss: Tensor, groups: dict[str, list[Tensor]]) -> list[str]:
    """What is not finite after ``loss.backward()``: "loss" and the name of every group of
    parameters one of whose gradients holds a NaN or an infinity (empty: the step is sound).
    One device synchronisation for all of them."""
    checks = [torch.isfinite(loss).all()]
    names = ["loss"]
    for name, params in groups.items():
        grads = [p.grad for p in params if p.grad is not None]
        if grads:
            checks.append(torch.stack([torch.isfinite(g).all() for g in grads]).all())
            names.append(name)
    sound = torch.stack(checks).cpu().tolist()
    return [n for n, ok in zip(names, sound, strict=True) if not ok]


def skip_or_stop(skipped: list[int], step: int, bad: list[str], stage: str) -> None:
    """Record that ``step`` is skipped (``bad``: what was not finite) and raise
    ReconstructionDiverged once MAX_SKIPPED_IN_A_ROW steps in a row were."""
    skipped.append(step)
    recent = skipped[-MAX_SKIPPED_IN_A_ROW:]
    if len(recent) == MAX_SKIPPED_IN_A_ROW and recent[-1] - recent[0] == len(recent) - 1:
        raise ReconstructionDiverged(
            stage=stage,
            step=step,
            what=f"{len(recent)} steps in a row with a non-finite {' and '.join(bad)}",
            advice="Lower the learning rates (reconstructor.lr_*) or the number of Gaussians "
            "(reconstructor.max_gaussians), and check the masks of the scene",
        )
