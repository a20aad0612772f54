"""Running the standalone renderer `sync4d-render` from the tests, and the Python render it is
compared with. The binary is built by `cargo test --workspace --release` (make test); set
SYNC4D_RENDER to use another build. Outside CI a missing binary skips the calling test; in CI
it fails it. A wgpu run without an adapter skips, or fails when SYNC4D_REQUIRE_GPU=1 (CI,
which installs lavapipe)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from support import ROOT
from sync4d.phase1.gaussians import DeformableGaussians


def render_binary() -> Path:
    """The `sync4d-render` binary (skips the test outside CI when it is not built)."""
    path = Path(os.environ.get("SYNC4D_RENDER", ROOT / "target" / "release" / "sync4d-render"))
    if not path.exists():
        # A bare `pytest` without the cargo build has no binary to test; CI builds it first.
        if os.environ.get("CI"):
            pytest.fail(f"{path} is missing: `cargo test --workspace --release` builds it")
        pytest.skip(f"{path} is not built (run `cargo build --release -p sync4d-render`)")
    return path


def run_render(*args: str) -> subprocess.CompletedProcess:
    """`sync4d-render ARGS`, its output captured."""
    return subprocess.run([str(render_binary()), *args], capture_output=True, text=True,
                          timeout=300)  # fmt: skip


def skip_without_adapter(proc: subprocess.CompletedProcess, backend: str) -> None:
    """Skip the test when a wgpu run found no Vulkan/Metal/DX12 adapter on this machine
    (nothing to compare); fail instead when SYNC4D_REQUIRE_GPU=1."""
    if backend == "wgpu" and proc.returncode != 0 and "adapter" in proc.stderr:
        if os.environ.get("SYNC4D_REQUIRE_GPU") == "1":
            pytest.fail(proc.stderr)
        pytest.skip(proc.stderr.strip())


def python_png(model: DeformableGaussians, frame, t: float) -> np.ndarray:
    """`model` rendered at `t` from `frame`'s camera on white, as 8-bit RGB [H, W, 3]."""
    with torch.no_grad():
        img = model.render(frame.camera, t, background=torch.ones(3), threads=1).features
    return (img.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def nan_render(real):
    """`DeformableGaussians.render` (`real`) whose image comes out all NaN: a checkpoint that
    is not finite at a time, without making one (monkeypatch it onto the class)."""

    def render(self, *args, **kwargs):
        out = real(self, *args, **kwargs)
        out.features = torch.full_like(out.features, float("nan"))
        return out

    return render
