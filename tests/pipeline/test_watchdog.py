"""The watchdog (`sync4d.watchdog`): a NaN injected into each phase stops it with one message
naming the tensor, the iteration and the rows, and the run keeps a loadable, finite checkpoint
(the state before the failure, or the last good one); never a poisoned one."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from support.datasets import write_blender
from support.scenes import small_synthetic
from sync4d import watchdog
from sync4d.cli import main
from sync4d.config import RunConfig
from sync4d.data import synthetic as syn
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.nodes import NodeConfig
from sync4d.runs import CHECKPOINT_NAME, read_checkpoint

SETTINGS = ["--iters", "12", "--threads", "1", "--set", "phase1.init_points=300", "--set",
            "eval_every=0", "--set", "phase2.iterations=8", "--set", "phase2.motion_start=2",
            "--set", "checkpoint_every=3"]  # fmt: skip


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("watchdog") / "tiny"
    write_blender(root, n=4, size=24)
    return root


@pytest.fixture(scope="module")
def moving(tmp_path_factory) -> Path:
    """The embedded scene, small: its objects move, so Phase 2 trains and refines."""
    return syn.write_synthetic_scene(tmp_path_factory.mktemp("watchdog") / "objects",
                                     small_synthetic())


OBJECTS = ["--set", "phase1.init_points=3000", "--set", "phase1.init_from=random", "--set",
           "phase2.still_position=0", "--set", "phase2.still_rotation=0", "--set",
           "phase2.static_fraction=0"]  # every object counts as moving


def _iteration(run: Path) -> int:
    tensors, meta = read_checkpoint(run / CHECKPOINT_NAME)  # checks every tensor is finite
    assert all(torch.isfinite(t).all() for t in tensors.values() if t.is_floating_point())
    return int(meta["iteration"])


def test_a_nan_gradient_stops_phase1_and_keeps_the_state_before_it(data, tmp_path, capsys):
    run = tmp_path / "run"
    with watchdog.injected("Phase 1", 5, "grad:means"):
        assert main(["fit", str(data), "--out", str(run), *SETTINGS, "--phases", "1"]) == 3
    err = capsys.readouterr().err
    assert "Phase 1 stopped at iteration 5: the gradient of 'means' is NaN or inf in 1 " \
           "Gaussians (0)" in err, err
    assert "Try: lower the learning rates" in err and "after iteration 4 is saved" in err
    assert "Traceback" not in err
    assert _iteration(run) == 4
    assert main(["fit", "--out", str(run), "--resume", "--threads", "1"]) == 0  # it goes on


def test_a_nan_after_the_optimizer_step_keeps_the_last_good_checkpoint(data, tmp_path, capsys):
    run = tmp_path / "run"
    with watchdog.injected("Phase 1", 8, "param:quats"):
        assert main(["fit", str(data), "--out", str(run), *SETTINGS, "--phases", "1"]) == 3
    err = capsys.readouterr().err
    assert "iteration 8: the value of 'quats' is NaN or inf in 1 Gaussians" in err, err
    assert "keeps the last good checkpoint (iteration 6)" in err
    assert _iteration(run) == 6


@pytest.mark.parametrize(("phase", "target"), [("Phase 2", "loss"),
                                               ("Phase 2 refinement", "loss")])
def test_phase2_and_its_refinement_stop_on_a_nan(moving, tmp_path, capsys, phase, target):
    run = tmp_path / "run"
    refine = ["--set", "phase2.motion.init=fit", "--set", "phase2.motion.refine_steps=2"]
    iteration = 3 if phase == "Phase 2" else 0  # the refinement counts stored frames
    with watchdog.injected(phase, iteration, target):
        assert main(["fit", str(moving), "--out", str(run), *SETTINGS, *OBJECTS, *refine]) == 3
    err = capsys.readouterr().err
    assert f"{phase} stopped at iteration {iteration}: the loss is NaN or inf" in err, err
    assert "Try: lower" in err and "Traceback" not in err
    _iteration(run)  # a finite checkpoint: Phase 1's, or Phase 2's state before the failure


def test_phase3_stops_on_a_nan_in_its_solve(moving, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["fit", str(moving), "--out", str(run), *SETTINGS, *OBJECTS]) == 0
    with watchdog.injected("Phase 3", 0, "array:the ridge map W_k"):
        assert main(["fit", "--out", str(run), "--phases", "3", "--threads", "1"]) == 3
    err = capsys.readouterr().err
    assert "Phase 3 stopped: the ridge map W_k is NaN or inf in 1 objects (0)" in err, err
    assert "ridge_lambda" in err and not (run / "phase3" / "field.json").exists()
    # What Phase 3's crop renders, `eval` and `render` receive is checked too: a NaN there is
    # the watchdog's one message and exit 3, not the rasteriser's ValueError.
    cases = [("Phase 3 observation", ["fit", "--out", str(run), "--phases", "3"]),
             ("Evaluation", ["eval", str(run)]),
             ("Rendering", ["render", str(run), "--time", "0.5", "--out", str(tmp_path / "r")])]
    for phase, args in cases:
        with watchdog.injected(phase, None, "input:means"):
            assert main([*args, "--threads", "1"]) == 3, phase
        err = capsys.readouterr().err
        assert f"{phase} stopped: the deformed means ('means') is NaN or inf in 1 Gaussians " \
            "(0)" in err and "Try: " in err and "Traceback" not in err, err
    _iteration(run)


def test_the_checks_name_the_rows():
    good = {"means": torch.zeros(5, 3, requires_grad=True)}
    good["means"].grad = torch.zeros(5, 3)
    watchdog.check_grads("Phase 1", 1, good)
    good["means"].grad[[1, 3], 2] = float("inf")
    with pytest.raises(watchdog.NonFinite, match=r"'means' is NaN or inf in 2 elements \(1, 3\)"):
        watchdog.check_grads("Phase 1", 1, good)
    large = {"w": torch.full((4,), 9e3)}  # within +-1e4: trained, if unusual
    watchdog.check_params("Phase 2", 2, large)
    large["w"][2] = float("nan")
    with pytest.raises(watchdog.NonFinite, match=r"value of 'w' is NaN or inf in 1 elements \(2\)"):
        watchdog.check_params("Phase 2", 2, large)
    huge = {"w": torch.tensor([0.0, -3e38, 1.0, 2e4])}  # finite, but diverged
    with pytest.raises(watchdog.NonFinite, match=r"'w' diverged \(finite, but beyond \+-1e\+04.*"
                       r"in 2 elements \(1, 3\)"):  # fmt: skip
        watchdog.check_params("Phase 2", 2, huge)
    # Positions are bounded relative to the scene's scale, and only when it is known.
    far = {"means": torch.tensor([[0.0, 0.0, 5e6], [1.0, 2.0, 3.0]])}
    watchdog.check_inputs("Evaluation", None, far)
    watchdog.check_inputs("Phase 1", 3, far, scale=10.0)
    with pytest.raises(watchdog.NonFinite, match=r"deformed means \('means'\) diverged .*1e\+06 "
                       r"times the scene's scale \(4\).* in 1 Gaussians \(0\)"):  # fmt: skip
        watchdog.check_inputs("Phase 1", 3, far, scale=4.0)
    with pytest.raises(watchdog.NonFinite, match=r"Phase 3 stopped: W is NaN or inf in 1 objects"):
        watchdog.check_array("Phase 3", "W", np.array([[0.0, 1.0], [np.nan, 2.0]]))


def _setting_exists(key: str) -> bool:
    node: object = RunConfig()
    for part in key.split("."):
        if not dataclasses.is_dataclass(node) or part not in {f.name for f in
                                                              dataclasses.fields(node)}:
            return False
        node = getattr(node, part)
    return True


def test_every_setting_the_watchdog_names_exists():
    """Each setting a message suggests (`SETTINGS`, and every ``phaseN.key`` in `HINTS`) is a
    real key of the config classes (the Phase 1 hint once named `phase1.lr_position`)."""
    named = {s for settings in watchdog.SETTINGS.values() for s in settings}
    for hint in watchdog.HINTS.values():
        named |= set(re.findall(r"\b(phase[123](?:\.\w+)+)", hint))
    assert "phase1.lr_means" in named and "phase2.motion.refine_lr" in named
    missing = sorted(s for s in named if not _setting_exists(s))
    assert not missing, missing
    # every parameter of a Phase 1 / Phase 2 model has its settings
    for name in ("means", "log_scales", "deform.trunk.0.weight", "nodes.log_radii",
                 "motion.rotation", "input:scales", "input:node_shifts"):  # fmt: skip
        assert watchdog.settings_for(name), name


def test_a_nan_in_what_the_rasteriser_receives_keeps_the_last_good_checkpoint(data, tmp_path,
                                                                              capsys):
    run = tmp_path / "run"
    with watchdog.injected("Phase 1", 5, "input:scales"):
        assert main(["fit", str(data), "--out", str(run), *SETTINGS, "--phases", "1"]) == 3
    err = capsys.readouterr().err
    assert "Phase 1 stopped at iteration 5: the activated scales (exp of the deformed " \
           "log-scales) ('scales') is NaN or inf in 1 Gaussians (0)" in err, err
    assert "--set phase1.lr_scales=..." in err and "Traceback" not in err
    assert "keeps the last good checkpoint (iteration 3)" in err
    assert _iteration(run) == 3


def test_an_overflowing_log_scale_stops_before_the_rasteriser():
    """A finite log-scale whose exponential overflows float32 is the parameter check's
    failure, not the rasteriser's ValueError at the next render."""
    params = {"log_scales": torch.zeros(4, 3)}
    watchdog.check_params("Phase 1", 2, params)
    params["log_scales"][2, 1] = 100.0
    with pytest.raises(watchdog.NonFinite, match=r"activated value \(exp\) of 'log_scales' is "
                       r"NaN or inf in 1 elements \(2\).*--set phase1.lr_scales="):
        watchdog.check_params("Phase 1", 2, params)


