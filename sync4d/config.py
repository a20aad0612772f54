"""Hyperparameters: dataclass defaults hold the paper's values; a TOML file (the shipped ones
are in `sync4d/configs/`) and `section.key=value` overrides from the command line replace them.
Sections mirror the phases (`phase1`, `phase2`); the run's own settings stand at the top."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from sync4d.phase1.trainer import Phase1Config
from sync4d.phase2.trainer import Phase2Config

__all__ = [
    "ConfigError",
    "ALIASES",
    "config_path",
    "RunConfig",
    "apply_overrides",
    "config_from_dict",
    "load_config",
    "parse_phases",
    "repo_configs",
    "phase2_budget",
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


class ConfigError(ValueError):
    """A bad config file or override; the message names the key and what to do."""


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything a run (Phase 1, then Phase 2) needs besides the data: one section per phase
    and the run's own settings (which phases, image scale, evaluation and checkpoints)."""

    phase1: Phase1Config = dataclasses.field(default_factory=Phase1Config)
    phase2: Phase2Config = dataclasses.field(default_factory=Phase2Config)
    #: Which phases `fit` runs: "1", "2" (from the run's Phase 1 checkpoint) or "1,2".
    phases: str = "1,2"
    #: Image downsampling factor of the dataset (0.5: half width and height).
    resolution_scale: float = 1.0
    #: Which split `fit`/`eval` report on: "test", or "val" for D-NeRF's validation frames.
    test_split: str = "test"
    #: Test-split PSNR/SSIM every this many iterations during `fit` (0: only at the end).
    eval_every: int = 1_000
    #: Test frames used by the periodic evaluation (0: all); the final evaluation uses all.
    eval_frames: int = 0
    #: Atomic checkpoint every this many iterations (and always at the end and on Ctrl-C).
    checkpoint_every: int = 1_000

    def __getattr__(self, name: str) -> Any:
        """Read-only spellings of the keys that moved into the phase sections (`ALIASES`):
        ``cfg.iterations`` is ``cfg.phase1.iterations``."""
        if name not in ALIASES:
            raise AttributeError(f"'RunConfig' object has no attribute '{name}'")
        value: Any = self
        for part in ALIASES[name].split("."):
            value = getattr(value, part)
        return value


#: Top-level keys of earlier config files and their place in the phase sections.
ALIASES = {
    "iterations": "phase1.iterations",
    "sh_degree": "phase1.sh_degree",
    "deform": "phase1.deform",
    "near": "phase1.near",
    "init_from": "phase1.init_from",
    "init_points": "phase1.init_points",
    "init_box_fraction": "phase1.init_box_fraction",
    "phase2_iterations": "phase2.iterations",
}


def parse_phases(text: str) -> tuple[int, ...]:
    """The phases of a `phases` value ("1", "2", "1,2") as a sorted tuple."""
    try:
        phases = tuple(sorted({int(p) for p in str(text).split(",") if p.strip()}))
    except ValueError:
        phases = ()
    if not phases or not set(phases) <= {1, 2}:
        raise ConfigError(f"phases: expected 1, 2 or 1,2, got {text!r}")
    return phases


def with_budget(cfg: RunConfig, iterations: int) -> RunConfig:
    """`cfg` bounded to `iterations` per phase (`fit --iters N`). Phase 1 trains `iterations`
    instead of `cfg.phase1.iterations`, with its iteration-based schedules (densification
    start/stop/interval, opacity reset, SH degree steps, static warm-up, periodic evaluation and
    checkpoints) scaled by the same ratio, so a shorter run still densifies, resets opacities
    and reaches full SH degree at the same fractions of training. Phase 2 trains at most
    `iterations` (`phase2_budget`)."""
    if iterations < 1:
        raise ConfigError(f"iterations: expected a positive integer, got {iterations}")
    r = iterations / cfg.phase1.iterations

    def scaled(v: int, floor: int = 1) -> int:
        return max(floor, int(round(v * r)))

    d = cfg.phase1.densify
    densify = dataclasses.replace(
        d,
        start=scaled(d.start, 0),
        stop=scaled(d.stop, 0),
        interval=scaled(d.interval, 10),
        opacity_reset_interval=scaled(d.opacity_reset_interval),
    )
    phase1 = dataclasses.replace(
        cfg.phase1,
        iterations=iterations,
        densify=densify,
        sh_degree_interval=scaled(cfg.phase1.sh_degree_interval),
        static_warmup=scaled(cfg.phase1.static_warmup, 0),
    )
    return dataclasses.replace(
        cfg,
        phase1=phase1,
        phase2=phase2_budget(cfg.phase2, iterations),
        eval_every=scaled(cfg.eval_every) if cfg.eval_every else 0,
        checkpoint_every=scaled(cfg.checkpoint_every) if cfg.checkpoint_every else 0,
    )


