"""sync4d — 4D Synchronized Fields.

Deformable 4D Gaussians with in-loop per-object motion decomposition and a language field,
built on a CPU Gaussian-splatting rasterizer written in Rust (``sync4d._core``) and exposed to
PyTorch as differentiable ops in :mod:`sync4d.raster`.

This module stays light: it imports neither torch nor the compiled extension, so
``python -m sync4d --help`` works before anything heavy is loaded.
"""

from __future__ import annotations

from importlib import metadata as _metadata

try:
    __version__: str = _metadata.version("sync4d")
except _metadata.PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
