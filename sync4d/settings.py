"""What each config field accepts, declared beside the field: `ranged` (numbers, and tuples of
numbers, within a range) and `choice` (one of a fixed set of strings) build the
`dataclasses.field` and keep an `Allowed` in its metadata, which `sync4d.config` checks for
values from a file and from ``--set`` alike, and `scripts/gen_docs.py` prints. `ranged(...,
scales=floor)` also marks an iteration count (a start, a warm-up end, steps of work) that a
shorter budget scales (`budget_floor`; `sync4d.config.phase2_budget` scales every field so
marked, so a new one cannot be forgotten).

Standard library only, so every config dataclass (`sync4d.phase1`, `sync4d.phase2`,
`sync4d.config`) may import it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

from sync4d.errors import Sync4dError

__all__ = ["BACKENDS", "Allowed", "ConfigError", "allowed", "budget_floor", "choice", "ranged"]

class ConfigError(Sync4dError, ValueError):
    """A bad config file or override; the message names the key and what to do (here, below
    every config class, so the phases raise it too; `sync4d.config` re-exports it)."""


#: The metadata key of a field's `Allowed`.
KEY = "sync4d.allowed"
#: The metadata key of the floor of a field that scales with the budget (`budget_floor`).
SCALES_KEY = "sync4d.scales"
#: The compositing backends: ``backend=`` of `sync4d.raster` and ``--backend`` (here, light, so
#: that the command line's options need not import the rasterizer).
BACKENDS = ("cpu", "wgpu", "auto")


def _num(x: float) -> str:
    """`x` as written in a range: 1, 0.5, 1e-06, 4294967295."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e16 else repr(float(x))


@dataclasses.dataclass(frozen=True)
class Allowed:
    """The values a config field accepts. Numbers (`kind` "int" or "float"; "tuple" for a
    tuple of `item` numbers, `length` of them or one or more): finite, within `lo`..`hi`
    (None: unbounded; `lo_open`/`hi_open` exclude the end). Strings (`kind` "str"): one of
    `choices`, or what `check` accepts (it returns the problem, None when fine)."""

    kind: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    item: str = "float"
    length: int | None = None
    choices: tuple[str, ...] = ()
    check: Callable[[str], str | None] | None = None
    #: What the values are, in messages ("distance"); default "integer" or "number".
    what: str = ""
    #: `describe`'s text when the rule is `check`'s.
    text: str = ""

    def bounds(self) -> str:
        """The range alone: "in 0..3", ">= 1", "in (0, 1]", "> 0", "" when unbounded."""
        lo, hi = self.lo, self.hi
        ints = (self.item if self.kind == "tuple" else self.kind) == "int"
        if lo is not None and hi is not None:
            if ints and not (self.lo_open or self.hi_open):
                return f"in {_num(lo)}..{_num(hi)}"
            left, right = "(" if self.lo_open else "[", ")" if self.hi_open else "]"
            return f"in {left}{_num(lo)}, {_num(hi)}{right}"
        if lo is not None:
            return f"{'>' if self.lo_open else '>='} {_num(lo)}"
        if hi is not None:
            return f"{'<' if self.hi_open else '<='} {_num(hi)}"
        return ""

    def describe(self) -> str:
        """The accepted values in a few words, for the docs: "0..3", "(0, 1]", ">= 1",
        "3 x [0, 1]", '"se3", "affine", "mlp"'."""
        if self.kind == "str":
            return self.text or ", ".join(f'"{c}"' for c in self.choices)
        bounds = self.bounds().removeprefix("in ") or "any"
        if self.kind == "tuple":
            count = str(self.length) if self.length is not None else "1 or more"
            return f"{count} x {bounds}"
        return bounds

    def _wanted(self, kind: str) -> str:
        """What a number of `kind` must be: "an integer >= 1", "a finite number in [0, 1]"."""
        noun = self.what or ("integer" if kind == "int" else "number")
        article = "an" if noun[0] in "aeiou" else "a"
        wanted = f"{article} {noun}" if kind == "int" else f"{article} finite {noun}"
        return f"{wanted} {self.bounds()}".rstrip()

    def _number_ok(self, value: Any, kind: str) -> bool:
        """Whether `value` is a number of `kind` (an int is a float too), finite, in range."""
        if isinstance(value, bool) or not isinstance(value, int if kind == "int" else int | float):
            return False
        if isinstance(value, float) and not math.isfinite(value):
            return False
        lo, hi = self.lo, self.hi
        below = lo is not None and (value <= lo if self.lo_open else value < lo)
        above = hi is not None and (value >= hi if self.hi_open else value > hi)
        return not (below or above)

    def problem(self, value: Any) -> str | None:
        """What is wrong with `value` ("must be an integer >= 1, got -3"), None if nothing."""
        if self.kind == "str":
            if not isinstance(value, str):
                return f"expected a string, got {value!r}"
            if self.check is not None:
                return self.check(value)
            if value not in self.choices:
                return f"expected one of {', '.join(self.choices)}, got {value!r}"
            return None
        if self.kind == "tuple":
            count = str(self.length) if self.length is not None else "1 or more"
            if (
                not isinstance(value, tuple)
                or not value
                or (self.length is not None and len(value) != self.length)
            ):
                return f"must be {count} numbers, got {value!r}"
            if not all(self._number_ok(v, self.item) for v in value):
                return f"must be {count} numbers, each {self._wanted(self.item)}, got {value!r}"
            return None
        if not self._number_ok(value, self.kind):
            return f"must be {self._wanted(self.kind)}, got {value!r}"
        return None


