"""Splat files: the Gaussians of a run, canonical or deformed to a time by D_theta, in the files
3DGS viewers and tools read.

`Splats` holds Gaussians in the 3DGS PLY convention (pre-activation float32 values: log-scales,
opacity logits, SH coefficients; quaternions w, x, y, z) plus each Gaussian's object id
(Phase 2's label, 0 = background or no Phase 2). `splats_at(run, t)` makes them from a run.

PLY (`write_ply` / `read_ply`): binary little endian through plyfile, one ``vertex`` element
whose float32 properties follow gsplat 1.5.3's exporter exactly (``x y z``, ``f_dc_0..2``,
``f_rest_0..3K-1`` channel-major: all K red coefficients, then green, then blue, ``opacity``,
``scale_0..2``, ``rot_0..3``), then one ``int object_id``; comments ``sync4d <version>`` and
``time <t>`` (or ``canonical``). Lossless: reading gives every value back exactly. A plain
3DGS PLY of another tool reads too (object ids 0).

SPZ (`write_spz` / `read_spz`): Niantic's compressed format (gzip container, version 3)
through gsply. Lossy; with gsply 0.4.6's quantisation, a value inside the stated range comes
back within (values outside it are clipped to its ends):

- positions: 24-bit fixed point with 12 fractional bits, |error| <= 2^-13 = 1.2e-4 world
  units, |x| < 2048 (`write_spz` refuses positions beyond: write a PLY);
- opacity: 8 bits of sigmoid(logit), |error of the opacity| <= 1/510 = 2.0e-3 (the logit read
  back is clamped at opacities 1e-6 and 1 - 1e-6);
- DC colour: 8 bits of ``sh_dc * 0.15 * 255 + 127.5``, |error| <= 1/76.5 = 0.0131 for
  ``sh_dc`` in [-3.33, 3.33];
- scales: 8 bits of ``(log_scale + 10) * 16``, |error of the log-scale| <= 1/32 for log-scales
  in [-10, 5.94];
- rotations: unit quaternions (normalised on write), smallest-three with 9 bits: each stored
  component within 6.9e-4, the largest, recomputed, within 2.1e-3 (of q or -q: a rotation's
  sign is not kept, and read-back quaternions are unit with the largest component >= 0);
- higher SH bands: 8 bits of ``sh * 128 + 128``, |error| <= 1/256 = 3.9e-3 in [-1, 127/128].

SPZ has no place for object ids (read back as 0) nor for the time. Coordinates: Niantic's
reference stores SPZ data in RUB axes (OpenGL: x right, y up, z back) and converts when its
caller names a source or target system (``PackOptions.from`` / ``UnpackOptions.to``; the
default, UNSPECIFIED, converts nothing), while PLY files are usually RDF. gsply writes the
values it is given, unconverted, and so does sync4d: an SPZ holds the run's world coordinates,
exactly as its PLY does. A viewer that assumes RUB content and converts it shows the scene with
y and z flipped relative to the PLY.

4D files (`write_sequence` / `read_sequence`), frames at given times (`default_times`):

- ``.ply``: brush's delta-frame PLY. The base ``vertex`` element is the canonical Gaussians
  (exactly as `write_ply` writes them, object ids included); then, for each frame i, an element
  ``delta_vertex_<i>`` of N rows of float32 ``x y z scale_0 scale_1 scale_2 rot_0 rot_1 rot_2
  rot_3`` holding (value at the frame's time) - (base value) for the mean, the log-scale and
  the raw quaternion (a reader adds it to the base and normalises the quaternion; without
  ``meta_delta_min_/max_`` elements brush reads float deltas unscaled). Opacity and colours do
  not change over time. Frame times are in the comments (``frame <i> time <t>``).
- a folder (``DIR/``, or a path without suffix): SuperSplat's PLY sequence. One standard PLY
  per time, ``DIR/<NAME>_<i:04d>.ply`` (NAME: the folder's name, characters other than letters,
  digits, ``-`` and ``_`` replaced by ``_``), each byte for byte what `write_ply` writes for that
  time (its time in the comment), and nothing else in the folder: SuperSplat's import
  (``src/file-handler.ts`` ``isPlySequence``) treats dropped files as a sequence only when every
  one matches ``(.*?)(\\d+)(?:\\.compressed)?\\.ply$`` with one shared prefix, so a sidecar inside
  would turn the drop into separate imports. The frame times are in the sidecar ``DIR.json``
  beside the folder (`sequence_sidecar`).
- ``.zip`` (deprecated: no viewer found to import it): one standard PLY per time,
  ``frame_<i:04d>_t<time:.4f>.ply``, each byte for byte what `write_ply` writes for that time.

Writes are atomic (`sync4d.files.write_atomic`) and deterministic: the same run and arguments
give the same bytes (zip members carry a fixed date; SPZ's gzip header no time stamp). Every
file that cannot be read raises `ExportError` naming it, never a parser's traceback.
"""

