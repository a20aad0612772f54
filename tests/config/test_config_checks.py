"""Config values get the same checks from a TOML file as from `--set`: every number its declared
range (finite), every string its choices, bools and numbers kept apart, and a `--config` that is
a folder, binary or unreadable one clear ConfigError."""

from __future__ import annotations

import dataclasses
import math
import pathlib
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from sync4d.config import ConfigError, RunConfig, apply_overrides, load_config, with_budget

#: (key as written, TOML literal, --set text, the message after "SOURCE: key: "; a pair when
#: the file's and the command line's differ).
BAD: list[tuple[str, str, str, str | tuple[str, str]]] = [
    ("phase1.iterations", "-3", "-3", "must be an integer >= 1, got -3"),
    ("eval_every", "-1", "-1", "must be an integer >= 0, got -1"),
    ("checkpoint_every", "-1", "-1", "must be an integer >= 0, got -1"),
    ("phase2.iterations", "-4", "-4", "must be an integer >= 0, got -4"),
    ("phase1.sh_degree", "7", "7", "must be an integer in 0..3, got 7"),
    ("phase1.init_points", "-10", "-10", "must be an integer >= 1, got -10"),
    ("phase1.lr_means", "nan", "nan", "must be a finite number > 0, got nan"),
    ("phase1.lr_means", "inf", "inf", "must be a finite number > 0, got inf"),
    ("phase1.iterations", "true", "true", "expected an integer, got the bool true"),
    ("phase1.background", "[true, 1, 1]", "true,1,1", "expected numbers, got the bool true"),
    (
        "phase2.motion.mlp_affine",
        "1",
        "1",
        ("expected true or false, got 1", "expected true or false, got '1'"),
    ),
    ("phases", '"1,3"', "1,3",
     'expected "1", "2", "3", "1,2", "2,3" or "1,2,3", got \'1,3\''),
    ("test_split", '"train"', "train", "expected one of test, val, got 'train'"),
    (
        "phase1.init_from",
        '"sfm"',
        "sfm",
        "expected one of auto, points, triangulate, random, got 'sfm'",
    ),
    ("phase2.motion.kind", '"se4"', "se4", "expected one of se3, affine, mlp, got 'se4'"),
    (
        "phase2.assign.source",
        '"sam"',
        "sam",
        "expected one of auto, masks, trajectories, got 'sam'",
    ),
    ("resolution_scale", "1.5", "1.5", "must be a finite number in (0, 1], got 1.5"),
    ("phase1.near", "-1", "-1", "must be a finite distance > 0, got -1.0"),
    ("phase1.densify.interval", "0", "0", "must be an integer >= 1, got 0"),
    (
        "phase1.background",
        "[0, 2, 0]",
        "0,2,0",
        "must be 3 numbers, each a finite number in [0, 1], got (0.0, 2.0, 0.0)",
    ),
    ("phase1.background", "[0, 0]", "0,0", "must be 3 numbers, got (0.0, 0.0)"),
]


def _write_toml(folder: Path, key: str, literal: str, name: str = "bad.toml") -> Path:
    """A TOML file that sets dotted `key` to the TOML `literal` (`[a.b]` then `c = ...`)."""
    *section, leaf = key.split(".")
    head = f"[{'.'.join(section)}]\n" if section else ""
    path = folder / name
    path.write_text(f"{head}{leaf} = {literal}\n", encoding="utf-8")
    return path


def _refusal(source: str, path: Path, key: str, value: str) -> str:
    """The ConfigError message of setting `key` to `value` from a file at `path` or `--set`."""
    with pytest.raises(ConfigError) as info:
        if source == "file":
            load_config(_write_toml(path, key, value))
        else:
            load_config(None, [f"{key}={value}"])
    return str(info.value)


@pytest.mark.parametrize("source", ["file", "--set"])
@pytest.mark.parametrize(
    ("key", "literal", "text", "message"), BAD, ids=[f"{b[0]}={b[2]}" for b in BAD]
)
def test_a_bad_value_is_refused_naming_source_key_value_and_range(
    tmp_path: Path, source: str, key: str, literal: str, text: str, message: str | tuple
) -> None:
    got = _refusal(source, tmp_path, key, literal if source == "file" else text)
    if isinstance(message, tuple):
        message = message[0] if source == "file" else message[1]
    prefix = f"{tmp_path / 'bad.toml'}: " if source == "file" else "--set "
    assert got == f"{prefix}{key}: {message}"


