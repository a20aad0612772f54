"""The watchdog: every training loop (Phase 1, Phase 2 and its photometric refinement) and
Phase 3's solve check their numbers each step and stop at the first NaN or inf, or the first
value that has diverged while staying finite, naming the tensor, the iteration and the
Gaussians or objects involved, and saying what to try.

Diverged but finite (`limits`): a learning rate of 1e9 moves every Adam-trained value by about
1e9 per step, which float32 holds; the model is then garbage (opacities saturated to exactly 0
or 1 with zero gradient, colours 1e8 times white, a rotation re-drawn each step) though
nothing is inf. Such a value is out of range: beyond ``DIVERGED`` (1e4) in the tensor's own
unit, or ``DIVERGED_WORLD`` (1e6) times the scene's scale for positions and sizes (a float32
position there resolves no better than 1/16 of the scene). Trained runs stay far inside: the
largest value of 16 trained checkpoints (D-NeRF lego, bouncingballs, hook, hellwarrior and the
embedded scene; `docs/bench/watchdog-ranges.json`, `scripts/watchdog_ranges.py`) is 18.2, an
opacity logit, and their positions lie within 1.4 units of scenes whose cameras sit 4 units
out; and Adam moves a value by about its rate per step, so the paper's rates (at most 0.05)
cannot reach 1e4 in 30k iterations.

A step checks what the rasteriser and the losses receive (`check_inputs`: the deformed means,
normalised rotations, activated scales and opacities, SH coefficients and colours, the node
motion; evaluation renders too, as phase "Evaluation"), its loss, every watched gradient
(before the optimizer moves anything) and every parameter (after; a log-scale whose
exponential overflows float32 counts as non-finite, and values and inputs are held to
`limits`). Cheap enough to stay on: one fused `aminmax` per tensor (a NaN propagates to both
ends, an inf is one), one comparison with the bounds over all of them, and only on a failure
are the offending rows looked up.

A failure of the loss or the gradients leaves the model as the previous iteration left it
(`NonFinite.clean`): the loop saves that state as the run's checkpoint. A failure of the
parameters after the optimizer step, or of the inputs (which the previous step's parameters
produced), does not save: the checkpoint on disk is the last good one. Never a poisoned
checkpoint.

Each message names the settings its evidence points to (`advice`; every one a real key of
`RunConfig`, which `tests/pipeline/test_watchdog.py` checks). The watchdog keeps, per phase,
each watched tensor's range when it was first seen (before any optimizer step moved it) and
after the last good step, and the live parameters: a size (the Gaussians' scales, the nodes'
radii) already collapsed or exploded before any step names its initial setting
(`phase1.init_scale`, `phase1.nodes.radius_scale`), not a rate; a node graph of coinciding
nodes names the node settings; otherwise the learning rates that move the tensor
(`SETTINGS`), with how far its magnitude grew over the steps when it did.

Tests inject a NaN with `injected(phase, iteration, target)`: target ``"loss"``, ``"grad:NAME"``,
``"param:NAME"`` or ``"input:NAME"`` (a watched tensor's name) at that iteration of that phase.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from collections.abc import Iterator, Mapping

import numpy as np
import torch
from torch import Tensor

from sync4d.errors import Sync4dError

__all__ = ["DIVERGED", "DIVERGED_WORLD", "HINTS", "INPUTS", "SETTINGS", "SIZES", "Advice",
           "Evidence", "NonFinite", "advice", "check_array", "check_grads", "check_inputs",
           "check_loss", "check_params", "forget", "injected", "limits",
           "settings_for"]  # fmt: skip

#: What to try, per phase.
HINTS = {
    "Phase 1": "lower the learning rates (--set phase1.lr_means=..., phase1.lr_scales=..., "
               "phase1.lr_deform=...), train at a smaller --resolution-scale, or check the "
               "dataset's images and poses for NaN",
    "Phase 2": "lower M_phi's learning rate (--set phase2.motion.lr=...) or the regulariser "
               "weights, or redo Phase 2 from the Phase 1 checkpoint (fit --out RUN --phases 2)",
    "Phase 2 refinement": "lower the refinement's step (--set phase2.motion.refine_lr=...) or "
                          "turn it off (--set phase2.motion.refine_steps=0)",
    "Phase 3 observation": "the checkpoint's motion is not finite at this time: train Phases 1 "
                           "and 2 again with lower learning rates (fit --out RUN --force)",
    "Rendering": "the checkpoint's motion is not finite at this time: train again with lower "
                 "learning rates (fit --out RUN --force)",
    "Phase 3": "raise the ridge's regularisation (--set phase3.ridge_lambda=...); an object seen "
               "in too few frames may need phase3.min_visible lowered",
}  # fmt: skip

#: The settings whose learning rates move each watched tensor: a parameter's name, a prefix
#: ending in "." (D_theta's, M_phi's), or ``input:NAME`` for what the rasteriser receives.
#: Phase 2 trains Phase 1's parameters with Phase 1's rates.
SETTINGS: dict[str, tuple[str, ...]] = {
    "means": ("phase1.lr_means",),
    "quats": ("phase1.lr_quats",),
    "log_scales": ("phase1.lr_scales",),
    "opacity_logits": ("phase1.lr_opacity",),
    "sh_dc": ("phase1.lr_sh",),
    "sh_rest": ("phase1.lr_sh",),
    "embeddings": ("phase1.lr_embed",),
    "deform.": ("phase1.lr_deform",),
    "nodes.positions": ("phase1.nodes.lr_position",),
    "nodes.log_radii": ("phase1.nodes.lr_radius",),
    "nodes.embeddings": ("phase1.lr_embed",),
    "motion.": ("phase2.motion.lr",),
    "rotation": ("phase2.motion.refine_lr",),
    "shift": ("phase2.motion.refine_lr",),
    "input:means": ("phase1.lr_means", "phase1.lr_deform", "phase1.lr_embed"),
    "input:quats": ("phase1.lr_quats", "phase1.lr_deform"),
    "input:scales": ("phase1.lr_scales", "phase1.lr_deform"),
    "input:opacities": ("phase1.lr_opacity",),
    "input:sh": ("phase1.lr_sh",),
    "input:colors": ("phase1.lr_sh",),
    "input:node_rotations": ("phase1.lr_deform", "phase1.lr_embed"),
    "input:node_shifts": ("phase1.lr_deform", "phase1.lr_embed"),
    "input:node_log_scales": ("phase1.lr_deform", "phase1.lr_embed"),
}

#: What each of the rasteriser's inputs is (``check_inputs``' names).
INPUTS = {
    "means": "the deformed means",
    "quats": "the normalised rotations",
    "scales": "the activated scales (exp of the deformed log-scales)",
    "opacities": "the opacities (sigmoid of the logits)",
    "sh": "the SH coefficients",
    "colors": "the SH colours",
    "node_rotations": "the node motion's rotations",
    "node_shifts": "the node motion's translations",
    "node_log_scales": "the node motion's log-scale offsets",
}

#: exp(x) overflows float32 above this.
_EXP_MAX = 88.72

#: A watched value whose magnitude passes this (in its own unit) has diverged.
DIVERGED = 1e4
#: Positions and sizes (`WORLD`) have diverged past this many times the scene's scale.
DIVERGED_WORLD = 1e6
#: The watched tensors in world units (parameters, and ``input:`` what the rasteriser gets).
WORLD = frozenset({"means", "nodes.positions", "motion.translations", "motion.offsets", "shift",
                   "input:means", "input:scales", "input:node_shifts"})  # fmt: skip
#: Log-values the rasteriser receives exponentiated: above `_EXP_MAX` their exp is inf.
EXPONENTIATED = frozenset({"log_scales", "nodes.log_radii", "input:node_log_scales"})

_INJECT: dict[tuple[str, int | None], str] = {}

#: The sizes whose initial value a setting gives: the log-valued parameter, the input that is
#: its exp (or ""), the setting, and what it sizes (in messages).
SIZES: tuple[tuple[str, str, str, str], ...] = (
    ("log_scales", "input:scales", "phase1.init_scale", "the Gaussians' scales"),
    ("nodes.log_radii", "", "phase1.nodes.radius_scale", "the nodes' radii"),
)
#: A size below this many times the scene's scale has collapsed (1e-9), above it exploded.
COLLAPSED, EXPLODED = math.log(1e-9), math.log(DIVERGED_WORLD)
#: The node settings a degenerate node graph (fewer than 2 distinct nodes) names.
NODE_SETTINGS = ("phase1.nodes.count", "phase1.nodes.init_min_opacity",
                 "phase1.nodes.prune_weight")  # fmt: skip
#: A magnitude that grew this many times over the steps is a rate's doing.
GROWTH = 10.0


@dataclasses.dataclass
class Evidence:
    """What the watchdog saw of a phase's run at its stop: each watched tensor's (min, max)
    when `first` seen (before any optimizer step moved it; ``input:NAME`` for the inputs,
    gradients not kept) and after the `last` good optimizer step (parameters), the live
    parameter `values`, and the scene's `scale` (world units; None: 1)."""

    first: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    last: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    values: Mapping[str, Tensor] = dataclasses.field(default_factory=dict)
    scale: float | None = None
    #: The iteration of the last check (a lower one starts a new run's evidence).
    iteration: int = 0


