"""Object assignment (paper Sec. 3.2, Appendix C): which object each Gaussian belongs to.

With instance masks, every Gaussian, deformed to each training frame's time, is projected into
that frame's mask; a Gaussian landing on label k > 0 gets one vote for k. The vote matrix
V [N, K + 1] (column 0 counts background hits) gives each Gaussian its majority object label,
subject to a minimum number of object votes and a minimum consistency; failures, and objects
left with too few Gaussians, are background (label 0).

Without masks, `cluster_trajectories` groups the Gaussians by their Phase 1 deformation
trajectories (k-means on per-Gaussian displacement curves, K chosen by silhouette): Gaussians
that barely move are background, each cluster of the rest one object.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from sync4d.data.scene import Frame, Scene
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.motion import ControlPoints
from sync4d.phase1.nodes import knn
from sync4d.settings import choice, ranged

__all__ = [
    "ASSIGN_SOURCES",
    "Assignment",
    "adjusted_rand_index",
    "assign_objects",
    "AssignConfig",
    "assign_from_masks",
    "cluster_trajectories",
    "displacement_curves",
    "node_votes",
    "count_votes",
    "labels_from_votes",
]


#: Values of `AssignConfig.source`.
ASSIGN_SOURCES = ("auto", "masks", "trajectories")


@dataclass(frozen=True)
class AssignConfig:
    """Assignment thresholds (Appendix A/C: min votes 3, min consistency 0.6)."""

    #: "masks" (mask voting), "trajectories" (unsupervised clustering of Phase 1 motion), or
    #: "auto": masks when every training frame has one, else trajectories.
    source: str = choice("auto", ASSIGN_SOURCES)
    #: Mask voting: a Gaussian needs at least this many object votes to join an object.
    min_votes: int = ranged(3, 0)
    #: Mask voting: and its majority label's share of its votes at least this.
    min_consistency: float = ranged(0.6, 0.0, 1.0)
    #: Objects assigned fewer Gaussians than this merge into background.
    min_gaussians: int = ranged(10, 0)
    #: Count background (label 0) hits in the consistency denominator, so the majority over
    #: all K + 1 labels decides. Appendix C's formula counts object labels only (False); that
    #: hands static Gaussians occluded by an object in a few views (e.g. the ground behind it)
    #: to the object (tests/phase2/test_assign.py shows the case), so True is the default.
    background_votes: bool = True
    #: Unsupervised assignment: Gaussians whose displacement never exceeds this fraction of the
    #: scene extent are background; K is searched in [1, max_clusters].
    static_fraction: float = ranged(0.01, 0.0)
    #: Unsupervised assignment: most objects (clusters) K searched.
    max_clusters: int = ranged(8, 1)
    #: Unsupervised assignment: times sampled in [0, 1] for the displacement curves.
    trajectory_samples: int = ranged(16, 2)
    #: Seed of the k-means initialisation.
    seed: int = ranged(42, 0, 2**32 - 1)


@dataclass
class Assignment:
    """Per-Gaussian object labels and how they were obtained."""

    #: [N] int64 labels in [0, K): 0 is background, k > 0 an object.
    labels: np.ndarray
    #: Number of label slots K (background included); labels index rows of M_phi.
    num_objects: int
    #: Display names per label (from the dataset's labels.json, or "object k").
    names: dict[int, str] = field(default_factory=dict)
    #: "masks" or "trajectories".
    source: str = "masks"
    #: [N, K + 1] vote matrix (masks only).
    votes: np.ndarray | None = None

    def counts(self) -> dict[int, int]:
        """Gaussians per label."""
        return {k: int((self.labels == k).sum()) for k in range(self.num_objects)}


@torch.no_grad()
def count_votes(
    positions_at: Callable[[float], np.ndarray],
    frames: Sequence[Frame],
    num_labels: int,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Vote matrix V [N, L + 1] (int64, L = the larger of `num_labels` and the highest label
    seen in the masks): for every frame with a mask, each Gaussian
    whose position `positions_at(frame.time)` [N, 3] projects inside the image in front of the
    camera adds one vote to the mask label under it (column 0 = background)."""
    votes: np.ndarray | None = None
    cache: dict[float, np.ndarray] = {}
    for n, frame in enumerate(frames):
        mask = frame.load_mask()
        if mask is None:
            continue
        if frame.time not in cache:
            cache = {frame.time: np.asarray(positions_at(frame.time), dtype=np.float64)}
        pts = cache[frame.time]
        if votes is None:
            votes = np.zeros((len(pts), num_labels + 1), dtype=np.int64)
        uv, z = frame.camera.project(pts)
        u = np.floor(uv[:, 0]).astype(np.int64)
        v = np.floor(uv[:, 1]).astype(np.int64)
        h, w = mask.shape
        ok = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        lab = mask[v[ok], u[ok]]
        top = int(lab.max(initial=0))
        if top >= votes.shape[1]:  # a label beyond labels.json: widen V
            votes = np.pad(votes, ((0, 0), (0, top + 1 - votes.shape[1])))
        keep = lab >= 0
        np.add.at(votes, (np.nonzero(ok)[0][keep], lab[keep]), 1)
        if progress is not None:
            progress(n + 1, len(frames))
    if votes is None:
        raise ValueError("object assignment from masks needs frames with instance masks")
    return votes


