"""The watchdog's advice names the setting its evidence points to (`sync4d.watchdog.advice`):
a size already collapsed or exploded before any step names the setting that sizes it, a node
graph of coinciding nodes the node settings, and only a tensor a rate moved the rates."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from support.scenes import small_synthetic
from sync4d import watchdog
from sync4d.cli import main
from sync4d.data import synthetic as syn
from sync4d.watchdog import Evidence, advice


def test_collapsed_node_radii_name_the_radius_scale() -> None:
    ev = Evidence(first={"nodes.log_radii": (-72.0, -70.0)}, scale=4.0)
    a = advice("Phase 1", "nodes.log_radii", ev)
    assert a.settings == ("phase1.nodes.radius_scale",) and "collapsed" in a.text, a
    assert "learning rate" not in a.text and "lr_" not in a.text
    assert advice("Phase 1", "loss", ev).settings == ("phase1.nodes.radius_scale",)


def test_exploded_scales_before_any_step_name_the_initial_scale() -> None:
    ev = Evidence(first={"input:scales": (1e30, 1e30)}, scale=4.0)
    a = advice("Phase 1", "input:scales", ev)
    assert a.settings == ("phase1.init_scale",) and "exploded" in a.text, a
    tiny = Evidence(first={"log_scales": (math.log(1e-20),) * 2}, scale=1.0)
    assert advice("Phase 1", "loss", tiny).settings == ("phase1.init_scale",)


def test_a_size_a_rate_blew_up_names_the_rate() -> None:
    """Sane when first seen, huge after the steps: the rate moved it (`lr_scales` = 1e9)."""
    ev = Evidence(first={"log_scales": (-4.5, -3.0)}, last={"log_scales": (-2e9, 3e9)}, scale=4.0)
    a = advice("Phase 1", "log_scales", ev)
    assert a.settings == ("phase1.lr_scales",), a
    assert "lower the learning rates that move it (its magnitude grew from 4.5 to 3e+09" in a.text


def test_coinciding_nodes_name_the_node_settings() -> None:
    ev = Evidence(values={"nodes.positions": torch.zeros(3, 3)})
    a = advice("Phase 1", "loss", ev)
    assert "phase1.nodes.count" in a.settings and "1 distinct" in a.text, a
    spread = Evidence(values={"nodes.positions": torch.eye(3)})
    assert "phase1.nodes.count" not in advice("Phase 1", "loss", spread).settings


def test_without_evidence_the_rates_that_move_it_are_named() -> None:
    a = advice("Phase 1", "means", Evidence())
    assert a.settings == ("phase1.lr_means",) and "--set phase1.lr_means=..." in a.text
    assert advice("Phase 1", "loss", Evidence()).settings == ()


def test_the_evidence_is_gathered_by_the_checks_and_forgotten_at_a_stop() -> None:
    """A real check sequence: log-radii first seen collapsed, then a NaN gradient at the
    same iteration; the stop's message names the radius scale and the evidence is reset."""
    radii = torch.full((4,), -70.0, requires_grad=True)
    radii.grad = torch.full((4,), float("nan"))
    with pytest.raises(watchdog.NonFinite) as e:
        watchdog.check_grads("Test phase", 3, {"nodes.log_radii": radii})
    assert "--set phase1.nodes.radius_scale=..." in str(e.value), e.value
    assert "Test phase" not in watchdog._EVIDENCE


def test_a_tiny_radius_scale_fit_names_it(tmp_path: Path, capsys) -> None:
    """The real fit: control nodes of radius 1e-30 of their spacing stop at the nodes' first
    step, and the message names phase1.nodes.radius_scale, not a learning rate."""
    data = syn.write_synthetic_scene(tmp_path / "scene",
                                     small_synthetic(size=24, frames=4, train_cameras=2))
    args = ["fit", str(data), "--out", str(tmp_path / "run"), "--iters", "6", "--threads", "1",
            "--phases", "1", "--set", "phase1.init_points=200", "--set", "eval_every=0",
            "--set", "checkpoint_every=0", "--set", "phase1.init_from=random",
            "--set", "phase1.motion=nodes", "--set", "phase1.nodes.count=16",
            "--set", "phase1.nodes.init_after=2", "--set", "phase1.nodes.radius_scale=1e-30"]
    assert main(args) == 3
    err = capsys.readouterr().err
    assert "--set phase1.nodes.radius_scale=..." in err and "Traceback" not in err, err
    assert "lr_radius" not in err, err
