"""Phase 2 end to end on the embedded synthetic scene: `fit` (Phase 1 from random points, the
photometric refinement of M_phi, Phase 2) with `configs/synthetic.toml`, then every object's
exported motion against the scene's known SE(3) trajectories (issue 4's acceptance).

About 15 minutes on two cores, hence `slow`; the unit tests of each piece are in
test_phase2.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import safetensors.numpy

from sync4d.commands.fit import CHECKPOINT_NAME, PHASE2_FILE, repo_configs, run_fit
from sync4d.config import load_config
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene

pytestmark = pytest.mark.slow


def test_fit_recovers_the_synthetic_scene_motion(tmp_path) -> None:
    root = syn.write_synthetic_scene(tmp_path / "scene", syn.SyntheticConfig())
    cfg = load_config(repo_configs() / "synthetic.toml", ["eval_every=0", "checkpoint_every=0"])
    run = tmp_path / "run"
    summary = run_fit(load_scene(root), cfg, run, root, threads=2, quiet=True)
    assert summary["iterations"] == cfg.phase2_iterations

    # The motion export written into the checkpoint, relative to each object's first frame.
    tensors = safetensors.numpy.load_file(str(run / CHECKPOINT_NAME))
    export = {k.removeprefix("export."): v.astype(np.float64)
              for k, v in tensors.items() if k.startswith("export.")}  # fmt: skip
    gt = syn.load_ground_truth(root)
    errors = {}
    for label in gt.ids:
        rot, centre = gt.motion_errors(
            export["rotations"][label], export["translations"][label], export["times"], label
        )
        errors[gt.names[gt.ids.index(label)]] = (
            round(float(rot.mean()), 3), round(float(100 * centre.mean() / gt.extent), 3)
        )
    print("mean rotation error (degrees), mean centre error (% of the extent):", errors)
    for label in gt.ids:
        rot, centre = errors[gt.names[gt.ids.index(label)]]
        if gt.static[gt.ids.index(label)]:
            assert rot < 1.0 and centre < 0.5, (label, rot, centre)
        else:
            assert rot < 2.0 and centre < 2.0, (label, rot, centre)

    diag = json.loads((run / PHASE2_FILE).read_text())
    assert diag["shuffle_ratio"] >= 1.5, diag["shuffle_ratio"]
