"""Hyperparameters: dataclass defaults hold the paper's values; a TOML file (the shipped ones
are in `sync4d/configs/`) and `section.key=value` overrides from the command line replace them.
Sections mirror the phases (`phase1`, `phase2`, `phase3`: each phase defines its own section
class); the run's own settings stand at the top."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from sync4d.data.loaders import offered_splits
from sync4d.phase1.config import Phase1Config
from sync4d.phase2.config import Phase2Config
from sync4d.phase3.config import Phase3Config
from sync4d.settings import ConfigError, allowed, budget_floor, choice, ranged

__all__ = [
    "ConfigError",
    "Phase3Config",
    "config_path",
    "RunConfig",
    "apply_overrides",
    "config_from_dict",
    "load_config",
    "parse_phases",
    "repo_configs",
    "phase2_budget",
    "validate",
    "with_budget",
]


def repo_configs() -> Path:
    """The folder of the shipped config files (`sync4d/configs/`, installed with the package)."""
    return Path(__file__).resolve().parent / "configs"


def config_path(name: str | Path) -> Path:
    """The config file `name` names: a path, or the name of a shipped config ("dnerf" or
    "dnerf.toml" for sync4d/configs/dnerf.toml) when no such path exists."""
    path = Path(name)
    if path.exists() or path.parent != Path("."):
        return path
    shipped = repo_configs() / (path.name if path.suffix == ".toml" else f"{path.name}.toml")
    return shipped if shipped.exists() else path


_PHASES_TEXT = '"1", "2", "3", "1,2", "2,3" or "1,2,3"'


def parse_phases(text: str) -> tuple[int, ...]:
    """The phases of a `phases` value ("1", "2", "3", "1,2", "2,3", "1,2,3") as a sorted tuple
    (contiguous: Phase 3 reads Phase 2's result, Phase 2 Phase 1's)."""
    try:
        phases = tuple(sorted({int(p) for p in str(text).split(",") if p.strip()}))
    except ValueError:
        phases = ()
    if not phases or not set(phases) <= {1, 2, 3} or phases[-1] - phases[0] + 1 != len(phases):
        raise ConfigError(f"phases: expected {_PHASES_TEXT}, got {text!r}")
    return phases


def _phases_problem(text: str) -> str | None:
    """What is wrong with a `phases` value (`parse_phases`'s complaint), None if nothing."""
    try:
        parse_phases(text)
    except ConfigError:
        return f"expected {_PHASES_TEXT}, got {text!r}"
    return None


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything a run (Phase 1, then Phase 2) needs besides the data: one section per phase
    and the run's own settings (which phases, image scale, evaluation and checkpoints)."""

    phase1: Phase1Config = dataclasses.field(default_factory=Phase1Config)
    phase2: Phase2Config = dataclasses.field(default_factory=Phase2Config)
    phase3: Phase3Config = dataclasses.field(default_factory=Phase3Config)
    #: Which phases `fit` runs: "1", "2" (from the run's Phase 1 checkpoint), "3" (the language
    #: field of the run's Phase 2 checkpoint) or a contiguous list such as "1,2".
    phases: str = choice("1,2", check=_phases_problem, text=_PHASES_TEXT)
    #: Image downsampling factor of the dataset (0.5: half width and height).
    resolution_scale: float = ranged(1.0, 0.0, 1.0, lo_open=True)
    #: Which split `fit`/`eval` report on: "test", or "val" for D-NeRF's validation frames
    #: (the splits the dataset loaders offer, `sync4d.data.loaders`).
    test_split: str = choice("test", offered_splits())
    #: Test-split PSNR/SSIM every this many iterations during `fit` (0: only at the end).
    eval_every: int = ranged(1_000, 0, scales=1)
    #: Test frames used by the periodic evaluation (0: all); the final evaluation uses all.
    eval_frames: int = ranged(0, 0)
    #: Atomic checkpoint every this many iterations (0: none in between); always one at the
    #: end and on Ctrl-C.
    checkpoint_every: int = ranged(1_000, 0, scales=1)


def with_budget(cfg: RunConfig, iterations: int) -> RunConfig:
    """`cfg` bounded to `iterations` per phase (`fit --iters N`). Phase 1 trains `iterations`
    instead of `cfg.phase1.iterations`, with every iteration count marked `ranged(...,
    scales=floor)` in it and in the run's cadence (densification start/stop/interval, opacity
    reset, SH degree steps, static and learning-rate warm-ups, coarse iterations, node start
    and refresh, periodic evaluation and checkpoints) scaled by the same ratio, so a shorter
    run still densifies, resets opacities and reaches full SH degree at the same fractions of
    training. Phase 2 trains at most `iterations` (`phase2_budget`). The marks, not a list
    here, say what scales."""
    if iterations < 1:
        raise ConfigError(f"iterations: expected a positive integer, got {iterations}")
    r = iterations / cfg.phase1.iterations
    phase1 = dataclasses.replace(_scale_marked(cfg.phase1, r), iterations=iterations)
    return dataclasses.replace(_scale_marked(cfg, r, sections=False), phase1=phase1,
                               phase2=phase2_budget(cfg.phase2, iterations))  # fmt: skip


def phase2_budget(p2: Phase2Config, iterations: int) -> Phase2Config:
    """`p2` with at most `iterations` iterations. When that shortens it, every iteration count
    marked `ranged(..., scales=floor)` in it (its start and warm-up iterations, and the
    photometric refinement's work: steps per frame, re-tracking steps and texture rounds)
    shrinks by the same ratio, so Phase 2's whole cost is bounded, not only its loop (before
    2026-12-02, `fit --iters 30` still refined for over 5 minutes). The marks, not a list
    here, say what scales: a new term's start scales once its field is marked."""
    if iterations >= p2.iterations:
        return p2
    return dataclasses.replace(_scale_marked(p2, iterations / p2.iterations), iterations=iterations)


def _scale_marked(obj: Any, r: float, sections: bool = True) -> Any:
    """Dataclass `obj` with every field marked `ranged(..., scales=floor)` (`budget_floor`),
    in it and (with `sections`) in its sections, times `r`: rounded, at least `floor`; 0
    stays 0."""
    changes: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            if sections:
                changes[f.name] = _scale_marked(value, r)
        elif (floor := budget_floor(f)) is not None and value > 0:
            changes[f.name] = max(floor, int(round(value * r)))
    return dataclasses.replace(obj, **changes)


def _replace(obj: Any, path: list[str], value: Any, full: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(obj)}
    name = path[0]
    if name not in fields:
        raise ConfigError(f"{full}: unknown key '{name}' (known: {', '.join(sorted(fields))})")
    current = getattr(obj, name)
    if len(path) > 1:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"{full}: '{name}' is a value, not a section")
        return dataclasses.replace(obj, **{name: _replace(current, path[1:], value, full)})
    if dataclasses.is_dataclass(current):
        if not isinstance(value, dict):
            raise ConfigError(f"{full}: '{name}' is a section; set its keys")
        for k, v in value.items():
            current = _replace(current, [k], v, f"{full}.{k}")
        return dataclasses.replace(obj, **{name: current})
    new = _coerce(value, current, full)
    _check(fields[name], new, full)
    return dataclasses.replace(obj, **{name: new})