def ranged(
    default: Any,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    length: int | None = None,
    what: str = "",
    scales: int | None = None,
) -> Any:
    """A dataclass field of number `default` (an int, a float or a tuple of them) whose values
    must be finite and lie in `lo`..`hi` (None: unbounded on that side; `lo_open`/`hi_open`
    exclude the end); a tuple must hold `length` numbers (None: one or more). `scales`: an
    integer field counting iterations that a shorter budget scales by its ratio, to no less
    than `scales` (`budget_floor`); None: the budget leaves it alone."""
    if isinstance(default, bool) or not isinstance(default, int | float | tuple):
        raise TypeError(f"ranged: expected a number or a tuple of numbers, got {default!r}")
    if isinstance(default, tuple):
        item = "int" if all(isinstance(v, int) for v in default) else "float"
        kind = "tuple"
    else:
        kind = item = "int" if isinstance(default, int) else "float"
    rule = Allowed(kind, lo, hi, lo_open, hi_open, item, length, what=what)
    if rule.problem(default) is not None:
        raise ValueError(f"ranged: the default {default!r} {rule.problem(default)}")
    if scales is not None and (kind != "int" or isinstance(scales, bool) or scales < 0):
        raise TypeError(f"ranged: scales needs an integer field and a floor >= 0, got {scales!r}")
    metadata: dict[str, Any] = {KEY: rule}
    if scales is not None:
        metadata[SCALES_KEY] = scales
    return dataclasses.field(default=default, metadata=metadata)


def choice(
    default: str,
    choices: Sequence[str] = (),
    *,
    check: Callable[[str], str | None] | None = None,
    text: str = "",
) -> Any:
    """A dataclass field of string `default` whose values must be one of `choices`, or pass
    `check` (the problem, or None), described as `text` in the docs."""
    rule = Allowed("str", choices=tuple(choices), check=check, text=text)
    if rule.problem(default) is not None:
        raise ValueError(f"choice: the default {default!r}: {rule.problem(default)}")
    return dataclasses.field(default=default, metadata={KEY: rule})


def allowed(field: dataclasses.Field) -> Allowed | None:
    """The `Allowed` declared for `field` by `ranged` or `choice`, None if none was."""
    return field.metadata.get(KEY)


def budget_floor(field: dataclasses.Field) -> int | None:
    """The floor `ranged(..., scales=floor)` declared for `field`, an iteration count that a
    shorter budget scales; None when the budget leaves it alone."""
    return field.metadata.get(SCALES_KEY)
