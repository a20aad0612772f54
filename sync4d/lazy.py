"""Packages whose public names are imported on first use (PEP 562), so that importing a
package for one light name (a registry, a file name) does not load torch or numpy."""

from __future__ import annotations

from collections.abc import Callable
from importlib import import_module
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(package: str, exports: dict[str, str]) -> tuple[list[str], Callable[[str], Any]]:
    """`__all__` and the module `__getattr__` of `package`, whose public names map to the
    submodule defining each (`exports`: name -> submodule, relative to `package`)."""

    def __getattr__(name: str) -> Any:  # noqa: N807 - the PEP 562 module hook
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(import_module(f"{package}.{exports[name]}"), name)

    return sorted(exports), __getattr__
