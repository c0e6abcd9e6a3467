"""The sandwich (Huber-White) covariance of an identified point, robust to a wrong model.

The loss is a sum of block shares, L(u) = sum_b l_b(u) (for identification: one block per
observed frame, l_b that frame's loss over the number of frames). The identified point u0
solves grad L = 0, so a small change of the data moves it by -H^-1 (sum_b delta grad l_b): its
covariance is H^-1 J H^-1, with H the Hessian of L and J the covariance of the summed block
scores s_b = grad l_b(u0). J is estimated from the scores themselves, centred on their mean:
what the frames disagree on about where the optimum lies. Nothing here reads the loss as a
likelihood or assumes the model generated the data; what it assumes is that the blocks are
draws of one stationary process whose dependence dies out within a few blocks, which the
Newey-West (Bartlett-weighted) estimate of J allows for (successive frames of one motion are
far from independent: a misfit that builds up over the motion shows in neighbouring frames
alike).

With T blocks the estimate of J has T - 1 degrees of freedom after centring; it is scaled by
T / (T - 1) and the interval uses Student's t quantile with T - 1 degrees of freedom instead of
the normal one, the usual small-sample corrections of a cluster-robust covariance.
"""

from __future__ import annotations

import math

import torch

#: the two-sided 95 % level of the intervals
LEVEL = 0.95


def newey_west_lag(blocks: int) -> int:
    """The Bartlett kernel's lag for ``blocks`` successive blocks: floor(4 (T / 100)^(2/9)),
    Newey and West's (1994) rule (2 for 15 frames, 3 for 36, 4 for 100)."""
    if blocks < 1:
        raise ValueError(f"newey_west_lag needs at least one block, got {blocks}")
    return int(math.floor(4.0 * (blocks / 100.0) ** (2.0 / 9.0)))


def hac_meat(scores: torch.Tensor, lag: int) -> torch.Tensor:
    """J: the Bartlett-weighted (Newey-West) covariance of the summed scores.

    Args:
        scores: [T, d] per-block gradients, in the blocks' order (time).
        lag: the largest lag with weight; 0: the blocks are taken as independent.

    Returns:
        [d, d] J = T / (T - 1) sum_{|l| <= lag} (1 - |l| / (lag + 1)) sum_t c_t c_{t+l}^T over
        the centred scores c_t = s_t - mean(s); positive semi-definite by construction.
    """
    if scores.ndim != 2:
        raise ValueError(f"scores must be [blocks, parameters], got shape {tuple(scores.shape)}")
    if lag < 0:
        raise ValueError(f"the lag must be >= 0, got {lag}")
    t = scores.shape[0]
    if t < 2:
        raise ValueError(f"the spread of block scores needs at least 2 blocks, got {t}")
    c = (scores - scores.mean(dim=0, keepdim=True)).double()
    meat = c.T @ c
    for lag_l in range(1, min(lag, t - 1) + 1):
        gamma = c[:-lag_l].T @ c[lag_l:]
        meat = meat + (1.0 - lag_l / (lag + 1.0)) * (gamma + gamma.T)
    return meat * t / (t - 1)


def sandwich_covariance(inverse_hessian: torch.Tensor, meat: torch.Tensor) -> torch.Tensor:
    """H^-1 J H^-1, symmetrised (float64)."""
    cov = inverse_hessian.double() @ meat.double() @ inverse_hessian.double()
    return 0.5 * (cov + cov.T)


def t_quantile(blocks: int) -> float:
    """The two-sided ``LEVEL`` quantile of Student's t with ``blocks - 1`` degrees of freedom
    (2.14 for 15 blocks, 1.97 for 200)."""
    from scipy.stats import t as student_t

    if blocks < 2:
        raise ValueError(f"Student's t needs at least 2 blocks, got {blocks}")
    return float(student_t.ppf(0.5 + LEVEL / 2.0, blocks - 1))


def block_scores(
    centre: torch.Tensor,
    plus: list[torch.Tensor | None],
    minus: list[torch.Tensor | None],
    steps: list[float],
) -> torch.Tensor:
    """Per-block gradients by finite differences of the block shares.

    Args:
        centre: [T] the block shares at u0.
        plus: per coordinate i, the shares at u0 + steps[i] e_i.
        minus: per coordinate i, the shares at u0 - steps[i] e_i (central difference), or None:
            then ``plus[i]`` holds the shares at u0 + steps[i] e_i stacked with those at
            u0 + 2 steps[i] e_i ([2, T]) and the one-sided second-order difference
            (-3 l(0) + 4 l(h) - l(2h)) / (2h) is used (h = steps[i], negative to step down).
        steps: the signed step per coordinate.

    Returns:
        [T, d] scores, float64.
    """
    cols = []
    for up, down, h in zip(plus, minus, steps):
        if down is not None:
            cols.append((up.double() - down.double()) / (2.0 * h))
        else:
            one, two = up[0].double(), up[1].double()
            cols.append((-3.0 * centre.double() + 4.0 * one - two) / (2.0 * h))
    return torch.stack(cols, dim=1)