@dataclasses.dataclass(frozen=True)
class Advice:
    """What a stop's message says to try: the `settings` named and the sentence `text`."""

    settings: tuple[str, ...]
    text: str


def _size_range(ev: Evidence, log_name: str, exp_name: str) -> tuple[float, float] | None:
    """The (min, max) log of a size relative to the scene's scale when first seen, or None."""
    shift = math.log(ev.scale) if ev.scale and ev.scale > 0 else 0.0
    if log_name in ev.first:
        lo, hi = ev.first[log_name]
    elif exp_name and exp_name in ev.first:
        lo, hi = (math.log(v) if v > 0 else -math.inf for v in ev.first[exp_name])
    else:
        return None
    return lo - shift, hi - shift


def _degenerate_nodes(ev: Evidence) -> int | None:
    """The count of distinct node positions when fewer than 2 (a graph without edges, or
    of coinciding nodes: ARAP's mean edge is 0), else None."""
    p = ev.values.get("nodes.positions")
    if p is None or p.dim() != 2 or not bool(torch.isfinite(p).all()):
        return None
    distinct = int(torch.unique(p.detach(), dim=0).shape[0])
    return distinct if distinct < 2 else None


def advice(phase: str, key: str, ev: Evidence) -> Advice:
    """What to try after `phase` stopped on watched tensor `key` ("loss", a parameter's name,
    or ``input:NAME``), from the evidence `ev`: the initial-size setting when a size had
    collapsed or exploded before any step (`SIZES`), the node settings when the nodes
    coincide, else the learning rates that move `key` (`SETTINGS`) and the phase's hint."""
    for log_name, exp_name, setting, what in SIZES:
        related = key in ("loss", log_name, exp_name) or key.startswith("input:") \
            or (log_name.startswith("nodes.") and "node" in key)  # fmt: skip
        rng = _size_range(ev, log_name, exp_name)
        if not related or rng is None:
            continue
        found = None
        if rng[1] < COLLAPSED:
            found = f"collapsed before any step moved them (at most {math.exp(rng[1]):.2g}"
        elif rng[0] > EXPLODED:
            found = f"exploded before any step moved them (at least {math.exp(rng[0]):.2g}"
        if found is not None:
            return Advice((setting,), f"{what} had {found} times the scene's scale), so the "
                          f"setting that sizes them is the cause, not a rate: change it (--set "
                          f"{setting}=...)")  # fmt: skip
    if key == "loss" or key.startswith("nodes.") or "node" in key:
        distinct = _degenerate_nodes(ev)
        if distinct is not None:
            named = ", ".join(f"--set {s}=..." for s in NODE_SETTINGS)
            return Advice(NODE_SETTINGS, f"the control nodes lie at {distinct} distinct "
                          f"position(s), a graph without edges: keep more nodes ({named})")
    settings = settings_for(key)
    hint = HINTS.get(phase, "lower the learning rates")
    grew = ""
    if key in ev.first and key in ev.last:
        a = max(abs(v) for v in ev.first[key])
        b = max(abs(v) for v in ev.last[key])
        if math.isfinite(b) and b > GROWTH * max(a, 1e-12):
            grew = f" (its magnitude grew from {a:.3g} to {b:.3g} over the steps)"
    if settings:
        named = ", ".join(f"--set {s}=..." for s in settings)
        hint = f"lower the learning rates that move it{grew} ({named}); more generally, {hint}"
    return Advice(settings, hint)


