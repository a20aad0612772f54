"""What Phase 2 skips on objects that do not move (issue 40): still objects held at the identity
(`phase2.freeze_static`: no M_phi update, no Adam momentum, no refinement visit) and a scene
with no motion at all, whose Phase 2 loop is skipped (`phase2.skip_still_scene`) while its
checkpoint stays a valid Phase 2 run. Each switch changes what is computed (counters).

The moving cases use the oracle Phase 1 of `test_phase2` (D_theta replaced by the synthetic
scene's true motion); the still case is a `fit` of `SyntheticConfig(still=True)`.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from support.oracle import PHASE2_SCENE as SMALL
from support.oracle import OracleGaussians, oracle_points
from sync4d.cli import main
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.geometry import rotvec_to_matrix
from sync4d.phase1.config import Phase1Config
from sync4d.phase2 import MotionStrategy, Phase2Config, phase2_trainer
from sync4d.phase2.diagnostics import diagnostics
from sync4d.phase2.motion import MotionConfig, make_motion, still_objects
from sync4d.pipeline.fit import resume_trainer
from sync4d.runs import load_run

#: A small scene where nothing moves.
STILL = syn.SyntheticConfig(size=48, frames=6, train_cameras=4, test_cameras=1, test_every=3,
                            still=True)  # fmt: skip
#: Every Phase 2 term from iteration 0.
EARLY = dict(motion_start=0, velocity_start=0, residual_start=0, warmup_start=0, warmup_end=2)


def test_still_objects_tells_still_from_moving_and_turning() -> None:
    rng = np.random.default_rng(0)
    x0 = rng.uniform(-1, 1, (40, 3))
    x0[30:] = 0.02 * rng.uniform(-1, 1, (10, 3)) + 0.5  # object 3: small (radius ~0.03)
    labels = np.repeat([0, 1, 2, 3], 10)
    shift = np.array([0.05, -0.02, 0.01])
    positions = []
    for s in np.linspace(0.0, 1.0, 5):
        pos = x0.copy()
        pos[:10] += shift + 8e-4 * s  # 0: a constant offset, spread under the tolerance
        pos[10:20] += [3e-3 * s, 0.0, 0.0]  # 1: spreads 1.5e-3 about its mean
        pos[20] += [0.0, 0.0, 0.1 * s]  # 2: one Gaussian moves, the object is not still
        centre = x0[30:].mean(0)
        rot = rotvec_to_matrix(torch.tensor([0.0, 0.0, 0.04 * s], dtype=torch.float64)).numpy()
        pos[30:] = (x0[30:] - centre) @ rot.T + centre  # 3: turns 0.04 rad, moves < 1e-3
        positions.append(pos)
    assert np.abs(positions[-1][30:] - x0[30:]).max() < 1e-3
    still, linear, offset = still_objects(x0, positions, labels, 5, 1e-3, 0.01)
    assert still.tolist() == [True, False, False, False, True]  # 4 has no Gaussian: still
    # The held transform of 0 is the fit onto its mean positions: its constant offset.
    assert np.allclose(linear[0], np.eye(3), atol=1e-9)
    assert np.allclose(offset[0], shift + 4e-4, atol=1e-9)
    assert np.array_equal(linear[4], np.eye(3)) and not offset[4].any()
    lax, _, _ = still_objects(x0, positions, labels, 5, 1e-3, 0.1, rigid=False)
    assert lax.tolist() == [True, False, False, True, True]
    # All or none: the second frame moves object 2's Gaussian; nothing more is read.
    frames = _Reads(positions)
    none, _, _ = still_objects(x0, frames, labels, 5, 1e-3, 0.01, all_or_none=True)
    assert not none.any() and frames.reads == 2
    frames = _Reads([pos[:10] for pos in positions])
    every, _, _ = still_objects(x0[:10], frames, labels[:10], 2, 1e-3, 0.01, all_or_none=True)
    assert every.all() and frames.reads == 2 * len(positions)  # two passes


class _Reads:
    """A re-iterable list of frames that counts the frames read."""

    def __init__(self, frames: list[np.ndarray]) -> None:
        self.frames, self.reads = frames, 0

    def __iter__(self):
        for f in self.frames:
            self.reads += 1
            yield f


@pytest.mark.parametrize("kind", ["se3", "affine", "mlp"])
def test_held_objects_keep_their_transform_and_get_no_gradient(kind: str) -> None:
    times = np.linspace(0.0, 1.0, 4)
    m = make_motion(MotionConfig(kind=kind, init_std=0.1), 3, times)
    with torch.no_grad():  # move every object away from the identity (the MLP too)
        for p in m.parameters():
            p.add_(0.2)
    held_a = rotvec_to_matrix(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.0]]))
    held_b = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.2, 0.3], [0.0, 0.0, 0.0]])
    m.hold(torch.tensor([False, True, False]), held_a, held_b)
    x0 = torch.randn(9, 3)
    labels = torch.tensor([0, 1, 2] * 3)
    loss = sum((m(x0, labels, float(t)) ** 2).sum() for t in (0.2, 0.7))
    loss = loss + m.smoothness(2) + m.identity_prior(2, torch.tensor([True, True, True]))
    loss.backward()
    x = m(x0, labels, 0.4).detach()
    want = x0[labels == 1] @ held_a[1].T + held_b[1]
    assert torch.allclose(x[labels == 1], want, atol=1e-6)  # at any time
    for name in m.row_params:
        grad = getattr(m, name).grad
        assert (grad[1] == 0).all() and (grad[0] != 0).any(), name
    a, b = m.trajectory()
    assert np.allclose(a[1], held_a[1].numpy(), atol=1e-6)
    assert np.allclose(b[1], held_b[1].numpy(), atol=1e-6)
    if kind != "mlp":  # the tables store the held transform in its rows too
        raw = make_motion(MotionConfig(kind=kind), 3, times)
        raw.load_state_dict(m.state_dict())
        raw.frozen.zero_()
        ra, rb = raw.trajectory()
        assert np.allclose(ra[1], a[1], atol=1e-6) and np.allclose(rb[1], b[1], atol=1e-6)
    state = {f"motion.{k}": v for k, v in m.state_dict().items()}
    fresh = make_motion(MotionConfig(kind=kind), 3, times)
    fresh.load_state(state)  # the flags and transforms travel with M_phi's state
    assert fresh.frozen.tolist() == [False, True, False]
    assert np.allclose(fresh.trajectory()[1][1], b[1], atol=1e-6)
    for key in ("motion.frozen", "motion.held_linear", "motion.held_offset"):
        del state[key]  # a checkpoint from before: nothing held
    fresh.load_state(state)
    assert not fresh.frozen.any()


@pytest.fixture(scope="module")
def oracle(tmp_path_factory: pytest.TempPathFactory):
    """The scene and the Gaussians of `test_phase2`'s oracle (ball and box move, the pillar and
    the ground do not)."""
    scene = load_scene(syn.write_synthetic_scene(tmp_path_factory.mktemp("oracle"), SMALL))
    return (scene, *oracle_points())


def _trainer(oracle, iterations: int = 20, **phase2) -> MotionStrategy:
    scene, points, truth = oracle
    motion = phase2.pop("motion", MotionConfig(init="fit"))
    p2 = Phase2Config(motion=motion, **{**EARLY, **phase2})
    model = OracleGaussians(points, truth)
    return phase2_trainer(model, scene, Phase1Config(), p2, iterations, threads=1)


def test_freeze_holds_still_objects_and_never_a_moving_one(oracle) -> None:
    on = _trainer(oracle, freeze_static=True)
    off = _trainer(oracle, freeze_static=False)
    held = on.frozen.tolist()
    assert not held[1] and not held[2]  # the ball and the box move
    assert held[3]  # the pillar does not
    assert not off.frozen.any()
    start = {name: getattr(on.motion, name).detach().clone() for name in on.motion.row_params}
    for _ in range(6):
        on.trainer.step()
        off.trainer.step()
    h = int(on.frozen.sum())
    c = on.skip_counts()
    assert (c["held"], c["motion_updates"], c["motion_updates_skipped"]) == (h, 6 * (4 - h), 6 * h)
    assert off.skip_counts()["motion_updates_skipped"] == 0
    assert off.skip_counts()["motion_updates"] == 6 * 4
    # Held rows stay exactly as held, with no Adam moment; trained ones left the fit.
    for name in on.motion.row_params:
        p = getattr(on.motion, name)
        assert torch.equal(p[on.frozen], start[name][on.frozen])
        st = on.motion_optimizer.state[p]
        assert not st["exp_avg"][on.frozen].any() and not st["exp_avg_sq"][on.frozen].any()
    assert off.motion.translations[3].abs().max() > 1e-4
    assert all(torch.isfinite(p).all() for p in on.trainer.model.parameters())
    ex = on.motion_export()  # D_theta leaves the pillar in place: its fit is the identity
    assert np.allclose(ex["rotations"][3], np.eye(3), atol=1e-6)
    assert np.allclose(ex["translations"][3], 0.0, atol=1e-6)
    d = diagnostics(on, shuffles=0)
    assert [o["held"] for o in d["objects"]] == held


def test_freeze_changes_moving_objects_only_through_the_rigid_share(oracle) -> None:
    """Without the rigid-share hinge and the modulation (the terms that average over every
    Gaussian), the moving objects' M_phi rows train bit for bit as without the switch."""
    rows = {}
    for freeze in (True, False):
        tr = _trainer(oracle, freeze_static=freeze, hinge=False, modulation=False)
        for _ in range(5):
            tr.trainer.step()
        rows[freeze] = (tr.motion.rotvecs[1:3].detach(), tr.motion.translations[1:3].detach())
    assert all(torch.equal(a, b) for a, b in zip(rows[True], rows[False], strict=True))


