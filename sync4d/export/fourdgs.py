"""`.4dgs` files: a run's Gaussians with Phase 2's objects and tracks and Phase 3's embeddings,
through the reference writer and reader of the format, `fourdgs` (Apache-2.0, spec v1 draft,
PyPI ``fourdgs==0.6.0``; an optional dependency: ``pip install 'sync4d[4dgs]'``).

What is kept (`write_4dgs`):

- the Gaussians as the file's base state: each one's least-squares rest in its object's frame
  (D_theta's state at every stored frame with its track's pose undone, ``R^T (x - T)`` and
  ``R^-1 (x) q``, averaged; scales geometrically; untracked ones in world space), or for a
  Phase 1 run the canonical Gaussians; unit rotations, linear scales, opacity
  (``sigmoid(logit)``), SH bands 1..3 and the DC colour as the format's RGB
  ``0.5 + SH_C0 * sh_dc``, which its grid holds in [0, 1] only: a colour outside is clipped and
  the Gaussian's SH rest refit so that it looks the same from the run's training cameras
  (`_fit_into_gamut`; the share clipped is in the Header's metadata);
- Phase 2's object of every Gaussian in the format's ``object_id`` stream (0 = background);
- one Object Track per foreground object (``background_track``: also the background's, under a
  new id named "background", since the format lets no track move object 0): M_phi's pose at
  each stored frame (run.times) refined to D_theta (`_refine_tracks`: robust weighted
  generalised Procrustes from M_phi's poses; ``refine=False`` writes M_phi's as stored; in
  affine mode R is the rotation of the polar decomposition and the rest of A is lost),
  interpolated by the format's ``linear`` rule (translation lerp, shortest-arc slerp, clamped
  outside the samples), SE3Table's own rule between frames;
- the Object Table: per object its name, an anchor (the median canonical mean of its
  Gaussians) and, where Phase 3 ran, its static embedding (`Field.static`, the appearance
  embedding ``query`` ranks by) with the encoder named in the Header's metadata
  (``sync4d.encoder.kind``, ``.dim``, ``.fingerprint``);
- D_theta's residual where a track alone is not close enough: a Gaussian that its track leaves
  further from D_theta at some stored frame (`_state_error`: centre distance plus the Frobenius
  distance of the extents ``R diag(s) R^T``, world units) than ``tolerance`` pixels in the
  training camera that sees it largest, divided by its opacity (a pixel error's share of the
  image error: a faint Gaussian may stray further; one no training camera sees never counts),
  is written as piecewise-linear records of the format's temporal fields instead of one: a
  record per segment between stored frames a and b, its object-frame state at a with the
  centre moving linearly to b's, valid over ``[t_a, t_b)`` (the last open-ended); segments
  are halved while a stored frame inside is further than the tolerance (`_segments`).
  ``residual="background"`` allows this only for untracked Gaussians (the objects then move by
  their tracks alone), ``"none"`` for none.

What is lost: D_theta between the stored frames beyond linear, and within the tolerance at
them (all of its residual with ``residual="none"``); M_phi's pose of the background (unless
``background_track``); the per-frame embeddings (``sync``) and the rest of the field; values
are quantised (the ``default`` profile: RGB and opacity to 1/255, SH coefficients to 8 bits
over [-4, 4], values beyond clipped; positions to 5% of the median scale). docs/export.md
measures each on bouncingballs.

Memory: the states at every stored frame are held as float32, 52 bytes per Gaussian and frame.

Conventions: quaternions in the file are x, y, z, w (sync4d's are w, x, y, z); SH layout is the
format's (and PLY's) channel-major ``(n, 3 * coeffs)``, bands 1..3 only, DC in the RGB; space is
the run's world frame and units, unconverted (the Header's ``coordinate_system`` metadata says
``z-up-right-handed`` or ``y-up-right-handed`` when the cameras' mean up is that axis, and is
absent otherwise); time: the file's clock is sync4d's normalised time, ``duration_sec`` 1.0 (a
time t in [0, 1] is the scene second t), every Gaussian never fading (``sigma_t`` inf), a base
record valid over ``[0, inf)``; the checkpoint's SHA-256 in ``sync4d.checkpoint.sha256`` (so
`sync4d serve --4dgs` can refuse a file of another checkpoint).

Reading back (`read_4dgs`, `splats_from_4dgs`) uses the format's own object-layer rule
(`fourdgs.Scene.state_at`: the base state, then the object's track composed once); `render_4dgs`
renders that state with sync4d's rasterizer. `snapshot` writes one instant as glTF
(``KHR_gaussian_splatting``, +y up baked into the Gaussians and their SH) or USD through the
package's converters, with the tracks composed first (the package's converters alone would
leave objects at rest).
"""

