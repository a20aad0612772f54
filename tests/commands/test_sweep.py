"""`sync4d sweep` on Ray: three tiny jobs (one failing on purpose) on a local Ray, then again
(nothing new runs); a small sweep against a separate Ray head started with `ray start --head`
on loopback (`--address`); manifest errors named."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from support.datasets import write_blender
from support.ports import free_port
from sync4d.cli import main

ray = pytest.importorskip("ray", reason="sync4d sweep needs Ray (pip install 'sync4d[sweep]')")

MANIFEST = """
[defaults]
iters = 12
phases = "1"
threads = 1
set = ["init_points=300", "eval_every=0"]

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
def test_a_local_sweep_runs_reports_a_failure_and_resumes(folder, capsys):
    out = folder / "out"
    assert main(["sweep", str(folder / "manifest.toml"), "--out", str(out), "--cpus", "2"]) == 1
    printed = capsys.readouterr().out
    assert "broken-s42 failed: fit:" in printed and "dataset directory does not exist" in printed
    rows = {r["name"]: r for r in json.loads((out / "results.json").read_text())}
    assert rows["tiny-s1"]["status"] == rows["tiny-s2"]["status"] == "done"
    assert rows["broken-s42"]["status"] == "failed"
    assert rows["tiny-s1"]["psnr"] > 0 and rows["tiny-s1"]["threads"] == 1
    assert (out / "runs" / "tiny-s1" / "eval.json").is_file() and (out / "psnr-time.png").is_file()
    assert (out / "results.csv").read_text().count("\n") == 4
    # a second invocation runs nothing new (the failed job is tried again and fails again)
    assert main(["sweep", str(folder / "manifest.toml"), "--out", str(out), "--cpus", "2"]) == 1
    rows = {r["name"]: r for r in json.loads((out / "results.json").read_text())}
    assert rows["tiny-s1"]["status"] == rows["tiny-s2"]["status"] == "skipped"
    assert rows["tiny-s1"]["psnr"] > 0  # the table still reads the finished run


@pytest.mark.slow
def test_a_sweep_joins_a_running_ray_cluster(folder, tmp_path, capsys):
    ray_cli = shutil.which("ray") or str(Path(sys.executable).parent / "ray")
    port = free_port()
    env = {**os.environ, "RAY_ENABLE_UV_RUN_RUNTIME_ENV": "0"}
    subprocess.run([ray_cli, "start", "--head", "--node-ip-address", "127.0.0.1", "--port",
                    str(port), "--num-cpus", "2", "--include-dashboard", "false",
                    "--disable-usage-stats"], check=True, env=env, capture_output=True,
                   timeout=120)  # fmt: skip
    try:
        manifest = tmp_path / "one.toml"
        manifest.write_text(MANIFEST.split("[[job]]\nname = \"broken\"")[0].replace(
            'data = "tiny"', f'data = "{folder / "tiny"}"'))  # fmt: skip
        out = tmp_path / "out"
        assert main(["sweep", str(manifest), "--out", str(out), "--address",
                     f"127.0.0.1:{port}"]) == 0  # fmt: skip
        rows = json.loads((out / "results.json").read_text())
        assert [r["status"] for r in rows] == ["done", "done"]
    finally:
        subprocess.run([ray_cli, "stop", "--force"], env=env, capture_output=True, timeout=120)


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


def test_an_interrupted_job_continues_from_its_checkpoint(folder, tmp_path):
    """A run folder with a checkpoint but no final evaluation (the sweep was stopped mid-fit):
    the job resumes it with `fit --resume` instead of starting over."""
    from sync4d.sweep import Job, run_job

    job = Job(name="cut", data=str(folder / "tiny"), iters=12, phases="1",
              overrides=("init_points=300", "eval_every=0"))  # fmt: skip
    assert run_job(job, tmp_path)["status"] == "done"
    (tmp_path / "runs" / "cut" / "eval.json").unlink()  # as if stopped before its evaluation
    result = run_job(job, tmp_path)
    log = (tmp_path / "logs" / "cut.log").read_text()
    assert result["status"] == "done" and "fit --out" in log and "--resume" in log
    assert (tmp_path / "runs" / "cut" / "eval.json").is_file()
    assert run_job(job, tmp_path)["status"] == "skipped"