def test_momentum_does_not_move_objects_held_at_a_reassignment(oracle) -> None:
    tr = _trainer(oracle, freeze_static=False)
    for _ in range(3):
        tr.trainer.step()
    pillar = tr.motion.translations[3].detach().clone()
    st = tr.motion_optimizer.state[tr.motion.translations]
    assert pillar.abs().max() > 0 and st["exp_avg"][3].abs().max() > 0
    tr.phase2 = dataclasses.replace(tr.phase2, freeze_static=True)
    tr.on_gaussians_changed()  # densification's re-assignment decides again
    assert bool(tr.frozen[3]) and not tr.frozen[1:3].any()
    assert not st["exp_avg"][3].any() and not st["exp_avg_sq"][3].any()
    held = tr.motion.translations[3].detach().clone(), tr.motion.rotvecs[3].detach().clone()
    assert held[0].abs().max() < 1e-6  # the pillar's fit: the identity
    for _ in range(3):
        tr.trainer.step()
    assert torch.equal(tr.motion.translations[3], held[0])
    assert torch.equal(tr.motion.rotvecs[3], held[1])


def test_refinement_visits_moving_objects_only(oracle) -> None:
    mc = MotionConfig(init="fit", refine_steps=1, refine_texture_rounds=1, refine_colour_epochs=0)
    tr = _trainer(oracle, freeze_static=True, motion=mc)
    still = (tr.static | tr.frozen).tolist()
    assert still == [True, False, False, True]
    frames = SMALL.frames * 2  # every stored frame, tracked in the first pass and re-tracked
    assert (tr.refine_visits, tr.refine_visits_skipped) == (2 * frames, 2 * frames)
    assert tr.motion.translations[3].abs().max() < 1e-6  # the held pillar: the identity


