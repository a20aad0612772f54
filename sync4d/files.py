"""Writing into a run folder safely: every file is written under a unique temporary name in its
folder, flushed to disk (`fsync` of the file, then of the folder after the rename), and only
then renamed over the old one, so a kill at any instant leaves either the old file or the new
one, never a half-written one, and two writers never share a temporary name. `RunLock` makes a
process the only writer of a run folder (an OS lock on ``RUN/.lock``, released by the kernel on
any exit, SIGKILL included).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import socket
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from sync4d.errors import Sync4dError

__all__ = [
    "LOCK_FILE",
    "RunBusy",
    "RunLock",
    "WriteFailed",
    "check_writable",
    "file_sha256",
    "write_atomic",
    "write_text_atomic",
    "writer_of",
]

#: The lock file of a run folder: held (flock) by the process writing the run; its text says who.
LOCK_FILE = ".lock"


class WriteFailed(Sync4dError, OSError):
    """A file could not be written (disk full, file-size limit, permissions); the previous
    version of the file, if any, is untouched. The message names the file."""


class RunBusy(Sync4dError, RuntimeError):
    """Another process holds the run folder's lock; the message says which."""


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _new_file_mode(path: Path) -> int:
    """The permissions `path` gets: those of the file it replaces, else what a plain
    `open(path, "w")` gives (0o666 less the umask), not mkstemp's private 0o600."""
    try:
        return path.stat().st_mode & 0o777
    except OSError:
        mask = os.umask(0)
        os.umask(mask)
        return 0o666 & ~mask


def write_atomic(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Write `path` through `write(tmp)` (which writes the whole file at the temporary path
    `tmp`), then fsync it, rename it over `path` and fsync the folder. On any failure the
    temporary file is removed, `path` keeps its previous contents and `WriteFailed` names it."""
    path = Path(path)
    folder = path.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as e:
        raise WriteFailed(e.errno, f"{path}: cannot write ({e.strerror or e})") from None
    os.close(fd)
    tmp = Path(name)
    try:
        os.chmod(tmp, _new_file_mode(path))
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(folder)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(e, (KeyboardInterrupt, SystemExit)):
            raise
        if isinstance(e, OSError) or type(e).__name__ == "SafetensorError":
            reason = getattr(e, "strerror", None) or str(e)
            raise WriteFailed(getattr(e, "errno", None) or errno.EIO,
                              f"{path}: could not be written ({reason})") from None  # fmt: skip
        raise
    return path


def check_writable(folder: str | Path) -> Path:
    """Create `folder` if needed and check a file can be written there (before a long run
    whose results go there); `WriteFailed` names it otherwise."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".sync4d-probe-"):
            pass
    except OSError as e:
        raise WriteFailed(e.errno, f"{folder}: cannot write there ({e.strerror or e})") from None
    return folder


def write_text_atomic(path: str | Path, text: str) -> Path:
    """`write_atomic` of a UTF-8 text file."""
    return write_atomic(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


class RunLock:
    """The exclusive lock of a run folder, held from `acquire` until `release` or the process
    ends. A second holder gets `RunBusy` naming the first (pid, host, command, start time)."""

    #: Lock files this process holds -> (fd, depth): a holder may take its own lock again
    #: (the command line locks a run, then `run_fit` does).
    _held: dict[Path, list[int]] = {}

    def __init__(self, run_dir: str | Path, command: str) -> None:
        self.run_dir = Path(run_dir)
        self.command = command
        self._key: Path | None = None

    def acquire(self) -> RunLock:
        """Take the lock (creating the folder), or raise `RunBusy` / `WriteFailed`."""
        path = self.run_dir / LOCK_FILE
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            key = path.resolve()
            if key in RunLock._held:
                RunLock._held[key][1] += 1
                self._key = key
                return self
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise WriteFailed(e.errno, f"{self.run_dir}: cannot write to the run folder "
                              f"({e.strerror or e})") from None  # fmt: skip
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 4096, 0).decode("utf-8", "replace")
            os.close(fd)
            raise RunBusy(f"{self.run_dir} is in use by {_describe(holder)}; wait for it to "
                          "finish or stop it, or use another --out") from None  # fmt: skip
        info = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "command": self.command,
            "argv": sys.argv,
            "since": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(info) + "\n").encode(), 0)
        RunLock._held[key] = [fd, 1]
        self._key = key
        for stale in self.run_dir.glob(".*.tmp"):  # left by a killed writer; none can be live
            with contextlib.suppress(OSError):
                stale.unlink()
        return self

    def release(self) -> None:
        """Give the lock up (the kernel does so too when the process ends)."""
        if self._key is None:
            return
        held = RunLock._held[self._key]
        held[1] -= 1
        if held[1] == 0:
            del RunLock._held[self._key]
            with contextlib.suppress(OSError):
                os.ftruncate(held[0], 0)
            os.close(held[0])
        self._key = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _describe(holder: str) -> str:
    try:
        info = json.loads(holder)
        return (f"'{info['command']}' (pid {info['pid']} on {info['host']}, since "
                f"{info['since']})")  # fmt: skip
    except (ValueError, KeyError, TypeError):
        return "another process"


def writer_of(run_dir: str | Path) -> str | None:
    """Who holds `run_dir`'s lock ("'fit' (pid 12 on host, since ...)"), None when nobody does
    (readers such as the viewer check, and take no lock)."""
    path = Path(run_dir) / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _describe(os.pread(fd, 4096, 0).decode("utf-8", "replace"))
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


@contextlib.contextmanager
def locked(run_dir: str | Path, command: str) -> Iterator[RunLock]:
    """`with locked(run, "fit"):` hold the run's lock for the block."""
    with RunLock(run_dir, command) as lock:
        yield lock


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of the file at `path`, read in 1 MiB blocks (model and checkpoint
    digests)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