def phase2_budget(p2: Phase2Config, iterations: int) -> Phase2Config:
    """`p2` with at most `iterations` iterations. When that shortens it, its start and warm-up
    iterations and the photometric refinement's work (steps per frame, re-tracking steps and
    texture rounds) shrink by the same ratio, so Phase 2's whole cost is bounded, not only its
    loop (before 2026-12-02, `fit --iters 30` still refined for over 5 minutes)."""
    if iterations >= p2.iterations:
        return p2
    r = iterations / p2.iterations

    def scaled(v: int, floor: int = 1) -> int:
        return max(floor, int(round(v * r))) if v > 0 else v

    mc = p2.motion
    motion = dataclasses.replace(
        mc,
        refine_steps=scaled(mc.refine_steps),
        refine_retrack_steps=scaled(mc.refine_retrack_steps),
        refine_texture_rounds=scaled(mc.refine_texture_rounds, 0),
    )
    return dataclasses.replace(
        p2,
        iterations=iterations,
        motion=motion,
        motion_start=scaled(p2.motion_start, 0),
        velocity_start=scaled(p2.velocity_start, 0),
        warmup_start=scaled(p2.warmup_start, 0),
        warmup_end=scaled(p2.warmup_end, 0),
        residual_start=scaled(p2.residual_start, 0),
    )


def _replace(obj: Any, path: list[str], value: Any, full: str) -> Any:
    if isinstance(obj, RunConfig) and path[0] in ALIASES:
        path = ALIASES[path[0]].split(".") + path[1:]
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
    return dataclasses.replace(obj, **{name: _coerce(value, current, full)})


def _coerce(value: Any, like: Any, full: str) -> Any:
    try:
        if isinstance(like, bool):
            if isinstance(value, str):
                if value.lower() not in ("true", "false"):
                    raise ValueError(value)
                return value.lower() == "true"
            return bool(value)
        if isinstance(like, int):
            return int(value)
        if isinstance(like, float):
            return float(value)
        if isinstance(like, tuple):
            parts = value.split(",") if isinstance(value, str) else list(value)
            return tuple(type(like[0])(p) for p in parts)
    except (TypeError, ValueError):
        raise ConfigError(f"{full}: cannot use {value!r} as a {type(like).__name__}") from None
    return value


def apply_overrides(cfg: RunConfig, overrides: list[str]) -> RunConfig:
    """`cfg` with `section.key=value` overrides applied in order."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"{item}: overrides look like section.key=value")
        key, value = item.split("=", 1)
        cfg = _replace(cfg, key.strip().split("."), value.strip(), key.strip())
    return cfg


def config_from_dict(data: dict, source: str) -> RunConfig:
    """The config a dict of sections and keys describes (a parsed TOML file, or the `config`
    entry of a run record), on top of the defaults; `source` names it in errors."""
    cfg = RunConfig()
    for k, v in data.items():
        cfg = _replace(cfg, [k], v, f"{source}: {k}")
    return cfg


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> RunConfig:
    """Defaults, then the TOML file at `path` (if any; a shipped config's name such as "dnerf"
    works too, `config_path`), then `section.key=value` overrides."""
    cfg = RunConfig()
    if path is not None:
        path = config_path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ConfigError(f"{path}: config file is missing") from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"{path}: invalid TOML ({e})") from None
        cfg = config_from_dict(data, str(path))
    return apply_overrides(cfg, overrides or [])
