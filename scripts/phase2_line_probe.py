"""The refinement's loss along the straight line from the refined pose to the true pose of the
embedded scene's red ball at chosen frames (docs/results/phase2-robustness.md section 5): is a
miss a local minimum of the tracking, or a wrong optimum?

    python scripts/phase2_line_probe.py RUN/phase1.safetensors

Refines once (cached beside the checkpoint as `.table2.pt`), then prints, per frame, the mean
loss over the frame's views at fractions 0 (refined) to 1 (truth), with the template's fitted
colours and with the model's."""

import dataclasses
import os
import sys

import numpy as np
import torch

from sync4d.config import load_config
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.geometry import matrix_to_rotvec, rotvec_to_matrix
from sync4d.phase2 import phase2_trainer
from sync4d.phase2.refine import _RigidTemplate, _template_loss, refine_motion
from sync4d.pipeline import set_threads
from sync4d.runs import load_model

ck = sys.argv[1]
root = syn.default_scene_dir()
cfg = load_config("synthetic")
set_threads(1)
scene = load_scene(root, cfg.resolution_scale)
gt = syn.load_ground_truth(root)
model, _ = load_model(ck)
mc = cfg.phase2.motion
fitted = dataclasses.replace(cfg.phase2, motion=dataclasses.replace(mc, refine_steps=0))
tr = phase2_trainer(model, scene, cfg.phase1, fitted, 1, 1)
m = tr.motion
moving = [k for k in range(tr.assignment.num_objects) if not bool(tr.static[k])]
r0 = rotvec_to_matrix(m.rotvecs[moving, 0].detach().float())
b0 = m.translations[moving, 0].detach().float().clone()
cache = ck + ".table2.pt"
if os.path.exists(cache):
    rv, tt, colours = torch.load(cache)
    with torch.no_grad():
        m.rotvecs.copy_(rv)
        m.translations.copy_(tt)
else:
    refine_motion(tr, mc)
    colours = tr.template_colours
    torch.save((m.rotvecs.detach().clone(), m.translations.detach().clone(), colours), cache)
print(gt.export_errors(tr.motion_export()), flush=True)
template = _RigidTemplate.build(tr, moving)
centre = template.centre
times = tr.times
ball = moving.index(1)
gi = gt.ids.index(1)
rows = [int(np.argmin(np.abs(gt.times - t))) for t in np.asarray(times)]


def table_wd(j):
    a = rotvec_to_matrix(m.rotvecs[moving, j].detach().float())
    b = m.translations[moving, j].detach().float()
    R = a @ r0.transpose(1, 2)
    w = torch.stack(
        [
            torch.as_tensor(matrix_to_rotvec(R[i].double().numpy()), dtype=torch.float32)
            for i in range(len(moving))
        ]
    )
    d = b - centre - (R @ (b0 - centre).unsqueeze(-1)).squeeze(-1)
    return w, d


w0, d0 = table_wd(0)


def loss_at(j, w, d, sh):
    t = float(times[j])
    with torch.no_grad():
        dd = template.deformed(model, t)
        return np.mean(
            [
                float(_template_loss(tr, i, t, template.pose(w, d, dd), sh))
                for i in template.views[j]
            ]
        )


for j in [20, 30, 32, 34, 35, 36, 37, 38, 39]:
    w, d = table_wd(j)
    G = torch.as_tensor(
        gt.rotations[gi][rows[j]] @ gt.rotations[gi][rows[0]].T, dtype=torch.float32
    )
    T0 = torch.as_tensor(gt.translations[gi][rows[0]], dtype=torch.float32)
    Tj = torch.as_tensor(gt.translations[gi][rows[j]], dtype=torch.float32)
    wg, dg = w.clone(), d.clone()
    Rg = G @ rotvec_to_matrix(w0[ball : ball + 1])[0]
    wg[ball] = torch.as_tensor(matrix_to_rotvec(Rg.double().numpy()), dtype=torch.float32)
    dg[ball] = G @ (centre[ball] + d0[ball] - T0) + Tj - centre[ball]
    Rr = rotvec_to_matrix(w[ball : ball + 1])[0]
    err = np.degrees(np.arccos(np.clip((float(torch.trace(Rr @ Rg.T)) - 1) / 2, -1, 1)))
    for name, sh in (("fitted colours", colours), ("model colours", model.sh_dc.detach())):
        line = [
            loss_at(j, w + a * (wg - w), d + a * (dg - d), sh) for a in (0.0, 0.25, 0.5, 0.75, 1.0)
        ]
        print(
            f"frame {j} err {err:.2f} deg {name}: loss refined->GT (0 .25 .5 .75 1): "
            + " ".join(f"{v:.5f}" for v in line),
            flush=True,
        )
