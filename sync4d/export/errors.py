"""The error of the export room: a splat or scene file that cannot be written or read."""

from __future__ import annotations

from pathlib import Path

from sync4d.errors import Sync4dError

__all__ = ["ExportError"]


class ExportError(Sync4dError, ValueError):
    """A file of the export room that is malformed, truncated, foreign or cannot be written;
    the message names the file (`path`), says what is wrong and what to do."""

    def __init__(self, path: str | Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        #: The file the error is about (a zip member as ``ZIP:MEMBER``).
        self.path = str(path)
