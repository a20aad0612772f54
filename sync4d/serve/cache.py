"""The scene description `sync4d serve` keeps between starts, outside the run folder, so a
server started again on the same run answers `describe` at once (docs/mcp.md, "How it runs").

Design:

* **Outside the run.** `serve` is read-only on its run folder (its tools say so to the client),
  so the description is kept in sync4d's cache folder (``$SYNC4D_CACHE/serve/``, default
  ``~/.cache/sync4d/serve/``; ``$SYNC4D_SERVE_CACHE`` names another), never in ``RUN/``: the
  run-folder contract (docs/run-folder.md) is untouched, and a run folder on a read-only disk
  is served the same.
* **Invalidated with what it is made of.** An entry's name is a SHA-256 over the run folder's
  resolved path, the size and modification time of every file the description reads (the
  checkpoint, ``run.json``, ``phase2.json``, the field's two files) and of every file of the
  sync4d package (a new version or a local edit of the code that writes the description). A
  refit, a rebuilt field or a new sync4d names another entry; the stale one is never read.
* **Bounded.** At most `KEPT_DESCRIPTIONS` entries; writing one removes the oldest beyond it.
* **Best effort.** A cache folder that cannot be read or written (no home, a full disk) only
  means the description is built again: nothing here raises.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
from pathlib import Path

from sync4d import __version__
from sync4d.data.scene import cache_dir
from sync4d.files import write_text_atomic
from sync4d.runs import names

__all__ = ["KEPT_DESCRIPTIONS", "description_key", "read_description", "write_description"]

#: Scene descriptions kept (one per run and build); the oldest beyond it are removed.
KEPT_DESCRIPTIONS = 16
#: Bumped when what an entry holds changes.
_FORMAT = "sync4d-serve-description-1"
#: The run's files the description is made of (relative to the run folder).
_INPUTS = (names.CHECKPOINT_NAME, names.RUN_FILE, names.PHASE2_FILE,
           f"{names.FIELD_DIR}/{names.FIELD_META}",
           f"{names.FIELD_DIR}/{names.FIELD_FILE}")  # fmt: skip


def _folder() -> Path:
    """``$SYNC4D_SERVE_CACHE``, else ``serve/`` in sync4d's cache folder (`cache_dir`)."""
    return Path(os.environ.get("SYNC4D_SERVE_CACHE") or cache_dir() / "serve")


def _stamp(path: Path) -> str:
    """`path`'s size and modification time (ns), or "-" when it is missing."""
    try:
        st = path.stat()
    except OSError:
        return "-"
    return f"{st.st_size}:{st.st_mtime_ns}"


@functools.cache
def _code() -> str:
    """A digest of the sync4d package's files (names, sizes, modification times), once per
    process: any change to the code invalidates every kept description."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256(__version__.encode())
    for p in sorted(root.rglob("*")):
        if p.suffix in (".py", ".so", ".json") and "__pycache__" not in p.parts:
            h.update(f"{p.relative_to(root)}={_stamp(p)};".encode())
    return h.hexdigest()


def description_key(run_dir: str | Path) -> str:
    """The name of `run_dir`'s description entry (see the module notes)."""
    run = Path(run_dir).resolve()
    h = hashlib.sha256(f"{_FORMAT};{run};{_code()}".encode())
    for name in _INPUTS:
        h.update(f"{name}={_stamp(run / name)};".encode())
    return h.hexdigest()[:40]


def read_description(key: str) -> tuple[str, str] | None:
    """The kept (scene JSON text, prompt) of entry `key`, or None when there is none."""
    path = _folder() / f"{key}.json"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        if data.get("key") != key:
            return None
        scene, prompt = data["scene"], data["prompt"]
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    if not isinstance(scene, str) or not isinstance(prompt, str):
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used: the last to be removed
    return scene, prompt


def write_description(key: str, scene: str, prompt: str) -> None:
    """Keep the scene JSON text and prompt as entry `key` (atomically), then remove the oldest
    entries beyond `KEPT_DESCRIPTIONS`; does nothing when the cache folder is not writable."""
    folder = _folder()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(folder / f"{key}.json",
                          json.dumps({"key": key, "scene": scene, "prompt": prompt}))  # fmt: skip
        entries = sorted(folder.glob("*.json"), key=lambda p: p.stat().st_mtime_ns,
                         reverse=True)  # fmt: skip
        for old in entries[KEPT_DESCRIPTIONS:]:
            old.unlink(missing_ok=True)
    except OSError:
        pass  # best effort: the next start builds the description again