def _number(value: Any, like: int | float) -> int | float:
    """`value` (a TOML number or a command-line string) as a number of `like`'s type; a bool
    is not a number, and an int takes whole numbers only ("3e4" and 3.0e4 are 30000)."""
    if isinstance(value, bool):
        raise TypeError(value)
    if isinstance(like, float):
        return float(value)
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        try:
            return int(value)
        except ValueError:
            pass
    number = float(value)
    if not number.is_integer():
        raise ValueError(value)
    return int(number)


def _flag(value: Any) -> bool | None:
    """`value` as a TOML bool or a command-line "true"/"false"; None when it is neither."""
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip().lower() in ("true", "false"):
        return value.strip().lower() == "true"
    return None


def _coerce(value: Any, like: Any, full: str) -> Any:
    """`value` (a TOML value or a command-line string) as the type of the field's default
    `like`; ConfigError (naming `full`) when it is not one. A flag takes true or false only
    (not 1), and a number is never a flag (not true)."""
    if isinstance(like, bool):
        if _flag(value) is None:
            raise ConfigError(f"{full}: expected true or false, got {value!r}")
        return _flag(value)
    if isinstance(like, str):
        if isinstance(value, int) and not isinstance(value, bool):
            return str(value)  # phases = 2
        if not isinstance(value, str):
            raise ConfigError(f"{full}: cannot use {value!r} as a str")
        return value
    parts = [value]
    if isinstance(like, tuple):
        if isinstance(value, str):  # "0,0,0", or TOML's own "[0, 0, 0]" (or "(0, 0, 0)")
            text = value.strip()
            if len(text) >= 2 and (text[0], text[-1]) in (("[", "]"), ("(", ")")):
                text = text[1:-1]
            parts = text.split(",")
        else:
            parts = value
        parts = list(parts) if isinstance(parts, list | tuple) else [parts]  # a tuple in code
    flags = [_flag(p) for p in parts if _flag(p) is not None]
    if flags:
        kind = {int: "an integer", float: "a number"}.get(type(like), "numbers")
        raise ConfigError(f"{full}: expected {kind}, got the bool {str(flags[0]).lower()}")
    try:
        if isinstance(like, tuple):
            return tuple(_number(p.strip() if isinstance(p, str) else p, like[0]) for p in parts)
        if isinstance(like, int | float):
            return _number(value, like)
    except (TypeError, ValueError, OverflowError):
        if isinstance(like, tuple):
            form = ",".join(str(x) for x in like)
            raise ConfigError(f"{full}: cannot use {value!r} as {len(like)} numbers; write "
                              f"them as {form} (or [{form}])") from None
        raise ConfigError(f"{full}: cannot use {value!r} as a {type(like).__name__}") from None
    return value


