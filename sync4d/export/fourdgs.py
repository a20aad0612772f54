"""`.4dgs` files: a run's Gaussians with Phase 2's objects and tracks and Phase 3's embeddings,
through the reference writer and reader of the format, `fourdgs` (Apache-2.0, spec v1 draft,
PyPI ``fourdgs==0.6.0``; an optional dependency: ``pip install 'sync4d[4dgs]'``).

What is kept (`write_4dgs`):

- the Gaussians as the file's base state: each one's least-squares rest in its object's frame
  (D_theta's state at every stored frame with M_phi's pose undone, ``R^T (x - T)`` and
  ``R^-1 (x) q``, averaged; scales geometrically; untracked ones averaged in world space), or
  for a Phase 1 run the canonical Gaussians; unit rotations, linear scales, opacity
  (``sigmoid(logit)``), the DC colour as the format's RGB ``0.5 + SH_C0 * sh_dc`` clipped to
  [0, 1] (the format's colour grid: its writer's own check refuses values outside; the share
  clipped is in the Header's metadata) and SH bands 1..3;
- Phase 2's object of every Gaussian in the format's ``object_id`` stream (0 = background);
- one Object Track per foreground object (``background_track``: also the background's, under a
  new id named "background", since the format lets no track move object 0): M_phi's pose at
  each stored frame (run.times), interpolated by the format's ``linear`` rule (translation
  lerp, shortest-arc slerp, clamped outside the samples), which is SE3Table's own rule
  between frames, so the track moves the base as M_phi moves its points (``R x + t``; in
  affine mode R is the rotation of the polar decomposition and the rest of A is lost);
- the Object Table: per object its name, an anchor (the median canonical mean of its
  Gaussians) and, where Phase 3 ran, its static embedding (`Field.static`, the appearance
  embedding ``query`` ranks by) with the encoder named in the Header's metadata
  (``sync4d.encoder.kind``, ``.dim``, ``.fingerprint``);
- optionally (``keyframes=K``) D_theta's residual over M_phi as the format's temporal fields:
  each Gaussian is written K times, copy j valid over ``[s_j, s_{j+1})`` (s: K + 1 of the stored
  frames, evenly picked; the last window open-ended), its base centre in the object's frame at
  s_j (``R(s_j)^T (x_D(s_j) - T(s_j))``) moving linearly to the one at s_{j+1}, its rotation
  (``R(s_j)^-1 (x) q_D(s_j)``) and scale D_theta's at s_j. The state is exact (up to
  quantisation) at the s_j, linear in the object's frame between them. It costs K times the
  Gaussians.

What is lost: without ``keyframes`` D_theta's residual (the non-rigid part: the background's
motion, per-Gaussian deviations from the object's pose, scale changes; measured in
docs/export.md); M_phi's pose of the background (unless ``background_track``); the per-frame
embeddings (``sync``) and the rest of the field; SH and colours are quantised (the
``default`` profile: RGB and opacity to 1/255, SH coefficients to 8 bits over [-4, 4], error
<= 4/255, values beyond clipped; positions to 5% of the median scale).

Conventions: quaternions in the file are x, y, z, w (sync4d's are w, x, y, z); SH layout is the
format's (and PLY's) channel-major ``(n, 3 * coeffs)``, bands 1..3 only, DC in the RGB; space is
the run's world frame and units, unconverted (the Header's ``coordinate_system`` metadata says
``z-up-right-handed`` or ``y-up-right-handed`` when the cameras' mean up is that axis, and is
absent otherwise); time: the file's clock is sync4d's normalised time, ``duration_sec`` 1.0 (a
time t in [0, 1] is the scene second t), every base Gaussian valid from 0 on and never fading
(``sigma_t`` inf, window ``[0, inf)``).

Reading back (`read_4dgs`, `splats_from_4dgs`) uses the format's own object-layer rule
(`fourdgs.Scene.state_at`: the base state, then the object's track composed once); `render_4dgs`
renders that state with sync4d's rasterizer. `snapshot` writes one instant as glTF
(``KHR_gaussian_splatting``) or USD through the package's converters, with the tracks composed
first (the package's converters alone would leave objects at rest).
"""

from __future__ import annotations

