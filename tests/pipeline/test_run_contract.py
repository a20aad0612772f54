"""The run folder as a contract (docs/run-folder.md): resume takes the run's own data and
settings, one writer per run, saves that cannot be half-done, results never overwritten by
another experiment. One test per case of the issue that asked for it."""

from __future__ import annotations

import datetime
import errno
import json
import os
import platform
import random
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import safetensors.torch

from support.datasets import write_blender
from sync4d.cli import main
from sync4d.config import load_config, repo_configs, with_budget
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.runs import CHECKPOINT_NAME, CheckpointError, load_run, read_checkpoint
from sync4d.runs import checkpoint as checkpoint_module

TINY = ["--set", "phase1.init_points=300", "--set", "eval_every=0", "--threads", "1",
        "--set", "phases=1"]  # fmt: skip
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RAYON_NUM_THREADS": "1"}


@pytest.fixture
def data(tmp_path: Path) -> Path:
    root = tmp_path / "tiny"
    write_blender(root, n=4, size=24)
    return root


def _meta(run: Path) -> dict:
    return read_checkpoint(run / CHECKPOINT_NAME)[1]


def _no_temporaries(run: Path) -> bool:
    return not [p for p in run.iterdir() if p.name.endswith(".tmp")]


def _interrupt_at(monkeypatch, iteration: int) -> None:
    original = Phase1Trainer.step

    def step(self):
        if self.iteration == iteration:
            os.kill(os.getpid(), signal.SIGINT)
        return original(self)

    monkeypatch.setattr(Phase1Trainer, "step", step)


def _continue_command(err: str) -> list[str]:
    line = next(ln for ln in err.splitlines() if "continue with:" in ln)
    argv = shlex.split(line.split("continue with:", 1)[1])
    assert argv[:3] == ["python", "-m", "sync4d"]
    return argv[3:]


# 1. --resume without DATA continues on the run's dataset; another DATA is refused.
def test_resume_uses_the_recorded_dataset_and_refuses_another(
    data: Path, tmp_path: Path, capsys
) -> None:
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "6", *TINY]) == 0
    assert main(["fit", "--out", str(run), "--resume", "--iters", "9"]) == 0
    assert "embedded synthetic scene" not in capsys.readouterr().err
    assert _meta(run)["iteration"] == 9 and _meta(run)["run"]["scene"] == "tiny"
    other = tmp_path / "other"
    write_blender(other, n=3, size=24)
    assert main(["fit", str(other), "--out", str(run), "--resume", "--iters", "12"]) == 2
    err = capsys.readouterr().err
    assert "is not the dataset of the run" in err and "train frames 3 against the run's 4" in err
    assert _meta(run)["iteration"] == 9
    moved = tmp_path / "moved"  # the same frames elsewhere are the same dataset
    data.rename(moved)
    assert main(["fit", "--out", str(run), "--resume"]) == 2
    assert "pass its new path as DATA" in capsys.readouterr().err
    assert main(["fit", str(moved), "--out", str(run), "--resume", "--iters", "12"]) == 0


