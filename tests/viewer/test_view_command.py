"""`sync4d view` as a user starts it: one clear line for a missing run, a run with no checkpoint
yet, a busy port; a run without a field or one being trained is served with a note; Ctrl-C and
SIGTERM end the server cleanly (closing the last tab does too: test_viewer_browser.py)."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from support.oracle import oracle_run_folder
from support.ports import free_port
from sync4d.cli import main
from sync4d.files import RunLock


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return oracle_run_folder(tmp_path_factory.mktemp("view_cmd"))



def _start(args: list[str]) -> tuple[subprocess.Popen, str]:
    """`sync4d view ARGS` in a process, once it printed its address (the line printed)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RAYON_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "sync4d", "view", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("view: ") and "http://" in line:
            return proc, line
    proc.kill()
    raise AssertionError(f"view never printed its address: {proc.stderr.read()}")


def _ended(proc: subprocess.Popen) -> tuple[str, str]:
    """The output of `proc` once it ended; a server still up after 60 s is killed (never left
    behind holding its port) and fails the test."""
    try:
        return proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"view did not stop 60 s after the signal: {err[-2000:]}") from None


def test_a_missing_run_and_a_run_without_a_checkpoint(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope")]) == 2
    assert "no such run folder" in capsys.readouterr().err
    young = tmp_path / "young"
    with RunLock(young, "fit"):
        assert main(["view", str(young), "--port", str(free_port())]) == 2
    err = capsys.readouterr().err
    assert "no checkpoint yet" in err and "'fit' (pid" in err and "first save" in err


def test_a_busy_port_is_named(run_dir, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["view", str(run_dir), "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"port {port} on 127.0.0.1 is in use" in err and "--port" in err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_the_server_stops_cleanly_on_a_signal(run_dir, tmp_path, sig):
    bare = tmp_path / "bare"  # no language field: served, with the command that builds it
    shutil.copytree(run_dir, bare, ignore=shutil.ignore_patterns("phase3"))
    port = free_port()
    proc, line = _start([str(bare), "--port", str(port), "--threads", "1"])
    assert f"http://localhost:{port}" in line
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as page:
        assert page.status == 200 and b"<html" in page.read().lower()  # it serves the page
    proc.send_signal(sig)
    out, err = _ended(proc)
    assert proc.returncode == 0, err
    assert "queries are off" in err and "--phases 3" in err and "view: stopped" in err
    assert "Traceback" not in err


def test_a_run_being_trained_is_served_with_a_note(run_dir):
    port = free_port()
    with RunLock(run_dir, "fit"):
        proc, _ = _start([str(run_dir), "--port", str(port), "--threads", "1"])
        proc.send_signal(signal.SIGINT)
        _, err = _ended(proc)
    assert proc.returncode == 0
    assert "is being written by 'fit'" in err and "reloaded as it saves" in err
