"""One error root (issue 63): every error a user can fix is a `sync4d.errors.Sync4dError`,
beside the built-in base code relies on, and a command line catches it once."""

from __future__ import annotations

import argparse
import importlib
import types

import pytest

from sync4d import cli
from sync4d.errors import Sync4dError

#: (module, class, the built-in base it keeps, its exit code)
ERRORS = [
    ("sync4d.settings", "ConfigError", ValueError, 2),
    ("sync4d.data.scene", "DatasetError", ValueError, 2),
    ("sync4d.files", "WriteFailed", OSError, 2),
    ("sync4d.files", "RunBusy", RuntimeError, 2),
    ("sync4d.runs.checkpoint", "CheckpointError", ValueError, 2),
    ("sync4d.runs.folder", "RunError", ValueError, 2),
    ("sync4d.phase3.store", "FieldError", ValueError, 2),
    ("sync4d.phase3.encoders.encoder", "EncoderError", RuntimeError, 2),
    ("sync4d.phase3.texts", "QueryError", ValueError, 2),
    ("sync4d.phase3.relational.plan", "RelationalError", ValueError, 2),
    ("sync4d.phase3.evaluation.annotations", "AnnotationError", ValueError, 2),
    ("sync4d.metrics.lpips", "LPIPSWeightsMissing", RuntimeError, 2),
    ("sync4d.sweep", "ManifestError", ValueError, 2),
    ("sync4d.export.errors", "ExportError", ValueError, 2),
    ("sync4d.export.schema", "SceneError", ValueError, 2),
    ("sync4d.serve.tools", "ToolProblem", ValueError, 2),
    ("sync4d.viewer.state", "RenderFailed", ValueError, 2),
    ("sync4d.watchdog", "NonFinite", FloatingPointError, 3),
    ("sync4d.pipeline.fit", "TrainingDiverged", RuntimeError, 3),
]


@pytest.mark.parametrize(("module", "name", "base", "code"), ERRORS)
def test_every_user_facing_error_derives_from_the_root(module, name, base, code) -> None:
    cls = getattr(importlib.import_module(module), name)
    assert issubclass(cls, Sync4dError) and issubclass(cls, base) and cls.exit_code == code


def test_an_interrupted_fit_is_no_error() -> None:
    from sync4d.pipeline.fit import FitInterrupted

    assert not issubclass(FitInterrupted, Sync4dError)  # Ctrl-C: exit 130, nothing to fix


def _command(error: BaseException) -> types.ModuleType:
    module = types.ModuleType("failing")

    def main(args: argparse.Namespace) -> int:
        raise error

    module.main = main  # type: ignore[attr-defined]
    return module


def test_the_cli_reports_a_root_error_that_a_command_lets_through(capsys) -> None:
    """`cli._call`: a `Sync4dError` its one line and its exit code (the watchdog's: 3, by its
    type, not its name); an OSError, `WriteFailed` too, the line naming the path; anything
    else a traceback."""
    from sync4d.files import WriteFailed
    from sync4d.pipeline.fit import TrainingDiverged
    from sync4d.settings import ConfigError

    args = argparse.Namespace(command="render")
    assert cli._call(_command(ConfigError("near: must be > 0")), args) == 2
    assert capsys.readouterr().err.endswith(" render: near: must be > 0\n")
    assert cli._call(_command(TrainingDiverged("Phase 1 stopped: NaN")), args) == 3
    assert capsys.readouterr().err.endswith(" render: Phase 1 stopped: NaN\n")
    assert cli._call(_command(WriteFailed(28, "out.png: cannot write", "out.png")), args) == 2
    assert "check the paths on the command line" in capsys.readouterr().err
    with pytest.raises(FloatingPointError):  # not the watchdog's
        cli._call(_command(FloatingPointError("overflow")), args)