from __future__ import annotations

import io
import json
import math
import re
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyElementParseError, PlyHeaderParseError

from sync4d import __version__
from sync4d.export.errors import ExportError
from sync4d.files import write_atomic, write_text_atomic
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.runs.folder import Run

__all__ = [
    "ExportError",
    "Splats",
    "default_times",
    "is_sequence_folder",
    "ply_properties",
    "read_ply",
    "read_sequence",
    "read_spz",
    "sequence_frame_name",
    "sequence_sidecar",
    "splats_at",
    "write_ply",
    "write_sequence",
    "write_sequence_folder",
    "write_spz",
]

#: Vertex properties every splat PLY needs (besides ``f_rest_*``, absent at SH degree 0).
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")  # fmt: skip
#: The float32 properties of a ``delta_vertex_<i>`` element of a delta-frame PLY.
_DELTA = ("x", "y", "z", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
#: Largest |position| SPZ's 24-bit fixed point holds with gsply's 12 fractional bits.
_SPZ_POSITION_LIMIT = 2.0**23 / 2.0**12
#: The date of every zip member (zip's earliest), so the same frames give the same bytes.
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)
_ZIP_FRAME = re.compile(r"frame_(\d{4})_t([0-9.]+)\.ply")
_HINT = "export it again (sync4d writes splat PLYs of 3DGS layout)"


