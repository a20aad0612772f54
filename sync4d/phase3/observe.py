"""What Phase 3 observes of a frozen Phase 2 run, frame by frame (Appendix A, Phase 3 steps 1
and 4): object crops, occlusion-aware visibility, Phase 2's residual statistics and rigid
share, and the gaps between objects (for the contact predicates).

For each stored frame time t of M_phi and each training view at t:

* **visibility** renders every Gaussian with its object label as a one-hot feature through the
  rasterizer (occlusion-aware: the front surface wins); object k's visible fraction is the share
  of its Gaussians whose centre lands, in front of the camera and inside the image, on a pixel
  whose dominant label is k (Appendix B dim 5);
* the **crop** box is the 2nd-98th percentile of the projected centres of the object's Gaussians
  in front of the camera, grown by 12 % of its width and height on each side and clipped to the
  image; the frame's crop comes from the view with the largest visible fraction (ties: the
  larger box), recorded by name so multi-view runs say where each crop came from. An object is
  *observed* at a frame when that fraction is at least `min_visible` and the box is at least
  `min_box` pixels on each side. Only observed object-frames are cropped (and so encoded):
  the field reads e_obs on the observed frames F_k alone, so a crop of an invisible object (no
  box, or none of its Gaussians visible: the crop would show its occluder) or of a sliver
  would be encoded for nothing. `skip_unobserved=False` crops those that have a box as well,
  apart (`extra_crops`), to measure what the skip saves; `counts` says what was cropped;
* **residuals** r_i = x_i(t) - x~_i(t) (D_theta's position minus M_phi's, Eq. 6) give per object
  the mean and standard deviation of |r_i| and the rigid share rho (Phase 2's own
  `rigid_share`, averaged over the object's Gaussians: dims 3, 4, 18);
* **gaps**: to each other object, the 5th smallest over the object's Gaussians of the distance
  to the nearest Gaussian of the other object (a surface-to-surface distance that four stray
  Gaussians cannot close); to the background, the object's height above the background surface
  under it (`_support_gap`): the background holds the floor and, in reconstructions, floaters
  near the objects, which a nearest-point gap would take for contact (measured on bouncingballs:
  the blue ball was 0.14-0.31 radii from a background Gaussian at every frame, apex included).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from sync4d import raster, watchdog
from sync4d.data import Scene
from sync4d.events import Advanced, Finished, Started, emit
from sync4d.phase2.terms import rigid_share
from sync4d.runs import Run

__all__ = ["Observations", "crop_box", "observe"]


@dataclass
class Observations:
    """Per foreground object (`labels`, K of them) and stored frame (`times`, T of them).

    `visible` [K, T] fraction of the object's Gaussians visible in the chosen view; `observed`
    [K, T] bool; `boxes` [K, T, 4] crop boxes (x0, y0, x1, y1) in pixels of the chosen view
    (zeros when unobserved); `views` [K][T] the chosen training frame's name ("" when none);
    `residual_mean`, `residual_std`, `rigid_share` [K, T]; `canonical_centroids` [K, 3];
    `radius` [K] median distance of the object's canonical Gaussians from their centroid;
    `gaps` [K, L, T] robust distance from object k to each label in `gap_labels` (L of them:
    0 = background, then the objects); `crops` the crop images [h, w, 3] in [0, 1] of the
    observed pairs, in the order of `crop_index` [(k, f)]; `extra_crops` and `extra_index` the
    same of the unobserved pairs that have a box (only with `skip_unobserved=False`; the field
    never reads them). `counts`: ``object_frames`` (K T), ``observed``, ``invisible``
    (unobserved with no crop box or a visible fraction of 0), ``below_threshold`` (unobserved,
    partly visible: under `min_visible` or `min_box`), ``crops`` (observed crops made),
    ``extra_crops``, ``images_loaded`` (training images read for crops).
    """

    labels: list[int]
    times: np.ndarray
    visible: np.ndarray
    observed: np.ndarray
    boxes: np.ndarray
    views: list[list[str]]
    residual_mean: np.ndarray
    residual_std: np.ndarray
    rigid_share: np.ndarray
    canonical_centroids: np.ndarray
    radius: np.ndarray
    gaps: np.ndarray
    gap_labels: list[int]
    crops: list[np.ndarray] = field(default_factory=list)
    crop_index: list[tuple[int, int]] = field(default_factory=list)
    extra_crops: list[np.ndarray] = field(default_factory=list)
    extra_index: list[tuple[int, int]] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)


def crop_box(
    uv: np.ndarray, width: int, height: int, margin: float = 0.12, lo: float = 2.0,
    hi: float = 98.0,
) -> tuple[int, int, int, int] | None:  # fmt: skip
    """Integer crop box (x0, y0, x1, y1), x1/y1 exclusive, of projected points `uv` [n, 2]
    (pixels): the `lo`-`hi` percentile box grown by `margin` of its size on each side, clipped
    to the image; None when no point is given or the box misses the image."""
    if len(uv) == 0:
        return None
    x0, y0 = np.percentile(uv, lo, axis=0)
    x1, y1 = np.percentile(uv, hi, axis=0)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    bx0, by0 = int(np.floor(max(0.0, x0 - mx))), int(np.floor(max(0.0, y0 - my)))
    bx1, by1 = int(np.ceil(min(width, x1 + mx))), int(np.ceil(min(height, y1 + my)))
    if bx1 <= bx0 or by1 <= by0:
        return None
    return bx0, by0, bx1, by1


def _robust_gap(a: torch.Tensor, b: torch.Tensor, rank: int = 5) -> float:
    """The `rank`-th smallest, over points `a` [n, 3], of their distance to the nearest point
    of `b` [m, 3]: the gap between two point sets that a few stray points cannot close."""
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    nearest = torch.cat([torch.cdist(chunk, b).min(1).values for chunk in a.split(256)])
    r = min(rank, len(nearest)) - 1
    return float(np.partition(nearest.numpy(), r)[r])


def _support_gap(obj: np.ndarray, bg: np.ndarray, up: np.ndarray) -> float:
    """Height of object points `obj` [n, 3] above the background surface under them: the 5th
    percentile of their height along `up` minus the median height of the background points `bg`
    [m, 3] in the object's footprint (horizontal distance to its centroid within its 90th
    percentile horizontal radius) and below its centroid; inf when nothing is under it."""
    if len(obj) == 0 or len(bg) == 0:
        return float("inf")
    c = obj.mean(0)
    h_obj, h_bg = obj @ up, bg @ up
    flat = lambda x: (x - c) - np.outer((x - c) @ up, up)  # noqa: E731
    reach = float(np.percentile(np.linalg.norm(flat(obj), axis=1), 90))
    under = (np.linalg.norm(flat(bg), axis=1) <= reach) & (h_bg < c @ up)
    if not under.any():
        return float("inf")
    return max(0.0, float(np.percentile(h_obj, 5) - np.median(h_bg[under])))


def _subsample(idx: np.ndarray, n: int) -> np.ndarray:
    """At most `n` evenly spaced entries of `idx` (deterministic)."""
    if len(idx) <= n:
        return idx
    return idx[np.linspace(0, len(idx) - 1, n).round().astype(np.int64)]


def _crop(images: dict[int, np.ndarray], vi: int, scene: Scene, box: tuple[int, int, int, int],
          background) -> np.ndarray:  # fmt: skip
    """The `box` of training view `vi`'s image, read into `images` on first use."""
    if vi not in images:
        images[vi] = scene.train[vi].load_image(tuple(background))
    x0, y0, x1, y1 = box
    return images[vi][y0:y1, x0:x1].copy()