import io
import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sync4d import __version__
from sync4d.export.errors import ExportError
from sync4d.files import write_atomic
from sync4d.runs.folder import Run

__all__ = [
    "FOURDGS_VERSION",
    "INSTALL",
    "FourDGSReport",
    "fourdgs_module",
    "read_4dgs",
    "render_4dgs",
    "snapshot",
    "splats_from_4dgs",
    "validate_4dgs",
    "write_4dgs",
]

#: The `fourdgs` release this module is written and tested against.
FOURDGS_VERSION = "0.6.0"
INSTALL = f"pip install 'sync4d[4dgs]' (or: pip install fourdgs=={FOURDGS_VERSION})"
_SH_C0 = 0.28209479177387814
_SH_LO, _SH_HI = -4.0, 4.0


def fourdgs_module() -> Any:
    """The `fourdgs` package, or ExportError with the line that installs it."""
    try:
        import fourdgs
    except ImportError:
        raise ExportError("fourdgs", f"the .4dgs writer is not installed: {INSTALL}") from None
    return fourdgs


@dataclass
class FourDGSReport:
    """What `write_4dgs` wrote: the file, its size, the Gaussians (base and, with keyframes,
    all copies), objects, tracks, whether embeddings went in (and why not), seconds."""

    path: Path
    bytes: int
    gaussians: int
    records: int
    objects: list[str]
    tracks: int
    keyframes: int
    embeddings: str | None
    note: str = ""
    seconds: float = 0.0
    metadata: dict[str, str] = field(default_factory=dict)