#: Every learning rate of the config classes (not the schedules' final values and warm-ups),
#: with what a run needs to use it.
LEARNING_RATES = {
    **{f"phase1.{f.name}": [] for f in dataclasses.fields(Phase1Config)
       if f.name.startswith("lr_") and not f.name.endswith(("_final", "_warmup"))},
    **{f"phase1.nodes.{f.name}": ["--set", "phase1.motion=nodes", "--set",
                                  "phase1.nodes.init_after=2", "--set", "phase1.nodes.count=32"]
       for f in dataclasses.fields(NodeConfig) if f.name.startswith("lr_")},
    "phase2.motion.lr": ["--phases", "1,2"],
    "phase2.motion.refine_lr": ["--phases", "1,2", "--set", "phase2.motion.init=fit",
                                "--set", "phase2.motion.refine_steps=2"],
}  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("key", sorted(LEARNING_RATES))
def test_a_learning_rate_of_1e9_ends_cleanly(moving, tmp_path, capsys, key):
    """Issue 53's acceptance: `fit --set KEY=1e9` on the embedded scene ends with the
    watchdog's message and exit status 3 and a loadable, finite checkpoint; never a traceback,
    never a run that trains on. Where the rate cannot make a value non-finite (Adam's steps
    are bounded by the rate, rotations are normalised, opacities squashed) the value has
    diverged while finite, and the watchdog says so."""
    run = tmp_path / "run"
    args = ["fit", str(moving), "--out", str(run), *SETTINGS, *OBJECTS, "--set", f"{key}=1e9",
            *LEARNING_RATES[key]]  # fmt: skip
    if "--phases" not in args:
        args += ["--phases", "1"]
    code = main(args)
    err = capsys.readouterr().err
    assert code == 3 and "Traceback" not in err, (code, err)
    assert "stopped at iteration" in err and "Try: " in err, err
    assert "Nothing poisoned was saved" in err or "last good checkpoint" in err, err
    assert f"--set {key}=..." in err, err  # the setting to change is named
    _iteration(run)  # loadable, every tensor finite


