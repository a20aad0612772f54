"""A background drawn at each training step (`Phase1Config.train_background = "random"`,
SC-GS's random background): the target and the render share the step's colour, the colour
is the run's seed and iteration's (a resumed run draws the same), a coarse target on any
colour is exact, and images without alpha train on themselves."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from support.scenes import orbit_camera, orbit_student, random_gaussians
from sync4d.config import ConfigError, config_from_dict
from sync4d.data.scene import Frame, Scene
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.trainer import Phase1Trainer


def _rgba_scene(tmp_path: Path) -> Scene:
    """Six 40x32 RGBA views (alpha: the Gaussians' coverage) of 40 static Gaussians."""
    gt = random_gaussians(40, 0, spread=0.4, scale=0.12, opacity_logit=2.0, sh_degree=0)
    frames = []
    for i in range(6):
        cam = orbit_camera(2 * math.pi * i / 6)
        with torch.no_grad():
            out = gt.render(cam, 0.0, background=torch.zeros(3), threads=1)
        alpha = out.alpha.clamp(1e-3, 1)
        colour = (out.features / alpha).clamp(0, 1)  # straight (not premultiplied) colour
        rgba = torch.cat([colour, out.alpha.clamp(0, 1)], dim=-1).numpy()
        path = tmp_path / f"f{i}.png"
        Image.fromarray((rgba * 255).round().astype(np.uint8), "RGBA").save(path)
        frames.append(Frame(path, cam, i / 5))
    return Scene("rgba", frames, frames[:2])


def _trainer(scene: Scene, **config) -> Phase1Trainer:
    gt = random_gaussians(40, 0, spread=0.4, scale=0.12, opacity_logit=2.0, sh_degree=0)
    model = orbit_student(gt, 1)
    cfg = Phase1Config(densify=DensifyConfig(start=10_000), **config)
    return Phase1Trainer(model, scene, cfg, total_iterations=20, threads=1)


@pytest.mark.parametrize("background", [(1.0, 1.0, 1.0), (0.0, 0.0, 0.0), (0.2, 0.7, 0.4)])
def test_layers_composite_to_the_loaded_image(tmp_path: Path, background) -> None:
    frame = _rgba_scene(tmp_path).train[1]
    colour, alpha = frame.load_layers()
    assert alpha is not None and colour.shape == (32, 40, 3) and alpha.shape == (32, 40, 1)
    assert 0.0 < float(alpha.mean()) < 1.0  # partly covered: the test can tell backgrounds
    assert np.array_equal(colour + np.float32(background) * (1 - alpha),
                          frame.load_image(background))  # fmt: skip


def test_each_step_draws_its_own_colour_for_render_and_target(tmp_path: Path) -> None:
    scene = _rgba_scene(tmp_path)
    trainer = _trainer(scene, train_background="random")
    seen = []
    render = trainer.model.render

    def spy(camera, t, **kw):
        seen.append(kw["background"].clone())
        return render(camera, t, **kw)

    trainer.model.render = spy
    for _ in range(4):
        assert math.isfinite(trainer.step()["loss"])
    assert len({tuple(b.tolist()) for b in seen}) == 4  # a new colour at each step
    assert all(float(b.min()) >= 0 and float(b.max()) <= 1 for b in seen)
    # The colour is the seed's and the iteration's: a trainer at iteration 3 draws it again.
    again = _trainer(scene, train_background="random")
    again.iteration = 3
    assert torch.equal(again.step_background(), seen[2])
    # The target on that colour is the image composited on it.
    frame = scene.train[2]
    bg = seen[2]
    want = torch.from_numpy(frame.load_image(tuple(bg.tolist())))
    assert torch.allclose(trainer.target(2, frame, bg), want, atol=1e-6)


def test_a_fixed_background_is_the_configured_one(tmp_path: Path) -> None:
    trainer = _trainer(_rgba_scene(tmp_path), background=(0.0, 0.0, 0.0))
    for it in (1, 2, 3):
        trainer.iteration = it
        assert torch.equal(trainer.step_background(), torch.zeros(3))
    frame = trainer.scene.train[0]
    assert torch.equal(trainer.target(0, frame, torch.zeros(3)),
                       torch.from_numpy(frame.load_image((0.0, 0.0, 0.0))))  # fmt: skip


def test_coarse_target_on_a_random_colour_is_the_average_of_the_composite(tmp_path: Path) -> None:
    trainer = _trainer(_rgba_scene(tmp_path), train_background="random",
                       coarse_iterations=5, coarse_scale=0.5)  # fmt: skip
    frame = trainer.scene.train[1]
    for bg in (torch.tensor([0.9, 0.1, 0.3]), torch.tensor([0.0, 0.5, 1.0])):
        camera, small = trainer._coarse_view(1, frame, bg)
        full = torch.from_numpy(frame.load_image(tuple(bg.tolist())))
        want = full.reshape(16, 2, 20, 2, 3).mean(dim=(1, 3))
        assert (camera.width, camera.height) == (20, 16)
        assert torch.allclose(small, want, atol=1e-6)


def test_images_without_alpha_train_on_themselves(tmp_path: Path) -> None:
    from support.scenes import orbit_scene

    scene, _ = orbit_scene(tmp_path)  # RGB PNGs
    trainer = _trainer(scene, train_background="random")
    frame = scene.train[0]
    assert frame.load_layers()[1] is None
    for bg in (torch.zeros(3), torch.tensor([0.3, 0.6, 0.9])):
        assert torch.equal(trainer.target(0, frame, bg), torch.from_numpy(frame.load_image()))


def test_the_mode_is_a_checked_choice() -> None:
    with pytest.raises(ConfigError, match="phase1.train_background"):
        config_from_dict({"phase1": {"train_background": "noise"}}, "test")
    cfg = config_from_dict({"phase1": {"train_background": "random"}}, "test")
    assert cfg.phase1.train_background == "random"
