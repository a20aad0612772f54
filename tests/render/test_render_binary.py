"""The standalone Rust renderer `sync4d-render` against the Python render of the same
checkpoint: same image (8-bit) at a time between training frames, on the CPU and (when an
adapter exists) through wgpu; time sweeps and orbits; clear errors for bad checkpoints.

The binary is built by `cargo test --workspace --release` (make test); set SYNC4D_RENDER to
use another build. Outside CI a missing binary skips these tests; in CI it fails them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from support.render import python_png, run_render, skip_without_adapter
from support.scenes import orbit_scene, random_gaussians
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.deform import DeformConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.runs import camera_records, save_checkpoint


@pytest.fixture(
    scope="module",
    params=[(0, False, 1.0), (4, False, 1.0), (0, True, 1.0), (2, False, 0.5)],
    ids=["raw-position", "position-bands-4", "half-static", "position-unit"],
)
def run(tmp_path_factory, request) -> tuple[Path, DeformableGaussians, object]:
    """A checkpoint of a small model whose D_theta is far from the identity, with SH degree 1;
    D_theta reads the raw position (the paper) or its 4-band encoding; in the third variant
    every other Gaussian is static (its canonical state at every time); in the last D_theta
    reads the position in half units (`position_unit`), 2-band encoded, and time at a lowest
    frequency of 1 instead of pi (`time_frequency`)."""
    bands, half_static, unit = request.param
    tmp = tmp_path_factory.mktemp("render")
    scene, _ = orbit_scene(tmp)
    g = torch.Generator().manual_seed(5)
    config = DeformConfig(position_bands=bands, position_unit=unit,
                          time_frequency=1.0 if unit != 1.0 else math.pi)  # fmt: skip
    model = random_gaussians(60, g, spread=0.4, scale=0.08, opacity_logit=1.0, sh_degree=1,
                             config=config)  # fmt: skip
    if half_static:
        model.static[::2] = True
    with torch.no_grad():
        model.sh_rest.normal_(0.0, 0.2, generator=g)
        model.embeddings.normal_(0.0, 0.5, generator=g)
        for p in model.deform.parameters():
            p.normal_(0.0, 0.3, generator=g)
    model.near = 0.05
    trainer = Phase1Trainer(model, scene, Phase1Config(), total_iterations=10, threads=1)
    extra = {"cameras": camera_records(scene)}
    ck = save_checkpoint(trainer, tmp / "checkpoint.safetensors", extra)
    return ck, model, scene






@pytest.mark.parametrize("backend", ["cpu", "wgpu"])
def test_matches_the_python_render_between_frames(run, tmp_path, backend) -> None:
    ck, model, scene = run
    out = tmp_path / f"{backend}.png"
    proc = run_render(str(ck), "--camera", "test:0", "--time", "0.37", "--out", str(out),
                   "--backend", backend, "--threads", "1")  # fmt: skip
    skip_without_adapter(proc, backend)
    assert proc.returncode == 0, proc.stderr
    rust = np.asarray(Image.open(out).convert("RGB")).astype(np.float64) / 255.0
    py = python_png(model, scene.test[0], 0.37).astype(np.float64) / 255.0
    assert rust.shape == py.shape
    assert np.abs(rust - py).mean() < 1e-3, np.abs(rust - py).mean()
    # The deformation matters at this time: the canonical (t = 0) view differs.
    assert np.abs(python_png(model, scene.test[0], 0.0) / 255.0 - py).mean() > 5e-3
    if model.static.any():  # and so does the static set: all moving renders another image
        static, model.static = model.static, torch.zeros_like(model.static)
        moving = python_png(model, scene.test[0], 0.37) / 255.0
        model.static = static
        assert np.abs(moving - py).mean() > 5e-3
    assert "frames per second" in proc.stderr


def test_time_sweep_and_orbit_write_one_png_per_frame(run, tmp_path) -> None:
    ck = run[0]
    proc = run_render(str(ck), "--sweep", "3", "--out", str(tmp_path / "sweep"), "--threads", "1")
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in (tmp_path / "sweep").iterdir()) == [
        "frame_000.png", "frame_001.png", "frame_002.png"]  # fmt: skip
    proc = run_render(str(ck.parent), "--orbit", "4", "--camera", "train:2",
                   "--out", str(tmp_path / "orbit"), "--threads", "1")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    frames = [np.asarray(Image.open(p)) for p in sorted((tmp_path / "orbit").iterdir())]
    assert len(frames) == 4 and not np.array_equal(frames[0], frames[1])


def test_help_and_bad_inputs(run, tmp_path) -> None:
    ck = run[0]
    help_text = run_render("--help").stdout
    for flag in ("--camera", "--time", "--sweep", "--orbit", "--out", "--backend", "--threads"):
        assert flag in help_text
    truncated = tmp_path / "truncated.safetensors"
    truncated.write_bytes(ck.read_bytes()[:1000])
    for bad, words in [
        (truncated, "truncated.safetensors"),
        (tmp_path / "missing.safetensors", "cannot read"),
    ]:
        proc = run_render(str(bad), "--out", str(tmp_path / "x.png"))
        assert proc.returncode == 2 and words in proc.stderr, proc.stderr
        assert "panicked" not in proc.stderr
    proc = run_render(str(ck), "--camera", "test:99", "--out", str(tmp_path / "x.png"))
    assert proc.returncode == 2 and "test cameras" in proc.stderr
    proc = run_render(str(ck), "--time", "1.5", "--out", str(tmp_path / "x.png"))
    assert proc.returncode == 2 and "[0, 1]" in proc.stderr
