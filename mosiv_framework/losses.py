"""Identification losses: geometry-aligned objectives of the paper (eq. 3 and table 3).

Every loss compares a simulated ``GeometryFrames`` with a target one at the same observed frames
and returns a differentiable 0-d torch tensor:

- ``ObjectChamferLoss`` ("chamfer"): per frame, the sum over objects k of the symmetric squared
  Chamfer distance between simulated and target points of object k (m^2); mean over frames.
- ``SceneChamferLoss`` ("scene-chamfer"): one Chamfer per frame between the union of all
  simulated points and the union of all target points, blind to object identity (table 3).
- ``ObjectSilhouetteLoss`` ("silhouette"): the sum over objects of the per-pixel L1 between
  simulated and target alpha, mean over frames and cameras (dimensionless).
- ``SceneSilhouetteLoss`` ("scene-silhouette"): the L1 between union silhouettes.

Together, ``chamfer + silhouette`` with unit weights is eq. 3:
L = 1/m sum_i [ sum_k CD(S_k, S~_k) + 1/n sum_j sum_k L1(A_jk, A~_jk) ].
The L1 is the mean absolute difference per pixel (the paper's norm divided by the pixel count),
so a recipe's weights do not depend on image resolution. ``WeightedSum`` combines losses with
recipe weights for the identification stage.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields

import torch
from scipy.spatial import cKDTree

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Loss
from mosiv_framework.types import GeometryFrames

Tensor = torch.Tensor

__all__ = [
    "BUILTIN_LOSSES",
    "ChamferOptions",
    "ObjectChamferLoss",
    "ObjectSilhouetteLoss",
    "SceneChamferLoss",
    "SceneSilhouetteLoss",
    "SceneSilhouetteOptions",
    "SilhouetteOptions",
    "WeightedSum",
    "chamfer_m2",
    "union_silhouette",
]

#: how a scene silhouette is built from per-object alphas (see ``union_silhouette``)
UNION_MODES = ("soft-or", "clamp-sum")
#: nearest-neighbour searches of the Chamfer losses: KD-tree on CPU, chunked exhaustive on GPU
SEARCH_MODES = ("auto", "kdtree", "brute")


# --------------------------------------------------------------------------------------------
# options (the config schema the registry validates recipe options against)


def _check_weight(weight: float, component: str) -> None:
    if not (math.isfinite(weight) and weight >= 0):
        raise ConfigError(f"{component}.weight must be a finite number >= 0, got {weight!r}")


@dataclass
class ChamferOptions:
    """Options of the Chamfer losses.

    weight: factor of this term in the identification objective (>= 0);
    max_points: each point set is reduced to at most this many points, drawn at random on every
    call from a generator seeded with ``seed`` (0: use every point);
    search: nearest-neighbour search, ``auto`` (KD-tree for CPU tensors, chunked exhaustive
    search otherwise), ``kdtree`` or ``brute``;
    max_pairs: how many point pairs the exhaustive search compares at once, which bounds its
    memory (about 4 bytes per pair in float32).
    """

    weight: float = 1.0
    max_points: int = 4096
    seed: int = 0
    search: str = "auto"
    max_pairs: int = 1 << 24

    def __post_init__(self) -> None:
        _check_weight(self.weight, "chamfer")
        if self.max_points < 0:
            raise ConfigError(f"chamfer.max_points must be >= 0 (0: all), got {self.max_points}")
        if self.search not in SEARCH_MODES:
            raise ConfigError(
                f"chamfer.search must be one of {list(SEARCH_MODES)}, got {self.search!r}"
            )
        if self.max_pairs < 1:
            raise ConfigError(f"chamfer.max_pairs must be >= 1, got {self.max_pairs}")


@dataclass
class SilhouetteOptions:
    """Options of the object-wise silhouette loss. weight: factor in the objective (>= 0)."""

    weight: float = 1.0

    def __post_init__(self) -> None:
        _check_weight(self.weight, "silhouette")


@dataclass
class SceneSilhouetteOptions:
    """Options of the scene-wise silhouette loss.

    weight: factor in the objective (>= 0); union: how object alphas merge into one scene
    alpha, ``soft-or`` (1 - prod_k (1 - A_k)) or ``clamp-sum`` (min(1, sum_k A_k)).
    """

    weight: float = 1.0
    union: str = "soft-or"

    def __post_init__(self) -> None:
        _check_weight(self.weight, "scene-silhouette")
        if self.union not in UNION_MODES:
            raise ConfigError(
                f"scene-silhouette.union must be one of {list(UNION_MODES)}, got {self.union!r}"
            )


def _make_options(options_type: type, given: Mapping[str, object], component: str):
    """Build an options dataclass, naming unknown keys and the valid ones on error."""
    valid = [f.name for f in fields(options_type)]
    unknown = sorted(set(given) - set(valid))
    if unknown:
        raise ConfigError(f"{component} has no option(s) {unknown}; valid options: {valid}")
    return options_type(**given)


# --------------------------------------------------------------------------------------------
# differentiable Chamfer


def _nearest_index_brute(query: Tensor, reference: Tensor, max_pairs: int) -> Tensor:
    """Exhaustive nearest-neighbour search in row chunks of at most ``max_pairs`` distances.

    Suited to accelerators. Points are centred on the reference mean first, so the
    matrix-product distance formula loses little precision in float32.
    """
    centre = reference.mean(dim=0)
    query, reference = query - centre, reference - centre
    rows = max(1, max_pairs // reference.shape[0])
    return torch.cat(
        [
            torch.cdist(query[i : i + rows], reference).argmin(dim=1)
            for i in range(0, query.shape[0], rows)
        ]
    )


def _nearest_index_kdtree(query: Tensor, reference: Tensor) -> Tensor:
    """Exact nearest-neighbour search by KD-tree (CPU, float64), O(N log M) time, O(N+M) memory."""
    tree = cKDTree(reference.to(torch.float64).numpy())
    # threads pay off only for large queries; small ones are dominated by thread start-up
    workers = -1 if query.shape[0] >= 8192 else 1
    _, idx = tree.query(query.to(torch.float64).numpy(), k=1, workers=workers)
    return torch.from_numpy(idx).to(torch.int64)


def _nearest_index(query: Tensor, reference: Tensor, max_pairs: int, search: str) -> Tensor:
    """Index into ``reference`` of each query point's nearest neighbour, [N] int64, no tape.

    ``search``: ``kdtree`` (exact, fast on CPU), ``brute`` (chunked exhaustive, for GPUs) or
    ``auto`` (kdtree for CPU tensors, brute otherwise).
    """
    if search not in SEARCH_MODES:
        raise ValueError(
            f"nearest-neighbour search must be one of {list(SEARCH_MODES)}, got {search!r}"
        )
    with torch.no_grad():
        if search == "kdtree" or (search == "auto" and query.device.type == "cpu"):
            return _nearest_index_kdtree(query.cpu(), reference.cpu()).to(query.device)
        return _nearest_index_brute(query, reference, max_pairs)


def _mean_nearest_sq(query: Tensor, reference: Tensor, max_pairs: int, search: str) -> Tensor:
    """mean_{x in query} min_{y in reference} |x - y|^2 (m^2), differentiable in both sets.

    The minimum's gradient is that of the selected pair, so the nearest pair is found without
    a tape and only the N selected differences are recorded: backward memory is O(N).
    """
    idx = _nearest_index(query.detach(), reference.detach(), max_pairs, search)
    return (query - reference[idx]).square().sum(dim=1).mean()


def chamfer_m2(a: Tensor, b: Tensor, *, max_pairs: int = 1 << 24, search: str = "auto") -> Tensor:
    """Symmetric Chamfer distance of squared distances, in m^2, differentiable.

    CD(a, b) = mean_{x in a} min_{y in b} |x - y|^2 + mean_{y in b} min_{x in a} |x - y|^2
    for point sets a [N, 3] and b [M, 3] in metres (the quantity ``metrics.chamfer_mm2``
    reports in mm^2, i.e. 1e6 times this). ``search`` picks the nearest-neighbour search
    (see ``SEARCH_MODES``); ``max_pairs`` bounds the distances the ``brute`` search holds at once.
    """
    for name, p in (("a", a), ("b", b)):
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] == 0:
            raise ValueError(f"chamfer_m2: {name} must be a non-empty [N, 3], got {tuple(p.shape)}")
    return _mean_nearest_sq(a, b, max_pairs, search) + _mean_nearest_sq(b, a, max_pairs, search)


def _subsample(points: Tensor, max_points: int, generator: torch.Generator) -> Tensor:
    """At most ``max_points`` rows of ``points`` drawn without replacement (0: all rows)."""
    if max_points == 0 or points.shape[0] <= max_points:
        return points
    idx = torch.randperm(points.shape[0], generator=generator)[:max_points]
    return points[idx.to(points.device)]


# --------------------------------------------------------------------------------------------
# input checks shared by the losses


def _check_frames(predicted: GeometryFrames, target: GeometryFrames, loss: str) -> None:
    if list(predicted.frames) != list(target.frames):
        raise ValueError(
            f"{loss}: predicted frames {list(predicted.frames)} differ from target frames "
            f"{list(target.frames)}; compare geometry at the same observed frames"
        )
    if not predicted.frames:
        raise ValueError(f"{loss}: no frames to compare")


def _check_objects(predicted: GeometryFrames, target: GeometryFrames, loss: str) -> None:
    if not target.object_list:
        raise ValueError(f"{loss}: the target GeometryFrames holds no objects")
    if predicted.object_list != target.object_list:
        raise ValueError(
            f"{loss}: predicted objects {predicted.object_list} differ from target objects "
            f"{target.object_list}; object-wise losses need the same object ids on both sides"
        )


def _points_at(frames: GeometryFrames, k: int, i: int, side: str, loss: str) -> Tensor:
    sets = frames.points[k]
    if len(sets) != len(frames.frames):
        raise ValueError(
            f"{loss}: {side} object {k} has {len(sets)} point sets for {len(frames.frames)} frames"
        )
    return sets[i]


def _silhouettes(frames: GeometryFrames, side: str, loss: str) -> dict[int, Tensor]:
    if frames.silhouettes is None:
        raise ValueError(
            f"{loss}: {side} GeometryFrames has no silhouettes; render per-object alpha or drop "
            f"the silhouette loss from the recipe"
        )
    for k, alpha in frames.silhouettes.items():
        if alpha.ndim != 4 or alpha.shape[0] != len(frames.frames):
            raise ValueError(
                f"{loss}: {side} silhouette of object {k} must be [F={len(frames.frames)}, C, H, W]"
                f", got {tuple(alpha.shape)}"
            )
    return frames.silhouettes


# --------------------------------------------------------------------------------------------
# losses


class _ChamferBase(Loss):
    """Shared construction of the Chamfer losses: options, weight, seeded subsampling."""

    component = "chamfer"

    def __init__(self, **options: object) -> None:
        self.options: ChamferOptions = _make_options(ChamferOptions, options, self.component)
        self.weight = self.options.weight
        # one generator per loss: successive calls draw different subsets, reproducibly
        self._generator = torch.Generator().manual_seed(self.options.seed)

    @property
    def generator(self) -> torch.Generator:
        """The subsampling generator (its state set back makes the next calls draw the same
        subsets, as ``pipeline.contact`` does to score two models on common draws)."""
        return self._generator

    def _chamfer(self, a: Tensor, b: Tensor) -> Tensor:
        a = _subsample(a, self.options.max_points, self._generator)
        b = _subsample(b, self.options.max_points, self._generator)
        return chamfer_m2(a, b, max_pairs=self.options.max_pairs, search=self.options.search)


class ObjectChamferLoss(_ChamferBase):
    """Object-wise Chamfer (paper eq. 3, first term): 1/m sum_i sum_k CD(S_k(t_i), S~_k(t_i)).

    Squared distances in m^2. Points of object k are only matched with target points of the
    same object, so identities are preserved through contact.
    """

    component = "chamfer"

    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> Tensor:
        _check_frames(predicted, target, self.component)
        _check_objects(predicted, target, self.component)
        per_frame = []
        for i in range(len(predicted.frames)):
            per_frame.append(
                sum(
                    self._chamfer(
                        _points_at(predicted, k, i, "predicted", self.component),
                        _points_at(target, k, i, "target", self.component),
                    )
                    for k in predicted.object_list
                )
            )
        return torch.stack(per_frame).mean()


class SceneChamferLoss(_ChamferBase):
    """Scene-wise Chamfer (paper table 3, naive): 1/m sum_i CD(union_k S_k, union_k S~_k).

    Squared distances in m^2. A simulated point may be explained by any object's target point,
    so swapping two objects' identities costs nothing.
    """

    component = "scene-chamfer"

    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> Tensor:
        _check_frames(predicted, target, self.component)
        per_frame = []
        for i in range(len(predicted.frames)):
            union_pred = torch.cat(
                [
                    _points_at(predicted, k, i, "predicted", self.component)
                    for k in predicted.object_list
                ]
            )
            union_target = torch.cat(
                [_points_at(target, k, i, "target", self.component) for k in target.object_list]
            )
            per_frame.append(self._chamfer(union_pred, union_target))
        return torch.stack(per_frame).mean()


class ObjectSilhouetteLoss(Loss):
    """Object-wise silhouette L1 (paper eq. 3, second term), dimensionless.

    1/m sum_i 1/n sum_j sum_k mean_pixels |A_jk(t_i) - A~_jk(t_i)| over the [F, C, H, W] alpha
    of each object, i.e. sum_k of the mean absolute difference of object k's alpha.
    """

    component = "silhouette"

    def __init__(self, **options: object) -> None:
        self.options: SilhouetteOptions = _make_options(SilhouetteOptions, options, "silhouette")
        self.weight = self.options.weight

    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> Tensor:
        _check_frames(predicted, target, self.component)
        pred = _silhouettes(predicted, "predicted", self.component)
        targ = _silhouettes(target, "target", self.component)
        if sorted(pred) != sorted(targ):
            raise ValueError(
                f"silhouette: predicted silhouettes of objects {sorted(pred)} differ from target "
                f"objects {sorted(targ)}"
            )
        terms = []
        for k in sorted(pred):
            if pred[k].shape != targ[k].shape:
                raise ValueError(
                    f"silhouette: object {k} predicted alpha {tuple(pred[k].shape)} and target "
                    f"alpha {tuple(targ[k].shape)} differ in shape"
                )
            terms.append((pred[k] - targ[k]).abs().mean())
        return torch.stack(terms).sum()


def union_silhouette(alphas: list[Tensor], *, mode: str = "soft-or") -> Tensor:
    """Scene alpha from per-object alphas in [0, 1], all of one shape.

    ``soft-or``: 1 - prod_k (1 - A_k), the probability that some object covers the pixel; equal
    to the set union for binary masks and smooth everywhere. ``clamp-sum``: min(1, sum_k A_k).
    """
    if not alphas:
        raise ValueError("union_silhouette needs at least one object alpha")
    stacked = torch.stack(alphas)
    if mode == "soft-or":
        return 1.0 - torch.prod(1.0 - stacked, dim=0)
    if mode == "clamp-sum":
        return stacked.sum(dim=0).clamp(max=1.0)
    raise ValueError(f"union mode must be one of {list(UNION_MODES)}, got {mode!r}")


class SceneSilhouetteLoss(Loss):
    """Scene-wise silhouette L1 (paper table 3, naive): 1/m sum_i 1/n sum_j
    mean_pixels |A_j(t_i) - A~_j(t_i)| on union silhouettes, dimensionless and blind to which
    object covers which pixel."""

    component = "scene-silhouette"

    def __init__(self, **options: object) -> None:
        self.options: SceneSilhouetteOptions = _make_options(
            SceneSilhouetteOptions, options, self.component
        )
        self.weight = self.options.weight

    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> Tensor:
        _check_frames(predicted, target, self.component)
        pred = _silhouettes(predicted, "predicted", self.component)
        targ = _silhouettes(target, "target", self.component)
        mode = self.options.union
        union_pred = union_silhouette([pred[k] for k in sorted(pred)], mode=mode)
        union_target = union_silhouette([targ[k] for k in sorted(targ)], mode=mode)
        if union_pred.shape != union_target.shape:
            raise ValueError(
                f"scene-silhouette: predicted alpha {tuple(union_pred.shape)} and target alpha "
                f"{tuple(union_target.shape)} differ in shape"
            )
        return (union_pred - union_target).abs().mean()


# --------------------------------------------------------------------------------------------
# combination


class WeightedSum(Loss):
    """sum_name weight_name * loss_name(predicted, target): the identification objective.

    ``terms`` maps a name (usually the recipe's loss name) to a Loss. A term's weight is
    ``weights[name]`` when given, else the loss's own ``weight`` attribute (set from its
    options), else 1. Losses return unweighted values; only this class applies weights.
    """

    def __init__(self, terms: Mapping[str, Loss], *, weights: Mapping[str, float] | None = None):
        if not terms:
            raise ConfigError("the identification objective needs at least one loss term")
        weights = dict(weights or {})
        unknown = sorted(set(weights) - set(terms))
        if unknown:
            raise ConfigError(
                f"weights given for unknown loss terms {unknown}; terms: {list(terms)}"
            )
        self.terms = dict(terms)
        self.weights = {
            name: float(weights.get(name, getattr(loss, "weight", 1.0)))
            for name, loss in self.terms.items()
        }
        for name, w in self.weights.items():
            _check_weight(w, name)

    def evaluate(
        self, predicted: GeometryFrames, target: GeometryFrames
    ) -> tuple[Tensor, dict[str, float]]:
        """(weighted total, name -> unweighted value as a float for logging)."""
        total: Tensor | None = None
        values: dict[str, float] = {}
        for name, loss in self.terms.items():
            if self.weights[name] == 0.0:  # a switched-off term costs nothing
                continue
            value = loss(predicted, target)
            values[name] = float(value.detach())
            weighted = self.weights[name] * value
            total = weighted if total is None else total + weighted
        if total is None:
            raise ConfigError(f"every loss weight is 0 ({self.weights}); nothing to minimise")
        return total, values

    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> Tensor:
        return self.evaluate(predicted, target)[0]


#: (name, class, options dataclass, description): registered by the core's builtin plugin
BUILTIN_LOSSES: list[tuple[str, type[Loss], type, str]] = [
    (
        "chamfer",
        ObjectChamferLoss,
        ChamferOptions,
        "object-wise squared Chamfer distance (m^2), paper eq. 3",
    ),
    (
        "scene-chamfer",
        SceneChamferLoss,
        ChamferOptions,
        "scene-wise squared Chamfer on the union of objects (m^2), paper table 3 ablation",
    ),
    (
        "silhouette",
        ObjectSilhouetteLoss,
        SilhouetteOptions,
        "object-wise silhouette L1 per pixel, paper eq. 3",
    ),
    (
        "scene-silhouette",
        SceneSilhouetteLoss,
        SceneSilhouetteOptions,
        "scene-wise silhouette L1 on the union alpha, paper table 3 ablation",
    ),
]