def test_a_fractional_number_for_an_integer_is_refused_from_a_file(tmp_path: Path) -> None:
    path = _write_toml(tmp_path, "phase1.iterations", "2.5")
    with pytest.raises(ConfigError, match=r"bad.toml: phase1.iterations: cannot use 2.5 as a int"):
        load_config(path)


def test_overrides_after_with_budget_are_checked_too(tmp_path: Path) -> None:
    """`fit --iters N` loads the file, scales it (`with_budget`), then applies the overrides."""
    cfg = with_budget(load_config("synthetic"), 10)
    with pytest.raises(ConfigError, match=r"^--set eval_every: must be an integer >= 0, got -1$"):
        apply_overrides(cfg, ["eval_every=-1"])
    with pytest.raises(ConfigError, match=r"^--set phase1.seed: must be an integer in 0\.\."):
        apply_overrides(cfg, ["phase1.seed=-1"])


def test_validate_names_the_source_of_a_value_set_in_code() -> None:
    from sync4d.config import validate

    bad = dataclasses.replace(RunConfig(), checkpoint_every=-1)
    with pytest.raises(ConfigError, match=r"^run.toml: checkpoint_every: must be an integer >= 0"):
        validate(bad, "run.toml")
    phase2 = dataclasses.replace(RunConfig().phase2, densify=1)
    with pytest.raises(ConfigError, match=r"^phase2.densify: must be true or false, got 1$"):
        validate(dataclasses.replace(RunConfig(), phase2=phase2))
    with pytest.raises(ConfigError, match=r"must be an integer >= 1, got 0"):
        apply_overrides(dataclasses.replace(RunConfig(), phase1=_phase1(iterations=0)), [])


def _phase1(**changes: Any) -> Any:
    return dataclasses.replace(RunConfig().phase1, **changes)


def test_a_folder_as_config_is_one_clear_error(tmp_path: Path) -> None:
    folder = tmp_path / "scene.toml"
    folder.mkdir()
    with pytest.raises(ConfigError, match=re.escape(f"{folder}: is a folder, expected a .toml")):
        load_config(folder)
    with pytest.raises(ConfigError, match="is a folder"):
        load_config(tmp_path)


