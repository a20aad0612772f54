"""A user's install, as the README tells it: the wheel of this checkout installed into a fresh
virtual environment with the README's user lines (pip's cache and the package index CI already
reaches; nothing else), then the README's first-run commands through the `sync4d` console script,
with a small iteration count, from a folder outside the clone and with nothing of the developer
environment on the path. It catches what the in-process README test cannot: a dependency that
only `make setup` installs, a file missing from the wheel, an example that needs `.venv`."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from support import ROOT
from support.readme import first_run_commands, small_extra, user_install_lines

#: Building the venv copies torch (about 6 GB installed) from pip's cache: minutes.
pytestmark = pytest.mark.slow


def _run(args: list[str] | str, cwd: Path, env: dict[str, str], timeout: float = 1800) -> str:
    """Run a command (a shell line when `args` is a string); fail the test with its output when
    it fails. Returns its stdout and stderr together."""
    t0 = time.perf_counter()
    proc = subprocess.run(args, cwd=cwd, env=env, shell=isinstance(args, str), text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=timeout,
                          executable="/bin/bash" if isinstance(args, str) else None)  # fmt: skip
    shown = args if isinstance(args, str) else " ".join(args)
    print(f"$ {shown}   [{time.perf_counter() - t0:.0f} s, exit {proc.returncode}]")
    if proc.returncode != 0:
        pytest.fail(f"{shown} exited {proc.returncode}:\n{proc.stdout[-6000:]}")
    return proc.stdout


def _build_wheel(out: Path) -> Path:
    """This checkout's wheel, built once with maturin (release, as the README's wheel route)."""
    maturin = Path(sys.executable).with_name("maturin")
    assert maturin.is_file(), f"no maturin beside {sys.executable}: run make setup"
    env = dict(os.environ, PYO3_PYTHON=sys.executable)
    subprocess.run([str(maturin), "build", "--release", "--out", str(out), "-i", sys.executable],
                   cwd=ROOT, env=env, check=True, stdout=subprocess.DEVNULL)  # fmt: skip
    wheels = sorted(out.glob("sync4d-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def _fresh_venv(path: Path) -> None:
    """`python -m venv` from the interpreter under the dev venv (its base Python); where that
    Python lacks ensurepip (Debian without python3-venv) pip is bootstrapped as the Makefile
    does."""
    base = getattr(sys, "_base_executable", sys.executable)
    made = subprocess.run([base, "-m", "venv", str(path)], capture_output=True, text=True)
    if made.returncode != 0:
        shutil.rmtree(path, ignore_errors=True)
        subprocess.run([base, "-m", "venv", "--without-pip", str(path)], check=True)
        subprocess.run([sys.executable, "-m", "pip", "--python", str(path / "bin" / "python"),
                        "install", "-q", "pip"], check=True)  # fmt: skip


def _user_env(venv: Path, home: Path) -> dict[str, str]:
    """The environment of a user with `venv` activated: no PYTHONPATH, no dev venv on PATH."""
    keep = ("HOME", "LANG", "LC_ALL", "TMPDIR", "XDG_CACHE_HOME", "PIP_INDEX_URL",
            "PIP_EXTRA_INDEX_URL", "PIP_TRUSTED_HOST", "PIP_CERT", "SSL_CERT_FILE",
            "PIP_NO_INPUT", "PIP_CACHE_DIR", "REQUESTS_CA_BUNDLE", "OPENBLAS_CORETYPE",
            "OPENBLAS_L2_SIZE")  # fmt: skip
    env = {k: os.environ[k] for k in keep if k in os.environ}
    path = [p for p in os.environ.get("PATH", "/usr/bin:/bin").split(os.pathsep)
            if not p.startswith(str(ROOT))]  # fmt: skip
    env.update(
        PATH=os.pathsep.join([str(venv / "bin"), *path]),
        VIRTUAL_ENV=str(venv),
        SYNC4D_CACHE=str(home / "cache"),
        PIP_DISABLE_PIP_VERSION_CHECK="1",
        PIP_PROGRESS_BAR="off",
        OMP_NUM_THREADS="2",
        MKL_NUM_THREADS="2",
        RAYON_NUM_THREADS="2",
    )
    return env


def test_user_install_first_run(tmp_path: Path) -> None:
    wheel = _build_wheel(tmp_path / "wheels")
    venv = tmp_path / "venv"
    work = tmp_path / "work"  # outside the clone: nothing of the checkout is importable here
    work.mkdir()
    try:
        _fresh_venv(venv)
        env = _user_env(venv, tmp_path)
        lines = user_install_lines()
        assert lines[0] == "pip install .", lines
        for line in lines:
            if line == "pip install .":
                line = f"pip install {wheel}"  # the README's equivalent wheel route
            _run(line, work, env)
        out = _run(["python", "-c", "import sync4d, sys; print(sync4d.__file__)"], work, env)
        assert str(venv) in out, f"sync4d imported from outside the fresh venv: {out}"

        for cmd in first_run_commands():
            print(_run(["sync4d", *cmd, *small_extra(cmd)], work, env)[-600:])
        out = _run(["sync4d", "eval", "runs/first", "--threads", "2"], work, env)
        print(out[-800:])
        mean = json.loads((work / "runs/first/eval.json").read_text())["mean"]
        assert mean["psnr"] > 10.0, mean
        assert mean["lpips"] is not None, f"eval ran without LPIPS:\n{out}"
        assert (work / "runs/first/phase3/field.safetensors").is_file()
        assert len(list((work / "runs/first/renders").glob("*.png"))) == 24

        # The examples run for a pip user too (interpreter on PATH, no .venv).
        out = _run(["sh", str(ROOT / "examples/query.sh"), "runs/first"], work, env)
        assert "red ball" in out, out[-2000:]
        _run(["sh", str(ROOT / "examples/eval_run.sh"), "runs/first"], work, env)
        # export reads the schema shipped in the wheel and writes files viewers open
        print(_run(["sh", str(ROOT / "examples/export.sh"), "runs/first", "out"], work, env))
        assert "red ball" in (work / "out/prompt.txt").read_text()
        for name in ("scene.json", "scene.embeddings.safetensors", "canonical.ply", "t0.5.ply",
                     "t0.5.spz", "sequence.ply"):
            assert (work / "out" / name).stat().st_size > 0, name

        # Shell completion from the installed command.
        script = _run(["sync4d", "completion", "bash"], work, env)
        assert "_shtab_sync4d" in script
    finally:
        shutil.rmtree(venv, ignore_errors=True)  # about 6 GB; pytest keeps tmp dirs around
