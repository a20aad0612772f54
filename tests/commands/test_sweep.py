"""`sync4d sweep` on Ray: three tiny jobs (one failing on purpose) on a local Ray, then again
(nothing new runs); a small sweep against a separate Ray head started with `ray start --head`
on loopback (`--address`); manifest errors named; a job interrupted in the middle of training
resumes.

These tests cannot hurt the machine: each Ray they start has its own temporary folder
(`RAY_TMPDIR`, `--temp-dir`) and its own ports, 1 CPU, and is stopped by its own process ids,
never by `ray stop` (which stops every Ray on the host). Every process they start carries a
marker in its environment; `ray_sandbox` records the Ray processes running before and fails if
one of theirs is still running after (other Rays on the host are left alone)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import pytest

from support.datasets import write_blender
from support.ports import free_port
from sync4d.cli import main

ray = pytest.importorskip("ray", reason="sync4d sweep needs Ray (pip install 'sync4d[sweep]')")
psutil = pytest.importorskip("psutil", reason="the Ray process check needs psutil (Ray's own)")

#: The environment variable that marks every process these tests start (and its children).
MARKER = "SYNC4D_TEST_RAY_SANDBOX"
#: Words in the name or command line of a Ray process.
RAY_WORDS = ("raylet", "gcs_server", "ray::", "ray/dashboard", "ray/_private", "default_worker",
             "plasma_store", "log_monitor", "runtime_env")  # fmt: skip


def ray_processes() -> dict[int, str]:
    """The Ray processes on this host now: pid -> name."""
    found = {}
    for p in psutil.process_iter(["pid", "name", "cmdline"]):
        text = f"{p.info['name']} {' '.join(p.info['cmdline'] or [])}"
        if any(w in text for w in RAY_WORDS):
            found[p.info["pid"]] = p.info["name"]
    return found


def marked(token: str) -> list[psutil.Process]:
    """The processes (other than this one) whose environment carries `token`."""
    out = []
    for p in psutil.process_iter(["pid"]):
        if p.pid == os.getpid():
            continue
        try:
            if p.environ().get(MARKER) == token:
                out.append(p)
        except (psutil.Error, OSError):
            continue
    return out


def stop_marked(token: str, grace: float = 20.0) -> None:
    """End the processes these tests started (by their pids): SIGTERM, then SIGKILL."""
    procs = marked(token)
    for p in procs:
        with contextlib.suppress(psutil.Error):
            p.terminate()
    _, alive = psutil.wait_procs(procs, timeout=grace)
    for p in alive:
        with contextlib.suppress(psutil.Error):
            p.kill()
    psutil.wait_procs(alive, timeout=grace)


@pytest.fixture(scope="module")
def ray_sandbox():
    """A temporary folder of Ray's own (short: Ray's socket paths are limited to 107 bytes) and
    the marker, in this process's environment while the module runs; afterwards, no Ray process
    that these tests started is still running."""
    token = uuid.uuid4().hex
    root = Path(tempfile.mkdtemp(prefix="s4dray-", dir="/tmp"))
    before = ray_processes()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RAY_TMPDIR", str(root))
        mp.setenv(MARKER, token)
        mp.setenv("RAY_ENABLE_UV_RUN_RUNTIME_ENV", "0")
        mp.setenv("RAY_AUTH_MODE", "disabled")  # the driver finds no token of a `ray start` head
        mp.delenv("RAY_ADDRESS", raising=False)
        yield {"token": token, "root": root}
    deadline = time.monotonic() + 30  # ray.shutdown() ends its processes within seconds
    while marked(token) and time.monotonic() < deadline:
        time.sleep(0.5)
    left = marked(token)
    stop_marked(token)  # whatever is left, so one failure does not leave the machine loaded
    shutil.rmtree(root, ignore_errors=True)
    new = {pid: name for pid, name in ray_processes().items() if pid not in before}
    assert not left, (f"Ray processes these tests started are still running: "
                      f"{[(p.pid, p.name()) for p in left if p.is_running()]}; other new Ray "
                      f"processes on the host: {new}")  # fmt: skip

MANIFEST = """
[defaults]
iters = 12
phases = "1"
threads = 1
set = ["phase1.init_points=300", "eval_every=0"]

[[job]]
name = "tiny"
data = "tiny"
seeds = [1, 2]