from __future__ import annotations

import io
import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sync4d import __version__
from sync4d.export.errors import ExportError
from sync4d.files import file_sha256, write_atomic

if TYPE_CHECKING:  # torch and the run load with the functions that use them
    import torch

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
#: What `write_4dgs(residual=...)` accepts.
RESIDUAL_CHOICES = ("all", "background", "none")
#: How far a Gaussian may be from D_theta at a stored frame before it gets a residual: pixels
#: in the training camera that sees it largest, times its opacity (docs/export.md measures it
#: on bouncingballs and basketball).
TOLERANCE = 0.25
#: The pull of `_fit_into_gamut`'s SH refit towards the old coefficients (per view): of 1e-3,
#: 1e-2 and 1e-1, 1e-3 kept bouncingballs' 20 test views nearest the run's render (a sweep
#: whose fit also saw the test cameras, not recorded; docs/export.md measures the fit, over the
#: training cameras alone, against the clip).
COLOUR_RIDGE = 1e-3


def fourdgs_module() -> Any:
    """The `fourdgs` package, or ExportError with the line that installs it."""
    try:
        import fourdgs
    except ImportError:
        raise ExportError("fourdgs", f"the .4dgs writer is not installed: {INSTALL}") from None
    return fourdgs


@dataclass
class FourDGSReport:
    """What `write_4dgs` wrote: the file, its size, the Gaussians and the records (a Gaussian
    with a residual has one per segment), objects, tracks, how many Gaussians hold a residual,
    each one's largest distance from D_theta with its track alone [N] and the distance it was
    allowed [N] (world units, `_state_error`; inf: no camera sees it), whether embeddings went
    in (and why not), seconds."""

    path: Path
    bytes: int
    gaussians: int
    records: int
    objects: list[str]
    tracks: int
    residual_gaussians: int
    deviation: np.ndarray
    limit: np.ndarray
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