def labels_from_votes(votes: np.ndarray, config: AssignConfig) -> np.ndarray:
    """Majority object label per Gaussian from V [N, K + 1] (Appendix C): argmax over k >= 1
    with at least `min_votes` object votes and a winner share of at least `min_consistency`,
    else 0; then objects with fewer than `min_gaussians` Gaussians become 0."""
    obj = votes[:, 1:]
    total = obj.sum(1) + (votes[:, 0] if config.background_votes else 0)
    best = obj.argmax(1) + 1
    top = obj.max(1)
    share = np.divide(top, total, out=np.zeros(len(top), dtype=np.float64), where=total > 0)
    labels = np.where((obj.sum(1) >= config.min_votes) & (share >= config.min_consistency), best, 0)
    for k in range(1, votes.shape[1]):
        if 0 < (labels == k).sum() < config.min_gaussians:
            labels[labels == k] = 0
    return labels.astype(np.int64)


def assign_from_masks(
    positions_at: Callable[[float], np.ndarray],
    frames: Sequence[Frame],
    label_names: dict[int, str] | None,
    config: AssignConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Assignment:
    """Mask-vote assignment of the Gaussians whose positions at time t are
    `positions_at(t)` [N, 3], over the training `frames` (those with masks vote)."""
    config = config or AssignConfig()
    votes = count_votes(positions_at, frames, max(label_names or {0: ""}), progress)
    max_label = votes.shape[1] - 1  # labels.json may be missing or incomplete
    labels = labels_from_votes(votes, config)
    names = {0: "background"} | {
        k: (label_names or {}).get(k, f"object {k}") for k in range(1, max_label + 1)
    }
    return Assignment(labels, max_label + 1, names, "masks", votes)


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iters: int = 50) -> np.ndarray:
    """Lloyd's k-means with k-means++ seeding; cluster index per row of `x` [M, D]."""
    centres = [x[rng.integers(len(x))]]
    for _ in range(1, k):
        d2 = np.min(((x[:, None, :] - np.stack(centres)[None]) ** 2).sum(-1), axis=1)
        p = d2 / d2.sum() if d2.sum() > 0 else None
        centres.append(x[rng.choice(len(x), p=p)])
    c = np.stack(centres)
    assign = np.zeros(len(x), dtype=np.int64)
    for _ in range(iters):
        new = ((x[:, None, :] - c[None]) ** 2).sum(-1).argmin(1)
        if np.array_equal(new, assign) and _ > 0:
            break
        assign = new
        for j in range(k):
            if (assign == j).any():
                c[j] = x[assign == j].mean(0)
    return assign


def _silhouette(x: np.ndarray, assign: np.ndarray) -> float:
    """Mean silhouette coefficient of a clustering of `x` [M, D] (M small)."""
    d = np.sqrt(((x[:, None, :] - x[None]) ** 2).sum(-1))
    ks = np.unique(assign)
    if len(ks) < 2:
        return -1.0
    s = np.zeros(len(x))
    for i in range(len(x)):
        same = assign == assign[i]
        a = d[i, same].sum() / max(same.sum() - 1, 1)
        b = min(d[i, assign == k].mean() for k in ks if k != assign[i])
        s[i] = (b - a) / max(a, b, 1e-12)
    return float(s.mean())