# 2. --resume keeps the stored settings; the printed command is the one that works.
def test_the_printed_continue_command_keeps_every_setting(
    data: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    run = tmp_path / "run"
    _interrupt_at(monkeypatch, 5)
    args = ["fit", str(data), "--out", str(run), "--iters", "11", "--resolution-scale", "0.5",
            "--set", "phase1.sh_degree=1", *TINY]  # fmt: skip
    assert main(args) == 130
    argv = _continue_command(capsys.readouterr().err)
    monkeypatch.undo()
    assert main(argv) == 0
    meta = _meta(run)
    assert meta["iteration"] == 11 and meta["sh_degree"] == 1
    assert meta["run"]["resolution_scale"] == 0.5 and meta["run"]["cameras"][0]["width"] == 12
    # A setting that contradicts the run is named, not taken.
    assert main([*argv, "--resolution-scale", "1.0"]) == 2
    assert "resolution_scale: the run has 0.5, this command gives 1.0" in capsys.readouterr().err
    assert main([*argv, "--config", str(repo_configs() / "synthetic.toml")]) == 2
    err = capsys.readouterr().err
    assert "--resume continues the run with its recorded settings" in err and "init_from" in err


# 3. One writer per run folder.
def test_a_second_writer_is_told_who_holds_the_run(data: Path, tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "3", *TINY]) == 0
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from sync4d.files import RunLock; "
         "RunLock(sys.argv[1], 'fit').acquire(); print('held', flush=True); time.sleep(120)",
         str(run)],
        stdout=subprocess.PIPE, text=True, env=ENV,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        for argv in (["fit", str(data), "--out", str(run), "--resume", "--iters", "5"],
                     ["fit", str(data), "--out", str(run), "--force", *TINY],
                     ["eval", str(run), "--threads", "1"]):  # fmt: skip
            assert main(argv) == 2
            err = capsys.readouterr().err
            assert f"is in use by 'fit' (pid {holder.pid}" in err, err
    finally:
        holder.kill()
        holder.wait()
    assert _meta(run)["iteration"] == 3  # untouched; the lock died with its holder
    assert main(["fit", str(data), "--out", str(run), "--resume", "--iters", "5"]) == 0


def test_two_benches_sharing_keep_runs_get_one_line(data: Path, tmp_path: Path, capsys) -> None:
    """A bench whose --keep-runs budget folder another process holds ends in one line naming
    the holder and the fix, not a traceback."""
    keep = tmp_path / "keep"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from sync4d.files import RunLock; "
         "RunLock(sys.argv[1], 'fit').acquire(); print('held', flush=True); time.sleep(120)",
         str(keep / "s1.0_c1000000_i3")],
        stdout=subprocess.PIPE, text=True, env=ENV,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        assert main(["bench", "fit", str(data), "--iters", "3", "--out", str(tmp_path / "b.json"),
                     "--keep-runs", str(keep), *TINY]) == 2  # fmt: skip
    finally:
        holder.kill()
        holder.wait()
    err = capsys.readouterr().err
    assert f"(pid {holder.pid}" in err and "own --keep-runs" in err and "Traceback" not in err


# 4. A second Ctrl-C (and a hang-up) during a save waits for the save.
def test_signals_during_a_save_wait_for_it(data: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    run = tmp_path / "run"
    real = checkpoint_module.save_file
    calls = []

    def save_file(tensors, path, metadata=None):
        calls.append(path)
        if len(calls) == 2:  # the periodic save at iteration 4: Ctrl-C, then a hang-up
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGHUP)
        if len(calls) == 3:  # the final save: Ctrl-C again
            os.kill(os.getpid(), signal.SIGINT)
        real(tensors, path, metadata=metadata)

    monkeypatch.setattr(checkpoint_module, "save_file", save_file)
    args = ["fit", str(data), "--out", str(run), "--iters", "50", *TINY,
            "--set", "checkpoint_every=2"]  # fmt: skip
    assert main(args) == 130
    assert "continue with" in capsys.readouterr().err
    assert len(calls) == 3 and _meta(run)["iteration"] == 4 and _no_temporaries(run)


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGUSR1])
def test_a_hang_up_in_a_real_process_saves(data: Path, tmp_path: Path, sig: int) -> None:
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "sync4d", "fit", str(data), "--out", str(run), "--iters",
           "1000000", *TINY, "--set", "checkpoint_every=0"]  # fmt: skip
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            if line.startswith("fit 100/"):
                break
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert _meta(run)["iteration"] >= 100 and _no_temporaries(run)