def _still_fit(tmp_path: Path, name: str, *settings: str) -> Path:
    """`fit --phases 1,2` of a small still scene (Phase 1 with its default settings: D_theta
    is trained on every Gaussian and gives them small offsets)."""
    data = tmp_path / "still"
    if not data.exists():
        syn.write_synthetic_scene(data, STILL)
    run = tmp_path / name
    args = ["fit", str(data), "--out", str(run), "--phases", "1,2", "--iters", "40",
            "--threads", "1", "--set", "eval_every=0", "--set", "phase1.init_points=400",
            "--set", "phase1.init_from=random", "--set", "phase2.iterations=10",
            "--set", "phase2.motion_start=2"]  # fmt: skip
    for s in settings:
        args += ["--set", s]
    assert main(args) == 0
    return run


def _final(run: Path) -> dict:
    lines = (run / "metrics.jsonl").read_text().splitlines()
    return json.loads(lines[-1])["final"]


def test_a_scene_with_no_motion_skips_phase2_and_stays_a_phase2_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = _still_fit(tmp_path, "skip")
    err = capsys.readouterr().err
    line = next(ln for ln in err.splitlines() if "Phase 2 skipped" in ln)
    assert line == "fit: Phase 2 skipped: no object moves (4 static objects)"
    report = next(ln for ln in err.splitlines() if "fit: Phase 2 held" in ln)
    assert "held 4 of 4 objects" in report and "loop of 10 iterations skipped" in report
    skipped = _final(run)["phase2_skipped"]
    assert skipped["loop_skipped"] == 10 and skipped["motion_updates"] == 0
    r = load_run(run)  # a valid Phase 2 checkpoint: M_phi constant in time
    assert r.kind == "sync4d.phase2" and r.iteration == 10
    assert r.motion.frozen.all() and len(r.labels) == r.model.num_gaussians
    rot, trans = r.export["rotations"], r.export["translations"]
    assert np.allclose(rot, rot[:, :1], atol=1e-6) and np.allclose(trans, trans[:, :1], atol=1e-6)
    # A trainer resumed from it holds the same objects, unless the switches are now off.
    ckpt, scene = run / "checkpoint.safetensors", load_scene(tmp_path / "still")
    (p2,) = resume_trainer(ckpt, scene, threads=1, phase2=Phase2Config()).plugins
    assert p2.frozen.all() and torch.equal(p2.motion.held_offset, r.motion.held_offset)
    (p2,) = resume_trainer(ckpt, scene, threads=1,
                           phase2=Phase2Config(skip_still_scene=False)).plugins  # fmt: skip
    assert not p2.frozen.any()
    assert main(["eval", str(run), "--threads", "1"]) == 0
    assert main(["render", str(run), "--time", "0.5", "--no-gif", "--threads", "1"]) == 0
    assert main(["fit", "--out", str(run), "--phases", "3",
                 "--encoder", "offline", "--threads", "1"]) == 0
    capsys.readouterr()
    assert main(["query", str(run), "the green pillar", "--json", "--no-plot"]) == 0
    answers = json.loads(capsys.readouterr().out)
    assert answers["query"] == "the green pillar" and answers["objects"]
    # Resuming finds Phase 2 done.
    data = tmp_path / "still"
    assert main(["fit", str(data), "--out", str(run), "--resume", "--threads", "1"]) == 0
    assert load_run(run).iteration == 10