@dataclass(eq=False)
class Splats:
    """N Gaussians in the 3DGS PLY convention, float32 numpy arrays of pre-activation values:
    `means` [N, 3] world units, `quats` [N, 4] w, x, y, z (unit after deformation, the raw
    parameters in the canonical state), `log_scales` [N, 3] natural log of the standard
    deviations, `opacity_logits` [N], `sh_dc` [N, 3] and `sh_rest` [N, K, 3] SH coefficients
    (K = (degree + 1)^2 - 1, in band order), `object_ids` [N] int32 (0: background or no
    Phase 2). `time` in [0, 1] the state was deformed to, None for the canonical Gaussians.
    Arrays are converted and checked on creation (ValueError for a shape that does not fit)."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    object_ids: np.ndarray
    time: float | None = None

    def __post_init__(self) -> None:
        f32 = np.float32
        self.means = np.ascontiguousarray(self.means, dtype=f32)
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        self.quats = np.ascontiguousarray(self.quats, dtype=f32)
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=f32)
        self.opacity_logits = np.ascontiguousarray(self.opacity_logits, dtype=f32)
        self.sh_dc = np.ascontiguousarray(self.sh_dc, dtype=f32)
        self.sh_rest = np.ascontiguousarray(self.sh_rest, dtype=f32)
        self.object_ids = np.ascontiguousarray(self.object_ids, dtype=np.int32)
        k = self.sh_rest.shape[1] if self.sh_rest.ndim == 3 else -1
        want = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,),
                "sh_dc": (n, 3), "sh_rest": (n, k, 3), "object_ids": (n,)}  # fmt: skip
        for name, shape in want.items():
            got = getattr(self, name).shape
            if got != shape:
                raise ValueError(f"{name}: expected shape {_shape(shape)}, got {list(got)}")
        if math.isqrt(k + 1) ** 2 != k + 1:
            raise ValueError(f"sh_rest: {k} coefficients per channel is no SH degree's "
                             "(0, 3, 8, 15, ...)")  # fmt: skip
        if self.time is not None:
            self.time = _check_time(self.time)

    def __len__(self) -> int:
        """N, the number of Gaussians."""
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """The SH degree, from K = (degree + 1)^2 - 1 coefficients per channel."""
        return math.isqrt(self.sh_rest.shape[1] + 1) - 1


def _shape(shape: tuple[int, ...]) -> str:
    names = {0: "N", 1: "K"}
    return "[" + ", ".join(str(s) if s >= 0 else names.get(i, "?") for i, s in
                           enumerate(shape)) + "]"  # fmt: skip


def _check_time(time: float) -> float:
    t = float(time)
    if not (math.isfinite(t) and 0.0 <= t <= 1.0):
        raise ValueError(f"time: must lie in [0, 1] (the run's normalised time), got {time}")
    return t


def _model_and_labels(
    run_or_model: Run | DeformableGaussians, labels: np.ndarray | None
) -> tuple[DeformableGaussians, np.ndarray]:
    if isinstance(run_or_model, Run):
        model = run_or_model.model
        if labels is None:
            labels = run_or_model.labels
    elif isinstance(run_or_model, DeformableGaussians):
        model = run_or_model
    else:
        raise TypeError(f"expected a Run or DeformableGaussians, got {type(run_or_model)!r}")
    n = model.num_gaussians
    if labels is None:
        return model, np.zeros(n, dtype=np.int32)
    ids = np.asarray(labels)
    if ids.shape != (n,) or not (np.issubdtype(ids.dtype, np.integer) or ids.dtype == bool):
        raise ValueError(f"labels: expected {n} integer object ids (one per Gaussian), got "
                         f"shape {list(ids.shape)} of {ids.dtype}")  # fmt: skip
    return model, ids.astype(np.int32)


def splats_at(
    run_or_model: Run | DeformableGaussians,
    time: float | None,
    labels: np.ndarray | None = None,
) -> Splats:
    """The Gaussians of a run (or model) deformed to `time` in [0, 1] by D_theta (its
    `at_time`; static Gaussians stay canonical): deformed means, unit quaternions and the log
    of the deformed scales; opacity and SH unchanged. `time` None: the canonical Gaussians,
    raw parameters as stored. Object ids from `labels` [N] (default: the run's Phase 2 labels,
    zeros for a Phase 1 run or a bare model). ValueError for a time outside [0, 1]."""
    model, ids = _model_and_labels(run_or_model, labels)
    t = None if time is None else _check_time(time)
    with torch.no_grad():
        if t is None:
            means, quats, log_scales = model.means, model.quats, model.log_scales
        else:
            means, quats, scales = model.at_time(t)
            log_scales = torch.log(scales)
        return Splats(
            means=_copy(means), quats=_copy(quats), log_scales=_copy(log_scales),
            opacity_logits=_copy(model.opacity_logits), sh_dc=_copy(model.sh_dc[:, 0, :]),
            sh_rest=_copy(model.sh_rest), object_ids=ids, time=t,
        )  # fmt: skip


def _copy(t: torch.Tensor) -> np.ndarray:
    """A float32 numpy copy of `t` (never a view of a model's parameter)."""
    return t.detach().to(torch.float32).cpu().numpy().copy()


def default_times(run: Run, frames: int | None = None) -> np.ndarray:
    """Frame times [T] float64 in [0, 1]: `frames` evenly spaced ones (both ends included)
    when given, else the run's stored frame times (Phase 2's `run.times`; for a Phase 1 run
    the distinct times of its training cameras). ValueError when there are none."""
    if frames is not None:
        if isinstance(frames, bool) or int(frames) != frames or frames < 1:
            raise ValueError(f"frames: expected a count >= 1, got {frames!r}")
        return np.linspace(0.0, 1.0, int(frames))
    if run.times is not None and len(run.times):
        return np.asarray(run.times, dtype=np.float64).copy()
    times = sorted({float(c["time"]) for c in run.cameras
                    if c.get("split", "train") == "train" and "time" in c})  # fmt: skip
    if not times:
        raise ValueError(f"{run.path}: the run stores no frame times; give a frame count")
    return np.asarray(times, dtype=np.float64)


# ------------------------------------------------------------------------------------------
# PLY
# ------------------------------------------------------------------------------------------


def ply_properties(k: int) -> list[str]:
    """The float32 vertex properties of a splat PLY with `k` SH coefficients per channel
    beyond the DC band, in gsplat 1.5.3's exporter order (`object_id` not included)."""
    return ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *(f"f_rest_{i}" for i in range(3 * k)),
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2",
            "rot_3"]  # fmt: skip


