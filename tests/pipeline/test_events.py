"""The pipeline reports as events (`sync4d.events`): a small fit's sequence, silence without
a subscriber, and the command line's renderer and words (`sync4d.terminal`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import get_args

import pytest

from support.datasets import write_blender
from sync4d.config import apply_overrides, load_config, with_budget
from sync4d.events import (
    Advanced,
    Assigned,
    DatasetChosen,
    Diagnostics,
    Evaluated,
    Event,
    EventLog,
    FieldBuilt,
    Finished,
    FitStarted,
    FitSummary,
    FrameScore,
    FramesEvaluated,
    GeneratingScene,
    InitialPoints,
    Interrupted,
    LoopSummary,
    Means,
    MetricUnavailable,
    MotionDiagnosed,
    Note,
    NothingMoves,
    ObjectCount,
    Override,
    Phase1Skips,
    Phase2Starting,
    Phase3Started,
    PhaseDone,
    Resumed,
    ScaleAdvice,
    SettingChanged,
    Skipped,
    Started,
    Stats,
    Triangulating,
    Wrote,
    emit,
    note,
    read_events,
    subscribe,
)
from sync4d.pipeline import FitData, run_fit
from sync4d.runs import EVAL_FILE, EVENTS_FILE, RENDERS_DIR
from sync4d.terminal import BARS, WORDS, Line, TerminalRenderer, words

SMALL = ["phase1.init_points=300", "eval_frames=2", "phases=1", "eval_every=3",
         "checkpoint_every=0"]


def _fit(tmp_path: Path, name: str) -> dict:
    root = tmp_path / "tiny"
    if not root.exists():
        write_blender(root, n=4, size=24)
    cfg = apply_overrides(with_budget(load_config(None), 6), SMALL)
    return run_fit(FitData.load(root, cfg), cfg, tmp_path / name, threads=1)


def test_a_fit_reports_its_loop_phase_and_evaluation_as_events(tmp_path: Path, capsys) -> None:
    seen: list = []
    with subscribe(seen.append):
        summary = _fit(tmp_path, "run")
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""  # a subscriber that prints nothing: nothing printed

    fit = [e for e in seen if getattr(e, "task", None) == "fit" and not isinstance(e, Evaluated)]
    assert fit[0] == Started("fit", 6, start=0, log_every=100)
    assert [e.done for e in fit[1:-1]] == [1, 2, 3, 4, 5, 6]
    stats = fit[1].stats
    assert stats.rho is None and fit[-1] == Finished("fit")  # no rho in Phase 1
    assert all(isinstance(v, (int, float)) for v in (stats.loss, stats.psnr, stats.gaussians))
    kinds = [type(e).__name__ for e in seen]
    i_eval = next(i for i, e in enumerate(seen) if isinstance(e, Evaluated))
    assert seen[i_eval - 1] == fit[3]  # after step 3
    ev = seen[i_eval]
    assert (ev.task, ev.iteration, ev.frames, ev.gaussians) == ("fit", 3, 2, fit[3].stats
        .gaussians) and 0 < ev.psnr < 100 and ev.train_seconds > 0  # fmt: skip
    i_phase1 = kinds.index("PhaseDone")
    (skipped,) = seen[seen.index(Finished("fit")) + 1:i_phase1]  # what Phase 1 skipped
    assert isinstance(skipped, Skipped) and skipped.phase == "phase1"
    assert skipped.counts.gaussians == fit[-2].stats.gaussians  # numbers, not words
    assert seen[i_phase1].phase == "phase1" and seen[i_phase1].summary.iteration == 6

    # The final evaluation, on white (the run's) then black (RGBA frames): LPIPS cannot run
    # on 24x24 images, one event for each says why.
    unavailable = [e for e in seen if isinstance(e, MetricUnavailable)]
    assert len(unavailable) == 2
    assert all(u.metric == "LPIPS" and "32x32" in u.reason for u in unavailable)
    tail = [e for e in seen[i_phase1 + 1:] if not isinstance(e, MetricUnavailable)]
    run = tmp_path / "run"
    for k, (name, file) in enumerate((("white", EVAL_FILE), ("black", "eval-black.json"))):
        part = tail[9 * k: 9 * k + 9]
        assert part[0] == Started("eval test", 4, log_every=4)
        assert [e.done for e in part[1:5]] == [1, 2, 3, 4] and part[5] == Finished("eval test")
        table, wrote, done = part[6:]
        assert isinstance(table, FramesEvaluated) and len(table.frames) == 4  # numbers
        assert table.background == name
        assert [f.psnr for f in table.frames] == [e.stats.psnr for e in part[1:5]]
        assert table.mean.lpips is None
        renders = f"{run / RENDERS_DIR / ('test' if k == 0 else name)}/"
        assert wrote == Wrote("eval", (str(run / file), renders))
        assert done.phase == "eval" and done.summary.mean == table.mean
    assert tail[6].mean.psnr == pytest.approx(summary["psnr"])
    whole = tail[-1]
    assert len(tail) == 19
    assert not [e for e in seen if isinstance(e, Note)]  # the library emits no text
    assert whole.phase == "fit" and whole.summary.psnr == pytest.approx(summary["psnr"])
    assert whole.summary.iterations == 6 and whole.summary.run_dir == str(tmp_path / "run")
    assert whole.summary.background == "white"
    (black,) = whole.summary.backgrounds
    assert black.name == "black" and black.scores.psnr == tail[15].mean.psnr


def test_the_run_folder_holds_the_events_another_process_follows(tmp_path: Path) -> None:
    """`events.jsonl`: the typed events as JSON lines (the loop's every `log_every` steps and
    its last), written by the fit whoever listens; `read_events` reads them back, and skips a
    line a writer has not finished."""
    summary = _fit(tmp_path, "run")
    path = tmp_path / "run" / EVENTS_FILE
    events = read_events(path)
    kinds = [e["event"] for e in events]
    assert kinds[0] == "Started" and "Evaluated" in kinds and kinds[-1] == "PhaseDone"
    advanced = [e for e in events if e["event"] == "Advanced" and e["task"] == "fit"]
    assert [e["done"] for e in advanced] == [6]  # log_every 100: only the loop's last step
    assert isinstance(advanced[0]["stats"]["psnr"], float) and "Note" not in kinds
    (done,) = [e for e in read_events(path, ("PhaseDone",)) if e["phase"] == "fit"]
    assert done["summary"]["psnr"] == pytest.approx(summary["psnr"])
    assert all(isinstance(e["time"], float) for e in events)
    with path.open("a") as f:
        f.write('{"event": "Advanced", "task": "fi')  # a writer cut short
    assert read_events(path) == events
    assert read_events(tmp_path / "nothing.jsonl") == []
    log = EventLog(tmp_path / "notes.jsonl", notes=True)
    log(Note("hello"))
    log.close()
    assert read_events(tmp_path / "notes.jsonl") == [
        {"event": "Note", "time": pytest.approx(read_events(tmp_path / "notes.jsonl")[0]["time"]),
         "text": "hello", "stream": "err", "detail": False}]  # fmt: skip


def test_without_a_subscriber_the_pipeline_prints_nothing(tmp_path: Path, capsys) -> None:
    _fit(tmp_path, "run")
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""


def test_the_terminal_renderer_prints_the_commands_lines(tmp_path: Path, capsys) -> None:
    with TerminalRenderer().installed():
        _fit(tmp_path, "run")
    out = capsys.readouterr()
    err = out.err.splitlines()
    assert any(ln.startswith("fit 6/6 [") and "ETA" in ln for ln in err)
    assert any(ln.startswith("[eval @ 3] test PSNR") and "Gaussians" in ln for ln in err)
    assert any(ln.startswith("eval test 4/4 [") for ln in err)
    assert "mean" in out.out and "eval: wrote " in out.out
    assert "fit: done in " in out.out and "test PSNR" in out.out  # the fit's PhaseDone
    with TerminalRenderer(details=False).installed():  # bench fit: no tables
        _fit(tmp_path, "again")
    out = capsys.readouterr()
    assert out.out == "" and "fit 6/6 [" in out.err


def test_subscriptions_end_with_their_block(capsys) -> None:
    first: list = []
    second: list = []
    note("nobody hears this")
    with subscribe(first.append):
        emit(Started("loop", 2))
        with subscribe(second.append) as sub:
            emit(Advanced("loop", 1, Stats(loss=1.0)))
            sub.close()  # closing twice is harmless
        note("done", "out", detail=True)
    emit(Finished("loop"))
    assert first == [Started("loop", 2), Advanced("loop", 1, Stats(loss=1.0)),
                     Note("done", "out", True)]  # fmt: skip
    assert second == [Advanced("loop", 1, Stats(loss=1.0))]
    assert capsys.readouterr().err == ""
    renderer = TerminalRenderer()
    with renderer.installed():
        emit(Started("loop", 2, log_every=1))
        emit(Advanced("loop", 1, Stats(loss=0.01234, psnr=24.5, gaussians=1800)))
        note("between")  # through the open bar: on its own line
        emit(Advanced("loop", 2))
        emit(Finished("loop"))
        emit(PhaseDone("phase1", LoopSummary(2, 1.0, 10)))  # the notes carry the text
    err = capsys.readouterr().err.splitlines()
    assert [ln.split(" [")[0] for ln in err] == ["loop 1/2", "between", "loop 2/2"]
    assert "loss 0.0123" in err[0] and "PSNR 24.50" in err[0] and "#G 1800" in err[0]
    assert renderer.bars == {}


def test_a_forced_restart_starts_a_new_event_log(tmp_path: Path, capsys) -> None:
    """`fit --force` deletes the run's results, its event log too: the log holds one run."""
    from sync4d.cli import main

    root = tmp_path / "tiny"
    write_blender(root, n=4, size=24)
    args = ["fit", str(root), "--out", str(tmp_path / "run"), "--iters", "3", "--threads", "1",
            "--phases", "1", "--set", "phase1.init_points=300", "--set", "eval_every=0"]
    assert main(args) == 0
    assert main([*args, "--force"]) == 0
    capsys.readouterr()
    done = read_events(tmp_path / "run" / EVENTS_FILE, ("PhaseDone",))
    assert [e["phase"] for e in done] == ["phase1", "eval", "eval", "fit"]  # white, black