#: Each phase's evidence so far (`Evidence`), for the stop's `advice`.
_EVIDENCE: dict[str, Evidence] = {}


def evidence(phase: str, iteration: int | None) -> Evidence:
    """`phase`'s evidence, a fresh one when `iteration` is below the last seen (a new run;
    a stop forgets its phase's evidence too, `_advice_at_stop`)."""
    ev = _EVIDENCE.get(phase)
    if ev is None or (iteration is not None and iteration < ev.iteration):
        ev = _EVIDENCE[phase] = Evidence()
    if iteration is not None:
        ev.iteration = iteration
    return ev


def forget() -> None:
    """Start every phase's evidence afresh (a training loop begins: what an earlier run in this
    process saw says nothing of it)."""
    _EVIDENCE.clear()


def _advice_at_stop(phase: str, key: str, ev: Evidence) -> Advice:
    """`advice` for a stop; the phase's evidence is forgotten (its run is over)."""
    _EVIDENCE.pop(phase, None)
    return advice(phase, key, ev)


def _first_seen(ev: Evidence, prefix: str, tensors: Mapping[str, Tensor]) -> None:
    """Record the (min, max) of each of `tensors` not seen before (one pass, once each)."""
    for k, v in tensors.items():
        if prefix + k not in ev.first and v is not None and v.numel():
            ev.first[prefix + k] = tuple(float(x) for x in torch.aminmax(v.detach().float()))