def _check(field: dataclasses.Field, value: Any, key: str) -> None:
    """Raise ConfigError when `value` is outside what `field` declares (`sync4d.settings`)."""
    rule = allowed(field)
    if rule is None:
        return
    problem = rule.problem(value)
    if problem is not None:
        raise ConfigError(f"{key}: {problem}")


def validate(cfg: RunConfig, source: str | None = None) -> None:
    """Raise ConfigError naming the key, the value and the allowed values when a value of `cfg`
    (any section) is outside its field's declared range or choices (`sync4d.settings`), a flag
    is not a bool, or a section's settings do not go together (its `combination_problem`,
    asked once the section's values are each in range: the rules that span two settings,
    listed in each section's docs); `source` (a file name, "--set") leads the message. The
    one place ranges are checked: the trainers take their configs as given."""
    prefix = f"{source}: " if source else ""

    def walk(obj: Any, path: str) -> None:
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            key = f"{path}{f.name}"
            if dataclasses.is_dataclass(value):
                walk(value, f"{key}.")
            elif isinstance(f.default, bool) and not isinstance(value, bool):
                raise ConfigError(f"{prefix}{key}: must be true or false, got {value!r}")
            else:
                _check(f, value, f"{prefix}{key}")
        # after every value's own range, so a rule may assume them in range
        combination = getattr(obj, "combination_problem", None)
        if combination is not None and (problem := combination()) is not None:
            raise ConfigError(f"{prefix}{path}{problem}")

    walk(cfg, "")


def apply_overrides(cfg: RunConfig, overrides: list[str]) -> RunConfig:
    """`cfg` with `section.key=value` overrides applied in order, each checked against its
    field's range (`validate`), as `load_config` checks a file's values."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item}: overrides look like section.key=value")
        key, value = item.split("=", 1)
        cfg = _replace(cfg, key.strip().split("."), value.strip(), f"--set {key.strip()}")
    validate(cfg)
    return cfg


def config_from_dict(data: dict, source: str) -> RunConfig:
    """The config a dict of sections and keys describes (a parsed TOML file, or the `config`
    entry of a run record), on top of the defaults; `source` names it in errors."""
    cfg = RunConfig()
    for k, v in data.items():
        cfg = _replace(cfg, [k], v, f"{source}: {k}")
    validate(cfg, source)
    return cfg


def _read_toml(path: Path) -> dict[str, Any]:
    """The table of the TOML file at `path`; ConfigError for a missing, unreadable, non-text or
    malformed file, or a folder."""
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder, expected a .toml file")
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file is missing") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the config file ({e.strerror or e})") from None
    try:
        if b"\0" in raw:
            raise UnicodeError("NUL byte")
        text = raw.decode("utf-8")
    except UnicodeError:
        raise ConfigError(f"{path}: is not a text TOML file (binary or not UTF-8)") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML ({e})") from None


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> RunConfig:
    """Defaults, then the TOML file at `path` (if any; a shipped config's name such as "dnerf"
    works too, `config_path`), then `section.key=value` overrides; every value is checked
    against its field's range or choices (`validate`), the file's as the overrides'."""
    cfg = RunConfig()
    if path is not None:
        path = config_path(path)
        cfg = config_from_dict(_read_toml(path), str(path))
    return apply_overrides(cfg, overrides or [])
