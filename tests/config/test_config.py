"""Configs: paper defaults, the TOML file, command-line overrides and their errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from sync4d.config import ConfigError, RunConfig, load_config, repo_configs

CONFIGS = repo_configs()


def test_file_matches_the_paper_defaults() -> None:
    cfg = load_config(CONFIGS / "phase1.toml")
    assert cfg == RunConfig()
    assert cfg.phase1.densify.grad_threshold == 2e-4 and cfg.phase1.deform.input_dim == 48
    assert (cfg.phase1.lambda_l1, cfg.phase1.lambda_dssim) == (0.8, 0.2)


def test_overrides() -> None:
    cfg = load_config(
        CONFIGS / "phase1.toml",
        ["phase1.iterations=3000", "phase1.densify.stop=1000", "phase1.background=0,0,0"],
    )
    assert cfg.phase1.iterations == 3000 and cfg.phase1.densify.stop == 1000
    assert cfg.phase1.background == (0.0, 0.0, 0.0)


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="phase1.nope: unknown key 'nope'"):
        load_config(None, ["phase1.nope=1"])
    with pytest.raises(ConfigError, match="phase1.iterations: cannot use 'many' as a int"):
        load_config(None, ["phase1.iterations=many"])
    with pytest.raises(ConfigError, match="overrides look like"):
        load_config(None, ["iterations"])
    for old in ("iterations", "sh_degree", "phase2_iterations"):  # the spellings before 0.1.0
        with pytest.raises(ConfigError, match=f"{old}: unknown key '{old}'"):
            load_config(None, [f"{old}=3"])
    with pytest.raises(AttributeError):
        RunConfig().iterations  # noqa: B018
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
    assert cfg.phase1.iterations == 3000 and (d.start, d.stop, d.interval) == (50, 1500, 10)
    assert d.opacity_reset_interval == 300 and cfg.phase1.sh_degree_interval == 100
    assert cfg.eval_every == 100 and cfg.checkpoint_every == 100
    assert apply_overrides(cfg, ["eval_every=7"]).eval_every == 7
    with pytest.raises(ConfigError, match="positive"):
        with_budget(cfg, 0)


def test_phase2_budget_scales_every_marked_field() -> None:
    """`phase2_budget` scales the fields marked `ranged(..., scales=floor)`, not a list: the
    current ones as the hand-written list did (rounded, at least the floor, 0 stays 0), and
    one declared later without touching `sync4d.config`."""
    import dataclasses

    from sync4d.config import phase2_budget
    from sync4d.phase2.config import Phase2Config
    from sync4d.phase2.motion import MotionConfig
    from sync4d.settings import budget_floor, ranged

    motion = MotionConfig(refine_steps=40, refine_texture_rounds=2, refine_retrack_steps=80)
    p2 = Phase2Config(iterations=1000, motion=motion)
    got = phase2_budget(p2, 60)
    assert got.iterations == 60
    starts = (got.motion_start, got.velocity_start, got.warmup_start, got.warmup_end)
    assert starts == (12, 18, 30, 60) and got.residual_start == 36
    m = got.motion
    assert (m.refine_steps, m.refine_retrack_steps, m.refine_texture_rounds) == (2, 5, 0)
    assert phase2_budget(p2, 2).motion.refine_steps == 1  # floor 1
    assert phase2_budget(Phase2Config(iterations=1000), 60).motion.refine_steps == 0  # 0 stays
    assert phase2_budget(p2, 1000) is p2

    @dataclasses.dataclass(frozen=True)
    class WithNewTerm(Phase2Config):
        lambda_new: float = ranged(0.1, 0.0)
        new_start: int = ranged(400, 0, scales=0)

    new = phase2_budget(WithNewTerm(iterations=1000), 100)
    assert new.new_start == 40 and new.motion_start == 20 and new.lambda_new == 0.1

    # Every start (and the warm-up's end) of Phase 2 is marked.
    for f in dataclasses.fields(Phase2Config):
        if f.name.endswith(("_start", "_end")):
            assert budget_floor(f) == 0, f.name
    tau = next(f for f in dataclasses.fields(Phase2Config) if f.name == "tau")
    assert budget_floor(tau) is None
    with pytest.raises(TypeError, match="scales"):
        ranged(0.5, 0.0, scales=0)


def test_every_iteration_count_of_phase1_and_the_run_is_marked_to_scale() -> None:
    """`with_budget` scales what is marked `ranged(..., scales=floor)`, not a list: every
    integer field of Phase 1's sections and the run's cadence named as an iteration count (a
    start, stop, interval, period, warm-up or coarse length) carries the mark, so a new one
    cannot be forgotten; `iterations` itself is set, not scaled."""
    import dataclasses
    import re

    from sync4d.config import RunConfig
    from sync4d.settings import budget_floor

    counts = re.compile(r"(^|_)(start|stop|interval|every|warmup|after|until|iterations)$")

    def walk(obj, path: str):
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                if f.name not in ("phase2", "phase3"):  # phase2_budget: its own test
                    yield from walk(value, f"{path}{f.name}.")
            elif type(value) is int and counts.search(f.name) and f.name != "iterations":
                yield f"{path}{f.name}", budget_floor(f)

    fields = dict(walk(RunConfig(), ""))
    assert len(fields) >= 12, fields
    assert not [k for k, floor in fields.items() if floor is None], fields


def test_a_list_is_taken_in_toml_s_own_syntax_and_a_bad_one_shows_the_form() -> None:
    """`--set phase1.background=[0,0,0]` (TOML's list) is `0,0,0`; a value that is no list of
    numbers is refused with the form that works."""
    for text in ("[0,0,0]", "0,0,0", "(0, 0, 0)", " [0, 0, 0] "):
        assert load_config(None, [f"phase1.background={text}"]).phase1.background == (0.0,) * 3
    with pytest.raises(ConfigError, match=r"as 3 numbers; write them as 1.0,1.0,1.0 \(or "
                                          r"\[1.0,1.0,1.0\]\)"):  # fmt: skip
        load_config(None, ["phase1.background=black"])
