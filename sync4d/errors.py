"""The one root of sync4d's errors: a problem the user can fix.

Design. Every error that the library raises for the user to read derives from `Sync4dError`:
a bad config or override (`sync4d.settings.ConfigError`), a dataset, run folder, checkpoint,
language field, encoder, question or scene file that cannot be used, a file that cannot be
written, a run folder another process holds, the watchdog's stop on a NaN or a diverged value,
a serve tool's refusal. Its message is one sentence that names the thing and says what to
do; `exit_code` is the command's exit status for it (2; 3 for training that diverged, the
watchdog's `sync4d.watchdog.NonFinite` and `sync4d.pipeline.fit.TrainingDiverged`).

The front ends catch the root once, where a tuple of classes stood before (issue 63): a
command prints ``f"{command}: {e}"`` on stderr and returns ``e.exit_code``; `sync4d.cli` does
the same, with the program's name, for one that a command does not catch. A new error class
that derives from the root is caught everywhere without touching a front end.

An error keeps the built-in base that code relies on beside the root (multiple inheritance):
`ConfigError` is still a ValueError, `WriteFailed` an OSError, `NonFinite` a
FloatingPointError, so ``except ValueError`` and ``pytest.raises(ValueError)`` hold. What is
not a problem to fix is no `Sync4dError`: `sync4d.pipeline.fit.FitInterrupted` (the user's
Ctrl-C, exit 130, no message) and the programming errors (TypeError, an assertion), which stay
tracebacks. This module is the lowest floor: every room may raise its errors.
"""

from __future__ import annotations

__all__ = ["Sync4dError"]


class Sync4dError(Exception):
    """A problem the user can fix, told in one sentence that says what to do; `exit_code`:
    the command's exit status for it."""

    #: The exit status of a command that stops on this error.
    exit_code: int = 2