def settings_for(name: str) -> tuple[str, ...]:
    """The settings `SETTINGS` names for watched tensor `name` (exact, else the longest
    matching prefix); () when none."""
    if name in SETTINGS:
        return SETTINGS[name]
    best = max((k for k in SETTINGS if k.endswith(".") and name.startswith(k)), key=len,
               default=None)  # fmt: skip
    return SETTINGS[best] if best else ()


class NonFinite(Sync4dError, FloatingPointError):
    """A NaN or inf in training, or a value that diverged (`limits`): `phase`, `iteration`,
    the tensor's `name`, the offending `rows` (Gaussians, objects or elements, the first few),
    and whether the model still holds the previous iteration's good state (`clean`). The
    message says all of it and what to try; exit status 3."""

    exit_code = 3

    def __init__(self, phase: str, iteration: int | None, name: str, rows: list[int],
                 count: int, unit: str, clean: bool, settings: tuple[str, ...] = (),
                 problem: str = "is NaN or inf", hint: str | None = None) -> None:  # fmt: skip
        self.phase, self.iteration, self.name = phase, iteration, name
        self.rows, self.count, self.unit, self.clean = rows, count, unit, clean
        self.settings = settings
        shown = ", ".join(str(r) for r in rows) + (", ..." if count > len(rows) else "")
        where = f" in {count} {unit} ({shown})" if rows else ""
        if hint is None:  # no evidence (`advice`): the rates that move it
            hint = HINTS.get(phase, "lower the learning rates")
            if settings:
                named = ", ".join(f"--set {s}=..." for s in settings)
                hint = f"lower the learning rates that move it ({named}); more generally, {hint}"
        super().__init__(
            f"{phase} stopped{'' if iteration is None else f' at iteration {iteration}'}: "
            f"{name} {problem}{where}. Try: {hint}"
        )