def _vertex_element(s: Splats) -> PlyElement:
    n, k = len(s), s.sh_rest.shape[1]
    columns = np.concatenate(
        [s.means, s.sh_dc, s.sh_rest.transpose(0, 2, 1).reshape(n, 3 * k),
         s.opacity_logits[:, None], s.log_scales, s.quats], axis=1,
    )  # fmt: skip
    names = ply_properties(k)
    rows = np.empty(n, dtype=[*((p, "<f4") for p in names), ("object_id", "<i4")])
    for j, p in enumerate(names):
        rows[p] = columns[:, j]
    rows["object_id"] = s.object_ids
    return PlyElement.describe(rows, "vertex")


def _time_comment(time: float | None) -> str:
    return "canonical" if time is None else f"time {time!r}"


def _check_finite(path: str | Path, s: Splats) -> None:
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        if not np.isfinite(getattr(s, name)).all():
            raise ExportError(path, f"cannot write: {name} holds NaN or inf (a diverged fit?); "
                              "check the run or export an earlier checkpoint")  # fmt: skip


def _ply_bytes(elements: list[PlyElement], comments: list[str]) -> bytes:
    buf = io.BytesIO()
    PlyData(elements, text=False, byte_order="<", comments=comments).write(buf)
    return buf.getvalue()


def _splat_ply_bytes(s: Splats) -> bytes:
    return _ply_bytes([_vertex_element(s)], [f"sync4d {__version__}", _time_comment(s.time)])


def write_ply(path: str | Path, splats: Splats) -> Path:
    """Write `splats` as a binary little-endian 3DGS PLY (gsplat's property order plus an
    int32 `object_id`; comments: the sync4d version and the time) atomically; the path.
    ExportError for NaN or inf values, `WriteFailed` when the file cannot be written."""
    _check_finite(path, splats)
    data = _splat_ply_bytes(splats)
    return write_atomic(path, lambda tmp: tmp.write_bytes(data))


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise ExportError(path, f"cannot read it ({e.strerror or e})") from None


def _parse_ply(data: bytes, label: str | Path) -> PlyData:
    if not data:
        raise ExportError(label, f"the file is empty, not a PLY; {_HINT}")
    if not data.startswith(b"ply"):
        raise ExportError(label, f"not a PLY file (it does not start with 'ply'); {_HINT}")
    try:
        return PlyData.read(io.BytesIO(data), mmap=False)
    except PlyHeaderParseError as e:
        raise ExportError(label, f"malformed PLY header ({e}); {_HINT}") from None
    except PlyElementParseError as e:
        raise ExportError(label, f"truncated or malformed PLY data ({e}); the write was "
                          f"probably interrupted: {_HINT}") from None  # fmt: skip
    except Exception as e:  # plyfile and numpy raise many kinds on foreign data
        raise ExportError(label, f"unreadable PLY ({type(e).__name__}: {e}); {_HINT}") from None


def _element(ply: PlyData, name: str, label: str | Path) -> np.ndarray:
    names = [el.name for el in ply.elements]
    if name not in names:
        raise ExportError(label, f"no '{name}' element (it has {names or 'none'}); not a splat "
                          f"PLY: {_HINT}")  # fmt: skip
    return ply[name].data


def _column(rows: np.ndarray, name: str, label: str | Path) -> np.ndarray:
    try:
        col = np.asarray(rows[name], dtype=np.float32)
    except (TypeError, ValueError):
        raise ExportError(label, f"property '{name}' is not a number per row; {_HINT}") from None
    bad = ~np.isfinite(col)
    if bad.any():
        raise ExportError(label, f"property '{name}' holds NaN or inf (row {int(np.argmax(bad))})"
                          f"; {_HINT}")  # fmt: skip
    return col


