"""The standalone Rust renderer `sync4d-render` on node checkpoints (`"motion": "nodes"`,
`sync4d.phase1.nodes`): D_theta evaluated on the control nodes, each Gaussian blending its
nodes' rigid motions, must give the Python render's image (8-bit) at a time between training
frames, for the linear and the dual-quaternion blend, on the CPU and (when an adapter exists)
through wgpu; and a node checkpoint that does not fit is refused by name.

The binary is built by `cargo test --workspace --release` (make test); set SYNC4D_RENDER to
use another build. Outside CI a missing binary skips these tests; in CI it fails them."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from support.render import python_png, run_render, skip_without_adapter
from support.scenes import orbit_scene, random_gaussians
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.deform import DeformConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.nodes import NodeConfig
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.runs import camera_records, save_checkpoint

#: (blend, D_theta's position input, a static set left in the checkpoint).
VARIANTS = {
    "linear": ("linear", DeformConfig(), False),
    "dual-quaternion": ("dual_quaternion", DeformConfig(), False),
    "dq-encoded-unit-static": (
        "dual_quaternion", DeformConfig(position_bands=3, position_unit=0.5), True),
}  # fmt: skip


@pytest.fixture(scope="module", params=list(VARIANTS), ids=list(VARIANTS))
def run(tmp_path_factory, request) -> tuple[Path, DeformableGaussians, object]:
    """A node checkpoint of a small model (80 Gaussians, SH degree 1, 12 nodes of 4 each)
    whose D_theta (random trunk and head) moves the nodes far from the identity; the nodes are
    moved off the Gaussians they were sampled at and their radii varied, so every Gaussian
    blends several nodes. The last variant encodes the position in half units and leaves a
    static set in the file, which node motion ignores."""
    blend, config, static = VARIANTS[request.param]
    tmp = tmp_path_factory.mktemp("render-nodes")
    scene, _ = orbit_scene(tmp)
    g = torch.Generator().manual_seed(11)
    model = random_gaussians(80, g, spread=0.4, scale=0.08, opacity_logit=1.0, sh_degree=1,
                             config=config)  # fmt: skip
    with torch.no_grad():
        model.sh_rest.normal_(0.0, 0.2, generator=g)
        model.embeddings.normal_(0.0, 0.5, generator=g)
        for p in model.deform.parameters():
            p.normal_(0.0, 0.3, generator=g)
    nodes = model.use_nodes(NodeConfig(count=12, neighbours=4, blend=blend), g)
    with torch.no_grad():
        nodes.positions.add_(torch.randn(nodes.positions.shape, generator=g) * 0.05)
        nodes.log_radii.add_(torch.randn(nodes.log_radii.shape, generator=g) * 0.3)
        nodes.embeddings.normal_(0.0, 0.5, generator=g)
    if static:
        model.static[::2] = True
    model.near = 0.05
    cfg = Phase1Config(motion="nodes", nodes=nodes.config)
    trainer = Phase1Trainer(model, scene, cfg, total_iterations=10, threads=1)
    ck = save_checkpoint(trainer, tmp / "checkpoint.safetensors",
                         {"cameras": camera_records(scene)})  # fmt: skip
    tensors = load_file(str(ck))
    assert tensors["gaussians.node_index"].dtype == torch.int32
    assert ("gaussians.static" in tensors) == static
    return ck, model, scene




@pytest.mark.parametrize("backend", ["cpu", "wgpu"])
def test_node_checkpoints_match_the_python_render_between_frames(run, tmp_path, backend
                                                                 ) -> None:  # fmt: skip
    ck, model, scene = run
    out = tmp_path / f"{backend}.png"
    proc = run_render(str(ck), "--camera", "test:0", "--time", "0.37", "--out", str(out),
                   "--backend", backend, "--threads", "1")  # fmt: skip
    skip_without_adapter(proc, backend)
    assert proc.returncode == 0, proc.stderr
    nodes = model.nodes
    assert f"moved by {nodes.count} nodes ({nodes.config.neighbours} each" in proc.stderr
    rust = np.asarray(Image.open(out).convert("RGB")).astype(np.float64) / 255.0
    py = python_png(model, scene.test[0], 0.37).astype(np.float64) / 255.0
    assert rust.shape == py.shape
    assert np.abs(rust - py).mean() < 1e-3, np.abs(rust - py).mean()
    # The node motion matters at this time: the canonical (t = 0) view differs, and so does
    # the other blend's image.
    assert np.abs(python_png(model, scene.test[0], 0.0) / 255.0 - py).mean() > 5e-3
    kind = nodes.config
    other = "linear" if kind.blend == "dual_quaternion" else "dual_quaternion"
    nodes.config = dataclasses.replace(kind, blend=other)
    try:
        assert np.abs(python_png(model, scene.test[0], 0.37) / 255.0 - py).mean() > 1e-3
    finally:
        nodes.config = kind


def test_a_sweep_of_a_node_checkpoint_moves(run, tmp_path) -> None:
    ck = run[0]
    proc = run_render(str(ck.parent), "--sweep", "3", "--out", str(tmp_path / "sweep"),
                   "--threads", "1")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    frames = [np.asarray(Image.open(p)) for p in sorted((tmp_path / "sweep").iterdir())]
    assert len(frames) == 3 and not np.array_equal(frames[0], frames[2])


def test_node_checkpoints_that_do_not_fit_are_refused_by_name(run, tmp_path) -> None:
    ck = run[0]
    tensors = load_file(str(ck))
    with safe_open(str(ck), "pt") as f:
        metadata = f.metadata()
    m, k = tensors["nodes.positions"].shape[0], tensors["gaussians.node_index"].shape[1]
    n = tensors["gaussians.means"].shape[0]
    settings = json.loads(metadata["sync4d"])

    def refused(name: str, edit, words: list[str], header=None) -> None:
        bad = dict(tensors)
        edit(bad)
        path = tmp_path / f"{name}.safetensors"
        meta = dict(metadata)
        if header is not None:
            meta["sync4d"] = json.dumps(header)
        save_file(bad, str(path), meta)
        proc = run_render(str(path), "--out", str(tmp_path / "x.png"))
        assert proc.returncode == 2, proc.stderr
        assert "panicked" not in proc.stderr
        for w in [f"{name}.safetensors", *words]:
            assert w in proc.stderr, (w, proc.stderr)

    refused("no-radii", lambda t: t.pop("nodes.log_radii"),
            ["nodes.log_radii", "missing", f"[{m}]"])  # fmt: skip
    refused("no-index", lambda t: t.pop("gaussians.node_index"),
            ["gaussians.node_index", "missing", f"[{n}, K]"])  # fmt: skip
    refused("short-embeddings",
            lambda t: t.update({"nodes.embeddings": t["nodes.embeddings"][:, :-1].clone()}),
            ["nodes.embeddings", "expected"])  # fmt: skip

    def out_of_range(t):
        index = t["gaussians.node_index"].clone()
        index[3, k - 1] = m
        t["gaussians.node_index"] = index

    refused("out-of-range", out_of_range, ["gaussians.node_index", str(m), f"[0, {m})"])
    refused("int64-index", lambda t: t.update(
        {"gaussians.node_index": t["gaussians.node_index"].long()}),
        ["gaussians.node_index", "I32"])  # fmt: skip
    node_config = {**settings["node_config"], "blend": "slerp"}
    refused("bad-blend", lambda t: None, ["node_config.blend", "slerp"],
            {**settings, "node_config": node_config})  # fmt: skip
    refused("bad-motion", lambda t: None, ["motion", "grid"], {**settings, "motion": "grid"})