@pytest.mark.parametrize(
    "content",
    [b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\xff", "iterations = 'caf\xe9'\n".encode("latin-1"),
     b"iterations = 3\x00\n"],
    ids=["binary", "latin-1", "nul-byte"],
)  # fmt: skip
def test_a_binary_or_non_utf8_config_is_one_clear_error(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "image.toml"
    path.write_bytes(content)
    with pytest.raises(ConfigError, match=re.escape(f"{path}: is not a text TOML file")):
        load_config(path)


def test_an_unreadable_config_is_one_clear_error(tmp_path: Path, monkeypatch) -> None:
    path = _write_toml(tmp_path, "iterations", "10", "locked.toml")
    real_open = pathlib.Path.open

    def locked(self: Path, *args: Any, **kwargs: Any):
        if self == path:
            raise PermissionError(13, "Permission denied", str(self))
        return real_open(self, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "open", locked)
    with pytest.raises(ConfigError, match=re.escape(f"{path}: cannot read the config file")):
        load_config(path)


def _leaves(cls: type, prefix: str = "") -> Iterator[tuple[str, dataclasses.Field, Any]]:
    """(dotted key, field, default) of every leaf of config dataclass `cls`, sections walked."""
    for f in dataclasses.fields(cls):
        default = f.default_factory() if f.default is dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            yield from _leaves(type(default), f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f, default


def test_every_numeric_field_declares_a_range_and_every_string_its_choices() -> None:
    from sync4d.settings import allowed

    numbers = 0
    for key, f, default in _leaves(RunConfig):
        rule = allowed(f)
        if isinstance(default, bool):
            assert rule is None, key
        elif isinstance(default, int | float | tuple):
            assert rule is not None, f"{key}: a number without a declared range"
            kind = "tuple" if isinstance(default, tuple) else type(default).__name__
            assert rule.kind == kind, key
            assert rule.lo is not None or rule.hi is not None, f"{key}: unbounded"
            numbers += 1
        elif isinstance(default, str):
            assert rule is not None and (rule.choices or rule.check), f"{key}: no choices"
        else:
            raise AssertionError(f"{key}: a {type(default).__name__} field nothing checks")
    assert numbers >= 80


def test_choices_match_the_values_the_code_acts_on() -> None:
    from sync4d.phase1.init import INIT_SOURCES
    from sync4d.phase2.assign import ASSIGN_SOURCES
    from sync4d.phase2.motion import MOTION_KINDS
    from sync4d.settings import allowed

    rules = {key: allowed(f) for key, f, _ in _leaves(RunConfig)}
    assert rules["phase1.init_from"].choices == INIT_SOURCES
    assert rules["phase2.motion.kind"].choices == MOTION_KINDS
    assert rules["phase2.assign.source"].choices == ASSIGN_SOURCES


def _outside(rule: Any, default: Any) -> list[Any]:
    """Values just outside `rule`'s range (and nan for a float) in `default`'s type."""
    one = (lambda v: v) if rule.kind != "tuple" else (lambda v: (v,) * len(default))
    step = 1 if (rule.item if rule.kind == "tuple" else rule.kind) == "int" else 0.5
    out = []
    if rule.lo is not None:
        out.append(one(rule.lo if rule.lo_open else rule.lo - step))
    if rule.hi is not None:
        out.append(one(rule.hi if rule.hi_open else rule.hi + step))
    if step != 1:
        out.append(one(math.nan))
    return out


def _toml(value: Any) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return "nan" if isinstance(value, float) and math.isnan(value) else repr(value)


NUMERIC = [
    (key, f, default)
    for key, f, default in _leaves(RunConfig)
    if isinstance(default, int | float | tuple) and not isinstance(default, bool)
]


@pytest.mark.parametrize(("key", "field", "default"), NUMERIC, ids=[k for k, _, _ in NUMERIC])
def test_every_bound_is_enforced_alike_from_a_file_and_from_set(
    tmp_path: Path, key: str, field: dataclasses.Field, default: Any
) -> None:
    from sync4d.settings import allowed

    rule = allowed(field)
    assert rule is not None
    for value in _outside(rule, default):
        text = ",".join(map(repr, value)) if isinstance(value, tuple) else repr(value)
        from_file = _refusal("file", tmp_path, key, _toml(value))
        from_set = _refusal("--set", tmp_path, key, text)
        tail = from_set.removeprefix(f"--set {key}: ")
        assert from_file == f"{tmp_path / 'bad.toml'}: {key}: {tail}"
        assert tail.startswith("must be ") and ", got " in tail, tail
    number = int if (rule.item if rule.kind == "tuple" else rule.kind) == "int" else float
    for edge, is_open in ((rule.lo, rule.lo_open), (rule.hi, rule.hi_open)):
        if edge is not None and not is_open:  # a closed end is allowed, from both
            value: Any = number(edge)
            value = (value,) * len(default) if isinstance(default, tuple) else value
            sources = ((_write_toml(tmp_path, key, _toml(value)), None),
                       (None, [f"{key}={_toml(value).strip('[]')}"]))  # fmt: skip
            for path, sets in sources:
                try:
                    cfg = load_config(path, sets) if sets else load_config(path)
                except ConfigError as e:
                    # the edge is in range; a section's rule across settings may still refuse
                    # it beside the other settings' defaults (phase1.nodes.count = 1 with 8
                    # neighbours): that message names the combination, never the bound
                    msg = str(e)
                    assert "must be" not in msg, msg
                    assert any(w in msg for w in ("exceeds", "needs", "below")), msg
                    continue
                assert _get(cfg, key) == value


def _get(cfg: Any, key: str) -> Any:
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def test_the_defaults_and_the_shipped_configs_validate() -> None:
    from sync4d.config import repo_configs, validate

    validate(RunConfig())
    shipped = sorted(repo_configs().glob("*.toml"))
    assert len(shipped) >= 4
    for path in shipped:
        cfg = load_config(path)
        validate(cfg, path.name)
        for iterations in (1, 7, 100, 100_000):  # every budget `fit --iters` may scale it to
            validate(with_budget(cfg, iterations), f"{path.name} at {iterations} iterations")