def test_without_the_switch_the_still_scene_trains_phase2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = _still_fit(tmp_path, "train", "phase2.skip_still_scene=false")
    err = capsys.readouterr().err
    assert "Phase 2 skipped" not in err
    skipped = _final(run)["phase2_skipped"]
    assert skipped["loop_skipped"] == 0 and skipped["held"] == 0
    assert skipped["motion_updates"] > 0 and skipped["motion_updates"] % 4 == 0  # K = 4 rows
    r = load_run(run)
    assert r.iteration == 10 and not r.motion.frozen.any()


def test_phase2_ignores_phase1s_coarse_iterations_and_late_pruning(oracle) -> None:
    """Phase 2 refines at full resolution and changes rows only through its own `densify`,
    whatever Phase 1's coarse and pruning switches say."""
    scene, points, truth = oracle
    densify = dataclasses.replace(Phase1Config().densify, prune_after_stop=True)
    p1 = Phase1Config(coarse_iterations=100, densify=densify)
    p2 = Phase2Config(motion=MotionConfig(init="fit"), **EARLY)
    tr = phase2_trainer(OracleGaussians(points, truth), scene, p1, p2, 5, threads=1).trainer
    assert not tr.coarse() and not tr.densifier.config.prune_after_stop
    tr.step()
    assert tr.coarse_pixels == 0 and tr.pixels > 0
