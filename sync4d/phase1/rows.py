"""Row operations on parameters that an Adam optimizer holds: the densifier's (per-Gaussian
rows) and the adaptive nodes' (per-node rows) share them, so a parameter and its moments always
change rows together."""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch
from torch import Tensor, nn

__all__ = ["replace_param_rows"]


def replace_param_rows(optimizer: torch.optim.Optimizer, owner: nn.Module, names: Iterable[str],
                       fn: Callable[[str, Tensor, bool], Tensor]) -> None:  # fmt: skip
    """Replace each parameter `owner.<name>` (for `names`) by `fn(name, p, is_state=False)` and
    its Adam moments by `fn(name, moment, is_state=True)`, in place in `optimizer`'s groups."""
    for name in names:
        old = getattr(owner, name)
        new = nn.Parameter(fn(name, old.data, False))
        for group in optimizer.param_groups:
            for i, p in enumerate(group["params"]):
                if p is old:
                    group["params"][i] = new
                    state = optimizer.state.pop(old, None)
                    if state:
                        for k in ("exp_avg", "exp_avg_sq"):
                            if k in state:
                                state[k] = fn(name, state[k], True)
                        optimizer.state[new] = state
        setattr(owner, name, new)
