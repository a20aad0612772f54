"""Rules that span two settings (each section's `combination_problem`): every combination that
trains without effect is refused when the config is read, in one line naming the settings and
the fix; the shipped configs pass at every budget `fit --iters` scales them to."""

from __future__ import annotations

import pytest

from sync4d.config import ConfigError, RunConfig, load_config, repo_configs, validate, with_budget

#: (overrides, what the one-line refusal starts with after "phase...").
REFUSED: list[tuple[list[str], str]] = [
    (["phase1.lambda_l1=0", "phase1.lambda_dssim=0"], "phase1.lambda_l1 = 0 and lambda_dssim"),
    (["phase1.iterations=100", "phase1.static_warmup=100", "phase1.densify.stop=0"],
     "phase1.static_warmup = 100 is not below iterations = 100"),
    (["phase1.densify.start=300", "phase1.densify.stop=200"],
     "phase1.densify.start = 300 is not below densify.stop = 200"),
    (["phase1.iterations=400"], "phase1.densify.start = 500 is not below iterations = 400"),
    (["phase1.motion=nodes", "phase1.iterations=900", "phase1.densify.start=10"],
     "phase1.nodes.init_after = 1000 is not below iterations = 900"),
    (["phase1.static.enabled=true", "phase1.iterations=2000"],
     "phase1.static.start = 3000 is after iterations = 2000"),
    (["phase1.nodes.arap_until=500"], "phase1.nodes.arap_until = 500 is not after init_after"),
    (["phase1.nodes.count=1"], "phase1.nodes.neighbours = 8 exceeds count = 1"),
    (["phase1.nodes.max_count=100"], "phase1.nodes.max_count = 100 is below count = 512"),
    (["phase2.warmup_start=900", "phase2.warmup_end=800"],
     "phase2.warmup_end = 800 is below warmup_start = 900"),
    (["phase2.iterations=100"], "phase2.motion_start = 200 is after iterations = 100"),
    (["phase2.iterations=250"], "phase2.velocity_start = 300 is after iterations = 250"),
    (["phase2.motion.refine_texture_rounds=1"],
     "phase2.motion.refine_texture_rounds = 1 acts only in the refinement"),
    (["phase2.motion.refine_restart_jump=0.1"],
     "phase2.motion.refine_restart_jump = 0.1 acts only in the refinement"),
    (["phase2.motion.init=fit", "phase2.motion.refine_steps=5", "phase2.motion.refine_lr=0.01",
      "phase2.motion.refine_lr_final=0.1"], "phase2.motion.refine_lr_final = 0.1 is above"),
]  # fmt: skip


@pytest.mark.parametrize(("sets", "start"), REFUSED, ids=[r[1][:40] for r in REFUSED])
def test_a_combination_without_effect_is_refused_in_one_line(sets: list[str], start: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_config(None, sets)
    msg = str(e.value)
    assert msg.startswith(start) and "\n" not in msg, msg
    assert "; " in msg and msg.split("; ")[-1].split()[0] in ("raise", "lower", "set"), msg


@pytest.mark.parametrize(
    "sets",
    [
        ["phase1.iterations=400", "phase1.densify.stop=0"],  # densification off
        ["phase1.nodes.arap_until=0"],  # a constant ARAP weight
        ["phase1.nodes.arap_until=500", "phase1.nodes.arap_weight=0"],  # no ARAP
        ["phase2.iterations=0"],  # only M_phi's start
        ["phase2.iterations=100", "phase2.simultaneous=true"],  # every term from the start
        ["phase2.warmup_start=900", "phase2.warmup_end=900"],  # a step, not a ramp
        ["phase1.background=[0,0,0]"],
        ["phase1.background=0,0,0"],
    ],
)
def test_the_same_settings_in_a_combination_that_works_are_accepted(sets: list[str]) -> None:
    load_config(None, sets)


def test_the_shipped_configs_pass_the_rules_at_every_budget() -> None:
    """`fit --iters N` scales the counts of a rule together (rounding keeps their order), so a
    config that passes is never refused for its budget."""
    budgets = sorted({*range(1, 120), *(int(1.1**k) for k in range(50, 130))})
    for cfg in [RunConfig(), *(load_config(p) for p in sorted(repo_configs().glob("*.toml")))]:
        for n in budgets:
            validate(with_budget(cfg, n), f"at {n} iterations")


def test_a_refused_tuple_shows_the_accepted_form() -> None:
    form = r"write them as 1\.0,1\.0,1\.0 \(or \[1\.0,1\.0,1\.0\]\)"
    with pytest.raises(ConfigError, match=form):
        load_config(None, ["phase1.background=black"])
    assert load_config(None, ["phase1.background=[0,0,0]"]).phase1.background == (0.0, 0.0, 0.0)
    assert load_config(None, ["phase1.background=(0, 0.5, 1)"]).phase1.background == \
        (0.0, 0.5, 1.0)  # fmt: skip


def test_a_tuple_value_in_a_dict_is_accepted() -> None:
    """A config dict built in code holds tuples (`dataclasses.asdict`): before, `(1.0, 1.0,
    1.0)` was refused with "write them as 1.0,1.0,1.0"."""
    from sync4d.config import config_from_dict

    cfg = config_from_dict({"phase1": {"background": (0.0, 0.5, 1.0)}}, "code")
    assert cfg.phase1.background == (0.0, 0.5, 1.0)


def test_a_coarse_scale_below_the_ssim_window_is_refused_in_one_line(tmp_path, capsys) -> None:
    """A setting against the images' size (known once the dataset is read): `coarse_scale`
    shrinking the images below the loss's 3x3 SSIM window is refused before training, not a
    traceback from the loss."""
    from support.scenes import small_synthetic
    from sync4d.cli import main
    from sync4d.data import synthetic as syn

    scene = syn.write_synthetic_scene(tmp_path / "scene", small_synthetic(size=24, train_cameras=2))
    code = main(["fit", str(scene), "--out", str(tmp_path / "run"), "--iters", "8", "--threads",
                 "1", "--phases", "1", "--set", "phase1.coarse_scale=0.001", "--set",
                 "phase1.coarse_iterations=4"])  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert code == 2 and "Traceback" not in err, err
    line = err.splitlines()[-1]
    assert "phase1.coarse_scale" in line and "SSIM window" in line and "0.125" in line