[[job]]
name = "broken"
data = "no-such-dataset"
"""


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sweep")
    write_blender(root / "tiny", n=4, size=24)
    (root / "manifest.toml").write_text(MANIFEST)
    return root


@pytest.mark.slow
def test_a_local_sweep_runs_reports_a_failure_and_resumes(folder, capsys, ray_sandbox):
    out = folder / "out"
    assert main(["sweep", str(folder / "manifest.toml"), "--out", str(out), "--cpus", "1"]) == 1
    printed = capsys.readouterr().out
    assert "broken-s42 failed: fit:" in printed and "dataset directory does not exist" in printed
    rows = {r["name"]: r for r in json.loads((out / "results.json").read_text())}
    assert rows["tiny-s1"]["status"] == rows["tiny-s2"]["status"] == "done"
    assert rows["broken-s42"]["status"] == "failed"
    assert rows["tiny-s1"]["psnr"] > 0 and rows["tiny-s1"]["threads"] == 1
    assert (out / "runs" / "tiny-s1" / "eval.json").is_file() and (out / "psnr-time.png").is_file()
    assert (out / "results.csv").read_text().count("\n") == 4
    # a second invocation runs nothing new (the failed job is tried again and fails again)
    assert main(["sweep", str(folder / "manifest.toml"), "--out", str(out), "--cpus", "1"]) == 1
    rows = {r["name"]: r for r in json.loads((out / "results.json").read_text())}
    assert rows["tiny-s1"]["status"] == rows["tiny-s2"]["status"] == "skipped"
    assert rows["tiny-s1"]["psnr"] > 0  # the table still reads the finished run


@pytest.mark.slow
def test_a_sweep_joins_a_running_ray_cluster(folder, tmp_path, capsys, ray_sandbox):
    ray_cli = shutil.which("ray") or str(Path(sys.executable).parent / "ray")
    port = free_port()  # its folder: $RAY_TMPDIR/ray, as the driver's (and its auth token)
    subprocess.run([ray_cli, "start", "--head", "--node-ip-address", "127.0.0.1", "--port",
                    str(port), "--num-cpus", "1", "--include-dashboard", "false",
                    "--dashboard-agent-listen-port", str(free_port()),
                    "--disable-usage-stats"], check=True, env=dict(os.environ),
                   capture_output=True, timeout=120)  # fmt: skip
    try:
        manifest = tmp_path / "one.toml"
        manifest.write_text(MANIFEST.split("[[job]]\nname = \"broken\"")[0].replace(
            'data = "tiny"', f'data = "{folder / "tiny"}"'))  # fmt: skip
        out = tmp_path / "out"
        assert main(["sweep", str(manifest), "--out", str(out), "--address",
                     f"127.0.0.1:{port}"]) == 0  # fmt: skip
        rows = json.loads((out / "results.json").read_text())
        assert [r["status"] for r in rows] == ["done", "done"]
    finally:  # this head's processes only, by pid (never `ray stop`: every Ray on the host)
        stop_marked(ray_sandbox["token"])


def test_manifest_errors_are_named(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[[job]]\ndata = 'x'\nspeed = 3\n")
    assert main(["sweep", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "bad.toml: [[job]] 1 has unknown keys ['speed']" in capsys.readouterr().err
    bad.write_text("[[job]\n")
    assert main(["sweep", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "bad.toml: not valid TOML" in capsys.readouterr().err
    bad.write_text("[defaults]\niters = 3\n")
    assert main(["sweep", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "no jobs" in capsys.readouterr().err


#: Iterations of the interrupted job: its first progress line (iteration 100) comes long
#: before its end, so the signal lands in the middle of training.
CUT_ITERS = 160


@pytest.mark.slow
def test_an_interrupted_job_continues_from_its_checkpoint(folder, tmp_path, ray_sandbox):
    """A sweep job interrupted in the middle of training (Ctrl-C on its process group, as a
    terminal sends it, once its fit has logged progress): fit saves the iteration it reached,
    and the job run again continues it with `fit --resume` instead of starting over."""
    from sync4d.runs.checkpoint import read_checkpoint
    from sync4d.sweep import Job, run_job

    job = Job(name="cut", data=str(folder / "tiny"), iters=CUT_ITERS, phases="1",
              overrides=("phase1.init_points=300", "eval_every=0"))  # fmt: skip
    run = tmp_path / "runs" / "cut"
    code = ("from pathlib import Path; from sync4d.sweep import Job, run_job; "
            f"run_job(Job(**{dataclasses.asdict(job)!r}), Path({str(tmp_path)!r}))")  # fmt: skip
    metrics = run / "metrics.jsonl"
    with open(tmp_path / "job.err", "w") as err:
        proc = subprocess.Popen([sys.executable, "-c", code], start_new_session=True,
                                stdout=subprocess.DEVNULL, stderr=err)  # fmt: skip
    try:
        deadline = time.monotonic() + 300
        while not (metrics.is_file() and '"iteration"' in metrics.read_text()):
            assert proc.poll() is None, (tmp_path / "job.err").read_text()[-2000:]
            assert time.monotonic() < deadline, "no progress line in 300 s"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)  # mid-training: progress logged, far from the end
        proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    _, meta = read_checkpoint(run / "checkpoint.safetensors")
    assert 100 <= meta["iteration"] < CUT_ITERS, meta["iteration"]  # saved where it stopped
    assert not (run / "eval.json").exists()
    result = run_job(job, tmp_path)
    log = (tmp_path / "logs" / "cut.log").read_text()
    assert result["status"] == "done" and "fit --out" in log and "--resume" in log
    assert (run / "eval.json").is_file()
    assert read_checkpoint(run / "checkpoint.safetensors")[1]["iteration"] == CUT_ITERS
    assert run_job(job, tmp_path)["status"] == "skipped"