def _splats_from_rows(rows: np.ndarray, comments: list[str], label: str | Path) -> Splats:
    props = list(rows.dtype.names or ())
    missing = [p for p in _REQUIRED if p not in props]
    if missing:
        raise ExportError(label, f"the vertices lack {', '.join(missing)}: not a 3DGS splat PLY "
                          f"(a point cloud?); {_HINT}")  # fmt: skip
    n_rest = sum(p.startswith("f_rest_") for p in props)
    k = n_rest // 3
    if n_rest % 3 or math.isqrt(k + 1) ** 2 != k + 1 or any(
        f"f_rest_{i}" not in props for i in range(n_rest)
    ):
        raise ExportError(label, f"{n_rest} f_rest_* properties fit no SH degree (0, 9, 24 or 45 "
                          f"numbered from 0 are expected); {_HINT}")  # fmt: skip
    n = len(rows)

    def cols(names: Sequence[str]) -> np.ndarray:
        return np.stack([_column(rows, p, label) for p in names], axis=1).reshape(n, len(names))

    rest = np.zeros((n, 0, 3), np.float32)
    if n_rest:
        rest = cols([f"f_rest_{i}" for i in range(n_rest)]).reshape(n, 3, k).transpose(0, 2, 1)
    if "object_id" in props:
        ids = np.asarray(rows["object_id"])
        if not np.issubdtype(ids.dtype, np.integer):
            raise ExportError(label, f"property 'object_id' is {ids.dtype}, not an integer; "
                              f"{_HINT}")  # fmt: skip
    else:
        ids = np.zeros(n, dtype=np.int32)
    return Splats(
        means=cols(("x", "y", "z")), quats=cols(("rot_0", "rot_1", "rot_2", "rot_3")),
        log_scales=cols(("scale_0", "scale_1", "scale_2")),
        opacity_logits=_column(rows, "opacity", label),
        sh_dc=cols(("f_dc_0", "f_dc_1", "f_dc_2")), sh_rest=rest, object_ids=ids,
        time=_comment_time(comments, label),
    )  # fmt: skip


def _comment_time(comments: list[str], label: str | Path) -> float | None:
    for c in comments:
        if c.startswith("time "):
            try:
                return _check_time(float(c.removeprefix("time ")))
            except ValueError:
                raise ExportError(label, f"bad time comment {c!r}: the time must be a number in "
                                  "[0, 1]") from None  # fmt: skip
    return None


def _splats_from_bytes(data: bytes, label: str | Path) -> Splats:
    ply = _parse_ply(data, label)
    return _splats_from_rows(_element(ply, "vertex", label), list(ply.comments), label)


def read_ply(path: str | Path) -> Splats:
    """The Gaussians of a splat PLY (the `vertex` element; object ids 0 when the file has no
    `object_id`, so 3DGS PLYs of other tools read too; `time` from a sync4d comment, else
    None). ExportError naming the file for anything that is not such a PLY."""
    path = Path(path)
    return _splats_from_bytes(_read_bytes(path), path)


# ------------------------------------------------------------------------------------------
# SPZ
# ------------------------------------------------------------------------------------------


def write_spz(path: str | Path, splats: Splats) -> Path:
    """Write `splats` as an SPZ file (gzip container, version 3, 12 fractional position bits)
    through gsply, atomically; lossy within the bounds of the module docstring, object ids and
    time are not stored. ExportError for NaN or inf, SH degree above 3 or positions beyond
    +-2048 (SPZ's fixed-point range)."""
    import gsply

    _check_finite(path, splats)
    if splats.sh_degree > 3:
        raise ExportError(path, f"SPZ holds SH degrees up to 3, these splats have "
                          f"{splats.sh_degree}; write a PLY instead")  # fmt: skip
    far = float(np.abs(splats.means).max(initial=0.0))
    if far >= _SPZ_POSITION_LIMIT:
        limit = _SPZ_POSITION_LIMIT
        raise ExportError(path, f"a position reaches {far:.1f} world units, beyond SPZ's "
                          f"fixed-point range (+-{limit:g}); write a PLY instead")  # fmt: skip
    data = gsply.GSData.from_arrays(
        means=splats.means, scales=splats.log_scales, quats=splats.quats,
        opacities=splats.opacity_logits, sh0=splats.sh_dc,
        shN=splats.sh_rest if splats.sh_rest.shape[1] else None, format="ply",
    )  # fmt: skip

    def write(tmp: Path) -> None:
        gsply.write_spz(tmp, data, version=3)
        raw = bytearray(tmp.read_bytes())
        if raw[:2] == b"\x1f\x8b":  # gzip: clear MTIME (RFC 1952: 0 = no time stamp)
            raw[4:8] = b"\x00\x00\x00\x00"
            tmp.write_bytes(bytes(raw))

    return write_atomic(path, write)