# 5. A failed write keeps the previous checkpoint, says so in one line, exits non-zero.
@pytest.mark.parametrize("interrupted", [False, True])
def test_a_failed_save_keeps_the_previous_checkpoint(
    data: Path, tmp_path: Path, monkeypatch, capsys, interrupted: bool
) -> None:
    run = tmp_path / "run"
    real = checkpoint_module.save_file
    calls = []

    def save_file(tensors, path, metadata=None):
        calls.append(path)
        if len(calls) >= 2:
            Path(path).write_bytes(b"partial")  # the disk fills up half-way
            raise OSError(errno.ENOSPC, "No space left on device")
        real(tensors, path, metadata=metadata)

    monkeypatch.setattr(checkpoint_module, "save_file", save_file)
    if interrupted:
        _interrupt_at(monkeypatch, 2)
    args = ["fit", str(data), "--out", str(run), "--iters", "8", *TINY,
            "--set", "checkpoint_every=2"]  # fmt: skip
    assert main(args) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if "could not be written" in ln]
    assert len(err) == 1 and "No space left on device" in err[0] and CHECKPOINT_NAME in err[0]
    assert _meta(run)["iteration"] == 2 and _no_temporaries(run)


def test_a_file_size_limit_is_one_line_and_no_traceback(data: Path, tmp_path: Path) -> None:
    import resource

    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "sync4d", "fit", str(data), "--out", str(run), "--iters", "4",
           *TINY]  # fmt: skip

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, resource.RLIM_INFINITY))

    done = subprocess.run(cmd, capture_output=True, text=True, env=ENV, preexec_fn=limit,
                          timeout=120)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and "could not be written" in done.stderr
    assert not (run / CHECKPOINT_NAME).exists() and _no_temporaries(run)


# 6. bench fit checks its output folder before training.
def test_bench_fit_checks_its_output_before_training(
    data: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    import sync4d.bench.fit as bench_fit

    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setattr(bench_fit, "run_grid", lambda *a, **k: pytest.fail("trained first"))
    args = ["bench", "fit", str(data), "--iters", "3", *TINY]
    assert main([*args, "--out", str(blocker / "bench.json")]) == 2
    assert "cannot write there" in capsys.readouterr().err


# 8. Evaluating another split or dataset never overwrites the run's eval.json.
def test_eval_of_another_split_or_dataset_writes_its_own_file(data: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "3", *TINY]) == 0
    own = (run / "eval.json").read_bytes()
    assert main(["eval", str(run), "--split", "train", "--threads", "1"]) == 0
    assert json.loads((run / "eval-train.json").read_text())["split"] == "train"
    other = tmp_path / "other"
    write_blender(other, n=3, size=24)
    assert main(["eval", str(run), "--data", str(other), "--threads", "1"]) == 0
    assert len(json.loads((run / "eval-other-test.json").read_text())["frames"]) == 3
    assert (run / "eval.json").read_bytes() == own
    assert (run / "renders" / "train").is_dir() and (run / "renders" / "other-test").is_dir()


# 9. Checkpoint headers: metadata that is not JSON, a negative iteration.
@pytest.mark.parametrize(
    ("header", "message"),
    [("{not json", "not JSON"),
     ('{"format_version": 1, "kind": "sync4d.phase1", "iteration": -5}', "'iteration' must be"),
     ('{"format_version": 1, "run": {"train_seconds": "x"}}', "run.train_seconds"),
     ('{"format_version": 1, "kind": "sync4d.phase9"}', "unknown checkpoint kind")],
)  # fmt: skip
def test_bad_checkpoint_headers_are_named(
    data: Path, tmp_path: Path, capsys, header: str, message: str
) -> None:
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "3", *TINY]) == 0
    tensors = safetensors.torch.load_file(str(run / CHECKPOINT_NAME))
    safetensors.torch.save_file(tensors, str(run / CHECKPOINT_NAME), metadata={"sync4d": header})
    with pytest.raises(CheckpointError, match=message):
        load_run(run)
    assert main(["fit", str(data), "--out", str(run), "--resume", "--iters", "5"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


# 10. Training time accumulates; --iters bounds Phase 2; --resume --force is refused.
def test_training_seconds_accumulate_across_resumes(data: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "6", *TINY]) == 0
    first = _meta(run)["run"]["train_seconds"]
    assert main(["fit", str(data), "--out", str(run), "--resume", "--iters", "12"]) == 0
    final = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines()][-1]
    assert first > 0 and final["train_seconds"] > first
    assert _meta(run)["run"]["train_seconds"] == final["train_seconds"]


