"""Configs: paper defaults, the TOML file, command-line overrides and their errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from sync4d.config import ConfigError, RunConfig, load_config, repo_configs

CONFIGS = repo_configs()


def test_file_matches_the_paper_defaults() -> None:
    cfg = load_config(CONFIGS / "phase1.toml")
    assert cfg == RunConfig()
    assert cfg.phase1.densify.grad_threshold == 2e-4 and cfg.deform.input_dim == 48
    assert (cfg.phase1.lambda_l1, cfg.phase1.lambda_dssim) == (0.8, 0.2)


def test_overrides() -> None:
    cfg = load_config(
        CONFIGS / "phase1.toml",
        ["iterations=3000", "phase1.densify.stop=1000", "phase1.background=0,0,0"],
    )
    assert cfg.iterations == 3000 and cfg.phase1.densify.stop == 1000
    assert cfg.phase1.background == (0.0, 0.0, 0.0)


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="phase1.nope: unknown key 'nope'"):
        load_config(None, ["phase1.nope=1"])
    with pytest.raises(ConfigError, match="iterations: cannot use 'many' as a int"):
        load_config(None, ["iterations=many"])
    with pytest.raises(ConfigError, match="overrides look like"):
        load_config(None, ["iterations"])
    bad = tmp_path / "bad.toml"
    bad.write_text("[phase1\n")
    with pytest.raises(ConfigError, match="bad.toml: invalid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="missing.toml: config file is missing"):
        load_config(tmp_path / "missing.toml")


def test_with_budget_scales_the_schedule_and_overrides_win() -> None:
    from sync4d.config import apply_overrides, with_budget

    cfg = with_budget(load_config(), 3000)
    d = cfg.phase1.densify
    assert cfg.iterations == 3000 and (d.start, d.stop, d.interval) == (50, 1500, 10)
    assert d.opacity_reset_interval == 300 and cfg.phase1.sh_degree_interval == 100
    assert cfg.eval_every == 100 and cfg.checkpoint_every == 100
    assert apply_overrides(cfg, ["eval_every=7"]).eval_every == 7
    with pytest.raises(ConfigError, match="positive"):
        with_budget(cfg, 0)