def read_spz(path: str | Path) -> Splats:
    """The Gaussians of an SPZ file through gsply (unit quaternions, object ids 0, time None:
    SPZ stores neither). ExportError naming the file when it is not a readable SPZ."""
    import gsply

    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as e:
        raise ExportError(path, f"cannot read it ({e.strerror or e})") from None
    if size == 0:
        raise ExportError(path, "the file is empty, not an SPZ; export it again")
    try:
        data = gsply.read_spz(path)
        n = int(np.asarray(data.means).shape[0])
        rest = data.shN
        rest = np.zeros((n, 0, 3), np.float32) if rest is None or np.size(rest) == 0 else rest
        out = Splats(
            means=data.means, quats=data.quats, log_scales=data.scales,
            opacity_logits=np.asarray(data.opacities).reshape(n), sh_dc=data.sh0,
            sh_rest=rest, object_ids=np.zeros(n, np.int32),
        )  # fmt: skip
    except Exception as e:  # gsply raises ValueError, struct.error, EOFError, ...
        why = str(e).replace(f": {path}", "")  # gsply's messages end with the path
        raise ExportError(path, f"not a readable SPZ file ({type(e).__name__}: {why}); export "
                          "it again") from None  # fmt: skip
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        if not np.isfinite(getattr(out, name)).all():
            raise ExportError(path, f"SPZ {name} decode to NaN or inf; export it again")
    return out


# ------------------------------------------------------------------------------------------
# 4D sequences
# ------------------------------------------------------------------------------------------


def _check_times(times: Sequence[float] | np.ndarray) -> list[float]:
    out = [_check_time(t) for t in np.asarray(times, dtype=np.float64).reshape(-1)]
    if not out:
        raise ValueError("times: give at least one frame time")
    return out


def write_sequence(
    path: str | Path,
    run_or_model: Run | DeformableGaussians,
    times: Sequence[float] | np.ndarray,
    labels: np.ndarray | None = None,
) -> Path:
    """Write the scene at each of `times` (in [0, 1]) as a 4D file, atomically; the path.
    ``.ply``: brush's delta-frame PLY (canonical base + one delta element per frame); a folder
    (`is_sequence_folder`): SuperSplat's PLY sequence (`write_sequence_folder`); ``.zip``
    (deprecated): one standard PLY per frame (see the module docstring). Object ids as in
    `splats_at`."""
    if is_sequence_folder(path):
        return write_sequence_folder(path, run_or_model, times, labels)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".zip"):
        raise ValueError(f"{path}: a 4D file is a .ply (delta frames), a folder DIR/ (one PLY "
                         "per frame, SuperSplat's sequence) or a .zip")  # fmt: skip
    ts = _check_times(times)
    model, ids = _model_and_labels(run_or_model, labels)
    frames = [splats_at(model, t, ids) for t in ts]
    for s in frames:
        _check_finite(path, s)
    if suffix == ".zip":
        members = [(f"frame_{i:04d}_t{t:.4f}.ply", _splat_ply_bytes(s))
                   for i, (t, s) in enumerate(zip(ts, frames, strict=True))]  # fmt: skip

        def write_zip(tmp: Path) -> None:
            with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as z:
                for name, data in members:
                    info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
                    info.compress_type = zipfile.ZIP_DEFLATED
                    info.external_attr = 0o644 << 16
                    z.writestr(info, data, compresslevel=6)

        return write_atomic(path, write_zip)
    base = splats_at(model, None, ids)
    _check_finite(path, base)
    elements = [_vertex_element(base)]
    for i, s in enumerate(frames):
        delta = np.concatenate([s.means - base.means, s.log_scales - base.log_scales,
                                s.quats - base.quats], axis=1)  # fmt: skip
        rows = np.empty(len(base), dtype=[(p, "<f4") for p in _DELTA])
        for j, p in enumerate(_DELTA):
            rows[p] = delta[:, j]
        elements.append(PlyElement.describe(rows, f"delta_vertex_{i}"))
    comments = [f"sync4d {__version__}", "canonical",
                "delta_vertex_<i>: value at frame i minus vertex (x y z, log-scales, raw quats)",
                *(f"frame {i} time {t!r}" for i, t in enumerate(ts))]  # fmt: skip
    data = _ply_bytes(elements, comments)
    return write_atomic(path, lambda tmp: tmp.write_bytes(data))


#: A frame file of a PLY-sequence folder as SuperSplat's import matches it
#: (``src/file-handler.ts`` ``isPlySequence``): any prefix, a trailing frame number, ``.ply``.
_SEQUENCE_FILE = re.compile(r"(.*?)(\d+)(?:\.compressed)?\.ply")


def is_sequence_folder(path: str | Path) -> bool:
    """Whether `path` names a PLY-sequence folder: it ends with a slash, is an existing folder,
    or has no suffix (``bb-4d``)."""
    text = str(path)
    p = Path(path)
    return text.endswith(("/", "\\")) or p.is_dir() or p.suffix == ""


