"""A minimal MOSIV plugin: a loss comparing per-object centroids, with one option."""

from dataclasses import dataclass

import torch

from mosiv_framework.interfaces import Loss
from mosiv_framework.registry import Component, hookimpl


@dataclass
class CentroidLossOptions:
    weight: float = 1.0


class CentroidLoss(Loss):
    """Mean over frames and objects of the squared distance (m^2) between centroids."""

    def __init__(self, *, weight: float = 1.0):
        self.weight = weight

    def __call__(self, predicted, target):
        terms = [
            ((p.mean(dim=0) - t.mean(dim=0)) ** 2).sum()
            for k in target.object_list
            for p, t in zip(predicted.points[k], target.points[k])
        ]
        return self.weight * torch.stack(terms).mean()


@hookimpl
def mosiv_losses(register):
    register(
        Component(
            "loss",
            "centroid",
            factory=CentroidLoss,
            options=CentroidLossOptions,
            description="squared distance between per-object centroids",
        )
    )
