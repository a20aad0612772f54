"""The oracle Phase 1 of the embedded synthetic scene: Gaussians sampled inside its objects
whose D_theta is replaced by the true motion, so any error downstream comes from Phase 2 or 3
alone; and an oracle Phase 2 run on which Phase 3 is tested."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from support.scenes import small_synthetic
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.gaussians import DeformableGaussians, rgb_to_sh_dc
from sync4d.phase1.nodes import NodeConfig
from sync4d.phase2 import Phase2Config, phase2_trainer
from sync4d.phase2.motion import MotionConfig
from sync4d.runs import CHECKPOINT_NAME, Run, camera_records, save_checkpoint

#: Base colour of the oracle Gaussians of each label in a saved oracle run (plate, red ball,
#: blue box, green pillar).
OBJECT_COLOURS = {0: (0.85, 0.85, 0.8), 1: (0.85, 0.15, 0.15), 2: (0.15, 0.25, 0.85),
                  3: (0.2, 0.7, 0.25)}  # fmt: skip
#: The scene of the Phase 2 oracle tests (64 px, 8 frames).
PHASE2_SCENE = small_synthetic(size=64, frames=8, test_every=4)
#: The scene of the oracle Phase 2 run (48 px, 21 frames).
PHASE3_SCENE = small_synthetic(frames=21, train_cameras=3, test_every=4)


class OracleGaussians(DeformableGaussians):
    """Gaussians whose deformation is the synthetic scene's true object motion."""

    def __init__(self, points: np.ndarray, truth: np.ndarray, rotate: bool = True) -> None:
        super().__init__(torch.as_tensor(points, dtype=torch.float32), None, sh_degree=0)
        self.truth = truth
        #: False: carry each object along its true translation without turning it (the point
        #: correspondences then show no rotation, as when Phase 1 morphs a turning shape).
        self.rotate = rotate
        poses0 = syn.object_poses(0.0)
        self.local = {k: (points[truth == k] - poses0[k][1]) @ poses0[k][0]
                      for k in (1, 2, 3)}  # fmt: skip

    def at_time(self, t: float, deform: bool = True):
        means, quats, scales = super().at_time(t, deform=False)
        if not deform:
            return means, quats, scales
        pos = self.means.detach().double().numpy().copy()
        poses = syn.object_poses(float(t))
        for k, loc in self.local.items():
            rot = poses[k][0] if self.rotate else syn.object_poses(0.0)[k][0]
            pos[self.truth == k] = loc @ rot.T + poses[k][1]
        return torch.as_tensor(pos, dtype=torch.float32), quats, scales


def oracle_points(
    per_object: int = 300, fill: float = 0.8, ground: int = 400, ground_z: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] on the embedded scene's objects at time 0 (`per_object` drawn uniformly
    in each object's box shrunk by `fill`, spheres cut to the ellipsoid) and `ground` points on
    the plate at height `ground_z`, with their true labels [N] (0: the plate). Seeded (0)."""
    rng = np.random.default_rng(0)
    poses0 = syn.object_poses(0.0)
    pts, truth = [], []
    for obj in syn.OBJECTS:
        half = np.asarray(obj.size) * fill
        local = rng.uniform(-1, 1, (per_object, 3)) * half
        if obj.kind == "sphere":
            local = local[np.linalg.norm(local / half, axis=1) <= 1.0]
        r, t = poses0[obj.label]
        pts.append(local @ r.T + t)
        truth.append(np.full(len(local), obj.label))
    pts.append(np.c_[rng.uniform(-1.2, 1.2, (ground, 2)), np.full(ground, ground_z)])
    truth.append(np.zeros(ground, dtype=int))
    return np.concatenate(pts), np.concatenate(truth)


def oracle_phase2_run(
    tmp: Path, model_cls: type[OracleGaussians] = OracleGaussians,
    scene_config: syn.SyntheticConfig = PHASE3_SCENE, save: bool = False,
    motion: str = "gaussians",
):  # fmt: skip
    """An oracle Phase 2 run of the embedded scene (`scene_config`) written under `tmp` (no
    checkpoint): Gaussians on the objects and the plate (`oracle_points`) moved by
    `model_cls`, M_phi fitted to them. Returns (run, scene root). `save`: also write its
    checkpoint (with the cameras and the dataset), so `load_run` reads the folder (where the
    model's motion is plain D_theta's: none) and a field built on `run` records it. `motion`
    "nodes": the saved model moves by control nodes (64, sampled on the oracle Gaussians;
    their D_theta, too, moves nothing), so what reads the folder reads a node run."""
    root = syn.write_synthetic_scene(tmp / "scene", scene_config)
    scene = load_scene(root)
    points, labels = oracle_points(per_object=400, fill=0.95, ground=1500, ground_z=0.0)
    model = model_cls(points, labels)
    with torch.no_grad():
        model.log_scales.fill_(float(np.log(0.04)))
        model.opacity_logits.fill_(3.0)
    tr = phase2_trainer(model, scene, Phase1Config(),
                        Phase2Config(motion=MotionConfig(init="fit")), 100, threads=1)  # fmt: skip
    run_dir = tmp / "run"
    run_dir.mkdir()
    if save and motion == "nodes":
        model.use_nodes(NodeConfig(count=64), torch.Generator().manual_seed(0))
    if save:  # a run folder as `fit` leaves it (the model reads back as plain D_theta)
        with torch.no_grad():  # the objects' own colours, for what shows the splats
            for label, rgb in OBJECT_COLOURS.items():
                model.sh_dc[torch.as_tensor(labels == label), 0] = rgb_to_sh_dc(
                    torch.tensor(rgb))
        save_checkpoint(tr.trainer, run_dir / CHECKPOINT_NAME,
                        extra={"data": str(root), "cameras": camera_records(scene)})
    names = {0: "background", 1: "red ball", 2: "blue box", 3: "green pillar"}
    run = Run(path=run_dir, checkpoint=run_dir / "checkpoint.safetensors", kind="sync4d.phase2",
              model=model, meta={}, background=[1.0, 1.0, 1.0], cameras=camera_records(scene),
              settings={"data": str(root)}, motion=tr.motion, labels=labels, names=names,
              times=tr.times)  # fmt: skip
    return run, root


def oracle_run_folder(tmp: Path, queries: tuple[str, ...] = (), motion: str = "gaussians",
                      encoder: str | None = None) -> Path:  # fmt: skip
    """The oracle Phase 2 run saved as a run folder (`oracle_phase2_run(save=True)`) with its
    language field built by the colour encoder (`support.encoders.ColourEncoder`), and the
    texts of `queries` already in the field's text cache, so the run's own query code answers
    them without loading an encoder (the colour encoder is no registered kind). `motion`:
    as in `oracle_phase2_run`; `encoder`: a registered encoder ("offline") to build the field
    with instead, which every later query then loads."""
    from support.encoders import ColourEncoder
    from sync4d.phase3.build import build_field
    from sync4d.phase3.config import Phase3Config
    from sync4d.phase3.encoders.encoder import load_encoder
    from sync4d.phase3.query import TextCache, answer

    run, _ = oracle_phase2_run(tmp, save=True, motion=motion)
    enc = ColourEncoder() if encoder is None else load_encoder(encoder)
    field = build_field(run, Phase3Config(), enc, threads=1)
    field.save(run.path)
    cache = TextCache(run.path, field, enc)
    for q in queries:
        answer(field, q, cache=cache)
    cache.save()
    return run.path