#: One event of each kind, as the library emits it.
SAMPLES = [
    Note("a script's line"), Started("fit", 10, log_every=1), Advanced("fit", 1, Stats(0.5)),
    Finished("fit"), PhaseDone("fit", FitSummary(24.0, None, None, 10, 10, 2.0, "runs/x")),
    Evaluated("fit", 5, 24.0, None, 2, 100, 1.5),
    FitStarted("ball", 4, 2, 24, 24, 10, "runs/x"), Resumed("runs/x/ckpt", 5),
    Assigned("masks", 2, (ObjectCount("background", 3), ObjectCount("ball", 7))),
    Skipped("phase1", Phase1Skips(10, deform_rows=8, deform_rows_skipped=2, share=0.2,
                                  static=1)),  # fmt: skip
    DatasetChosen("cache/synthetic", True), GeneratingScene("cache/synthetic"),
    SettingChanged("phase1.iterations", 10, 20), Triangulating("ball"),
    InitialPoints("triangulation", 500, 3, 0.0, 2.0), ScaleAdvice(0.001, 0.0044, 4.4, (
        Override("phase1.near", 1e-5),)),
    Phase2Starting(100, "runs/x/phase1.safetensors"), NothingMoves(3),
    MotionDiagnosed(Diagnostics((), 1.0, 0.0, 0.0, 1.0, (1.0,), "masks", 1)),
    Phase3Started("offline", 64, True),
    FieldBuilt(2, 10, 18, 0.9, 1.0, 0.5, 0.4, "runs/x/phase3"),
    FramesEvaluated((FrameScore(0, "r_0", 0.0, 24.0, None, 0.9),),
                    Means(24.0, None, 0.9, None, 1)),
    MetricUnavailable("LPIPS", "too small"), Wrote("eval", ("runs/x/eval.json",)),
    Interrupted("runs/x/ckpt", "python -m sync4d fit --out runs/x --resume", 7),
]