@contextlib.contextmanager
def injected(phase: str, iteration: int | None, target: str) -> Iterator[None]:
    """A test hook: within the block, `phase`'s check at `iteration` finds a NaN in `target`
    ("loss", "grad:NAME", "param:NAME", "input:NAME"), written into the real tensor first."""
    _INJECT[(phase, iteration)] = target
    try:
        yield
    finally:
        _INJECT.pop((phase, iteration), None)


def _inject(phase: str, iteration: int | None, kind: str, tensors: Mapping[str, Tensor]) -> None:
    target = _INJECT.get((phase, iteration))
    if target is None or not target.startswith(kind + ":"):
        return
    t = tensors.get(target.split(":", 1)[1])
    if t is not None:
        t = t.grad if kind == "grad" else t
        if t is not None:
            with torch.no_grad():
                t.view(-1)[0] = float("nan")


def _bad_rows(t: Tensor) -> tuple[list[int], int]:
    bad = ~torch.isfinite(t.detach())
    rows = bad.reshape(bad.shape[0], -1).any(1) if bad.dim() > 0 else bad.reshape(1)
    idx = rows.nonzero().flatten()
    return [int(i) for i in idx[:8]], int(idx.numel())


def _ends(present: Mapping[str, Tensor]) -> Tensor:
    """[T, 2]: each tensor's (min, max), one fused pass each (NaN propagates to both)."""
    return torch.stack([torch.stack(torch.aminmax(v.detach())) for v in present.values()])


def limits(names: list[str], kind: str, scale: float | None) -> Tensor:
    """[T, 2]: the (low, high) range each watched tensor of `kind` ("param" or "input"; others
    unbounded) must stay in: +-`DIVERGED`, +-`DIVERGED_WORLD` * `scale` for `WORLD` tensors
    (unbounded without a scale), and an `EXPONENTIATED` one below `_EXP_MAX`. Built once per
    (names, kind, scale): every step asks the same (read-only: do not write into it)."""
    return _limits(tuple(names), kind, scale)


@functools.lru_cache(maxsize=64)
def _limits(names: tuple[str, ...], kind: str, scale: float | None) -> Tensor:
    inf = float("inf")
    if kind not in ("param", "input"):
        return torch.tensor([[-inf, inf]] * len(names))
    rows = []
    for name in names:
        key = f"input:{name}" if kind == "input" else name
        bound = DIVERGED
        if key in WORLD:
            bound = DIVERGED_WORLD * scale if scale else inf
        rows.append((-bound, _EXP_MAX if key in EXPONENTIATED else bound))
    return torch.tensor(rows)


def _check(phase: str, iteration: int | None, tensors: Mapping[str, Tensor | None], what: str,
           units: Mapping[str, str], clean: bool, kind: str = "",
           scale: float | None = None) -> None:  # fmt: skip
    present = {k: v for k, v in tensors.items() if v is not None and v.numel()}
    if not present:
        return
    ev = evidence(phase, iteration)
    if scale:
        ev.scale = scale
    ends = _ends(present)
    if what == "input":
        _first_seen(ev, "input:", present)
    bounds = limits(list(present), kind, scale)
    ok = (ends[:, 0] >= bounds[:, 0]) & (ends[:, 1] <= bounds[:, 1])  # False for NaN
    ok &= torch.isfinite(ends).all(1)
    if bool(ok.all()):
        if what == "value":  # after a good optimizer step: the parameters' latest ranges
            ev.values = tensors  # type: ignore[assignment]
            ev.last.update(zip(present, (tuple(r) for r in ends.tolist()), strict=True))
        return
    i = int((~ok).nonzero()[0])
    name = list(present)[i]
    t = present[name].detach()
    key = f"input:{name}" if what == "input" else name
    label = f"{INPUTS[name]} ('{name}')" if what == "input" and name in INPUTS \
        else f"the {what} of '{name}'"  # fmt: skip
    problem = "is NaN or inf"
    lo, hi = float(bounds[i, 0]), float(bounds[i, 1])
    if not bool(torch.isfinite(t).all()):
        rows, count = _bad_rows(t)
    elif key in EXPONENTIATED and bool((t >= _EXP_MAX).any()):  # finite, but its exp is inf
        rows, count = _bad_rows(torch.where(t < _EXP_MAX, 0.0, float("inf")))
        label = f"the activated value (exp) of '{name}'"
    else:
        rows, count = _bad_rows(torch.where((t >= lo) & (t <= hi), 0.0, float("inf")))
        bound = (f"{DIVERGED_WORLD:.0e} times the scene's scale ({scale:.3g})" if key in WORLD
                 else f"{DIVERGED:.0e}")  # fmt: skip
        problem = f"diverged (finite, but beyond +-{bound}, where no trained scene goes)"
    a = _advice_at_stop(phase, key, ev)
    raise NonFinite(phase, iteration, label, rows, count, units.get(name, "elements"), clean,
                    a.settings, problem, a.text)  # fmt: skip