def test_a_nan_in_an_evaluation_render_is_the_watchdogs_message(data, tmp_path, capsys):
    """The final evaluation renders D_theta at test times training did not visit: a NaN there
    is the watchdog's message and exit 3, not the rasteriser's ValueError."""
    run = tmp_path / "run"
    with watchdog.injected("Evaluation", None, "input:means"):
        assert main(["fit", str(data), "--out", str(run), *SETTINGS, "--phases", "1"]) == 3
    err = capsys.readouterr().err
    assert "Evaluation stopped: the deformed means ('means') is NaN or inf in 1 Gaussians (0)" \
        in err, err
    assert "--set phase1.lr_deform=..." in err and "Traceback" not in err
    _iteration(run)


#: Phase 2's initial value: M_phi's tables start at N(0, init_std) (the paper's identity start).
INITIAL_VALUES = {"phase2.motion.init_std": ["--phases", "1,2", "--set",
                                            "phase2.motion.init=identity"]}  # fmt: skip


@pytest.mark.slow  # 20 fits of the small scene: about 40 s
@settings(max_examples=20, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(key=st.sampled_from(sorted({**LEARNING_RATES, **INITIAL_VALUES})),
       exponent=st.integers(-8, 12))  # fmt: skip
def test_any_rate_or_initial_value_ends_finite_or_with_the_watchdog(moving, tmp_path_factory,
                                                                    key, exponent):  # fmt: skip
    """Whole fits through Phase 1, Phase 2 and the refinement with one learning rate or
    initial value anywhere in 1e-8 .. 1e12 (issue 53): exit 0 with a finite checkpoint, or the
    watchdog's message and exit 3; never another exception (the trainer-level property test,
    tests/phase1/test_training_step_properties.py, drives Phase 1's initial values)."""
    run = tmp_path_factory.mktemp("any") / "run"
    extra = {**LEARNING_RATES, **INITIAL_VALUES}[key]
    args = ["fit", str(moving), "--out", str(run), *SETTINGS, *OBJECTS, "--set",
            f"{key}={10.0**exponent:g}", *extra]  # fmt: skip
    if "--phases" not in args:
        args += ["--phases", "1,2"]
    with contextlib.redirect_stderr(io.StringIO()) as err:
        code = main(args)
    assert code in (0, 3) and "Traceback" not in err.getvalue(), (code, err.getvalue())
    if code == 3:
        assert "stopped" in err.getvalue() and "Try: " in err.getvalue(), err.getvalue()
    _iteration(run)
