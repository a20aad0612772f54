"""`sync4d.files`: atomic writes keep the permissions a plain write would give."""

from __future__ import annotations

import os
from pathlib import Path

from sync4d.files import write_atomic, write_text_atomic


def test_atomic_files_get_the_umask_mode_or_keep_the_old_one(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        new = write_text_atomic(tmp_path / "new.json", "{}\n")
        assert new.stat().st_mode & 0o777 == 0o644  # not mkstemp's private 0o600
        shared = tmp_path / "shared.bin"
        shared.write_bytes(b"old")
        shared.chmod(0o664)
        write_atomic(shared, lambda tmp: tmp.write_bytes(b"new"))
        assert shared.read_bytes() == b"new" and shared.stat().st_mode & 0o777 == 0o664
        os.umask(0o077)
        assert write_text_atomic(tmp_path / "private", "x").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)
