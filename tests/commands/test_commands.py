"""The fit / eval / render / bench fit commands end to end on a tiny D-NeRF-layout dataset."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from support.datasets import write_blender
from sync4d.cli import main
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.progress import Progress, format_duration
from sync4d.runs import load_model

TINY = ["--set", "phase1.init_points=300", "--set", "eval_frames=2", "--threads", "1",
        "--set", "phases=1"]  # fmt: skip


@pytest.fixture
def data(tmp_path: Path) -> Path:
    root = tmp_path / "tiny"
    write_blender(root, n=4, size=24)
    return root


def _iteration(run: Path) -> int:
    return load_model(run / "checkpoint.safetensors")[1]["iteration"]


def test_fit_eval_render(data: Path, tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    args = ["fit", str(data), "--out", str(run), "--iters", "20", *TINY]
    assert main(args + ["--set", "checkpoint_every=10", "--set", "eval_every=10"]) == 0
    out = capsys.readouterr()
    assert "test PSNR" in out.out and "[eval @ 10]" in out.err
    assert _iteration(run) == 20
    ev = json.loads((run / "eval.json").read_text())
    assert len(ev["frames"]) == 4 and ev["mean"]["psnr"] > 0
    side = sorted((run / "renders" / "test").glob("*.png"))
    assert len(side) == 4
    with Image.open(side[0]) as im:  # render beside ground truth
        assert im.size == (48, 24)
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert any("test" in r for r in records) and "final" in records[-1]
    meta = load_model(run / "checkpoint.safetensors")[1]
    assert len(meta["run"]["cameras"]) == 8 and meta["run"]["data"] == str(data.resolve())

    (run / "eval.json").unlink()
    assert main(["eval", str(run), "--threads", "1"]) == 0
    assert "mean" in capsys.readouterr().out
    assert len(json.loads((run / "eval.json").read_text())["frames"]) == 4

    assert main(["render", str(run), "--time", "0", "0.5", "1", "--camera", "train:1"]) == 0
    pngs = sorted((run / "renders").glob("*.png"))
    assert [p.name for p in pngs] == [
        "r_001_t0.000.png", "r_001_t0.500.png", "r_001_t1.000.png",
    ]  # fmt: skip
    assert (run / "renders" / "r_001_sweep.gif").stat().st_size > 0

    # --backend auto always works (wgpu on a GPU, else cpu) and says what it picked.
    capsys.readouterr()
    out_auto = tmp_path / "auto"
    assert main(["render", str(run), "--time", "0.5", "--camera", "train:1", "--no-gif",
                 "--backend", "auto", "--out", str(out_auto)]) == 0  # fmt: skip
    assert "backend auto ->" in capsys.readouterr().err
    _render_matches_cpu_on_wgpu(run, tmp_path)


def _render_matches_cpu_on_wgpu(run: Path, tmp_path: Path) -> None:
    """`render --backend wgpu` gives the CPU render (8-bit) when an adapter exists; in CI
    (SYNC4D_REQUIRE_GPU=1, lavapipe) a missing adapter fails."""
    from sync4d import _core

    try:
        _core.wgpu_adapter()
    except RuntimeError:
        if os.environ.get("SYNC4D_REQUIRE_GPU") == "1":
            raise
        return
    outs = {}
    for backend in ("cpu", "wgpu"):
        out = tmp_path / backend
        args = ["render", str(run), "--time", "0.5", "--camera", "train:1", "--no-gif",
                "--backend", backend, "--out", str(out)]  # fmt: skip
        assert main(args) == 0
        with Image.open(out / "r_001_t0.500.png") as im:
            outs[backend] = np.asarray(im, dtype=np.float64)
    assert np.abs(outs["cpu"] - outs["wgpu"]).mean() < 0.5  # of 255


def test_existing_run_needs_resume_and_resume_continues(data: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    base = ["fit", str(data), "--out", str(run), *TINY, "--set", "eval_every=0"]
    assert main(base + ["--iters", "10"]) == 0
    assert main(base + ["--iters", "10"]) == 2
    assert main(base + ["--iters", "15", "--resume"]) == 0
    assert _iteration(run) == 15
    assert main(base + ["--iters", "5", "--force"]) == 0
    assert _iteration(run) == 5


def test_interrupt_saves_the_last_state_and_resumes(
    data: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    run = tmp_path / "run"
    original = Phase1Trainer.step

    def step(self):
        if self.iteration == 7:
            raise KeyboardInterrupt
        return original(self)

    monkeypatch.setattr(Phase1Trainer, "step", step)
    base = ["fit", str(data), "--out", str(run), "--iters", "12", *TINY]
    assert main(base) == 130
    assert "--resume" in capsys.readouterr().err
    assert _iteration(run) == 7
    monkeypatch.setattr(Phase1Trainer, "step", original)
    assert main(base + ["--resume"]) == 0
    assert _iteration(run) == 12


def test_sigint_in_a_real_process_keeps_a_checkpoint(data: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RAYON_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "sync4d", "fit", str(data), "--out", str(run), "--iters",
           "1000000", *TINY, "--set", "checkpoint_every=0", "--set", "eval_every=0"]  # fmt: skip
    # A parent started in the background (nohup, `&` in a script) passes SIGINT down as ignored,
    # and Python then installs no KeyboardInterrupt handler: restore the default, as a terminal
    # would have it.
    proc = subprocess.Popen(
        cmd, stderr=subprocess.PIPE, text=True, env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        deadline = time.time() + 120
        assert proc.stderr is not None
        for line in proc.stderr:  # non-tty progress: one line per 100 iterations
            if line.startswith("fit 100/") or time.time() > deadline:
                break
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert _iteration(run) >= 100


def test_fit_runs_phase2_after_phase1_and_restarts_it(data: Path, tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    base = ["fit", str(data), "--out", str(run), "--iters", "12", *TINY, "--set", "eval_every=0",
            "--set", "phase2.iterations=8", "--set", "phase2.motion_start=2"]  # fmt: skip
    assert main(base + ["--phases", "1,2"]) == 0
    out = capsys.readouterr()
    assert "Phase 2" in out.out and "masks assignment, K = 3" in out.err
    model, meta = load_model(run / "checkpoint.safetensors")
    assert meta["kind"] == "sync4d.phase2" and meta["iteration"] == 8
    assert load_model(run / "phase1.safetensors")[1]["kind"] == "sync4d.phase1"
    diag = json.loads((run / "phase2.json").read_text())
    assert {"rigid_share", "shuffle_ratio", "objects", "residual_energy"} <= set(diag)
    assert len(diag["trajectories"]["times"]) == len(diag["trajectories"]["centroids"]["1"])
    assert (run / "phase2-trajectories.png").stat().st_size > 1000
    # Resume continues Phase 2; --phases 2 restarts it from the kept Phase 1 checkpoint.
    assert main(base + ["--resume", "--phases", "1,2", "--set", "phase2.iterations=10"]) == 0
    assert _iteration(run) == 10
    assert main(base + ["--phases", "2", "--set", "phase2.iterations=4"]) == 0
    assert _iteration(run) == 4
    # --resume keeps the run's phases (here "2"): Phase 1 cannot continue it.
    assert main(base + ["--resume", "--phases", "1"]) == 2
    assert "phases: the run has '2', this command gives '1'" in capsys.readouterr().err
    assert main(base + ["--phases", "3"]) == 2
    assert "phases" in capsys.readouterr().err
    bad = ["--phases", "2", "--set", "phase2.motion.kind=mlp", "--set", "phase2.motion.init=fit"]
    assert main(base + bad) == 2
    assert "no closed-form start" in capsys.readouterr().err
    assert main(base + ["--phases", "2", "--set", "phase2.assign.source=sam"]) == 2
    assert "phase2.assign.source" in capsys.readouterr().err
    assert main(base + ["--phases", "2", "--set", "phase2.assign.source=trajectories"]) == 0
    out = capsys.readouterr()
    assert "trajectories assignment" in out.out and "adjusted Rand index" in out.out


def test_bad_inputs_give_one_clear_message(data: Path, tmp_path: Path, capsys) -> None:
    (data / "transforms_train.json").write_text("{not json")
    assert main(["fit", str(data), "--out", str(tmp_path / "r")]) == 2
    assert "transforms_train.json" in capsys.readouterr().err
    assert main(["eval", str(tmp_path / "missing")]) == 2
    assert "missing" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "nope"), "--out", str(tmp_path / "r")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["fit", str(data), "--set", "phase1.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err


def test_bad_near_plane_is_one_clear_message(data: Path, tmp_path: Path, capsys) -> None:
    args = ["fit", str(data), "--out", str(tmp_path / "r"), "--iters", "3", *TINY]
    assert main(args + ["--set", "phase1.near=-1"]) == 2
    assert "near: must be a finite distance > 0" in capsys.readouterr().err


def test_bench_fit_writes_json_and_plot(data: Path, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "bench.json"
    args = ["bench", "fit", str(data), "--iters", "5", "10", "--out", str(out), *TINY]
    assert main(args) == 0
    rec = json.loads(out.read_text())
    assert [r["iterations"] for r in rec["results"]] == [5, 10]
    assert all(r["psnr"] > 0 and r["train_seconds"] > 0 for r in rec["results"])
    assert any(r["pareto"] for r in rec["results"])
    assert out.with_suffix(".png").stat().st_size > 1000
    worst = rec["results"][-1]["worst_view"]
    assert worst["psnr"] <= rec["results"][-1]["psnr"] and worst["name"].endswith(".png")
    from PIL import Image

    with Image.open(rec["worst_view_png"]) as im:  # render beside ground truth
        assert im.size[0] > im.size[1]


def test_bench_fit_variants_train_side_by_side(data: Path, tmp_path: Path, capsys) -> None:
    """Two config variants over one budget: each trains, the table and JSON name them, and
    the skip counters show the static skip only where it is on (after 5 iterations D_theta
    has hardly moved anything, so rows are found still from the first check on)."""
    out = tmp_path / "variants.json"
    args = ["bench", "fit", str(data), "--iters", "20", "--out", str(out), *TINY,
            "--variant", "off", "--variant",
            "skip:phase1.static.enabled=true,phase1.static.start=5"]  # fmt: skip
    args[-3:-2] = ["off:phase1.train_background=random"]
    assert main(args) == 0
    rec = json.loads(out.read_text())
    by = {r["variant"]: r for r in rec["results"]}
    assert set(by) == {"off", "skip"}
    assert rec["variants"]["off"] == ["phase1.train_background=random"]
    # RGBA frames: each row is scored on white (the run's own) and on black, and says what
    # it trained on.
    assert by["off"]["backgrounds"]["train_background"] == "random"
    assert by["skip"]["backgrounds"]["train_background"] == "white"
    for r in by.values():
        on = r["backgrounds"]["on"]
        assert set(on) == {"white", "black"} and on["white"]["psnr"] == r["psnr"]
        assert on["black"]["worst"]["psnr"] <= on["black"]["psnr"]
    assert by["off"]["skipped"]["deform_rows_skipped"] == 0
    assert by["skip"]["skipped"]["deform_rows_skipped"] > 0
    table = capsys.readouterr().out
    assert "variant" in table and "D_theta skipped" in table and "PSNR black" in table
    assert main(args[:-1] + ["skip:phase1.static.enabled"]) == 2
    assert "--variant" in capsys.readouterr().err
    assert main(args[:-1] + ["more:budget=-2"]) == 2
    assert "budget" in capsys.readouterr().err


def test_bench_fit_budget_factor_trains_a_variant_longer(data: Path, tmp_path: Path) -> None:
    out = tmp_path / "budget.json"
    args = ["bench", "fit", str(data), "--iters", "10", "--out", str(out), *TINY,
            "--variant", "base", "--variant", "more:budget=1.5"]  # fmt: skip
    assert main(args) == 0
    by = {r["variant"]: r for r in json.loads(out.read_text())["results"]}
    assert by["base"]["iterations"] == 10 and "budget" not in by["base"]
    assert by["more"]["iterations"] == 15 and by["more"]["budget"] == 10


def test_bench_fit_trains_several_scenes_in_one_invocation(data: Path, tmp_path: Path,
                                                           capsys) -> None:  # fmt: skip
    """Two datasets x two motion variants (per-Gaussian D_theta and nodes at 1.5x the
    iterations): one JSON with a row per scene and variant, a plot and a worst view per scene,
    and a table with a scene column."""
    other = tmp_path / "other"
    write_blender(other, n=4, size=24)
    out = tmp_path / "scenes.json"
    args = ["bench", "fit", str(data), str(other), "--iters", "8", "--out", str(out), *TINY,
            "--variant", "gaussians", "--variant",
            "nodes:phase1.motion=nodes,phase1.nodes.count=16,budget=1.5"]  # fmt: skip
    assert main(args) == 0
    rec = json.loads(out.read_text())
    got = {(r["scene"], r["variant"]): r["iterations"] for r in rec["results"]}
    assert got == {("tiny", "gaussians"): 8, ("tiny", "nodes"): 12, ("other", "gaussians"): 8,
                   ("other", "nodes"): 12}  # fmt: skip
    assert rec["data"] == [str(data), str(other)]
    for scene in ("tiny", "other"):
        assert (tmp_path / f"scenes-{scene}.png").stat().st_size > 1000
        assert Path(rec["worst_view_pngs"][scene]).is_file()
    table = capsys.readouterr().out
    assert table.splitlines()[0].split()[:2] == ["scene", "variant"]
    assert main(["bench", "fit", str(data), str(data), "--iters", "5", "--out", str(out),
                 *TINY]) == 2  # fmt: skip
    assert "share a name" in capsys.readouterr().err


def test_bench_step_times_both_motion_models(data: Path, tmp_path: Path, capsys) -> None:
    """`bench step` on a per-Gaussian run: both variants step the same Gaussians; the node
    variant evaluates D_theta on its nodes only."""
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "6", *TINY]) == 0
    out = tmp_path / "step.json"
    args = ["bench", "step", str(run), "--steps", "2", "--rounds", "1", "--threads", "1",
            "--variant", "gaussians:phase1.motion=gaussians", "--variant",
            "nodes:phase1.motion=nodes,phase1.nodes.count=8", "--out", str(out)]  # fmt: skip
    assert main(args) == 0
    rows = {r["variant"]: r for r in json.loads(out.read_text())["rows"]}
    assert rows["gaussians"]["motion_model"] == "gaussians"
    assert rows["gaussians"]["nodes"] is None
    assert rows["nodes"]["motion_model"] == "nodes" and rows["nodes"]["nodes"] == 8
    assert rows["nodes"]["gaussians"] == rows["gaussians"]["gaussians"]
    for r in rows.values():
        assert len(r["raw_s"]["step"]) == 2 and 0 < r["motion_share"] < 1
        for part in ("loss", "optimizer"):  # timed apart from the whole step
            assert len(r["raw_s"][part]) == 2 and r[f"{part}_ms"] > 0
            assert 0 < r[f"{part}_share"] < 1
    assert "speed-up" in capsys.readouterr().out
    assert main(["bench", "step", str(run), "--variant", "x:phase1.motion", "--out",
                 str(out)]) == 2  # fmt: skip


def test_bench_fit_tabulates_finished_runs(data: Path, tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "6", *TINY]) == 0
    capsys.readouterr()
    out = tmp_path / "table.json"
    assert main(["bench", "fit", "--runs", str(run), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    rec = json.loads(out.read_text())
    (row,) = rec["results"]
    final = json.loads((run / "eval.json").read_text())["mean"]
    assert row["iterations"] == 6 and row["psnr"] == pytest.approx(final["psnr"])
    assert row["scene"] in printed and "phase1.init_points=300" in " ".join(row["settings"])
    with Image.open(row["worst_view_png"]) as im:  # render beside ground truth
        assert im.size == (2 * row["width"], row["height"])
    # an unfinished run, or a dataset given with --runs, is one clear message
    (tmp_path / "empty").mkdir()
    assert main(["bench", "fit", "--runs", str(tmp_path / "empty"), "--out", str(out)]) == 2
    assert "empty" in capsys.readouterr().err
    assert main(["bench", "fit", "--runs", str(tmp_path / "gone"), "--out", str(out)]) == 2
    assert "no such run folder" in capsys.readouterr().err
    assert main(["bench", "fit", str(data), "--runs", str(run), "--out", str(out)]) == 2
    assert "trains nothing" in capsys.readouterr().err
    lines = (run / "metrics.jsonl").read_text().splitlines()
    (run / "metrics.jsonl").write_text("\n".join(ln for ln in lines if '"final"' not in ln))
    assert main(["bench", "fit", "--runs", str(run), "--out", str(out)]) == 2
    assert "no final evaluation" in capsys.readouterr().err


def test_pareto_front() -> None:
    from sync4d.bench.fit import pareto_front

    pts = [(1.0, 20.0), (2.0, 25.0), (3.0, 24.0), (2.0, 25.0), (4.0, 30.0), (0.5, 10.0)]
    assert pareto_front(pts) == [True, True, False, True, True, True]


def test_progress_lines_and_durations() -> None:
    assert format_duration(5.25) == "5.2s" and format_duration(125) == "2m05s"
    assert format_duration(3 * 3600 + 60) == "3h01m" and format_duration(float("nan")) == "?"
    buf = io.StringIO()
    bar = Progress(10, desc="x", stream=buf, log_every=5)
    for i in range(1, 11):
        bar.update(i, {"loss": "1.0"})
    bar.close()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 2 and lines[-1].startswith("x 10/10 [") and "ETA" in lines[-1]


def test_render_and_eval_reject_bad_arguments(data: Path, tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "3", *TINY]) == 0
    capsys.readouterr()
    assert main(["render", str(run), "--time", "0.5", "1.5"]) == 2
    assert "[0, 1]" in capsys.readouterr().err
    assert main(["render", str(run), "--camera", "test:99"]) == 2
    assert "only 4 test cameras" in capsys.readouterr().err
    assert main(["render", str(run), "--camera", "no_such_frame"]) == 2
    assert "no camera with that name" in capsys.readouterr().err
    assert main(["render", str(tmp_path / "nothing")]) == 2
    assert "missing" in capsys.readouterr().err
    moved = tmp_path / "moved"
    data.rename(moved)
    assert main(["eval", str(run)]) == 2
    assert "--data" in capsys.readouterr().err
    assert main(["eval", str(run), "--data", str(moved), "--threads", "1"]) == 0