def test_every_event_has_its_words_or_draws_a_bar(capsys) -> None:
    """A new event without a rule in `sync4d.terminal.WORDS` fails here (and without a sample
    above): the command line would print nothing for it."""
    kinds = set(get_args(Event))
    assert {type(e) for e in SAMPLES} == kinds
    for event in SAMPLES:
        if isinstance(event, BARS):
            assert type(event) not in WORDS
            continue
        line = words(event)
        assert type(event) in WORDS and isinstance(line, Line) and line.stream in ("err", "out")
        assert line.text and "None" not in line.text, event  # every sample says something
    renderer = TerminalRenderer(details=False)
    with renderer.installed():
        for event in SAMPLES:
            emit(event)
    out = capsys.readouterr()
    assert "fit 1/10 [" in out.err and "done in" not in out.out  # details left out
    assert "continue with: python -m sync4d fit --out runs/x --resume" in out.err
    assert "--set phase1.near=1e-05" in out.err and "r_0" not in out.out


def test_typed_payloads_write_the_dicts_they_replaced(tmp_path: Path) -> None:
    """`events.jsonl` is unchanged by the typing (issue 63): each payload's JSON is the dict
    the event carried before, key for key and in order, a switch that was off left out."""
    from sync4d.events import (
        BackgroundScore,
        EvalSummary,
        FieldSummary,
        FieldTimings,
        NoCounts,
        Phase2Brief,
        Phase3Skips,
        Scores,
        to_json,
    )

    def written(event) -> list:  # the line EventLog writes, its keys in order, less the time
        path = tmp_path / "one.jsonl"
        path.unlink(missing_ok=True)
        log = EventLog(path)
        log(event)
        log.close()
        (record,) = read_events(path)
        record.pop("time")
        return json.loads(json.dumps(record), object_pairs_hook=list)

    stats = Advanced("fit", 3, Stats(loss=0.5, psnr=20.0, gaussians=10))
    assert written(stats) == [("event", "Advanced"), ("task", "fit"), ("done", 3),
                              ("stats", [("loss", 0.5), ("psnr", 20.0), ("gaussians", 10)])]
    assert to_json(Stats(psnr=21.0)) == {"psnr": 21.0} and to_json(Stats()) == {}
    nodes = Phase1Skips(50, nodes=4, nodes_from=11, nodes_added=1, nodes_removed=0, pruned=3,
                        prune_opacity=0.005)  # fmt: skip
    assert list(to_json(nodes)) == ["gaussians", "nodes", "nodes_from", "nodes_added",
                                    "nodes_removed", "pruned", "prune_opacity"]  # fmt: skip
    assert written(Skipped("phase3", NoCounts()))[-1] == ("counts", [])  # {} in the file
    assert to_json(Skipped.of("phase3", {})) == {"phase": "phase3", "counts": {}}
    counts = {"object_frames": 20, "observed": 18, "invisible": 1, "below_threshold": 1,
              "crops": 18, "extra_crops": 0, "images_loaded": 40, "crops_encoded": 18,
              "encoder_calls": 1, "relational": 20, "relational_skipped": 0,
              "relational_unobserved": 4}  # fmt: skip
    timings = {"observe_s": 1.0, "encode_s": 2.0, "field_s": 0.5, "total_s": 3.5, "crops": 18}
    field = FieldSummary(2, 10, FieldTimings(**timings), Phase3Skips(**counts))
    assert list(to_json(field).items()) == list(
        {"objects": 2, "frames": 10, **timings, **counts}.items())  # "crops" once, in place
    means = Means(24.0, None, 0.9, None, 4)
    assert to_json(EvalSummary("test", "eval.json", means)) == {
        "split": "test", "file": "eval.json", "psnr": 24.0, "ssim": None, "ssim_box3": 0.9,
        "lpips": None, "frames": 4}  # fmt: skip
    fit = FitSummary(24.0, None, 0.1, 10, 60, 2.0, "runs/x", "white",
                     (BackgroundScore("black", Scores(22.0, None, 0.2)),),
                     Phase2Brief(0.9, 1.5, 3, "masks"))  # fmt: skip
    assert json.dumps(to_json(fit)) == json.dumps({
        "psnr": 24.0, "ssim": None, "lpips": 0.1, "gaussians": 10, "iterations": 60,
        "train_seconds": 2.0, "run_dir": "runs/x", "background": "white",
        "backgrounds": {"black": {"psnr": 22.0, "ssim": None, "lpips": 0.2}},
        "phase2": {"rigid_share": 0.9, "shuffle_ratio": 1.5, "objects": 3,
                   "assignment": "masks"}})  # fmt: skip
    assert list(to_json(FitSummary(None, None, None, 1, 1, 0.5, "r"))) == [
        "psnr", "ssim", "lpips", "gaussians", "iterations", "train_seconds", "run_dir"]
    assigned = Assigned("masks", 2, (ObjectCount("background", 3), ObjectCount("ball", 7)))
    assert to_json(assigned)["counts"] == {"background": 3, "ball": 7}
    advice = ScaleAdvice(0.001, 0.0044, 4.4, (Override("phase1.near", 1e-5),))
    assert to_json(advice)["settings"] == {"phase1.near": 1e-5}
    diag = {"objects": [{"label": 0, "name": "background", "gaussians": 5, "static": True,
                         "held": True, "rigid_share": 1.0, "residual_mean": 0.0,
                         "motion_variance": 0.0}],
            "rigid_share": 1.0, "residual_energy": 0.0, "modulated_fraction": 0.0,
            "shuffle_ratio": 1.0, "shuffle_ratios": [1.0, 1.0], "assignment": "trajectories",
            "num_objects": 1, "mask_agreement_ari": 0.5, "mask_objects": 1,
            "trajectories": {"times": []}}  # fmt: skip
    assert json.dumps(to_json(Diagnostics.of(diag))) == json.dumps(
        {k: v for k, v in diag.items() if k != "trajectories"})