def _frame_stem(folder: Path) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", folder.name).strip("_") or "frame"


def sequence_frame_name(folder: str | Path, index: int) -> str:
    """The file name of frame `index` in PLY-sequence folder `folder`: ``<NAME>_<index:04d>.ply``
    (NAME from the folder's name)."""
    return f"{_frame_stem(Path(folder))}_{index:04d}.ply"


def sequence_sidecar(folder: str | Path) -> Path:
    """The sidecar JSON of PLY-sequence folder `folder` (the frame files and their times):
    ``DIR.json`` beside the folder, not in it (a file in it would break SuperSplat's
    sequence detection)."""
    folder = Path(folder)
    return folder.with_name(folder.name + ".json")


def write_sequence_folder(
    folder: str | Path,
    run_or_model: Run | DeformableGaussians,
    times: Sequence[float] | np.ndarray,
    labels: np.ndarray | None = None,
) -> Path:
    """Write the scene at each of `times` as a PLY-sequence folder (module docstring): one
    standard PLY per frame, ``<NAME>_0000.ply``, ... (`sequence_frame_name`), each written
    atomically, and the sidecar `sequence_sidecar` with each file's time; the folder. A folder
    holding files other than an earlier export's frames is refused (ExportError): SuperSplat
    imports every file of a dropped folder."""
    folder = Path(folder)
    ts = _check_times(times)
    model, ids = _model_and_labels(run_or_model, labels)
    frames = [splats_at(model, t, ids) for t in ts]
    for s in frames:
        _check_finite(folder, s)
    mine = re.compile(re.escape(_frame_stem(folder)) + r"_\d{4,}\.ply")
    if folder.exists() and not folder.is_dir():
        raise ExportError(folder, "exists and is not a folder; give a new folder for the frames")
    old = sorted(p.name for p in folder.iterdir()) if folder.is_dir() else []
    others = [n for n in old if not mine.fullmatch(n)]
    if others:
        shown = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
        raise ExportError(folder, f"holds other files ({shown}); SuperSplat imports every file "
                          "of a dropped folder as one sequence only when all are its frames: "
                          "give an empty or new folder")  # fmt: skip
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ExportError(folder, f"cannot create the folder ({e.strerror or e})") from None
    names = [sequence_frame_name(folder, i) for i in range(len(ts))]
    for name, s in zip(names, frames, strict=True):
        data = _splat_ply_bytes(s)
        write_atomic(folder / name, lambda tmp, data=data: tmp.write_bytes(data))
    for name in set(old) - set(names):  # frames of an earlier, longer export
        (folder / name).unlink(missing_ok=True)
    doc = {"format": "sync4d ply sequence", "version": 1, "sync4d": __version__,
           "folder": folder.name, "gaussians": len(frames[0]),
           "frames": [{"file": n, "time": t} for n, t in zip(names, ts, strict=True)]}  # fmt: skip
    write_text_atomic(sequence_sidecar(folder), json.dumps(doc, indent=1) + "\n")
    return folder


def _folder_frames(folder: Path) -> tuple[list[float], list[Splats]]:
    """The frames of a PLY-sequence folder in SuperSplat's order (by trailing number), each
    time from the PLY's comment, else from the sidecar."""
    try:
        files = [p for p in folder.iterdir() if p.is_file()]
    except OSError as e:
        raise ExportError(folder, f"cannot read the folder ({e.strerror or e})") from None
    numbered = []
    for p in files:
        m = _SEQUENCE_FILE.fullmatch(p.name.lower())
        if m is None:
            raise ExportError(p, "not a frame of a PLY sequence (<NAME>_<number>.ply); the "
                              "folder must hold the frames alone")  # fmt: skip
        numbered.append((int(m[2]), p))
    if not numbered:
        raise ExportError(folder, "the folder holds no frames; export it again")
    numbered.sort()
    side: dict[str, float] = {}
    sidecar = sequence_sidecar(folder)
    if sidecar.is_file():
        try:
            doc = json.loads(sidecar.read_text(encoding="utf-8"))
            side = {str(f["file"]): _check_time(float(f["time"])) for f in doc["frames"]}
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ExportError(sidecar, f"not a readable sequence sidecar ({e}); export it "
                              "again") from None  # fmt: skip
    out_t, out_s = [], []
    for _, p in numbered:
        s = _splats_from_bytes(_read_bytes(p), p)
        if s.time is None:
            if p.name not in side:
                raise ExportError(p, f"unknown frame time: no time comment and no entry in "
                                  f"{sidecar}")  # fmt: skip
            s.time = side[p.name]
        out_t.append(s.time)
        out_s.append(s)
    return out_t, out_s