def check_loss(phase: str, iteration: int, loss: Tensor) -> Tensor:
    """NonFinite (clean) unless the loss is finite; returns it (NaN when a test injects one).
    The advice reads the phase's evidence (`advice`): the loss names no tensor itself."""
    if _INJECT.get((phase, iteration)) == "loss":
        loss = loss * float("nan")
    if not bool(torch.isfinite(loss.detach()).all()):
        a = _advice_at_stop(phase, "loss", evidence(phase, iteration))
        raise NonFinite(phase, iteration, "the loss", [], 0, "", clean=True,
                        settings=a.settings, hint=a.text)  # fmt: skip
    return loss


def check_grads(phase: str, iteration: int, params: Mapping[str, Tensor],
                units: Mapping[str, str] | None = None) -> None:  # fmt: skip
    """NonFinite (clean: nothing updated yet) unless every gradient of `params` is finite.
    The first time a parameter is seen its values' range is kept (`Evidence.first`)."""
    ev = evidence(phase, iteration)
    _first_seen(ev, "", params)
    ev.values = params
    _inject(phase, iteration, "grad", params)
    _check(phase, iteration, {k: p.grad for k, p in params.items()}, "gradient", units or {},
           clean=True)  # fmt: skip


def check_params(phase: str, iteration: int, params: Mapping[str, Tensor],
                 units: Mapping[str, str] | None = None,
                 scale: float | None = None) -> None:  # fmt: skip
    """NonFinite (not clean: the optimizer already wrote them) unless every parameter is
    finite and within `limits` (world-unit ones only given the scene's `scale`)."""
    _inject(phase, iteration, "param", params)
    _check(phase, iteration, dict(params), "value", units or {}, clean=False, kind="param",
           scale=scale)  # fmt: skip


def check_inputs(phase: str, iteration: int | None, inputs: Mapping[str, Tensor | None],
                 units: Mapping[str, str] | None = None,
                 scale: float | None = None) -> None:  # fmt: skip
    """NonFinite (not clean: the previous step's parameters produced them) unless every
    tensor the rasteriser or a loss is about to receive is finite and within `limits`
    (`INPUTS` names them: ``means``, ``quats``, ``scales``, ``opacities``, ``sh``,
    ``colors``, ``node_*``; world-unit ones bounded only given the scene's `scale`); rows
    are Gaussians unless `units` says otherwise."""
    _inject(phase, iteration, "input", inputs)
    names = {k: "nodes" if k.startswith("node_") else "Gaussians" for k in inputs}
    _check(phase, iteration, inputs, "input", {**names, **(units or {})}, clean=False,
           kind="input", scale=scale)  # fmt: skip


def check_array(phase: str, name: str, a: np.ndarray, unit: str = "objects") -> None:
    """NonFinite naming `name` and its offending rows (objects) unless numpy `a` is finite
    (test hook: target "array:NAME" at iteration 0)."""
    arr = np.asarray(a)
    if _INJECT.get((phase, 0)) == f"array:{name}":  # the test hook
        arr = arr.astype(np.float64)
        arr.reshape(-1)[0] = np.nan
    if np.isfinite(arr).all():
        return
    rows, count = _bad_rows(torch.as_tensor(arr))
    raise NonFinite(phase, None, name, rows, count, unit, clean=True)
