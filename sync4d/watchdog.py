"""The watchdog: every training loop (Phase 1, Phase 2 and its photometric refinement) and
Phase 3's solve check their numbers each step and stop at the first NaN or inf, naming the
tensor, the iteration and the Gaussians or objects involved, and saying what to try.

Cheap enough to stay on: a step checks its loss, then one float64 sum per watched gradient
(before the optimizer moves anything) and per parameter (after), all in a single `isfinite`
over the stacked sums; a non-finite element makes its tensor's sum non-finite (and float64 sums
of float32 values cannot overflow), and only then are the offending rows looked up.

A failure before the optimizer step leaves the model as the previous iteration left it
(`NonFinite.clean`): the loop saves that state as the run's checkpoint. A failure after it does
not save: the checkpoint on disk is the last good one. Never a poisoned checkpoint.

Tests inject a NaN with `injected(phase, iteration, target)`: target ``"loss"``, ``"grad:NAME"``
or ``"param:NAME"`` (a watched tensor's name) at that iteration of that phase.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping

import numpy as np
import torch
from torch import Tensor

__all__ = ["HINTS", "NonFinite", "check_array", "check_grads", "check_loss", "check_params",
           "injected"]  # fmt: skip

#: What to try, per phase.
HINTS = {
    "Phase 1": "lower the learning rates (--set phase1.lr_position=..., phase1.lr_deform=...), "
               "train at a smaller --resolution-scale, or check the dataset's images and "
               "poses for NaN",
    "Phase 2": "lower M_phi's learning rate (--set phase2.motion.lr=...) or the regulariser "
               "weights, or redo Phase 2 from the Phase 1 checkpoint (fit --out RUN --phases 2)",
    "Phase 2 refinement": "lower the refinement's step (--set phase2.motion.refine_lr=...) or "
                          "turn it off (--set phase2.motion.refine_steps=0)",
    "Phase 3": "raise the ridge's regularisation (--set phase3.ridge_lambda=...); an object seen "
               "in too few frames may need phase3.min_visible lowered",
}  # fmt: skip

_INJECT: dict[tuple[str, int], str] = {}


class NonFinite(FloatingPointError):
    """A NaN or inf in training: `phase`, `iteration`, the tensor's `name`, the offending `rows`
    (Gaussians, objects or elements, the first few), and whether the model still holds the
    previous iteration's good state (`clean`). The message says all of it and what to try."""

    def __init__(self, phase: str, iteration: int | None, name: str, rows: list[int],
                 count: int, unit: str, clean: bool) -> None:  # fmt: skip
        self.phase, self.iteration, self.name = phase, iteration, name
        self.rows, self.count, self.unit, self.clean = rows, count, unit, clean
        shown = ", ".join(str(r) for r in rows) + (", ..." if count > len(rows) else "")
        where = f" in {count} {unit} ({shown})" if rows else ""
        super().__init__(
            f"{phase} stopped{'' if iteration is None else f' at iteration {iteration}'}: "
            f"{name} is NaN or inf{where}. "
            f"Try: {HINTS.get(phase, 'lower the learning rates')}"
        )


@contextlib.contextmanager
def injected(phase: str, iteration: int, target: str) -> Iterator[None]:
    """A test hook: within the block, `phase`'s check at `iteration` finds a NaN in `target`
    ("loss", "grad:NAME", "param:NAME"), written into the real tensor first."""
    _INJECT[(phase, iteration)] = target
    try:
        yield
    finally:
        _INJECT.pop((phase, iteration), None)


def _inject(phase: str, iteration: int, kind: str, tensors: Mapping[str, Tensor]) -> None:
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


def _check(phase: str, iteration: int, tensors: Mapping[str, Tensor | None], what: str,
           units: Mapping[str, str], clean: bool) -> None:  # fmt: skip
    present = {k: v for k, v in tensors.items() if v is not None and v.numel()}
    if not present:
        return
    sums = torch.stack([v.detach().double().sum() for v in present.values()])
    if bool(torch.isfinite(sums).all()):
        return
    # float64 sums of float32 values cannot overflow: a non-finite sum has a non-finite element
    name = next(k for k, v in present.items() if not bool(torch.isfinite(v.detach()).all()))
    rows, count = _bad_rows(present[name])
    raise NonFinite(phase, iteration, f"the {what} of '{name}'", rows, count,
                    units.get(name, "elements"), clean)  # fmt: skip


def check_loss(phase: str, iteration: int, loss: Tensor) -> Tensor:
    """NonFinite (clean) unless the loss is finite; returns it (NaN when a test injects one)."""
    if _INJECT.get((phase, iteration)) == "loss":
        loss = loss * float("nan")
    if not bool(torch.isfinite(loss.detach()).all()):
        raise NonFinite(phase, iteration, "the loss", [], 0, "", clean=True)
    return loss


def check_grads(phase: str, iteration: int, params: Mapping[str, Tensor],
                units: Mapping[str, str] | None = None) -> None:  # fmt: skip
    """NonFinite (clean: nothing updated yet) unless every gradient of `params` is finite."""
    _inject(phase, iteration, "grad", params)
    _check(phase, iteration, {k: p.grad for k, p in params.items()}, "gradient", units or {},
           clean=True)  # fmt: skip


def check_params(phase: str, iteration: int, params: Mapping[str, Tensor],
                 units: Mapping[str, str] | None = None) -> None:  # fmt: skip
    """NonFinite (not clean: the optimizer already wrote them) unless every parameter is
    finite."""
    _inject(phase, iteration, "param", params)
    _check(phase, iteration, dict(params), "value", units or {}, clean=False)


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