def _delta_frames(ply: PlyData, base: Splats, label: Path) -> tuple[list[float], list[Splats]]:
    names = [el.name for el in ply.elements if el.name.startswith("delta_vertex_")]
    times: dict[int, float] = {}
    for c in ply.comments:
        m = re.fullmatch(r"frame (\d+) time (\S+)", c)
        if m:
            try:
                times[int(m[1])] = _check_time(float(m[2]))
            except ValueError:
                raise ExportError(label, f"bad frame time comment {c!r}") from None
    if not names:
        raise ExportError(label, "no delta_vertex_<i> elements: a single-frame PLY (read it with "
                          "read_ply)")  # fmt: skip
    out_t, out_s = [], []
    for i, name in enumerate(names):
        if name != f"delta_vertex_{i}":
            raise ExportError(label, f"delta elements out of order ({name} at position {i}); "
                              f"{_HINT}")  # fmt: skip
        rows = ply[name].data
        if len(rows) != len(base):
            raise ExportError(label, f"{name} has {len(rows)} rows for {len(base)} vertices; "
                              f"{_HINT}")  # fmt: skip
        missing = [p for p in _DELTA if p not in (rows.dtype.names or ())]
        if missing:
            raise ExportError(label, f"{name} lacks {', '.join(missing)}; {_HINT}")
        d = {p: _column(rows, p, label) for p in _DELTA}
        dm = np.stack([d["x"], d["y"], d["z"]], 1)
        ds = np.stack([d[f"scale_{j}"] for j in range(3)], 1)
        dq = np.stack([d[f"rot_{j}"] for j in range(4)], 1)
        t = times.get(i, i / max(1, len(names) - 1))
        out_t.append(t)
        out_s.append(Splats(
            means=base.means + dm, quats=base.quats + dq, log_scales=base.log_scales + ds,
            opacity_logits=base.opacity_logits, sh_dc=base.sh_dc, sh_rest=base.sh_rest,
            object_ids=base.object_ids, time=t,
        ))  # fmt: skip
    return out_t, out_s


def _zip_frames(path: Path) -> tuple[list[float], list[Splats]]:
    try:
        with zipfile.ZipFile(path) as z:
            members = [m for m in z.infolist() if not m.is_dir()]
            if not members:
                raise ExportError(path, "the zip holds no frames; export it again")
            out_t, out_s = [], []
            for m in members:
                label = f"{path}:{m.filename}"
                try:
                    data = z.read(m)
                except Exception as e:  # CRC errors, bad compression data
                    raise ExportError(label, f"damaged zip member ({e}); export it "
                                      "again") from None  # fmt: skip
                s = _splats_from_bytes(data, label)
                if s.time is None:
                    name = _ZIP_FRAME.fullmatch(Path(m.filename).name)
                    if name is None:
                        raise ExportError(label, "unknown frame time: neither a time comment "
                                          "nor a frame_<i>_t<time>.ply name")  # fmt: skip
                    s.time = _check_time(float(name[2]))
                out_t.append(s.time)
                out_s.append(s)
            return out_t, out_s
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError) as e:
        raise ExportError(path, f"not a readable zip ({e}); export it again") from None


def read_sequence(path: str | Path) -> tuple[np.ndarray, list[Splats]]:
    """The frame times [T] float64 and the Gaussians of each frame of a 4D file written by
    `write_sequence` (``.ply``: base + delta per frame, quaternions as base + delta, i.e. not
    renormalised, times from the comments, evenly spaced in [0, 1] in a file without them;
    a folder: its frames by trailing number, each time from its comment or the sidecar;
    ``.zip``: each member's PLY, its time from its comment or name). ExportError naming the
    file (a zip's member as ``ZIP:MEMBER``) for anything malformed."""
    path = Path(path)
    if path.is_dir():
        times, frames = _folder_frames(path)
    elif path.suffix.lower() == ".zip":
        times, frames = _zip_frames(path)
    else:
        ply = _parse_ply(_read_bytes(path), path)
        base = _splats_from_rows(_element(ply, "vertex", path), list(ply.comments), path)
        times, frames = _delta_frames(ply, base, path)
    return np.asarray(times, dtype=np.float64), frames