def _sh_values(codes: np.ndarray) -> np.ndarray:
    """The format's u8 SH codes [N, 3K] (channel-major) as coefficients [N, K, 3], float64:
    the inverse of `_sh_bytes` up to its rounding."""
    n, k3 = codes.shape
    vals = codes.astype(np.float64) * ((_SH_HI - _SH_LO) / 255.0) + _SH_LO
    return vals.reshape(n, 3, k3 // 3).transpose(0, 2, 1)


def _sh_basis(degree: int, dirs: np.ndarray) -> np.ndarray:
    """sync4d's real SH basis up to `degree` at view directions `dirs` [M, 3] (normalised
    inside), float64 [M, (degree + 1)^2]: the rasterizer's own SH with unit coefficients."""
    import torch

    from sync4d import raster

    k = (degree + 1) ** 2
    eye = torch.eye(k, dtype=torch.float64).expand(len(dirs), k, k).contiguous()
    return raster.spherical_harmonics(degree, torch.as_tensor(dirs, dtype=torch.float64), eye,
                                      threads=1).numpy()  # fmt: skip


def _training_cameras(run: Run) -> list[dict]:
    """The run's training cameras (its test views left out), each viewpoint once."""
    seen: dict[bytes, dict] = {}
    for c in run.cameras:
        if c.get("split", "train") == "train":
            seen.setdefault(np.asarray(c["viewmat"], dtype=np.float64).tobytes(), c)
    return list(seen.values())


def _camera_centres(cameras: list[dict]) -> np.ndarray:
    """The centres of `cameras`, float64 [C, 3] (world space)."""
    out = []
    for c in cameras:
        v = np.asarray(c["viewmat"], dtype=np.float64).reshape(4, 4)
        out.append(-v[:3, :3].T @ v[:3, 3])
    return np.asarray(out).reshape(-1, 3)


def _pixels_per_unit(points: np.ndarray, cameras: list[dict], near: float,
                     chunk: int = 65536) -> np.ndarray:  # fmt: skip
    """How many pixels a world unit at each of `points` [N, 3] spans in the training camera that
    sees it largest (focal length over depth, among the `cameras` that have it in front of
    `near` and inside the image), float64 [N]; 0 where no camera sees it."""
    out = np.zeros(len(points))
    for c in cameras:
        v = np.asarray(c["viewmat"], dtype=np.float64).reshape(4, 4)
        for s in range(0, len(points), chunk):
            x = points[s:s + chunk] @ v[:3, :3].T + v[:3, 3]
            z = x[:, 2]
            front = z > near
            zs = np.where(front, z, 1.0)
            u = c["fx"] * x[:, 0] / zs + c["cx"]
            w = c["fy"] * x[:, 1] / zs + c["cy"]
            seen = front & (u >= 0) & (u < c["width"]) & (w >= 0) & (w < c["height"])
            ppu = np.where(seen, max(c["fx"], c["fy"]) / zs, 0.0)
            out[s:s + chunk] = np.maximum(out[s:s + chunk], ppu)
    return out


def _fit_into_gamut(
    rgb: np.ndarray, sh_rest: np.ndarray, means: np.ndarray, centres: np.ndarray,
    ridge: float = COLOUR_RIDGE, chunk: int = 2048,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Colours the format's grid holds: the DC colour `rgb` [N, 3] clipped to [0, 1], and for
    each Gaussian that clipped, its SH rest [N, K, 3] refit so that its colour seen from the
    camera `centres` [C, 3] stays what it was (ridge least squares per Gaussian and channel over
    the C view directions from `means` [N, 3], pulled towards the old rest by `ridge` times C;
    bands 1.. are orthogonal to a constant on the whole sphere, not over the views a capture
    has). Returns the clipped RGB, the new rest and the clipped Gaussians' mask [N]."""
    clipped_rgb = np.clip(rgb, 0.0, 1.0)
    mask = (clipped_rgb != rgb).any(axis=1)
    rest = sh_rest.copy()
    k = sh_rest.shape[1]
    if not k or not mask.any() or not len(centres):
        return clipped_rgb, rest, mask
    degree = int(round(math.sqrt(k + 1))) - 1
    idx = np.flatnonzero(mask)
    c = len(centres)
    for s in range(0, len(idx), chunk):
        sel = idx[s:s + chunk]
        dirs = (means[sel, None, :] - centres[None]).reshape(-1, 3)
        basis = _sh_basis(degree, dirs).reshape(len(sel), c, k + 1)
        b0, br = basis[:, :, :1], basis[:, :, 1:]
        dc_old = (rgb[sel] - 0.5) / _SH_C0
        dc_new = (clipped_rgb[sel] - 0.5) / _SH_C0
        # keep B0 dc + Br rest: Br rest' = Br rest + B0 (dc - dc'), ridge towards rest
        target = br @ rest[sel] + b0 * (dc_old - dc_new)[:, None, :]
        lhs = np.swapaxes(br, 1, 2) @ br + ridge * c * np.eye(k)
        rhs = np.swapaxes(br, 1, 2) @ target + ridge * c * rest[sel]
        rest[sel] = np.linalg.solve(lhs, rhs)
    return clipped_rgb, rest, mask


def write_4dgs(
    path: str | Path, run: Run, *, tolerance: float = TOLERANCE, residual: str = "all",
    refine: bool = True, fit_colours: bool = True, profile: str = "default",
    background_track: bool = False,
) -> FourDGSReport:  # fmt: skip
    """Write `run` as a `.4dgs` file at `path` (atomically); what was written. `residual`:
    which Gaussians may hold D_theta's residual over their track ("all", "background": the
    untracked ones only, so the objects move by their tracks alone, "none"); those whose track
    alone leaves them further from D_theta at some stored frame than `tolerance` pixels (in the
    training camera that sees them largest, over their opacity) get piecewise-linear records
    instead of one (see the module docstring).
    `refine`: M_phi's poses refined to D_theta (else as stored); `fit_colours`: the SH rest of
    Gaussians whose colour the format clips refit over the run's views. ExportError when
    `fourdgs` is missing or the run cannot be written."""
    import torch

    fd = fourdgs_module()
    start = _time.perf_counter()
    path = Path(path)
    if residual not in RESIDUAL_CHOICES:
        raise ExportError(path, f"residual {residual!r}: give one of {', '.join(RESIDUAL_CHOICES)}")
    if not tolerance >= 0.0:
        raise ExportError(path, f"tolerance {tolerance}: give a number >= 0 (0: every stored "
                          "frame exact; larger: fewer records)")
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
        sh_rest = model.sh_rest.detach().double().numpy()
    for name, arr in (("means", means0), ("quats", quats0), ("scales", scales0), ("rgb", rgb),
                      ("sh_rest", sh_rest), ("opacity", alpha)):  # fmt: skip
        if not np.isfinite(arr).all():
            raise ExportError(path, f"cannot write: {name} holds NaN or inf (a diverged fit?)")
    cameras = _training_cameras(run)
    # The format's colour grid holds [0, 1] only: clip, and carry what clipping loses into the
    # SH rest over the run's views.
    if fit_colours:
        rgb, sh_rest, clip_mask = _fit_into_gamut(rgb, sh_rest, means0, _camera_centres(cameras))
    else:
        clip_mask = ((rgb < 0.0) | (rgb > 1.0)).any(axis=1)
        rgb = np.clip(rgb, 0.0, 1.0)
    clipped = float(clip_mask.mean())
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
            "[0, 1]" + ("; their SH rest refit over the run's camera views" if fit_colours
                        else "")}  # fmt: skip
    if fld is not None:
        static = np.asarray(fld.static, dtype=np.float64)
        for i, lab in enumerate(fld.labels):
            emb[int(lab)] = static[i].tolist()
        enc = dict(fld.encoder)
        meta.update({"sync4d.encoder.kind": str(enc.get("kind", "")),
                     "sync4d.encoder.dim": str(enc.get("dim", static.shape[1])),
                     "sync4d.encoder.fingerprint": str(enc.get("fingerprint", "")),
                     "sync4d.embeddings": "Field.static: each object's appearance embedding"})
    if run.checkpoint.is_file():  # (a Run built in memory has none)
        meta["sync4d.checkpoint.sha256"] = file_sha256(run.checkpoint)
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

    # The base state: one record per Gaussian, or piecewise-linear records for one that its
    # track alone leaves further from D_theta than its limit.
    tracked = (np.isin(file_ids, [tr.object_id for tr in tracks]) if tracks
               else np.zeros(n, bool))  # fmt: skip
    lab = np.where(tracked, labels, 0)  # the M_phi row that moves each Gaussian
    needs = np.zeros(n, bool)
    deviation = np.zeros(n)
    limit = np.full(n, np.inf)
    order = np.arange(n)  # the Gaussian each record is a copy of
    if times is None:  # a Phase 1 run: the canonical Gaussians, nothing moves them
        pos, vel, rots, scl = means0, np.zeros_like(means0), _quat_wxyz_to_xyzw(quats0), scales0
        mu, lo, hi = np.zeros(n), np.zeros(n), np.full(n, np.inf)
    else:
        if not cameras and residual != "none":
            raise ExportError(path, "the run records no training cameras (its checkpoint's "
                              "metadata), so the residual's tolerance, in pixels, has none to "
                              "measure in; write the tracks alone with --4dgs-residual none")
        wc, wq, ws = _world_states(model, times)
        # how far each Gaussian may be from D_theta: `tolerance` pixels in the training camera
        # that sees it largest, divided by its opacity (a faint one may stray further)
        ppu = _pixels_per_unit(wc.mean(axis=0, dtype=np.float64), cameras, float(model.near))
        limit = tolerance / np.maximum(alpha * ppu, 1e-12)
        if refine and tracks:
            rot, trans = _refine_tracks(wc, alpha, labels, rot, trans,
                                        sorted({int(k) for k in lab[tracked]}))  # fmt: skip
            for tr in tracks:
                k = tr.object_id if tr.object_id < rot.shape[0] else 0
                tr.rotations = [_matrix_to_quat_xyzw(r).tolist() for r in rot[k]]
                tr.translations = trans[k].tolist()
        _to_object_frame(wc, wq, rot, trans, lab, tracked)
        # the rest: least squares over the stored frames (mean centre, sign-aligned mean
        # quaternion, geometric mean scale)
        pos = wc.mean(axis=0, dtype=np.float64)
        rots = wq.sum(axis=0, dtype=np.float64)
        rots /= np.maximum(np.linalg.norm(rots, axis=1, keepdims=True), 1e-30)
        scl = np.exp(np.log(ws).mean(axis=0, dtype=np.float64))
        rest_ext = _shape(rots, scl)
        for j in range(len(times)):
            deviation = np.maximum(deviation, _extent_error(pos, rest_ext, wc[j],
                                                            _shape(wq[j], ws[j])))
        needs = {"all": deviation > limit, "background": (deviation > limit) & ~tracked,
                 "none": np.zeros(n, bool)}[residual]  # fmt: skip
        vel = np.zeros_like(pos)
        mu, lo, hi = np.zeros(n), np.zeros(n), np.full(n, np.inf)
        if needs.any():
            idx = np.flatnonzero(needs)
            parts = [np.flatnonzero(~needs)]
            cols: dict[str, list[np.ndarray]] = {k: [a[~needs]] for k, a in
                (("pos", pos), ("vel", vel), ("rot", rots), ("scl", scl), ("mu", mu),
                 ("lo", lo), ("hi", hi))}  # fmt: skip
            last = len(times) - 1
            for sub, a, b in _segments(times, wc[:, idx], wq[:, idx], ws[:, idx], limit[idx]):
                g = idx[sub]
                m = len(g)
                parts.append(g)
                cols["pos"].append(wc[a, g].astype(np.float64))
                cols["vel"].append((wc[b, g] - wc[a, g]).astype(np.float64)
                                   / (times[b] - times[a]))  # fmt: skip
                cols["rot"].append(wq[a, g].astype(np.float64))
                cols["scl"].append(ws[a, g].astype(np.float64))
                cols["mu"].append(np.full(m, times[a]))
                cols["lo"].append(np.full(m, times[a] if a else min(0.0, times[0])))
                cols["hi"].append(np.full(m, times[b] if b < last else np.inf))
            order = np.concatenate(parts)
            pos, vel, rots, scl, mu, lo, hi = (np.concatenate(cols[k]) for k in
                                               ("pos", "vel", "rot", "scl", "mu", "lo", "hi"))
    count = len(order)
    g = fd.GaussianSet(
        positions=pos.astype(np.float32), scales=scl.astype(np.float32),
        rotations=rots.astype(np.float32),
        colors=np.concatenate([rgb, alpha[:, None]], axis=1)[order].astype(np.float32),
        motions=vel.astype(np.float32), mu_t=mu.astype(np.float32),
        sigma_t=np.full(count, np.inf, dtype=np.float32), win_lo=lo, win_hi=hi,
        sh=None if sh is None else sh[order], sh_degree=degree,
        object_id=file_ids[order].astype(np.uint32),
    )  # fmt: skip
    nres = int(needs.sum())
    meta["sync4d.tracks"] = ("M_phi's poses refined to D_theta (weighted Procrustes)" if refine
                             else "M_phi's poses as stored")  # fmt: skip
    meta["sync4d.residual"] = (
        f"D_theta's residual ({residual}) as {count - n + nres} piecewise-linear records for "
        f"the {nres} Gaussians their track alone leaves further from D_theta at some stored "
        f"frame than {tolerance:g} pixels (times their opacity) in the training camera that "
        "sees them largest"
        if nres else f"none ({residual}): the tracks alone move the objects (D_theta's residual "
        "left out)"
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
        objects=[e.label for e in entries], tracks=len(tracks), residual_gaussians=nres,
        deviation=deviation, limit=limit,
        embeddings=None if fld is None else f"{len(emb)} objects, {fld.encoder.get('kind')} "
        f"encoder, {len(next(iter(emb.values())))} dims" if emb else None,
        note=why or "", seconds=_time.perf_counter() - start, metadata=meta,
    )  # fmt: skip


def _refine_tracks(
    centres: np.ndarray, weights: np.ndarray, labels: np.ndarray, rot: np.ndarray,
    trans: np.ndarray, objects: list[int], iters: int = 6,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """M_phi's poses refined to D_theta: for each of `objects`, from M_phi's rotations [K, T, 3,
    3] and translations [K, T, 3], `iters` rounds of robust weighted generalised Procrustes:
    the rest shape as the mean of the object's points with the poses undone, then per frame
    the rigid motion (`sync4d.geometry.kabsch`) that takes it nearest D_theta's `centres` [T, N,
    3], each point weighted by `weights` [N] (opacity) times a Cauchy weight
    ``1 / (1 + (r / 2 r_med)^2)`` of its RMS distance r over the frames, so the few Gaussians
    that leave the object (a shadow given to it, a squash) do not drag its pose. New arrays,
    float64."""
    from sync4d.geometry import kabsch  # (torch: imported with the writer, not the reader)

    rot, trans = rot.copy(), trans.copy()
    for k in objects:
        sel = labels == k
        if sel.sum() < 3:
            continue
        x = centres[:, sel].astype(np.float64)  # [T, n, 3]
        r, b = rot[k], trans[k]
        robust = np.ones(int(sel.sum()))
        for _ in range(iters):
            rest = np.einsum("tji,tnj->ni", r, x - b[:, None]) / len(x)
            w = weights[sel] * robust
            fits = [kabsch(rest, x[j], w) for j in range(len(x))]
            r = np.stack([f[0] for f in fits])
            b = np.stack([f[1] for f in fits])
            dist = np.sqrt(np.mean(np.sum((np.einsum("tij,nj->tni", r, rest) + b[:, None] - x)
                                          ** 2, axis=2), axis=0))  # fmt: skip
            robust = 1.0 / (1.0 + (dist / max(2.0 * float(np.median(dist)), 1e-12)) ** 2)
        rot[k], trans[k] = r, b
    return rot, trans


def _world_states(model: Any, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """D_theta's Gaussians at every stored frame: centres [T, N, 3], quaternions [T, N, 4]
    (x, y, z, w) and scales [T, N, 3], float32 (52 bytes per Gaussian and frame)."""
    import torch

    cs, qs, ss = [], [], []
    with torch.no_grad():
        for t in times:
            m, q, sc = model.at_time(float(t))
            cs.append(m.float().numpy())
            qs.append(_quat_wxyz_to_xyzw(q.double().numpy()).astype(np.float32))
            ss.append(sc.float().numpy())
    return np.stack(cs), np.stack(qs), np.stack(ss)


def _to_object_frame(
    centres: np.ndarray, quats: np.ndarray, rot: np.ndarray, trans: np.ndarray, lab: np.ndarray,
    tracked: np.ndarray,
) -> None:  # fmt: skip
    """Undo each tracked Gaussian's object pose in place, frame by frame: centres ``R^T (x -
    T)``, quaternions ``R^-1 (x) q`` (sign-aligned with frame 0); untracked ones stay."""
    for j in range(len(centres)):
        r, b = rot[lab, j], trans[lab, j]
        c = centres[j].astype(np.float64)
        centres[j] = np.where(tracked[:, None], np.einsum("nji,nj->ni", r, c - b), c)
        rq = np.stack([_matrix_to_quat_xyzw(m) for m in rot[:, j]]) * np.array([-1, -1, -1, 1.0])
        q = np.where(tracked[:, None], _quat_mul_xyzw(rq[lab], quats[j].astype(np.float64)),
                     quats[j])  # fmt: skip
        if j:
            q = np.where((np.sum(q * quats[0], axis=1) < 0)[:, None], -q, q)
        quats[j] = q


def _quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of quaternions [..., 4] (x, y, z, w; normalised here):
    `sync4d.geometry.quat_to_matrix` in the file's order, float64."""
    import torch

    from sync4d.geometry import quat_to_matrix

    wxyz = np.asarray(q, dtype=np.float64)[..., [3, 0, 1, 2]]
    return quat_to_matrix(torch.as_tensor(wxyz)).numpy()


def _shape(q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """A Gaussian's extent as the symmetric square root of its covariance, ``R diag(s) R^T``
    [..., 3, 3], from quaternions (x, y, z, w) [..., 4] and scales [..., 3]."""
    r = _quat_xyzw_to_matrix(q)
    return (r * s[..., None, :]) @ np.swapaxes(r, -1, -2)


def _state_error(
    c: np.ndarray, q: np.ndarray, s: np.ndarray, c_ref: np.ndarray, q_ref: np.ndarray,
    s_ref: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """How far a written state (`c`, `q`, `s`: centres, x, y, z, w quaternions, scales, [..., n,
    3|4|3]) is from D_theta's (`*_ref`), in world units [..., n]: the centres' distance plus
    the Frobenius distance of the extents (`_shape`: a scale's change counts as itself, a turn
    as the angle times the difference of the scales it mixes, so a sphere may turn freely)."""
    return _extent_error(c, _shape(q, s), c_ref, _shape(q_ref, s_ref))


def _extent_error(c: np.ndarray, e: np.ndarray, c_ref: np.ndarray,
                  e_ref: np.ndarray) -> np.ndarray:  # fmt: skip
    """`_state_error` on extents already made (`_shape`: [..., n, 3, 3])."""
    return np.linalg.norm(c - c_ref, axis=-1) + np.linalg.norm(e - e_ref, axis=(-2, -1))


def _segments(
    times: np.ndarray, c: np.ndarray, q: np.ndarray, s: np.ndarray, limit: np.ndarray,
) -> list[tuple[np.ndarray, int, int]]:  # fmt: skip
    """Piecewise-linear paths for Gaussians whose object-frame states `c`, `q`, `s` [T, m, ...]
    at the stored `times` [T] need more than one record: a segment from stored frame a to b
    holds the state at a, its centre moving linearly to b's; it is split at the middle frame
    while some frame in between is further than `limit` [m] (world units, `_state_error`)
    from D_theta's. Returns (Gaussian indices into m, a, b) per segment group."""
    out: list[tuple[np.ndarray, int, int]] = []
    ext = _shape(q, s).astype(np.float32)  # [T, m, 3, 3], once for every split
    work = [(np.arange(c.shape[1]), 0, len(times) - 1)]
    while work:
        idx, a, b = work.pop()
        if b - a <= 1:
            out.append((idx, a, b))
            continue
        w = ((times[a:b + 1] - times[a]) / (times[b] - times[a]))[:, None, None]
        lin = c[a, idx] + w * (c[b, idx] - c[a, idx])
        err = _extent_error(lin, ext[a, idx], c[a:b + 1, idx],
                            ext[a:b + 1, idx]).max(axis=0)  # fmt: skip
        fine = err <= limit[idx]
        if fine.any():
            out.append((idx[fine], a, b))
        if not fine.all():
            mid = (a + b) // 2
            work += [(idx[~fine], a, mid), (idx[~fine], mid, b)]
    return out


def read_4dgs(path: str | Path) -> Any:
    """The `.4dgs` file at `path` read by `fourdgs.read` (a `fourdgs.Scene`); ExportError naming
    the file when it cannot be read."""
    fd = fourdgs_module()
    try:
        return fd.read(str(path))
    except (fd.FourdgsError, OSError, ValueError) as e:
        raise ExportError(path, f"not a readable .4dgs file ({type(e).__name__}: {e})") from None


def read_summary(path: str | Path) -> dict[str, Any]:
    """A `.4dgs` file's Header and object layer without its Gaussians (milliseconds, by the
    format's indexed reader): ``bytes``, ``records``, ``duration_sec``, ``profile``,
    ``metadata`` (the Header's attributes: sync4d's ``sync4d.*`` keys), ``objects`` (id,
    label, whether it has an embedding) and ``tracks`` (the object ids with one). ExportError
    naming the file when it is missing or no readable `.4dgs`."""
    fourdgs_module()
    from fourdgs.exceptions import FourdgsError
    from fourdgs.indexed_reader import open_indexed, read_objects
    from fourdgs.readable import FileReadable

    path = Path(path)
    if not path.is_file():
        raise ExportError(path, "no such file; write it with `sync4d export RUN --4dgs "
                          f"{path}`")  # fmt: skip
    try:
        src = FileReadable(str(path))
        scene = open_indexed(src)
        layer = read_objects(src, scene)
    except (FourdgsError, OSError, ValueError) as e:
        raise ExportError(path, f"not a readable .4dgs file ({type(e).__name__}: {e})") from None
    head = scene.header
    table = layer.table.entries if layer is not None and layer.table is not None else []
    return {
        "bytes": path.stat().st_size, "records": int(head.gaussian_count),
        "duration_sec": float(head.duration_sec), "profile": str(head.profile),
        "metadata": {str(k): str(v) for k, v in dict(head.attributes or {}).items()},
        "objects": [{"id": int(e.object_id), "label": str(e.label),
                     "embedding": e.embedding is not None} for e in table],
        "tracks": sorted(int(t.object_id) for t in (layer.tracks if layer else [])),
    }  # fmt: skip


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
    import torch

    g = scene.gaussians
    st = scene.state_at(float(t))
    idx = st["indices"]
    q = np.asarray(st["orientations"], dtype=np.float64)
    rgb = g.colors[idx, :3].astype(np.float64)
    dc = (rgb - 0.5) / _SH_C0
    degree = int(g.sh_degree) if g.sh is not None else 0
    if degree:
        rest = _sh_values(g.sh[idx])[:, : (degree + 1) ** 2 - 1]
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
    import torch

    from sync4d import raster

    s = splats_from_4dgs(scene, t)
    viewmat = torch.as_tensor(camera.viewmat, dtype=torch.float32)
    colors = raster.sh_features(s["means"], s["sh"], viewmat, s["degree"], threads=threads)
    K = torch.as_tensor(camera.K, dtype=torch.float32)
    return raster.rasterize(s["means"], s["quats"], s["scales"], s["opacities"], colors, viewmat,
                            K, camera.width, camera.height, background=background, near=near,
                            threads=threads).features  # fmt: skip


#: The rotation (a matrix) that carries each coordinate system the converters know into glTF's
#: +y up, right-handed frame (fourdgs.gltf's node rotations, written as matrices).
_TO_Y_UP = {
    "y-up-right-handed": np.eye(3),
    "z-up-right-handed": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}


def _sh_rotation(degree: int, r: np.ndarray, samples: int = 512) -> np.ndarray:
    """The matrix X [K, K] (K = (degree + 1)^2 - 1, bands 1..degree) that turns a Gaussian's SH
    rest coefficients c into those of the Gaussian turned by the rotation `r` [3, 3]: the
    colour the turned one shows towards r d is the one the old showed towards d,
    ``Y(r d) . (X c) = Y(d) . c`` (sync4d's SH basis, fitted over `samples` directions; exact,
    a rotation keeps each band)."""
    d = np.random.default_rng(0).normal(size=(samples, 3))
    x, *_ = np.linalg.lstsq(_sh_basis(degree, d @ r.T)[:, 1:], _sh_basis(degree, d)[:, 1:],
                            rcond=None)  # B(r d) X = B(d)  # fmt: skip
    return x


def snapshot(out: str | Path, scene: Any, t: float) -> int:
    """Write the read `.4dgs` `scene` at time `t` as one static instant: glTF
    (``KHR_gaussian_splatting``; ``.glb`` or ``.gltf`` + ``.bin``; +y up baked into the
    Gaussians, SH rotated by `_sh_rotation`) or USD (``.usd``/``.usda``/``.usdc``, needs
    ``usd-core``; the run's up axis as the stage's) through `fourdgs`' converters, with the
    object tracks composed first; the bytes written. ExportError when the scene declares no
    coordinate system the converters know, or the converter refuses."""
    fd = fourdgs_module()
    out = Path(out)
    attrs = dict(getattr(scene.header, "attributes", {}) or {})
    coords = attrs.get("coordinate_system")
    if coords not in _TO_Y_UP:
        raise ExportError(out, "the run's cameras give no +y or +z up axis, so the file declares "
                          "no coordinate system and the glTF / USD converters cannot place it")
    g = scene.gaussians
    st = scene.state_at(float(t))
    idx = st["indices"]
    m = len(idx)
    centres = np.asarray(st["centers"], dtype=np.float64)
    quats = np.asarray(st["orientations"], dtype=np.float64)
    sh = None if g.sh is None else g.sh[idx]
    suffix = out.suffix.lower()
    if suffix in (".glb", ".gltf") and coords != "y-up-right-handed":
        # Bake glTF's +y up into the Gaussians (positions, orientations and SH) rather than
        # leave fourdgs' node rotation: a viewer then needs no transform, and SH of degree > 0
        # under a rotating node are what fourdgs' own importer refuses to read.
        r = _TO_Y_UP[coords]
        centres = centres @ r.T
        quats = _quat_mul_xyzw(_matrix_to_quat_xyzw(r), quats)
        if sh is not None and g.sh_degree:
            k = sh.shape[1] // 3
            sh = _sh_bytes(_sh_rotation(int(g.sh_degree), r)[:k, :k] @ _sh_values(sh))
        coords = "y-up-right-handed"
    still = fd.GaussianSet(
        positions=centres.astype(np.float32),
        scales=g.scales[idx].astype(np.float32),
        rotations=quats.astype(np.float32),
        colors=np.concatenate([g.colors[idx, :3], np.clip(st["opacity"], 0, 1)[:, None]],
                              axis=1).astype(np.float32),
        motions=np.zeros((m, 3), np.float32), mu_t=np.zeros(m, np.float32),
        sigma_t=np.full(m, np.inf, np.float32), win_lo=np.full(m, -np.inf),
        win_hi=np.full(m, np.inf), sh=sh, sh_degree=g.sh_degree,
        object_id=np.asarray(st["object_id"], dtype=np.uint32),
    )  # fmt: skip
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