@torch.no_grad()
def observe(
    run: Run, scene: Scene, *, min_visible: float = 0.05, min_box: int = 4,
    margin: float = 0.12, percentiles: tuple[float, float] = (2.0, 98.0),
    share_eps: float = 1e-6, up: np.ndarray | None = None, threads: int | None = None,
    skip_unobserved: bool = True,
) -> Observations:  # fmt: skip
    """Crops, visibility, residual statistics and gaps of every foreground object of the
    Phase 2 run `run` at each of its stored frames, from the training views of `scene`; `up`
    [3] is the world's up (default +z) for the gap to the background. Crops only of the
    observed object-frames unless `skip_unobserved` is False (then also `extra_crops`).
    Progress over the frames goes out as `sync4d.events` (task "phase3 observe")."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    if run.motion is None or run.labels is None or run.times is None:
        raise ValueError(f"{run.path}: not a Phase 2 run")
    model, motion = run.model, run.motion
    labels_np = run.labels
    num_labels = int(motion.num_objects)
    fg = [j for j in range(1, num_labels) if (labels_np == j).any()]
    times = np.asarray(run.times, dtype=np.float64)
    k, t = len(fg), len(times)
    labels = torch.as_tensor(labels_np, dtype=torch.long)
    x0 = model.means.detach()
    opac = torch.sigmoid(model.opacity_logits.detach())
    onehot = torch.zeros(len(labels_np), num_labels)
    onehot[torch.arange(len(labels_np)), labels] = 1.0
    members = [np.flatnonzero(labels_np == j) for j in fg]
    gap_labels = [0, *fg]
    gap_members = [_subsample(np.flatnonzero((labels_np == j) & (opac.numpy() > 0.1)), 4096)
                   for j in gap_labels]  # fmt: skip
    x0n = x0.double().numpy()
    cc = np.stack([x0n[m].mean(0) for m in members]) if k else np.zeros((0, 3))
    radius = np.array([np.median(np.linalg.norm(x0n[m] - c, axis=1))
                       for m, c in zip(members, cc, strict=True)])  # fmt: skip
    by_time: dict[int, list[int]] = {}
    for i, fr in enumerate(scene.train):
        j = int(np.argmin(np.abs(times - fr.time)))
        if abs(times[j] - fr.time) < 1e-6:
            by_time.setdefault(j, []).append(i)
    obs = Observations(
        labels=fg, times=times, visible=np.zeros((k, t)), observed=np.zeros((k, t), bool),
        boxes=np.zeros((k, t, 4), np.int64), views=[[""] * t for _ in fg],
        residual_mean=np.zeros((k, t)), residual_std=np.zeros((k, t)),
        rigid_share=np.zeros((k, t)), canonical_centroids=cc, radius=radius,
        gaps=np.full((k, len(gap_labels), t), np.inf), gap_labels=gap_labels,
    )  # fmt: skip
    n_invisible = n_below = n_loaded = 0
    emit(Started("phase3 observe", t, log_every=max(1, t // 10)))
    for f, tf in enumerate(times):
        means, quats, scales = model.at_time(float(tf))
        watchdog.check_inputs("Phase 3 observation", None, {"means": means, "quats": quats,
                                                              "scales": scales})  # fmt: skip
        r = means - motion(x0, labels, float(tf))
        rn = r.norm(dim=-1).double().numpy()
        rho = rigid_share(x0, means - r, r, share_eps).double().numpy()
        for a, m in enumerate(members):
            obs.residual_mean[a, f] = rn[m].mean()
            obs.residual_std[a, f] = rn[m].std()
            obs.rigid_share[a, f] = rho[m].mean()
        pts = means.detach()
        pts_np = pts.double().numpy()
        for a, m in enumerate(members):
            mine = pts[_subsample(m, 512)]
            for b, gm in enumerate(gap_members):
                if gap_labels[b] == 0:  # the background: the surface under the object
                    obs.gaps[a, b, f] = _support_gap(pts_np[m], pts_np[gm], up)
                elif gap_labels[b] != fg[a]:
                    obs.gaps[a, b, f] = _robust_gap(mine, pts[gm])
        best: list[tuple[float, int, int, tuple[int, int, int, int] | None]] = [
            (-1.0, 0, -1, None) for _ in fg
        ]
        mn = pts.double().numpy()
        for vi in by_time.get(f, []):
            cam = scene.train[vi].camera
            out = raster.rasterize(
                pts, quats, scales, opac, onehot, torch.as_tensor(cam.viewmat, dtype=torch.float32),
                torch.as_tensor(cam.K, dtype=torch.float32), cam.width, cam.height,
                background=torch.zeros(num_labels), near=model.near, threads=threads,
            )  # fmt: skip
            img = out.features.numpy()
            label_map = np.where(img.max(-1) >= 0.3, img.argmax(-1), -1)
            uv, z = cam.project(mn)
            for a, m in enumerate(members):
                front = m[z[m] > model.near]
                px = np.floor(uv[front]).astype(np.int64)
                inside = ((px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0)
                          & (px[:, 1] < cam.height))  # fmt: skip
                px = px[inside]
                vis = np.count_nonzero(label_map[px[:, 1], px[:, 0]] == fg[a]) / len(m)
                box = crop_box(uv[front], cam.width, cam.height, margin, *percentiles)
                area = 0 if box is None else (box[2] - box[0]) * (box[3] - box[1])
                if (vis, area) > best[a][:2]:
                    best[a] = (vis, area, vi, box)
        images: dict[int, np.ndarray] = {}  # read once per frame and view, only for a crop
        for a in range(k):
            vis, _, vi, box = best[a]
            obs.visible[a, f] = max(vis, 0.0)
            if vi < 0 or box is None:  # in front of no camera, or outside every image
                n_invisible += 1
                continue
            obs.boxes[a, f] = box
            obs.views[a][f] = scene.train[vi].name
            big = min(box[2] - box[0], box[3] - box[1]) >= min_box
            if vis >= min_visible and big:
                obs.observed[a, f] = True
                obs.crops.append(_crop(images, vi, scene, box, run.background))
                obs.crop_index.append((a, f))
                continue
            if vis > 0:
                n_below += 1
            else:
                n_invisible += 1
            if not skip_unobserved:
                obs.extra_crops.append(_crop(images, vi, scene, box, run.background))
                obs.extra_index.append((a, f))
        n_loaded += len(images)
        emit(Advanced("phase3 observe", f + 1))
    emit(Finished("phase3 observe"))
    obs.counts = {
        "object_frames": k * t, "observed": int(obs.observed.sum()), "invisible": n_invisible,
        "below_threshold": n_below, "crops": len(obs.crops), "extra_crops": len(obs.extra_crops),
        "images_loaded": n_loaded,
    }  # fmt: skip
    return obs
