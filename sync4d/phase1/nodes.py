"""Motion on control nodes (issue "motion on a few hundred nodes"; SC-GS, Huang et al. 2024):
D_theta evaluated on a few hundred nodes instead of every Gaussian, each Gaussian moved by
blending the rigid motions of its K nearest nodes.

Design. Motion in a dynamic scene is low-dimensional: a ball, a hook's arm or a warrior's
limbs move as a few hundred rigid pieces. With `Phase1Config.motion = "nodes"`, Phase 1 first
trains today's per-Gaussian D_theta for `NodeConfig.init_after` iterations (the coarse stage,
which settles the canonical Gaussians and a first motion), then samples `count` nodes among
the Gaussians by farthest-point sampling (`farthest_point_sample`; Gaussians at least
`init_min_opacity` opaque). Each node starts as a copy of the Gaussian it was sampled at: its
canonical position and its embedding, so D_theta, now evaluated on the nodes'
[position, embedding, gamma(t)], gives each node exactly the motion that Gaussian had. From
then on D_theta runs on M rows, not N:

    node j at time t:  (dx_j, dw_j, dl_j) = D_theta(p_j, z_j, gamma(t)),  q_j = aa2q(dw_j)
    weights:           w_ij = softmax_j(-|x0_i - p_j|^2 / (2 r_j^2)) over i's K nodes
    linear blend:      x_i = sum_j w_ij (R_j (x0_i - p_j) + p_j + dx_j),
                       q_i = normalize((sum_j w_ij q_j) (x) q0_i)
    dual quaternions:  each node's (q_j, 1/2 (0, T_j) (x) q_j), T_j = p_j + dx_j - R_j p_j,
                       blended and normalised (Kavan et al. 2007); x_i and q_i from the result
    scales:            s_i = exp(log s0_i + sum_j w_ij dl_j)

The node positions p_j, radii r_j = exp(log_radii_j) and embeddings z_j are trained with the
Gaussians. The softmax keeps the weights a partition of unity however far a Gaussian is from
its nodes (no 0 / 0). Each Gaussian's K nodes (`index`, [N, K]) and each node's graph
neighbours for ARAP (`edges`, [M, E]) are nearest neighbours in canonical space, refreshed
every `refresh_every` iterations; densification carries `index` row by row (children inherit
their parent's nodes) until then.

The ARAP regulariser (`arap_loss`) asks the node graph to move rigidly between two times:
for each node j and neighbour k, the edge y_k - y_j at t2 should be the edge at t1 turned by
R_j(t2) R_j(t1)^T, y = p + dx; it is divided by the mean squared canonical edge so its weight
does not depend on the scene's size. Adaptive nodes (`densify_nodes`): on Gaussian
densification steps until `densify_until`, a node whose Gaussians' screen-space gradient
(weighted by their blend weights) is above `grad_threshold` gets a new node at the
gradient-weighted centroid of its Gaussians; a node no Gaussian leans on (its summed weight
below `prune_weight`) is removed.

Checkpoints (docs/run-folder.md) hold ``nodes.positions`` [M, 3], ``nodes.log_radii`` [M],
``nodes.embeddings`` [M, E], ``nodes.edges`` [M, E'] and ``gaussians.node_index`` [N, K]
(int32), with ``"motion": "nodes"`` and the `NodeConfig` in the header; `sync4d-render`
evaluates the same blend.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from sync4d.geometry import axis_angle_to_quat, quat_multiply, quat_to_matrix
from sync4d.phase1.node_op import linear_epilogue, node_weighted_sum
from sync4d.phase1.rows import replace_param_rows
from sync4d.settings import choice, ranged

__all__ = [
    "BLENDS",
    "NodeConfig",
    "NodeMotion",
    "arap_loss",
    "blend",
    "strain_loss",
    "blend_weights",
    "densify_nodes",
    "farthest_point_sample",
    "gather_blend",
    "knn",
    "node_transforms",
]

#: The blends of node motions a Gaussian can use.
BLENDS = ("linear", "dual_quaternion")


@dataclass(frozen=True)
class NodeConfig:
    """Control nodes that carry the motion (`Phase1Config.motion = "nodes"`).

    Settings that must go together (checked when the config is read, `combination_problem`):
    `neighbours` at most `count`; `count` at least 2 while `arap_weight` or `strain_weight` is
    above 0; `max_count` at least `count`; and a falling ARAP weight (`arap_until` > 0,
    `arap_weight` > 0) ends after `init_after` (else it is zero before the nodes start)."""

    #: Nodes sampled by farthest-point sampling when the coarse stage ends (SC-GS: 512).
    count: int = ranged(512, 1)
    #: Iterations of per-Gaussian D_theta before the nodes take over (the coarse stage;
    #: scaled with `fit --iters`); below `phase1.iterations` with `motion = "nodes"`.
    init_after: int = ranged(1_000, 0, scales=0)
    #: Nodes are sampled among the Gaussians at least this opaque (all when too few are).
    init_min_opacity: float = ranged(0.05, 0.0, 1.0)
    #: Nodes K each Gaussian blends.
    neighbours: int = ranged(8, 1, 64)
    #: How node motions are blended: "linear" (rotations and translations averaged) or
    #: "dual_quaternion".
    blend: str = choice("linear", BLENDS)
    #: Initial radius of each node, times the mean distance to its 3 nearest nodes.
    radius_scale: float = ranged(1.0, 0.0, lo_open=True)
    #: Iterations between refreshes of the nearest-node tables (scaled with `fit --iters`).
    refresh_every: int = ranged(100, 1, scales=10)
    #: Weight of the ARAP loss between neighbouring nodes over a pair of times.
    arap_weight: float = ranged(1e-3, 0.0)
    #: The ARAP weight falls linearly from `arap_weight` when the coarse stage ends to zero at
    #: this iteration and stays zero after (scaled with `fit --iters`); 0 keeps it constant.
    #: Otherwise after `init_after` (checked when the config is read).
    arap_until: int = ranged(0, 0, scales=0)
    #: Graph neighbours of each node in the ARAP and strain losses.
    arap_neighbours: int = ranged(8, 1, 64)
    #: Weight of the strain prior (`strain_loss`): each graph edge's length at the frame's
    #: time against its canonical length, relative to that length; 0 off.
    strain_weight: float = ranged(0.0, 0.0)
    #: Adam rate of the node positions, times the scene extent (decays like the means').
    lr_position: float = ranged(1.6e-4, 0.0, lo_open=True)
    #: Adam rate of the nodes' log-radii.
    lr_radius: float = ranged(1e-3, 0.0, lo_open=True)
    #: Nodes are added and removed at Gaussian densification steps up to this iteration
    #: (scaled with `fit --iters`); 0 never.
    densify_until: int = ranged(15_000, 0, scales=0)
    #: A node whose Gaussians' mean screen-space gradient, weighted by their blend weights,
    #: is at least this gets a new node beside it.
    grad_threshold: float = ranged(2e-4, 0.0, lo_open=True)
    #: Most nodes added per densification step.
    add_per_step: int = ranged(32, 0)
    #: Nodes are never added beyond this count.
    max_count: int = ranged(2_048, 1)
    #: A node whose summed blend weight over all Gaussians is below this is removed.
    prune_weight: float = ranged(0.5, 0.0)

    def combination_problem(self) -> str | None:
        """What is wrong with these settings together (each is within its own range), or None;
        `sync4d.config.validate` calls it once all overrides are applied."""
        if self.neighbours > self.count:
            return (f"neighbours = {self.neighbours} exceeds count = {self.count}: a Gaussian "
                    "blends at most count nodes; lower phase1.nodes.neighbours or raise "
                    "phase1.nodes.count")  # fmt: skip
        graph = self.arap_weight > 0 or self.strain_weight > 0
        if graph and self.count < 2:
            return (f"count = {self.count} needs at least 2 nodes for the ARAP and strain "
                    "losses (each node is compared with its graph neighbours, at most count - "
                    "1 of them); raise phase1.nodes.count or set phase1.nodes.arap_weight = 0 "
                    "and phase1.nodes.strain_weight = 0")  # fmt: skip
        if self.max_count < self.count:
            return (f"max_count = {self.max_count} is below count = {self.count}: nodes are "
                    "never added beyond max_count; raise phase1.nodes.max_count")
        if self.arap_weight > 0 and 0 < self.arap_until <= self.init_after:
            return (f"arap_until = {self.arap_until} is not after init_after = "
                    f"{self.init_after}, so the ARAP weight is already 0 when the nodes start; "
                    "raise phase1.nodes.arap_until, or set it to 0 for a constant weight")
        return None


def knn(points: Tensor, refs: Tensor, k: int, chunk: int = 8_192,
        exclude_self: bool = False) -> Tensor:  # fmt: skip
    """Indices [P, k] (int64) of the `k` rows of `refs` [M, 3] nearest to each row of `points`
    [P, 3], nearest first (`k` is clipped to what `refs` holds; with `exclude_self`,
    `points` is `refs` and a row is not its own neighbour)."""
    k = min(k, refs.shape[0] - (1 if exclude_self else 0))
    out = []
    with torch.no_grad():
        for lo in range(0, points.shape[0], chunk):
            # Exact differences, not |a|^2 + |b|^2 - 2 a.b (which mis-orders close points).
            d = torch.cdist(points[lo : lo + chunk].float(), refs.float(),
                            compute_mode="donot_use_mm_for_euclid_dist")  # fmt: skip
            if exclude_self:
                rows = torch.arange(lo, lo + d.shape[0])
                d[rows - lo, rows] = float("inf")
            out.append(d.topk(k, dim=1, largest=False).indices)
    return torch.cat(out) if out else torch.zeros(0, k, dtype=torch.long)


@torch.no_grad()
def farthest_point_sample(points: Tensor, count: int, generator: torch.Generator | None = None
                          ) -> Tensor:  # fmt: skip
    """Indices [min(count, P)] of rows of `points` [P, 3] chosen by farthest-point sampling
    (each the row farthest from those chosen before), starting at a row drawn from
    `generator`."""
    p = points.shape[0]
    count = min(count, p)
    idx = torch.empty(count, dtype=torch.long)
    if count == 0:
        return idx
    cur = int(torch.randint(p, (1,), generator=generator))
    dist = torch.full((p,), float("inf"))
    pts = points.float()
    for k in range(count):
        idx[k] = cur
        dist = torch.minimum(dist, ((pts - pts[cur]) ** 2).sum(-1))
        cur = int(dist.argmax())
    return idx


def node_transforms(mlp: nn.Module, positions: Tensor, embeddings: Tensor, t: float | Tensor
                    ) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """Each node's motion at time `t` from D_theta `mlp`: unit quaternions [M, 4] (w >= 0),
    translations dx [M, 3] and log-scale offsets dl [M, 3]."""
    dx, dw, dl = mlp(positions, embeddings, t)
    q = axis_angle_to_quat(dw)
    q = torch.where(q[:, :1] < 0, -q, q)
    return q, dx, dl


def blend_weights(x0: Tensor, positions: Tensor, log_radii: Tensor, index: Tensor) -> Tensor:
    """Blend weights [N, K] of Gaussians at `x0` [N, 3] on their nodes `index` [N, K]:
    softmax of -|x0 - p_j|^2 / (2 r_j^2), r_j = exp(log_radii_j); each row sums to 1."""
    d2 = ((x0.unsqueeze(1) - positions[index]) ** 2).sum(-1)
    inv_r2 = torch.exp(-2.0 * log_radii).clamp_max(1e20)[index]
    return torch.softmax(-0.5 * d2 * inv_r2, dim=-1)


class _GatherBlend(torch.autograd.Function):
    """sum_k weights[:, k] table[index[:, k]] ([M, C], [N, K], [N, K] -> [N, C]), one
    neighbour slot at a time, so no [N, K, C] tensor is made forward or backward."""

    @staticmethod
    def forward(ctx, table: Tensor, index: Tensor, weights: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(table, index, weights)
        out = weights[:, :1] * table[index[:, 0]]
        for k in range(1, index.shape[1]):
            out.addcmul_(weights[:, k : k + 1], table[index[:, k]])
        return out

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None, Tensor]:  # type: ignore[override]
        table, index, weights = ctx.saved_tensors
        g_table = torch.zeros_like(table)
        g_w = torch.empty_like(weights)
        for k in range(index.shape[1]):
            rows = index[:, k]
            g_w[:, k] = (grad * table[rows]).sum(-1)
            g_table.index_add_(0, rows, grad * weights[:, k : k + 1])
        return g_table, None, g_w


def gather_blend(table: Tensor, index: Tensor, weights: Tensor) -> Tensor:
    """The weighted sum over each row's nodes: sum_k weights[i, k] table[index[i, k]],
    [M, C] x [N, K] x [N, K] -> [N, C], with gradients for `table` and `weights`."""
    return _GatherBlend.apply(table, index, weights)


def _normalize(q: Tensor) -> Tensor:
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _conj(q: Tensor) -> Tensor:
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def blend(
    x0: Tensor, q0: Tensor, log_s0: Tensor, positions: Tensor,
    motion: tuple[Tensor, Tensor, Tensor], index: Tensor, weights: Tensor | None = None,
    kind: str = "linear", log_radii: Tensor | None = None, threads: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """Gaussians (canonical means `x0` [N, 3], unit quaternions `q0` [N, 4], log-scales
    `log_s0` [N, 3]) moved by blending their nodes' motions (`node_transforms`' (q, dx, dl)
    of nodes at `positions` [M, 3]) over `index` [N, K] with `weights` [N, K], or, when
    `weights` is None, with `blend_weights` of the nodes' `log_radii` [M] computed from the
    same rows by the fused kernel (`sync4d.phase1.node_op`, on `threads` threads; None:
    torch's thread count), and for the linear blend applied to the Gaussians by the fused
    epilogue (`node_op.linear_epilogue`; with given `weights`, the torch expression its tests
    compare with): deformed means [N, 3], unit quaternions [N, 4], scales [N, 3].
    `kind`: "linear" or "dual_quaternion" (module docstring). Every node value a Gaussian
    needs is gathered once, as one table row."""
    if kind not in BLENDS:
        raise ValueError(f"blend: expected one of {', '.join(BLENDS)}, got {kind!r}")
    q, dx, dl = motion
    m = positions.shape[0]
    rot = quat_to_matrix(q)  # [M, 3, 3]
    trans = positions + dx - (rot @ positions.unsqueeze(-1)).squeeze(-1)  # x -> R x + T
    if kind == "linear":
        cols = [rot.reshape(m, 9), trans, q, dl]  # 19 columns
    else:
        zero = torch.zeros_like(trans[:, :1])
        dual = 0.5 * quat_multiply(torch.cat([zero, trans], dim=-1), q)
        cols = [q, dual, dl]  # 11 columns
    if weights is None:
        if log_radii is None:
            raise ValueError("blend: give the weights or the nodes' log_radii")
        inv_r2 = torch.exp(-2.0 * log_radii).clamp_max(1e20)
        b = node_weighted_sum(x0, positions, inv_r2, torch.cat(cols, dim=-1), index,
                              threads=threads or torch.get_num_threads())  # [N, C]
    else:
        b = gather_blend(torch.cat(cols, dim=-1), index, weights)  # [N, C]
    if kind == "linear" and weights is None:
        return linear_epilogue(b, x0, q0, log_s0, threads=threads or torch.get_num_threads())
    if kind == "linear":
        a = b[:, :9].reshape(-1, 3, 3)
        x = (a * x0.unsqueeze(1)).sum(-1) + b[:, 9:12]
        qt = _normalize(quat_multiply(b[:, 12:16], q0))
        return x, qt, torch.exp(log_s0 + b[:, 16:19])
    norm = b[:, :4].norm(dim=-1, keepdim=True).clamp_min(1e-12)
    real, dual_b = b[:, :4] / norm, b[:, 4:8] / norm
    moved = (quat_to_matrix(real) * x0.unsqueeze(1)).sum(-1)
    x = moved + 2.0 * quat_multiply(dual_b, _conj(real))[:, 1:]
    qt = _normalize(quat_multiply(real, q0))
    return x, qt, torch.exp(log_s0 + b[:, 8:11])


def arap_loss(positions: Tensor, edges: Tensor, motion_a: tuple[Tensor, Tensor, Tensor],
              motion_b: tuple[Tensor, Tensor, Tensor], scale: float | None = None
              ) -> Tensor:  # fmt: skip
    """As-rigid-as-possible loss of the node graph between two times: the mean over nodes j
    and their graph neighbours k (`edges` [M, E]) of |e_jk(b) - R_j(b) R_j(a)^T e_jk(a)|^2,
    e_jk(t) = y_k(t) - y_j(t), y = p + dx, divided by the mean squared canonical edge
    (detached; `scale` gives it instead), so it is a relative, scale-free measure.
    `motion_*`: `node_transforms`' (q, dx, dl) at the two times."""
    qa, dxa, _ = motion_a
    qb, dxb, _ = motion_b
    if edges.numel() == 0:  # one node left (pruning): no edge to keep rigid
        return (dxa.sum() + dxb.sum()) * 0.0
    ya, yb = positions + dxa, positions + dxb
    ea = ya[edges] - ya.unsqueeze(1)  # [M, E, 3]
    eb = yb[edges] - yb.unsqueeze(1)
    rel = quat_to_matrix(qb) @ quat_to_matrix(qa).transpose(-1, -2)  # [M, 3, 3]
    pred = (rel.unsqueeze(1) @ ea.unsqueeze(-1)).squeeze(-1)
    if scale is None:
        canon = (positions[edges] - positions.unsqueeze(1)).detach()
        scale = float((canon**2).sum(-1).mean())
    return ((eb - pred) ** 2).sum(-1).mean() / max(scale, 1e-30)


def strain_loss(positions: Tensor, edges: Tensor, motion: tuple[Tensor, Tensor, Tensor]
                ) -> Tensor:  # fmt: skip
    """Strain prior of the node graph at one time: the mean over nodes j and their graph
    neighbours k (`edges` [M, E]) of ((|y_k - y_j| - L_jk) / L_jk)^2, y = p + dx at the time
    of `motion` (`node_transforms`' (q, dx, dl)), L_jk = |p_k - p_j| the canonical length
    (the divisor detached). Each edge is normalised by its own length, so short edges between
    touching parts count as much as long ones; scale-free. Rotations are free (unlike
    `arap_loss`)."""
    _, dx, _ = motion
    if edges.numel() == 0:  # one node left (pruning): no edge to strain
        return dx.sum() * 0.0
    y = positions + dx
    length = (y[edges] - y.unsqueeze(1)).norm(dim=-1)  # [M, E]
    canon = (positions[edges] - positions.unsqueeze(1)).norm(dim=-1)
    divisor = canon.detach()
    floor = 1e-6 * max(float(divisor.max()) if divisor.numel() else 0.0, 1e-12)
    return (((length - canon) / divisor.clamp_min(floor)) ** 2).mean()


class NodeMotion(nn.Module):
    """The control nodes: canonical positions [M, 3], log-radii [M] and embeddings [M, E]
    (parameters), with each Gaussian's K nearest nodes `index` [N, K] and each node's graph
    neighbours `edges` [M, E'] (int64, refreshed by `refresh`)."""

    #: Per-node parameters (dimension 0 is M).
    PER_NODE = ("positions", "log_radii", "embeddings")

    def __init__(self, positions: Tensor, log_radii: Tensor, embeddings: Tensor,
                 config: NodeConfig) -> None:  # fmt: skip
        super().__init__()
        self.config = config
        self.positions = nn.Parameter(positions.detach().float().clone())
        self.log_radii = nn.Parameter(log_radii.detach().float().clone())
        self.embeddings = nn.Parameter(embeddings.detach().float().clone())
        self.index = torch.zeros(0, config.neighbours, dtype=torch.long)
        self.edges = torch.zeros(0, config.arap_neighbours, dtype=torch.long)
        #: The last `node_transforms` result (the ARAP loss reuses it) and its time.
        self.last_motion: tuple[Tensor, Tensor, Tensor] | None = None
        #: Nodes added and removed by `densify_nodes` (in this process).
        self.added = 0
        self.removed = 0

    @property
    def count(self) -> int:
        """Number of nodes M."""
        return self.positions.shape[0]

    @classmethod
    def sample(cls, means: Tensor, embeddings: Tensor, opacities: Tensor, config: NodeConfig,
               generator: torch.Generator | None = None) -> NodeMotion:  # fmt: skip
        """Nodes sampled among Gaussians (canonical `means` [N, 3], `embeddings` [N, E],
        `opacities` [N] in [0, 1]) by farthest-point sampling of the ones at least
        `init_min_opacity` opaque (all of them when fewer than `count` are), each a copy of
        its Gaussian's position and embedding; radii `radius_scale` times the mean distance
        to the 3 nearest other nodes. Tables refreshed for `means`."""
        cand = (opacities >= config.init_min_opacity).nonzero().squeeze(1)
        if cand.numel() < min(config.count, means.shape[0]):
            cand = torch.arange(means.shape[0])
        pick = cand[farthest_point_sample(means[cand], config.count, generator)]
        pos = means[pick].detach()
        if pos.shape[0] > 1:
            near = knn(pos, pos, 3, exclude_self=True)
            spacing = (pos[near] - pos.unsqueeze(1)).norm(dim=-1).mean(-1)
            spacing = spacing.clamp_min(1e-6 * max(1e-12, float(spacing.max())))
        else:
            spacing = torch.ones(1)
        nodes = cls(pos, torch.log(config.radius_scale * spacing), embeddings[pick], config)
        nodes.refresh(means)
        return nodes

    @torch.no_grad()
    def refresh(self, means: Tensor) -> None:
        """Recompute each Gaussian's K nearest nodes (of canonical `means` [N, 3]) and each
        node's ARAP neighbours."""
        pos = self.positions.detach()
        self.index = knn(means.detach(), pos, self.config.neighbours)
        self.edges = knn(pos, pos, self.config.arap_neighbours, exclude_self=True)

    def motion(self, mlp: nn.Module, t: float | Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """`node_transforms` of these nodes at `t`."""
        return node_transforms(mlp, self.positions, self.embeddings, t)

    def deformed(self, mlp: nn.Module, x0: Tensor, q0: Tensor, log_s0: Tensor, t: float
                 ) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
        """The Gaussians moved by the nodes at time `t` (`blend`); keeps the node motion in
        `last_motion` for the ARAP loss."""
        if self.index.shape[0] != x0.shape[0]:
            self.refresh(x0)
        motion = self.last_motion = self.motion(mlp, t)
        return blend(x0, q0, log_s0, self.positions, motion, self.index, None,
                     self.config.blend, self.log_radii)  # fmt: skip

    def state(self) -> dict[str, Tensor]:
        """The node tensors of a checkpoint (module docstring)."""
        return {
            "nodes.positions": self.positions.detach(),
            "nodes.log_radii": self.log_radii.detach(),
            "nodes.embeddings": self.embeddings.detach(),
            "nodes.edges": self.edges.to(torch.int32),
            "gaussians.node_index": self.index.to(torch.int32),
        }

    @classmethod
    def from_state(cls, tensors: dict[str, Tensor], config: dict, n: int, embed_dim: int
                   ) -> NodeMotion:  # fmt: skip
        """The nodes `state` wrote, for `n` Gaussians with `embed_dim`-d embeddings. Raises
        KeyError for a missing tensor, ValueError for one that does not fit."""
        cfg = NodeConfig(**config)
        pos = tensors["nodes.positions"]
        m = pos.shape[0] if pos.dim() == 2 else -1
        want = {"nodes.positions": [m, 3], "nodes.log_radii": [m],
                "nodes.embeddings": [m, embed_dim]}  # fmt: skip
        for name, shape in want.items():
            if m < 1 or list(tensors[name].shape) != shape:
                raise ValueError(f"'{name}' has shape {list(tensors[name].shape)}, expected "
                                 f"{shape if m >= 1 else '[M >= 1, 3]'}")  # fmt: skip
        nodes = cls(pos, tensors["nodes.log_radii"], tensors["nodes.embeddings"], cfg)
        index, edges = tensors["gaussians.node_index"].long(), tensors["nodes.edges"].long()
        if index.dim() != 2 or index.shape[0] != n:
            raise ValueError(f"'gaussians.node_index' has shape {list(index.shape)}, expected "
                             f"[{n}, K]")  # fmt: skip
        for name, t in (("gaussians.node_index", index), ("nodes.edges", edges)):
            if t.numel() and (int(t.min()) < 0 or int(t.max()) >= m):
                raise ValueError(f"'{name}' holds node indices outside [0, {m})")
        nodes.index, nodes.edges = index, edges
        return nodes

    def settings(self) -> dict:
        """The `NodeConfig` as JSON-ready settings."""
        return dataclasses.asdict(self.config)


@torch.no_grad()
def densify_nodes(nodes: NodeMotion, means: Tensor, grad: Tensor,
                  optimizer: torch.optim.Optimizer) -> tuple[int, int]:  # fmt: skip
    """Adaptive nodes: add a node beside each node (at most `add_per_step`, never beyond
    `max_count`, highest first) whose Gaussians' mean screen-space gradient `grad` [N],
    weighted by their blend weights, is at least `grad_threshold`, at the gradient-weighted
    centroid of those Gaussians (canonical `means` [N, 3]), with its parent's radius and
    embedding; remove the nodes whose summed weight is below `prune_weight` (never so many
    that fewer than K remain). Refreshes the tables; returns (added, removed)."""
    c = nodes.config
    m = nodes.count
    if nodes.index.shape[0] != means.shape[0]:
        nodes.refresh(means)
    w = blend_weights(means, nodes.positions, nodes.log_radii, nodes.index)
    flat, wf = nodes.index.reshape(-1), w.reshape(-1)
    wg = wf * grad.repeat_interleave(nodes.index.shape[1])
    wsum = torch.zeros(m).index_add_(0, flat, wf)
    acc = torch.zeros(m).index_add_(0, flat, wg)
    rows = torch.arange(means.shape[0]).repeat_interleave(nodes.index.shape[1])
    centroid = torch.zeros(m, 3).index_add_(0, flat, wg.unsqueeze(1) * means[rows])
    score = acc / wsum.clamp_min(1e-12)
    hot = (score >= c.grad_threshold) & (wsum >= c.prune_weight)
    room = max(0, min(c.add_per_step, c.max_count - m))
    parents = torch.zeros(0, dtype=torch.long)
    if room and bool(hot.any()):
        order = torch.argsort(torch.where(hot, score, -1.0), descending=True)
        parents = order[: min(room, int(hot.sum()))]
    keep = wsum >= c.prune_weight
    if int(keep.sum()) < min(m, c.neighbours):  # never strip the graph below K nodes
        keep[torch.argsort(wsum, descending=True)[: min(m, c.neighbours)]] = True
    new_pos = centroid[parents] / acc[parents].clamp_min(1e-30).unsqueeze(1)

    def grow(name: str, t: Tensor, is_state: bool) -> Tensor:
        extra = t[parents]
        if is_state:
            extra = torch.zeros_like(extra)
        elif name == "positions":
            extra = new_pos
        out = torch.cat([t, extra])
        return out[torch.cat([keep, torch.ones(len(parents), dtype=torch.bool)])]

    added, removed = len(parents), int((~keep).sum())
    if added or removed:
        replace_param_rows(optimizer, nodes, NodeMotion.PER_NODE, grow)
        nodes.refresh(means)
        nodes.added += added
        nodes.removed += removed
    return added, removed
