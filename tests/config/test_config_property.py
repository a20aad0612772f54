"""Whole config sections drawn from their declared ranges (`sync4d.settings.Allowed`, near each
default so a fit stays cheap): every draw is accepted or refused with one line (ConfigError),
never another exception; and accepted Phase 1 sections train a few iterations on a tiny scene
to exit 0 or a one-line refusal (exit 2), never a NaN stop or a traceback."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from support.scenes import small_synthetic
from sync4d.cli import main
from sync4d.config import ConfigError, RunConfig, config_from_dict
from sync4d.data import synthetic as syn
from sync4d.settings import Allowed, allowed


def _number(rule: Allowed, kind: str, default: float) -> st.SearchStrategy:
    """Numbers of `kind` in `rule`'s range within a decade of `default` (0: up to 1)."""
    lo = rule.lo if rule.lo is not None else -math.inf
    hi = rule.hi if rule.hi is not None else math.inf
    near_lo, near_hi = (0.0, 1.0) if default == 0 else sorted((default / 10, default * 10))
    a, b = max(lo, near_lo), min(hi, near_hi)
    if kind == "int":
        a, b = math.ceil(a + (1e-9 if rule.lo_open else 0)), math.floor(b)
        return st.integers(int(a), int(max(a, b)))
    return st.floats(a, b, exclude_min=rule.lo_open and a == lo,
                     exclude_max=rule.hi_open and b == hi)  # fmt: skip


def _value(f: dataclasses.Field, default: Any) -> st.SearchStrategy:
    rule = allowed(f)
    if isinstance(default, bool):
        return st.booleans()
    if rule is None:
        return st.just(default)
    if rule.kind == "str":
        return st.sampled_from(rule.choices) if rule.choices else st.just(default)
    if rule.kind == "tuple":
        return st.tuples(*(_number(rule, rule.item, d) for d in default))
    return _number(rule, rule.kind, default)


def section(obj: Any) -> st.SearchStrategy[dict]:
    """A dict of every setting of dataclass `obj` (its sections too), each drawn."""
    parts = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        parts[f.name] = section(value) if dataclasses.is_dataclass(value) else _value(f, value)
    return st.fixed_dictionaries(parts)


def _accepted_or_one_line(data: dict) -> RunConfig | None:
    try:
        return config_from_dict(data, "drawn")
    except ConfigError as e:
        assert "\n" not in str(e) and str(e).startswith("drawn: "), e
        REFUSED.append(str(e))
        return None


#: The refusals of the draws, newest last (in the assertions' messages).
REFUSED: list[str] = []


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["phase1", "phase2", "phase3"]).flatmap(
    lambda name: section(getattr(RunConfig(), name)).map(lambda d: {name: d})))  # fmt: skip
def test_a_drawn_section_is_accepted_or_refused_in_one_line(data: dict) -> None:
    _accepted_or_one_line(data)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return syn.write_synthetic_scene(tmp_path_factory.mktemp("property") / "scene",
                                     small_synthetic(size=24, frames=4, train_cameras=2))


#: What keeps a drawn Phase 1 cheap (the count of Gaussians), set after the draw.
CHEAP = {"init_points": 150, "init_from": "random", "init_dome_points": 0}


@settings(max_examples=12, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(phase1=section(RunConfig().phase1))
def test_a_drawn_phase1_trains_or_is_refused(scene: Path, tmp_path_factory, phase1: dict) -> None:
    phase1 = {**phase1, **CHEAP, "deform": {**phase1["deform"], "hidden": 16}}
    cfg = _accepted_or_one_line({"phase1": phase1})
    out = tmp_path_factory.mktemp("fit")
    path = out / "drawn.toml"
    path.write_text(_toml({"phase1": phase1, "eval_every": 0, "checkpoint_every": 0}))
    with contextlib.redirect_stderr(io.StringIO()) as err:
        code = main(["fit", str(scene), "--out", str(out / "run"), "--config", str(path),
                     "--iters", "8", "--threads", "1", "--phases", "1"])  # fmt: skip
    text = err.getvalue()
    assert "Traceback" not in text and code in (0, 2), (code, text[-2000:])
    refusals = [ln for ln in text.splitlines() if "drawn.toml: " in ln]
    if code == 2:  # refused up front in one line (as read, or once --iters scaled it)
        assert len(refusals) == 1, text[-2000:]
    else:
        assert cfg is not None and not refusals, (REFUSED[-1:], text[-2000:])
    ACCEPTED.append(code == 0)


#: Whether each drawn Phase 1 trained (True) or was refused (a check that both happen).
ACCEPTED: list[bool] = []


def test_the_draws_both_train_and_are_refused() -> None:
    assert not ACCEPTED or (any(ACCEPTED) and not all(ACCEPTED)), ACCEPTED


def _toml(data: dict, prefix: str = "") -> str:
    """`data` as TOML (tables after the keys)."""
    def literal(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, tuple):
            return "[" + ", ".join(literal(x) for x in v) + "]"
        return repr(v)

    keys = [f"{k} = {literal(v)}" for k, v in data.items() if not isinstance(v, dict)]
    tables = [f"\n[{prefix}{k}]\n" + _toml(v, f"{prefix}{k}.") for k, v in data.items()
              if isinstance(v, dict)]  # fmt: skip
    return "\n".join(keys) + "\n" + "".join(tables)
