"""The serve tests keep the descriptions their servers build (`sync4d.serve.cache`,
``$SYNC4D_SERVE_CACHE``) in a folder of the session, never in the user's cache; the servers
they start inherit it."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest


@pytest.fixture(scope="session", autouse=True)
def _session_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    previous = os.environ.get("SYNC4D_SERVE_CACHE")
    os.environ["SYNC4D_SERVE_CACHE"] = str(tmp_path_factory.mktemp("sync4d-cache"))
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("SYNC4D_SERVE_CACHE", None)
        else:
            os.environ["SYNC4D_SERVE_CACHE"] = previous
