"""Static Gaussians skip D_theta (`sync4d.phase1.static`): what is computed (row counters), what
is rendered, how the set is found, baked, released, inherited, stored, and a scene with no
motion at all trained without D_theta."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from support.scenes import STILL_SCENE, densify_case, random_gaussians
from sync4d.cli import main
from sync4d.data.synthetic import write_synthetic_scene
from sync4d.geometry import axis_angle_to_quat, quat_multiply
from sync4d.phase1.densify import Densifier, DensifyConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.static import StaticConfig, deformation_spread, update_static_set


class _Motion(torch.nn.Module):
    """A stand-in D_theta: offsets (z[:3] * t + c, z[3:6] * t, z[6:9] * t); Gaussians with
    z[:9] = 0 do not move (a constant offset c is no motion)."""

    def __init__(self, c: float = 0.0) -> None:
        super().__init__()
        self.c = c
        self.calls: list[int] = []

    def forward(self, x0, z, t):
        self.calls.append(x0.shape[0])
        t = torch.as_tensor(t, dtype=x0.dtype)
        return z[:, 0:3] * t + self.c, z[:, 3:6] * t, z[:, 6:9] * t


def _model(n: int = 8, seed: int = 0) -> DeformableGaussians:
    g = torch.Generator().manual_seed(seed)
    model = random_gaussians(n, g)
    with torch.no_grad():
        for p in model.deform.parameters():
            p.normal_(0.0, 0.3, generator=g)
        model.embeddings.normal_(0.0, 1.0, generator=g)
    return model


def test_static_rows_keep_their_canonical_state_and_skip_d_theta() -> None:
    model = _model()
    full = [x.detach().clone() for x in model.at_time(0.7)]
    assert (model.deform_rows, model.deform_rows_skipped) == (8, 0)
    model.static[[1, 4, 6]] = True
    means, quats, scales = model.at_time(0.7)
    assert (model.deform_rows, model.deform_rows_skipped) == (8 + 5, 3)
    moving = ~model.static
    for got, want in zip((means, quats, scales), full, strict=True):
        assert torch.allclose(got[moving], want[moving], atol=1e-6)  # D_theta as before
    q0 = model.quats / model.quats.norm(dim=-1, keepdim=True)
    assert torch.equal(means[model.static], model.means[model.static])
    assert torch.allclose(quats[model.static], q0[model.static])
    assert torch.allclose(scales[model.static], model.log_scales.exp()[model.static])
    # Backward: static rows' embeddings get no gradient, the moving rows' do.
    (means.sum() + scales.sum() + quats[:, 1:].sum()).backward()
    grad = model.embeddings.grad.abs().sum(dim=1)
    assert (grad[model.static] == 0).all() and (grad[moving] > 0).all()
    assert (model.means.grad[model.static] == 1).all()  # the canonical means still learn


def test_a_scene_where_nothing_moves_never_calls_d_theta() -> None:
    model = _model()
    model.deform = _Motion()
    model.static[:] = True
    means, _, _ = model.at_time(0.3)
    assert model.deform.calls == [] and torch.equal(means, model.means)
    assert (model.deform_rows, model.deform_rows_skipped) == (0, 8)


def test_update_marks_still_gaussians_baking_constant_offsets_and_releases_movers() -> None:
    model = _model(6)
    motion = _Motion(c=0.05)  # every Gaussian is offset by 0.05: that alone is no motion
    model.deform = motion
    with torch.no_grad():
        model.embeddings.zero_()
        model.embeddings[0, 0] = 1.0  # moves 1 unit along x over t in [0, 1]
        model.embeddings[1, 4] = 0.004  # turns 0.004 rad: under the 0.01 threshold
        model.embeddings[2, 7] = 0.5  # grows: log-scale spread 0.25
    times = torch.linspace(0.0, 1.0, 5)
    dpos, drot, dscale, (mdx, mdw, mdl) = deformation_spread(model, times, chunk=4)
    assert torch.allclose(dpos[0], torch.tensor(0.5))
    assert torch.allclose(dscale[2], torch.tensor(0.25))
    assert torch.allclose(mdx[3], torch.full((3,), 0.05))
    before = [model.means.data.clone(), model.quats.data.clone(), model.log_scales.data.clone()]
    render_before = [x.detach().clone() for x in model.at_time(0.5)]  # t = 0.5: the mean
    cfg = StaticConfig(enabled=True, position=1e-3, rotation=0.01, log_scale=0.01)
    up = update_static_set(model, times, extent=1.0, config=cfg)
    assert model.static.tolist() == [False, True, False, True, True, True]
    assert (up.marked, up.released, up.static, up.total) == (4, 0, 4, 6)
    # Baked: static rows render at every time what they rendered on average over time.
    assert torch.allclose(model.means.data[3], before[0][3] + 0.05)
    rot = axis_angle_to_quat(mdw[1:2])
    assert torch.allclose(model.quats.data[1], quat_multiply(rot, before[1][1:2])[0])
    assert torch.equal(model.log_scales.data[0], before[2][0])  # moving rows untouched
    after = model.at_time(0.9)
    for got, want in zip(after, render_before, strict=True):
        assert torch.allclose(got[model.static], want[model.static], atol=1e-5)
    # D_theta now moves Gaussian 3 (more than twice the threshold): released, bake undone.
    with torch.no_grad():
        model.embeddings[3, 1] = 0.01  # position spread 0.005 > 2 x 1e-3
        model.embeddings[4, 1] = 0.003  # 0.0015: between the thresholds, stays static
    up = update_static_set(model, times, extent=1.0, config=cfg)
    assert (up.marked, up.released) == (0, 1)
    assert model.static.tolist() == [False, True, False, False, True, True]
    mean_dx3 = 0.05 + 0.01 * times.mean()  # the mean offset D_theta gives it now
    assert torch.allclose(model.means.data[3, 1], before[0][3, 1] + 0.05 - mean_dx3, atol=1e-6)


def test_children_of_densification_inherit_the_flag() -> None:
    model, opt = densify_case()
    model.static[:] = torch.tensor([True, False, True, True, False, False])
    d = Densifier(DensifyConfig(grad_threshold=1e-3, percent_dense=0.1))
    d._ensure(6)
    d.grad_accum[:] = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0, 0.0])  # clone 0, 2; split 3
    d.count[:] = 1
    d.densify_and_prune(model, opt, scene_extent=1.0)
    # kept 0, 1, 2, 4 (5 pruned, 3 split), then clones of 0 and 2, then 3's two children.
    assert model.static.tolist() == [True, False, True, False, True, True, True, True]
    assert model.at_time(0.2)[0].shape[0] == 8


def test_checkpoint_state_keeps_the_set() -> None:
    model = _model()
    tensors, meta = model.state()
    assert "gaussians.static" not in tensors  # none static: the file is as before
    model.static[2:5] = True
    tensors, meta = model.state()
    again = DeformableGaussians.from_state(tensors, meta)
    assert torch.equal(again.static, model.static)
    tensors["gaussians.static"] = torch.zeros(3)
    with pytest.raises(ValueError, match="gaussians.static"):
        DeformableGaussians.from_state(tensors, meta)


@pytest.mark.parametrize("enabled", [True, False])
def test_fit_on_a_scene_with_no_motion(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], enabled: bool
) -> None:
    """A scene where nothing moves: with the skip on, fit finds every Gaussian static after
    the first check, stops evaluating D_theta and says so; with it off, it says nothing."""
    data = write_synthetic_scene(tmp_path / "still", STILL_SCENE)
    args = ["fit", str(data), "--out", str(tmp_path / "run"), "--phases", "1", "--iters", "40",
            "--threads", "1", "--set", "eval_every=0", "--set", "phase1.init_points=400",
            "--set", "phase1.init_from=random",
            "--set", f"phase1.static.enabled={str(enabled).lower()}"]  # fmt: skip
    assert main(args) == 0
    err = capsys.readouterr().err
    if not enabled:
        assert "skipped D_theta" not in err
        return
    line = next(ln for ln in err.splitlines() if "skipped D_theta" in ln)
    print(line)
    assert "no Gaussian moves" in line, line
    # The first check is at iteration 4 of 40 (3000 of 30000 scaled): 90 % of the rows skip.
    share = int(line.split("skipped D_theta on ")[1].split("%")[0])
    assert share >= 85, line
    assert math.isfinite(float(line.split("(")[1].split(" of ")[0]))