def test_iters_bounds_phase2_and_its_refinement(data: Path, tmp_path: Path) -> None:
    cfg = with_budget(load_config(repo_configs() / "synthetic.toml"), 30)
    assert cfg.phase1.iterations == 30 and cfg.phase2.iterations == 30
    m = cfg.phase2.motion
    assert (m.refine_steps, m.refine_retrack_steps, m.refine_texture_rounds) == (1, 2, 0)
    assert cfg.phase2.motion_start == 6 and cfg.phase2.warmup_end == 30
    run = tmp_path / "run"
    args = ["fit", str(data), "--out", str(run), "--iters", "7", *TINY, "--set", "phases=1,2"]
    assert main(args) == 0
    assert _meta(run)["kind"] == "sync4d.phase2" and _meta(run)["iteration"] == 7


def test_resume_and_force_together_are_refused(data: Path, tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    assert main(["fit", str(data), "--out", str(run), "--iters", "3", *TINY]) == 0
    assert main(["fit", str(data), "--out", str(run), "--resume", "--force"]) == 2
    assert "pass one of them" in capsys.readouterr().err
    assert _meta(run)["iteration"] == 3


_MARK_SAVES = (
    "import sys, sync4d.runs.checkpoint as c\n"
    "real = c.save_file\n"
    "def save_file(*a, **k):\n"
    "    print('S', flush=True)\n"
    "    real(*a, **k)\n"
    "c.save_file = save_file\n"
    "from sync4d.cli import main\n"
    "sys.exit(main(sys.argv[1:]))\n"
)


@pytest.mark.slow
def test_sigkill_during_saves_always_leaves_a_checkpoint_to_resume(
    data: Path, tmp_path: Path
) -> None:
    """24 SIGKILLs, each a random 0-40 ms after a save starts (the save of this checkpoint
    takes ~5-30 ms: temporary file, write, fsync, rename, fsync of the folder)."""
    run = tmp_path / "run"
    rng = random.Random(1234)
    base = ["fit", str(data), "--out", str(run), *TINY, "--set", "checkpoint_every=1"]
    iterations, delays, started = [], [], time.perf_counter()
    for kill in range(24):
        argv = [*base, "--iters", "100000"] + (["--resume"] if kill else [])
        proc = subprocess.Popen([sys.executable, "-c", _MARK_SAVES, *argv],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                                env=ENV)  # fmt: skip
        try:
            assert proc.stdout is not None
            saves = 0
            while saves < 2 + rng.randrange(3):  # at least one save has completed
                assert proc.stdout.readline() == "S\n", "fit ended before its saves"
                saves += 1
            delays.append(rng.uniform(0.0, 0.04))
            time.sleep(delays[-1])
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=30)
        finally:
            proc.kill()
        iterations.append(_meta(run)["iteration"])  # loadable: read and checked
    assert iterations == sorted(iterations) and iterations[-1] > iterations[0]
    last = iterations[-1]
    assert main([*base, "--resume", "--iters", str(last + 3)]) == 0
    assert _meta(run)["iteration"] == last + 3 and _no_temporaries(run)
    record = os.environ.get("SYNC4D_SIGKILL_RECORD")
    if record:
        with open("/proc/cpuinfo") as fh:
            cpu = next((ln.split(":", 1)[1].strip() for ln in fh
                        if ln.startswith("model name")), "")  # fmt: skip
        doc = {
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "command": f"SYNC4D_SIGKILL_RECORD={record} OMP_NUM_THREADS=1 python -m pytest -q "
            "tests/pipeline/test_run_contract.py -m slow -k sigkill -p no:cacheprovider",
            "machine": {"platform": platform.platform(), "cpu": cpu, "cpus": os.cpu_count()},
            "kills": len(delays),
            "delay_after_save_start_ms": [1e3 * d for d in delays],
            "iteration_after_each_kill": iterations,
            "resumed_to": last + 3,
            "all_loadable_and_resumed": True,
            "seconds": time.perf_counter() - started,
        }
        Path(record).write_text(json.dumps(doc, indent=1) + "\n")