def cluster_trajectories(
    displacements: np.ndarray, extent: float, config: AssignConfig | None = None
) -> Assignment:
    """Unsupervised assignment from Phase 1 displacement curves `displacements` [N, S, 3]
    (x_i(t_s) - x_i(t_0) at S sample times): Gaussians moving less than
    `static_fraction * extent` are background; the others are k-means clustered on their
    curves with K in [1, max_clusters] picked by the best silhouette on a subsample (K = 1 when
    no split scores above 0.25)."""
    config = config or AssignConfig()
    n = displacements.shape[0]
    labels = np.zeros(n, dtype=np.int64)
    peak = np.linalg.norm(displacements, axis=-1).max(axis=1)
    moving = np.nonzero(peak > config.static_fraction * extent)[0]
    if len(moving) < config.min_gaussians:
        return Assignment(labels, 1, {0: "background"}, "trajectories")
    x = displacements[moving].reshape(len(moving), -1)
    rng = np.random.default_rng(config.seed)
    sub = rng.choice(len(x), size=min(len(x), 1500), replace=False)
    best_k, best_s, best_assign = 1, 0.25, np.zeros(len(x), dtype=np.int64)
    for k in range(2, config.max_clusters + 1):
        if k > len(sub):
            break
        assign = _kmeans(x, k, np.random.default_rng(config.seed + k))
        s = _silhouette(x[sub], assign[sub])
        if s > best_s:
            best_k, best_s, best_assign = k, s, assign
    labels[moving] = best_assign + 1
    for k in range(1, best_k + 1):
        if (labels == k).sum() < config.min_gaussians:
            labels[labels == k] = 0
    used = [k for k in range(1, best_k + 1) if (labels == k).any()]
    remap = np.zeros(best_k + 1, dtype=np.int64)
    remap[used] = np.arange(1, len(used) + 1)
    labels = remap[labels]
    names = {0: "background"} | {k: f"cluster {k}" for k in range(1, len(used) + 1)}
    return Assignment(labels, len(used) + 1, names, "trajectories")


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Adjusted Rand index of two labelings [N] of the same items (1: identical partitions up
    to renaming, about 0: no better than chance; Hubert and Arabie 1985)."""
    a = np.asarray(a).reshape(-1)
    b = np.asarray(b).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"labelings differ in length: {a.shape[0]} vs {b.shape[0]}")
    n = a.shape[0]
    if n < 2:
        return 1.0
    _, ai = np.unique(a, return_inverse=True)
    _, bi = np.unique(b, return_inverse=True)
    table = np.zeros((ai.max() + 1, bi.max() + 1), dtype=np.float64)
    np.add.at(table, (ai, bi), 1.0)

    def pairs(x: np.ndarray) -> float:
        return float((x * (x - 1.0) / 2.0).sum())

    index = pairs(table)
    rows, cols = pairs(table.sum(1)), pairs(table.sum(0))
    expected = rows * cols / (n * (n - 1.0) / 2.0)
    best = 0.5 * (rows + cols)
    if best == expected:  # both labelings put everything in one class (or all singletons)
        return 1.0
    return (index - expected) / (best - expected)


@torch.no_grad()
def _positions_fn(model: DeformableGaussians):
    def positions_at(t: float) -> np.ndarray:
        return model.at_time(float(t))[0].double().numpy()

    return positions_at


@torch.no_grad()
def displacement_curves(model: DeformableGaussians, times: np.ndarray) -> np.ndarray:
    """[N, S, 3] float64 displacements x_i(t_s) - x_i(t_0) at the given sample times."""
    pos = np.stack([model.at_time(float(t))[0].double().numpy() for t in times], axis=1)
    return pos - pos[:, :1]


def assign_objects(
    model: DeformableGaussians, scene: Scene, extent: float, config: AssignConfig | None = None
) -> Assignment:
    """Object labels for `model`'s Gaussians: mask voting when the training frames have masks,
    otherwise trajectory clustering."""
    config = config or AssignConfig()
    if config.source not in ASSIGN_SOURCES:
        raise ValueError(
            f"phase2.assign.source: expected one of {', '.join(ASSIGN_SOURCES)}, "
            f"got {config.source!r}"
        )
    use_masks = config.source == "masks" or (config.source == "auto" and scene.has_masks)
    if use_masks:
        if not scene.has_masks:
            raise ValueError(
                f"phase2.assign.source=masks: scene '{scene.name}' has training frames without "
                "instance masks; use source=trajectories (unsupervised) or auto"
            )
        return assign_from_masks(_positions_fn(model), scene.train, scene.labels, config)
    times = np.linspace(0.0, 1.0, config.trajectory_samples)
    return cluster_trajectories(displacement_curves(model, times), extent, config)


@torch.no_grad()
def node_votes(points: ControlPoints, means: torch.Tensor, labels: np.ndarray, num_objects: int
               ) -> np.ndarray:  # fmt: skip
    """The object of each control point [M] (int; `Motion.control_points`: the nodes): the
    label its Gaussians (canonical `means` [N, 3], object `labels` [N]) vote for, each vote
    weighted by the Gaussian's weight on the point; a point no Gaussian leans on takes its
    nearest Gaussian's label."""
    index, w = points.index, points.weights
    m, k = points.positions.shape[0], index.shape[1]
    votes = torch.zeros(m * num_objects, dtype=torch.float64)
    lab = torch.as_tensor(labels, dtype=torch.long).repeat_interleave(k)
    votes.index_add_(0, index.reshape(-1) * num_objects + lab, w.reshape(-1).double())
    votes = votes.reshape(m, num_objects)
    out = votes.argmax(1)
    empty = votes.sum(1) <= 0
    if bool(empty.any()):
        near = knn(points.positions[empty], means, 1)[:, 0]
        out[empty] = torch.as_tensor(labels, dtype=torch.long)[near]
    return out.numpy()
