"""`eval RUN --background COLOUR`: render and ground truth composited on another colour than the
run trained on, written beside the run's own evaluation (docs/results/hellwarrior.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest
import torch

from support.datasets import write_blender
from sync4d.cli import main
from sync4d.commands.eval import background_tag
from sync4d.metrics import psnr
from sync4d.options import background_colour
from sync4d.pipeline.evaluate import render_frame
from sync4d.runs import load_run


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("evalbg")
    data = tmp / "tiny"
    write_blender(data, n=3, size=24)
    out = tmp / "run"
    args = ["fit", str(data), "--out", str(out), "--iters", "6", "--threads", "1",
            "--set", "phase1.init_points=300", "--set", "eval_every=0",
            "--set", "phases=1"]  # fmt: skip
    assert main(args) == 0
    return out


def test_black_is_written_beside_the_runs_own(run: Path, capsys) -> None:
    own = (run / "eval.json").read_text()
    assert main(["eval", str(run), "--background", "black", "--threads", "1"]) == 0
    assert "mean" in capsys.readouterr().out
    assert (run / "eval.json").read_text() == own  # the run's own result is kept
    black = json.loads((run / "eval-black.json").read_text())
    assert len(black["frames"]) == 3
    assert len(list((run / "renders" / "black").glob("*.png"))) == 3
    # both images composited on black: the first frame's PSNR recomputed by hand
    loaded = load_run(run)
    frame = loaded.scene().test[0]
    target = torch.from_numpy(frame.load_image((0.0, 0.0, 0.0)))
    pred = render_frame(loaded.model, frame, (0.0, 0.0, 0.0), threads=1)
    assert black["frames"][0]["psnr"] == pytest.approx(psnr(pred, target), abs=1e-4)
    white = json.loads(own)["frames"][0]["psnr"]
    assert black["frames"][0]["psnr"] != pytest.approx(white, abs=1e-3)


def test_the_runs_own_colour_writes_eval_json(run: Path) -> None:
    (run / "eval.json").unlink()
    assert main(["eval", str(run), "--background", "white", "--threads", "1"]) == 0
    assert (run / "eval.json").exists() and not (run / "eval-white.json").exists()


def test_colours_and_tags() -> None:
    assert background_colour("black") == (0.0, 0.0, 0.0)
    assert background_colour("WHITE") == (1.0, 1.0, 1.0)
    assert background_colour("0.5,0.25,1") == (0.5, 0.25, 1.0)
    for bad in ("red", "1,2,3", "0.5,0.5", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            background_colour(bad)
    assert background_tag((0.0, 0.0, 0.0)) == "black"
    assert background_tag([1.0, 1.0, 1.0]) == "white"
    assert background_tag((0.5, 0.25, 1.0)) == "bg-0.5-0.25-1"