def _quat_wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-30)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def _matrix_to_quat_xyzw(m: np.ndarray) -> np.ndarray:
    """Unit quaternion x, y, z, w of a rotation matrix [3, 3] (Shepperd's method)."""
    tr = float(np.trace(m))
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x = 0.25 * s, (m[2, 1] - m[1, 2]) / s
        y, z = (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w, x = (m[2, 1] - m[1, 2]) / s, 0.25 * s
        y, z = (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w, x = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s
        y, z = 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w, x = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s
        y, z = (m[1, 2] + m[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w], dtype=np.float64)
    return q / np.linalg.norm(q)


def _quat_mul_xyzw(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a (x) b row by row (x, y, z, w)."""
    ax, ay, az, aw = np.moveaxis(np.broadcast_to(a, b.shape), -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz],
                    axis=-1)  # fmt: skip


def _rotations(run: Run) -> tuple[np.ndarray, np.ndarray]:
    """M_phi at the stored frames: rotations [K, T, 3, 3] (the polar decomposition's in affine
    mode) and translations [K, T, 3], float64."""
    a, b = run.motion.trajectory()
    if not getattr(run.motion, "rigid", True):
        u, _, vt = np.linalg.svd(a)
        d = np.sign(np.linalg.det(u @ vt))
        u[..., :, -1] *= d[..., None]
        a = u @ vt
    return a, b


def coordinate_system(run: Run) -> str | None:
    """``z-up-right-handed`` / ``y-up-right-handed`` when the cameras' mean up vector (OpenCV
    cameras: -y of each world-to-camera rotation) is nearest +z / +y; None otherwise."""
    ups = [-np.asarray(c["viewmat"], dtype=np.float64).reshape(4, 4)[1, :3]
           for c in run.cameras if "viewmat" in c]  # fmt: skip
    if not ups:
        return None
    up = np.mean(ups, axis=0)
    axis = int(np.argmax(np.abs(up)))
    if up[axis] <= 0 or abs(up[axis]) < 0.8 * np.linalg.norm(up):
        return None
    return {2: "z-up-right-handed", 1: "y-up-right-handed"}.get(axis)


def _field(run: Run) -> tuple[Any, str | None]:
    """The run's language field and None, or None and why there is none."""
    from sync4d.phase3.store import FieldError, load_field

    try:
        return load_field(run.path), None
    except FieldError as e:
        return None, f"no embeddings: {e}"


def _sh_bytes(sh_rest: np.ndarray) -> np.ndarray:
    """sync4d's SH rest [N, K, 3] as the format's u8 codes, channel-major [N, 3K]."""
    n, k, _ = sh_rest.shape
    flat = sh_rest.transpose(0, 2, 1).reshape(n, 3 * k).astype(np.float64)
    return np.clip(np.rint((flat - _SH_LO) / (_SH_HI - _SH_LO) * 255.0), 0, 255).astype(np.uint8)


def _keyframe_times(times: np.ndarray, k: int) -> np.ndarray:
    idx = np.unique(np.rint(np.linspace(0, len(times) - 1, k + 1)).astype(int))
    return np.asarray(times, dtype=np.float64)[idx]


def write_4dgs(path: str | Path, run: Run, *, keyframes: int = 0, profile: str = "default",
               background_track: bool = False) -> FourDGSReport:  # fmt: skip
    """Write `run` as a `.4dgs` file at `path` (atomically); what was written. `keyframes` K > 0
    keeps D_theta's residual over M_phi at K + 1 stored frames (K copies of every Gaussian; see
    the module docstring). ExportError when `fourdgs` is missing or the run cannot be written."""
    fd = fourdgs_module()
    start = _time.perf_counter()
    path = Path(path)
    model = run.model
    n = model.num_gaussians
    labels = (np.zeros(n, dtype=np.int64) if run.labels is None
              else np.asarray(run.labels, dtype=np.int64))  # fmt: skip
    with torch.no_grad():
        means0 = model.means.detach().double().numpy()
        quats0 = model.quats.detach().double().numpy()
        scales0 = torch.exp(model.log_scales).detach().double().numpy()
        alpha = torch.sigmoid(model.opacity_logits).detach().double().numpy()
        rgb = 0.5 + _SH_C0 * model.sh_dc[:, 0, :].detach().double().numpy()
        clipped = float(((rgb < 0.0) | (rgb > 1.0)).any(axis=1).mean())
        rgb = np.clip(rgb, 0.0, 1.0)  # the format's colour grid holds [0, 1] only
        sh_rest = model.sh_rest.detach().double().numpy()
    for name, arr in (("means", means0), ("quats", quats0), ("scales", scales0), ("rgb", rgb),
                      ("sh_rest", sh_rest), ("opacity", alpha)):  # fmt: skip
        if not np.isfinite(arr).all():
            raise ExportError(path, f"cannot write: {name} holds NaN or inf (a diverged fit?)")
    degree = model.sh_degree if sh_rest.shape[1] else 0
    sh = _sh_bytes(sh_rest) if degree else None

    # Tracks: M_phi's pose of every foreground object at every stored frame.
    tracks: list[Any] = []
    rot = trans = None
    times = None
    if run.motion is not None and run.times is not None:
        times = np.asarray(run.times, dtype=np.float64)
        rot, trans = _rotations(run)
        present = set(np.unique(labels).tolist())
        for k in range(rot.shape[0]):
            if k not in present or (k == 0 and not background_track):
                continue
            tracks.append(fd.ObjectTrack(
                object_id=k if k else rot.shape[0], interpolation=0,
                times=[float(t) for t in times],
                rotations=[_matrix_to_quat_xyzw(rot[k, j]).tolist() for j in range(len(times))],
                translations=[trans[k, j].tolist() for j in range(len(times))],
            ))  # fmt: skip

    # Object Table: names, anchors, embeddings where Phase 3 ran.
    names = dict(run.names) if run.names else {}
    fld, why = (None, "no embeddings: the run has no Phase 2 (no objects)") \
        if run.motion is None else _field(run)
    emb: dict[int, list[float]] = {}
    meta = {"sync4d.version": __version__, "sync4d.run": run.path.name,
            "sync4d.checkpoint": run.checkpoint.name,
            "sync4d.time": "normalised: scene second t is the run's time t in [0, 1]",
            "sync4d.quaternions": "x, y, z, w (sync4d's are w, x, y, z)",
            "sync4d.colours_clipped": f"{clipped:.6f} of the Gaussians' DC colours clipped to "
            "[0, 1]"}  # fmt: skip
    if fld is not None:
        static = np.asarray(fld.static, dtype=np.float64)
        for i, lab in enumerate(fld.labels):
            emb[int(lab)] = static[i].tolist()
        enc = dict(fld.encoder)
        meta.update({"sync4d.encoder.kind": str(enc.get("kind", "")),
                     "sync4d.encoder.dim": str(enc.get("dim", static.shape[1])),
                     "sync4d.encoder.fingerprint": str(enc.get("fingerprint", "")),
                     "sync4d.embeddings": "Field.static: each object's appearance embedding"})
    coords = coordinate_system(run)
    if coords:
        meta["coordinate_system"] = coords
    entries = []
    ids = sorted(set(np.unique(labels).tolist()) | set(names))
    bg_id = rot.shape[0] if background_track and rot is not None else 0
    file_ids = np.where(labels == 0, bg_id, labels)
    if run.motion is not None:
        for k in ids:
            sel = labels == k
            anchor = np.median(means0[sel], axis=0) if sel.any() else np.zeros(3)
            entries.append(fd.ObjectTableEntry(
                object_id=int(k if k else bg_id),
                label=names.get(int(k), "background" if k == 0 else f"object {k}"),
                anchor=tuple(float(v) for v in anchor), embedding=emb.get(int(k)),
            ))  # fmt: skip
    table = (fd.ObjectTable(embedding_dim=len(next(iter(emb.values()))) if emb else 0,
                            entries=entries) if entries else None)  # fmt: skip
    layer = fd.ObjectLayer(table=table, tracks=tracks) if table or tracks else None

    # The base state (one copy per Gaussian), or K copies holding D_theta's residual.
    if keyframes and (times is None or len(times) < 2):
        raise ExportError(path, "--4dgs-keyframes needs a Phase 2 run (its stored frames)")
    tracked = (np.isin(file_ids, [tr.object_id for tr in tracks]) if tracks
               else np.zeros(n, bool))  # fmt: skip
    lab = np.where(tracked, labels, 0)  # the M_phi row that moves each Gaussian
    if times is None:  # a Phase 1 run: the canonical Gaussians, nothing moves them
        pos, vel, rots, scl = means0, np.zeros_like(means0), _quat_wxyz_to_xyzw(quats0), scales0
        mu, lo, hi, rep = np.zeros(n), np.zeros(n), np.full(n, np.inf), 1
    else:
        frames = times if not keyframes else _keyframe_times(times, int(keyframes))
        cs, qs, ss = [], [], []
        for t in frames:
            c, q, sc = _in_object_frame(model, rot, trans, times, float(t), lab, tracked)
            if keyframes:
                cs.append(c), qs.append(q), ss.append(sc)
            else:  # running sums for the rest state (least squares over the stored frames)
                if not cs:
                    cs, qs, ss = [np.zeros_like(c)], [q.copy()], [np.zeros_like(sc)]
                    first = q
                else:
                    qs[0] += np.where((np.sum(q * first, axis=1) < 0)[:, None], -q, q)
                cs[0] += c
                ss[0] += np.log(sc)
        if keyframes:
            kk = len(frames) - 1
            pos = np.concatenate(cs[:kk])
            vel = np.concatenate([(cs[j + 1] - cs[j]) / (frames[j + 1] - frames[j])
                                  for j in range(kk)])  # fmt: skip
            rots, scl = np.concatenate(qs[:kk]), np.concatenate(ss[:kk])
            mu = lo = np.repeat(frames[:kk], n)
            hi = np.repeat(np.r_[frames[1:kk], np.inf], n)
            rep = kk
        else:
            f = float(len(frames))
            pos, rots, scl = cs[0] / f, qs[0], np.exp(ss[0] / f)
            rots = rots / np.maximum(np.linalg.norm(rots, axis=1, keepdims=True), 1e-30)
            vel = np.zeros_like(pos)
            mu, lo, hi, rep = np.zeros(n), np.zeros(n), np.full(n, np.inf), 1
    count = n * rep
    g = fd.GaussianSet(
        positions=pos.astype(np.float32), scales=scl.astype(np.float32),
        rotations=rots.astype(np.float32),
        colors=np.tile(np.concatenate([rgb, alpha[:, None]], axis=1), (rep, 1)).astype(np.float32),
        motions=vel.astype(np.float32), mu_t=mu.astype(np.float32),
        sigma_t=np.full(count, np.inf, dtype=np.float32), win_lo=lo, win_hi=hi,
        sh=None if sh is None else np.tile(sh, (rep, 1)), sh_degree=degree,
        object_id=np.tile(file_ids, rep).astype(np.uint32),
    )  # fmt: skip
    meta["sync4d.residual"] = (
        f"D_theta's residual over M_phi at {rep + 1} stored frames ({rep} copies per Gaussian)"
        if keyframes else "none: the tracks alone move the objects (D_theta's residual left out)"
    )  # fmt: skip
    opts = fd.WriteOptions(profile=profile, metadata=meta, objects=layer,
                           scene_profile="objects" if table is not None else "",
                           library=f"sync4d {__version__}, fourdgs {fd.__version__}")
    buf = io.BytesIO()
    try:
        size = fd.write(buf, g, 1.0, options=opts)
    except fd.FourdgsError as e:
        raise ExportError(path, f"fourdgs refused the scene: {e}") from None
    data = buf.getvalue()
    write_atomic(path, lambda tmp: tmp.write_bytes(data))
    return FourDGSReport(
        path=path, bytes=size, gaussians=n, records=count,
        objects=[e.label for e in entries], tracks=len(tracks), keyframes=rep if keyframes else 0,
        embeddings=None if fld is None else f"{len(emb)} objects, {fld.encoder.get('kind')} "
        f"encoder, {len(next(iter(emb.values())))} dims" if emb else None,
        note=why or "", seconds=_time.perf_counter() - start, metadata=meta,
    )  # fmt: skip


def _in_object_frame(
    model: Any, rot: np.ndarray, trans: np.ndarray, times: np.ndarray, t: float,
    lab: np.ndarray, tracked: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """D_theta's Gaussians at the stored frame `t` in their object's frame (M_phi's pose there
    undone: ``R^T (x - T)``, ``R^-1 (x) q``; untracked ones as they are): centres [N, 3],
    quaternions [N, 4] x, y, z, w, scales [N, 3], float64."""
    j = int(np.argmin(np.abs(times - t)))
    with torch.no_grad():
        m, q, sc = model.at_time(float(times[j]))
    m, q = m.double().numpy(), _quat_wxyz_to_xyzw(q.double().numpy())
    r_g, b_g = rot[lab, j], trans[lab, j]
    base = np.where(tracked[:, None], np.einsum("nji,nj->ni", r_g, m - b_g), m)
    rq = np.stack([_matrix_to_quat_xyzw(r) for r in rot[:, j]]) * np.array([-1.0, -1.0, -1.0, 1.0])
    qb = np.where(tracked[:, None], _quat_mul_xyzw(rq[lab], q), q)
    return base, qb, sc.double().numpy()


def read_4dgs(path: str | Path) -> Any:
    """The `.4dgs` file at `path` read by `fourdgs.read` (a `fourdgs.Scene`); ExportError naming
    the file when it cannot be read."""
    fd = fourdgs_module()
    try:
        return fd.read(str(path))
    except (fd.FourdgsError, OSError, ValueError) as e:
        raise ExportError(path, f"not a readable .4dgs file ({type(e).__name__}: {e})") from None


def validate_4dgs(path: str | Path) -> list[str]:
    """The validator's errors for the file at `path` (empty: it validates)."""
    from fourdgs.validate import validate

    report = validate(Path(path).read_bytes())
    return [str(f) for f in report.findings if f.severity == "error"]


def splats_from_4dgs(scene: Any, t: float) -> dict[str, torch.Tensor | int]:
    """The state of a read `.4dgs` scene at time `t` by the format's own rule
    (`Scene.state_at`: base state, then the object's track), as float32 tensors in sync4d's
    conventions: `means` [n, 3], `quats` [n, 4] w, x, y, z, `scales` [n, 3], `opacities` [n],
    `sh` [n, (d + 1)^2, 3], `degree` d, `object_ids` [n]."""
    g = scene.gaussians
    st = scene.state_at(float(t))
    idx = st["indices"]
    q = np.asarray(st["orientations"], dtype=np.float64)
    rgb = g.colors[idx, :3].astype(np.float64)
    dc = (rgb - 0.5) / _SH_C0
    degree = int(g.sh_degree) if g.sh is not None else 0
    if degree:
        coeffs = g.sh.shape[1] // 3
        vals = g.sh[idx].astype(np.float64) * ((_SH_HI - _SH_LO) / 255.0) + _SH_LO
        rest = vals.reshape(len(idx), 3, coeffs).transpose(0, 2, 1)[:, : (degree + 1) ** 2 - 1]
        sh = np.concatenate([dc[:, None], rest], axis=1)
    else:
        sh = dc[:, None]
    f32 = torch.float32
    return {
        "means": torch.as_tensor(st["centers"], dtype=f32),
        "quats": torch.as_tensor(np.concatenate([q[:, 3:], q[:, :3]], axis=1), dtype=f32),
        "scales": torch.as_tensor(g.scales[idx], dtype=f32),
        "opacities": torch.as_tensor(np.clip(st["opacity"], 0.0, 1.0), dtype=f32),
        "sh": torch.as_tensor(sh, dtype=f32), "degree": degree,
        "object_ids": torch.as_tensor(np.asarray(st["object_id"], dtype=np.int64)),
    }


def render_4dgs(
    scene: Any, camera: Any, t: float, *, near: float, background: torch.Tensor | None = None,
    threads: int | None = None,
) -> torch.Tensor:  # fmt: skip
    """The image [H, W, 3] of a read `.4dgs` scene at `t` from `camera` (a `sync4d.data.Camera`)
    through sync4d's rasterizer, as `DeformableGaussians.render` builds its call."""
    from sync4d import raster

    s = splats_from_4dgs(scene, t)
    viewmat = torch.as_tensor(camera.viewmat, dtype=torch.float32)
    colors = raster.sh_features(s["means"], s["sh"], viewmat, s["degree"], threads=threads)
    K = torch.as_tensor(camera.K, dtype=torch.float32)
    return raster.rasterize(s["means"], s["quats"], s["scales"], s["opacities"], colors, viewmat,
                            K, camera.width, camera.height, background=background, near=near,
                            threads=threads).features  # fmt: skip


def snapshot(out: str | Path, scene: Any, t: float) -> int:
    """Write the read `.4dgs` `scene` at time `t` as one static instant: glTF
    (``KHR_gaussian_splatting``; ``.glb`` or ``.gltf`` + ``.bin``) or USD (``.usd``/``.usda``/
    ``.usdc``, needs ``usd-core``) through `fourdgs`' converters, with the object tracks composed
    first; the bytes written. ExportError when the scene declares no coordinate system the
    converters know, or the converter refuses."""
    fd = fourdgs_module()
    out = Path(out)
    attrs = dict(getattr(scene.header, "attributes", {}) or {})
    coords = attrs.get("coordinate_system")
    if coords is None:
        raise ExportError(out, "the run's cameras give no +y or +z up axis, so the file declares "
                          "no coordinate system and the glTF / USD converters cannot place it")
    g = scene.gaussians
    st = scene.state_at(float(t))
    idx = st["indices"]
    m = len(idx)
    still = fd.GaussianSet(
        positions=np.asarray(st["centers"], dtype=np.float32),
        scales=g.scales[idx].astype(np.float32),
        rotations=np.asarray(st["orientations"], dtype=np.float32),
        colors=np.concatenate([g.colors[idx, :3], np.clip(st["opacity"], 0, 1)[:, None]],
                              axis=1).astype(np.float32),
        motions=np.zeros((m, 3), np.float32), mu_t=np.zeros(m, np.float32),
        sigma_t=np.full(m, np.inf, np.float32), win_lo=np.full(m, -np.inf),
        win_hi=np.full(m, np.inf), sh=None if g.sh is None else g.sh[idx], sh_degree=g.sh_degree,
        object_id=np.asarray(st["object_id"], dtype=np.uint32),
    )  # fmt: skip
    suffix = out.suffix.lower()
    try:
        if suffix in (".glb", ".gltf"):
            return fd.to_gltf(str(out), still, float(t), cutoff=scene.header.cutoff,
                              coordinate_system=coords)  # fmt: skip
        if suffix in (".usd", ".usda", ".usdc"):
            return fd.to_usd(str(out), still, float(t), cutoff=scene.header.cutoff,
                             coordinate_system=coords)  # fmt: skip
    except fd.FourdgsError as e:
        raise ExportError(out, f"fourdgs' converter refused it: {e}") from None
    raise ExportError(out, "give a .glb / .gltf (glTF) or .usd / .usda / .usdc (USD) file")
