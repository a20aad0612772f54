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
from sync4d.metrics import psnr
from sync4d.options import background_colour
from sync4d.pipeline.evaluate import render_frame
from sync4d.runs import load_run
from sync4d.runs.names import background_tag


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    tmp = tmp_path_factory.mktemp("evalbg")
    data = tmp / "tiny"
    write_blender(data, n=3, size=24)
    out = tmp / "run"
    args = ["fit", str(data), "--out", str(out), "--iters", "6", "--threads", "1",
            "--set", "phase1.init_points=300", "--set", "eval_every=0",
            "--set", "phases=1"]  # fmt: skip
    with pytest.MonkeyPatch.context() as mp:
        printed: list[str] = []
        mp.setattr("sys.stdout.write", lambda text: printed.append(text) or len(text))
        assert main(args) == 0
    return out, "".join(printed)


@pytest.fixture
def run(fitted: tuple[Path, str]) -> Path:
    return fitted[0]


def test_a_fit_on_rgba_images_scores_white_and_black(fitted: tuple[Path, str]) -> None:
    run, printed = fitted
    white = json.loads((run / "eval.json").read_text())
    black = json.loads((run / "eval-black.json").read_text())
    assert len(white["frames"]) == len(black["frames"]) == 3
    assert len(list((run / "renders" / "black").glob("*.png"))) == 3
    assert "on black:" in printed  # the second table says which background it scored on
    line = next(ln for ln in printed.splitlines() if ln.startswith("fit: on black: test PSNR"))
    assert f"{black['mean']['psnr']:.2f} dB" in line
    assert "test PSNR on white" in printed


def test_eval_without_a_colour_scores_both_and_one_colour_only_that(
    run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for name in ("eval.json", "eval-black.json"):
        (run / name).unlink()
    assert main(["eval", str(run), "--threads", "1"]) == 0
    assert (run / "eval.json").exists() and (run / "eval-black.json").exists()
    assert "on black:" in capsys.readouterr().out
    (run / "eval-black.json").unlink()
    assert main(["eval", str(run), "--background", "white", "--threads", "1"]) == 0
    assert not (run / "eval-black.json").exists()


def test_images_without_alpha_are_scored_on_one_background(tmp_path: Path) -> None:
    from PIL import Image

    from sync4d.data.blender import load_blender
    from sync4d.pipeline.evaluate import other_backgrounds

    data = tmp_path / "tiny"
    write_blender(data, n=2, size=16, masks=False)
    scene = load_blender(data)
    assert other_backgrounds(scene.test, (1.0, 1.0, 1.0)) == [(0.0, 0.0, 0.0)]
    assert other_backgrounds(scene.test, (0.0, 0.0, 0.0)) == [(1.0, 1.0, 1.0)]
    assert other_backgrounds(scene.test, (0.5, 0.5, 0.5)) == [(1.0, 1.0, 1.0), (0.0, 0.0, 0.0)]
    for f in scene.test:  # the same frames as RGB: the background changes nothing
        Image.open(f.image_path).convert("RGB").save(f.image_path)
    assert other_backgrounds(scene.test, (1.0, 1.0, 1.0)) == []


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
