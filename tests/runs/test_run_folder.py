"""`load_run`: the read-only view of a run folder that later stages use instead of a trainer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from support.datasets import write_blender
from sync4d.cli import main
from sync4d.runs import CHECKPOINT_NAME, PHASE1_CHECKPOINT_NAME, RunError, load_model, load_run

SETTINGS = ["--iters", "12", "--threads", "1", "--set", "phase1.init_points=300",
            "--set", "eval_every=0",
            "--set", "phase2.iterations=8", "--set", "phase2.motion_start=2",
            "--set", "phase2.motion.kind=mlp"]  # fmt: skip


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("run_folder")
    write_blender(tmp / "tiny", n=4, size=24)
    assert main(["fit", str(tmp / "tiny"), "--out", str(tmp / "run"), *SETTINGS]) == 0
    return tmp / "run"


def test_load_run_gives_the_phase2_state_without_a_trainer(run: Path) -> None:
    r = load_run(run)
    model, meta = load_model(run / CHECKPOINT_NAME)
    assert r.kind == "sync4d.phase2" and r.iteration == meta["iteration"] == 8
    for name in ("means", "sh_dc", "embeddings"):
        assert torch.equal(getattr(r.model, name), getattr(model, name))
    assert not any(p.requires_grad for p in r.model.parameters())
    assert r.labels.shape == (r.model.num_gaussians,) and set(r.names) >= {1, 2}
    assert len(r.cameras) == 8 and r.scene() is not None
    # M_phi rebuilt from the file (an MLP: its config comes from the header) gives the export.
    a, b = r.motion.trajectory()
    np.testing.assert_allclose(a, r.export["rotations"], atol=1e-6)
    np.testing.assert_allclose(b, r.export["translations"], atol=1e-6)
    np.testing.assert_allclose(r.times, r.export["times"], atol=1e-7)  # stored as float32


def test_load_run_of_a_phase1_checkpoint_and_bad_paths(run: Path, tmp_path: Path) -> None:
    r = load_run(run / PHASE1_CHECKPOINT_NAME)
    assert r.kind == "sync4d.phase1" and r.motion is None and r.labels is None
    assert r.path == run
    with pytest.raises(RunError, match="missing"):
        load_run(tmp_path / "nothing")
