"""Splat files (`sync4d.export.splats`): PLY, SPZ and the 4D delta-frame PLY / zip of a run.

One tiny Phase 2 run is fitted for the module (a few seconds), then made lively so that every
exported quantity matters: D_theta's head gets random weights (visible motion), opacities and
higher SH bands random values, a tenth of the Gaussians are static and the labels four objects.
"""

from __future__ import annotations

import gzip
import io
import math
import types
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from support.datasets import write_blender
from sync4d import raster
from sync4d.cli import main
from sync4d.data.scene import Camera
from sync4d.export import (
    ExportError,
    Splats,
    default_times,
    ply_properties,
    read_ply,
    read_sequence,
    read_spz,
    splats_at,
    write_ply,
    write_sequence,
    write_spz,
)
from sync4d.runs import PHASE1_CHECKPOINT_NAME, Run, load_run

SETTINGS = ["--iters", "12", "--threads", "1", "--set", "phase1.init_points=300",
            "--set", "eval_every=0",
            "--set", "phase2.iterations=8", "--set", "phase2.motion_start=2",
            "--set", "phase2.motion.kind=mlp"]  # fmt: skip

# Renders of a PLY read back against `run.model.render` (max abs difference, colour units):
# (a) sync4d's rasterizer: the same Gaussians up to exp(log(scale)) rounding (measured: 0,
# the images are identical);
RASTER_ATOL = 1e-6
# (b) gsplat's CPU reference in float64, on the pixels no discrete decision makes ambiguous
# (2 of 4096 here): the tolerance of tests/raster/test_parity_gsplat.py (FWD_ATOL; measured
# 1.6e-6, on every pixel).
GSPLAT_ATOL = 1e-4

# SPZ's quantisation (module docstring of sync4d.export.splats), plus float32 slack. Measured:
# means 1.22e-4, opacity 1.96e-3, sh_dc 0.0131, log-scales 0.0308, quats 6.9e-4, sh_rest 3.9e-3.
SPZ_BOUNDS = {"means": 2.0**-13 + 1e-6, "opacity": 1 / 510 + 1e-6, "sh_dc": 0.5 / 38.25 + 1e-6,
              "log_scales": 1 / 32 + 1e-6, "quats": 2.1e-3, "sh_rest": 1 / 256 + 1e-6}  # fmt: skip


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    tmp = tmp_path_factory.mktemp("splats")
    write_blender(tmp / "tiny", n=4, size=24)
    assert main(["fit", str(tmp / "tiny"), "--out", str(tmp / "run"), *SETTINGS]) == 0
    r = load_run(tmp / "run")
    m = r.model
    gen = torch.Generator().manual_seed(7)
    n = m.num_gaussians
    with torch.no_grad():
        o = 0.05 + 0.85 * torch.rand(n, generator=gen)
        m.opacity_logits.copy_(torch.log(o / (1 - o)))
        m.sh_rest.copy_((0.2 * torch.randn(m.sh_rest.shape, generator=gen)).clamp(-0.9, 0.9))
        m.deform.head.weight.normal_(0.0, 0.5, generator=gen)
        m.quats.mul_(1.0 + torch.rand(n, 1, generator=gen))  # unnormalised, as a fit leaves them
    m.static = torch.arange(n) % 10 == 0
    r.labels = (np.arange(n) % 4).astype(np.int64)
    return r


def _camera(rec: dict, scale: int = 2) -> Camera:
    """The run's camera `rec` with `scale` times the pixels."""
    return Camera(
        viewmat=np.asarray(rec["viewmat"], dtype=np.float64).reshape(4, 4),
        fx=rec["fx"] * scale, fy=rec["fy"] * scale, cx=rec["cx"] * scale, cy=rec["cy"] * scale,
        width=rec["width"] * scale, height=rec["height"] * scale,
    )  # fmt: skip


def _fields(s: Splats) -> dict[str, np.ndarray]:
    names = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "object_ids")
    return {k: getattr(s, k) for k in names}


def _header_and_body(data: bytes) -> tuple[list[str], bytes]:
    head, body = data.split(b"end_header\n", 1)
    return head.decode("ascii").splitlines(), body


def test_ply_round_trip_is_exact(run: Run, tmp_path: Path) -> None:
    for t in (None, 0.0, 0.37, 1.0):
        s = splats_at(run, t)
        assert s.sh_degree == 3 and s.sh_rest.shape == (len(s), 15, 3)
        back = read_ply(write_ply(tmp_path / "a.ply", s))
        for name, want in _fields(s).items():
            got = getattr(back, name)
            assert got.dtype == want.dtype and np.array_equal(got, want), (t, name)
        assert back.time == t
    assert np.array_equal(back.object_ids, run.labels) and set(back.object_ids) == {0, 1, 2, 3}
    lines, _ = _header_and_body((tmp_path / "a.ply").read_bytes())
    assert lines[:4] == ["ply", "format binary_little_endian 1.0", lines[2], "comment time 1.0"]
    assert lines[2].startswith("comment sync4d ") and lines[-1] == "property int object_id"
    # Canonical: the stored parameters themselves (raw quaternions), whatever D_theta does.
    c = splats_at(run, None)
    assert np.array_equal(c.quats, run.model.quats.numpy())
    assert "comment canonical" in _header_and_body(write_ply(tmp_path / "c.ply", c).read_bytes())[0]
    # Explicit labels win over the run's.
    ids = np.arange(len(c)) % 7
    assert np.array_equal(read_ply(write_ply(tmp_path / "l.ply", splats_at(run, 0.5, ids)))
                          .object_ids, ids)  # fmt: skip


@pytest.mark.reference
def test_ply_matches_gsplat_exporter(run: Run, tmp_path: Path) -> None:
    pytest.importorskip("gsplat")
    from gsplat.exporter import export_splats

    s = splats_at(run, 0.6)
    theirs = export_splats(
        means=torch.from_numpy(s.means), scales=torch.from_numpy(s.log_scales),
        quats=torch.from_numpy(s.quats), opacities=torch.from_numpy(s.opacity_logits),
        sh0=torch.from_numpy(s.sh_dc)[:, None, :], shN=torch.from_numpy(s.sh_rest), format="ply",
    )  # fmt: skip
    ours = write_ply(tmp_path / "a.ply", s).read_bytes()
    their_lines, their_body = _header_and_body(theirs)
    our_lines, our_body = _header_and_body(ours)
    props = [ln.split()[-1] for ln in our_lines if ln.startswith("property")]
    their_props = [ln.split()[-1] for ln in their_lines if ln.startswith("property")]
    assert props[-1] == "object_id" and props[:-1] == their_props == ply_properties(15)
    assert all(ln == f"property float {p}" for ln, p in zip(
        [ln for ln in our_lines if ln.startswith("property")], props[:-1], strict=False))
    # Row for row, our floats (object_id left out) are gsplat's bytes.
    floats = [(p, "<f4") for p in props[:-1]]
    rows = np.frombuffer(our_body, dtype=[*floats, ("object_id", "<i4")])
    assert len(rows) == len(s)
    plain = np.empty(len(rows), dtype=floats)
    for p, _ in floats:
        plain[p] = rows[p]
    assert plain.tobytes() == their_body


@pytest.mark.reference
def test_ply_at_a_time_renders_like_the_model(run: Run, tmp_path: Path) -> None:
    pytest.importorskip("gsplat")
    from gsplat.cuda._torch_impl import _spherical_harmonics

    from sync4d.reference import gsplat as gr

    model = run.model
    t = 0.45
    cam = _camera(run.cameras[1])
    want = model.render(cam, t).features
    s = read_ply(write_ply(tmp_path / "t.ply", splats_at(run, t)))
    means, log_scales = torch.from_numpy(s.means), torch.from_numpy(s.log_scales)
    quats = torch.from_numpy(s.quats)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    opac = torch.sigmoid(torch.from_numpy(s.opacity_logits))
    coeffs = torch.cat([torch.from_numpy(s.sh_dc)[:, None], torch.from_numpy(s.sh_rest)], 1)
    viewmat = torch.as_tensor(cam.viewmat, dtype=torch.float32)
    K = torch.as_tensor(cam.K, dtype=torch.float32)
    # (a) sync4d's rasterizer, built as DeformableGaussians.render builds its call.
    colors = raster.sh_features(means, coeffs, viewmat, s.sh_degree)
    got = raster.rasterize(means, quats, torch.exp(log_scales), opac, colors, viewmat, K,
                           cam.width, cam.height, near=model.near).features  # fmt: skip
    err_a = float((got - want).abs().max())
    assert err_a <= RASTER_ATOL, err_a
    # (b) gsplat's reference in float64, its own SH; opacities stay below both clamps (sync4d
    # 0.99, gsplat 0.999), so only gsplat's ambiguous pixels are left out.
    assert float(opac.max()) < 0.99
    d = torch.float64
    m64, v64 = means.to(d), viewmat.to(d)
    campos = -v64[:3, :3].T @ v64[:3, 3]
    col64 = (_spherical_harmonics(s.sh_degree, m64 - campos, coeffs.to(d)) + 0.5).clamp_min(0)
    ref = gr.gsplat_render_full(m64, quats.to(d), torch.exp(log_scales.to(d)), opac.to(d),
                                col64, v64, K.to(d), cam.width, cam.height,
                                near=model.near)  # fmt: skip
    mask, _ = gr.ambiguous_pixels(ref)
    assert float(mask.float().mean()) <= 0.03 and float(ref.alpha.max()) > 0.5
    err_b = float(((ref.image - want.to(d)).abs() * (~mask)[..., None]).max())
    assert err_b <= GSPLAT_ATOL, err_b


def test_spz_round_trip_within_quantisation(run: Run, tmp_path: Path) -> None:
    s = splats_at(run, 0.8)
    assert np.abs(s.sh_rest).max() < 0.99 and np.abs(s.sh_dc).max() < 3.3  # inside SPZ's range
    back = read_spz(write_spz(tmp_path / "a.spz", s))
    assert len(back) == len(s) and back.sh_degree == 3 and back.time is None
    assert not back.object_ids.any()  # SPZ stores no object ids

    def sig(x: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))

    q = s.quats / np.linalg.norm(s.quats, axis=1, keepdims=True)
    sign = np.sign((q * back.quats).sum(1, keepdims=True))  # q and -q: the same rotation
    errors = {
        "means": np.abs(back.means - s.means).max(),
        "opacity": np.abs(sig(back.opacity_logits) - sig(s.opacity_logits)).max(),
        "sh_dc": np.abs(back.sh_dc - s.sh_dc).max(),
        "log_scales": np.abs(back.log_scales - s.log_scales).max(),
        "quats": np.abs(back.quats * sign - q).max(),
        "sh_rest": np.abs(back.sh_rest - s.sh_rest).max(),
    }
    for name, err in errors.items():
        assert err <= SPZ_BOUNDS[name], (name, err)
    with pytest.raises(ExportError, match="fixed-point range"):
        far = Splats(**{**_fields(s), "means": s.means + 3000.0})
        write_spz(tmp_path / "far.spz", far)


def test_delta_ply_sequence(run: Run, tmp_path: Path) -> None:
    times = default_times(run)
    path = write_sequence(tmp_path / "seq.ply", run, times)
    got_times, frames = read_sequence(path)
    assert np.array_equal(got_times, times) and len(frames) == len(times) == 4
    base = splats_at(run, None)
    for t, f in zip(times, frames, strict=True):
        want = splats_at(run, t)
        assert f.time == t
        moved = np.abs(want.means - base.means).max()
        assert moved > 1e-2  # D_theta moves the scene
        for name, b in (("means", base.means), ("log_scales", base.log_scales),
                        ("quats", base.quats)):  # fmt: skip
            w, g = getattr(want, name), getattr(f, name)
            # base + (value - base) in float32: within a few roundings of the magnitudes.
            tol = 2 * np.finfo(np.float32).eps * (np.abs(w) + np.abs(b))
            assert (np.abs(g - w) <= tol).all(), name
        for name in ("opacity_logits", "sh_dc", "sh_rest", "object_ids"):
            assert np.array_equal(getattr(f, name), getattr(want, name))
    # Static Gaussians do not move.
    still = run.model.static.numpy()
    assert np.array_equal(frames[2].means[still], base.means[still])
    # brush's layout: the base vertex element is write_ply's canonical file, byte for byte,
    # then delta_vertex_<i> of float32 x y z scale_* rot_*; frame times in the comments.
    lines, body = _header_and_body(path.read_bytes())
    c_lines, c_body = _header_and_body(write_ply(tmp_path / "c.ply", base).read_bytes())
    assert body[: len(c_body)] == c_body
    elements = [ln.split()[1:] for ln in lines if ln.startswith("element")]
    n = str(len(base))
    assert elements == [["vertex", n], *(["delta_vertex_" + str(i), n] for i in range(4))]
    start = lines.index(f"element delta_vertex_0 {n}")
    assert lines[start + 1 : start + 11] == [f"property float {p}" for p in
        ("x", "y", "z", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")]
    assert [ln for ln in lines if ln.startswith("comment frame")] == [
        f"comment frame {i} time {t!r}" for i, t in enumerate(times.tolist())]
    assert len(body) == len(c_body) + 4 * len(base) * 40


def test_zip_sequence(run: Run, tmp_path: Path) -> None:
    times = [0.0, 0.25, 1.0]
    path = write_sequence(tmp_path / "seq.zip", run, times)
    with zipfile.ZipFile(path) as z:
        names = z.namelist()
        assert names == ["frame_0000_t0.0000.ply", "frame_0001_t0.2500.ply",
                         "frame_0002_t1.0000.ply"]  # fmt: skip
        for name, t in zip(names, times, strict=True):
            want = write_ply(tmp_path / "f.ply", splats_at(run, t)).read_bytes()
            assert z.read(name) == want
    got_times, frames = read_sequence(path)
    assert got_times.tolist() == times
    for t, f in zip(times, frames, strict=True):
        for name, want in _fields(splats_at(run, t)).items():
            assert np.array_equal(getattr(f, name), want)


def test_writes_are_deterministic(
    run: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    s = splats_at(run, 0.5)
    for name, write in (("a.ply", lambda p: write_ply(p, s)),
                        ("s.ply", lambda p: write_sequence(p, run, [0.0, 0.5])),
                        ("s.zip", lambda p: write_sequence(p, run, [0.0, 0.5]))):  # fmt: skip
        first = write(tmp_path / "1" / name).read_bytes()
        assert write(tmp_path / "2" / name).read_bytes() == first, name
    # SPZ: gzip would stamp the write time into its header; two different clocks, same bytes.
    monkeypatch.setattr(gzip, "time", types.SimpleNamespace(time=lambda: 1.0e9))
    a = write_spz(tmp_path / "1.spz", s).read_bytes()
    monkeypatch.setattr(gzip, "time", types.SimpleNamespace(time=lambda: 2.0e9))
    b = write_spz(tmp_path / "2.spz", s).read_bytes()
    assert a == b and a[:2] == b"\x1f\x8b" and a[4:8] == bytes(4)


def _ply(path: Path, rows: dict[str, np.ndarray], comments: tuple[str, ...] = ()) -> Path:
    arr = np.empty(len(next(iter(rows.values()))), dtype=[(k, v.dtype) for k, v in rows.items()])
    for k, v in rows.items():
        arr[k] = v
    PlyData([PlyElement.describe(arr, "vertex")], comments=list(comments)).write(str(path))
    return path


def test_malformed_files_raise_export_error_naming_the_file(run: Run, tmp_path: Path) -> None:
    s = splats_at(run, 0.5)
    good = write_ply(tmp_path / "good.ply", s).read_bytes()
    cols = {p: np.zeros(4, np.float32) for p in ply_properties(0)}
    cases: list[tuple] = []

    def add(name: str, data: bytes | None, reader, match: str) -> None:
        path = tmp_path / name
        if data is not None:
            path.write_bytes(data)
        cases.append((path, reader, match))

    add("truncated.ply", good[: len(good) - 1000], read_ply, "truncated")
    add("text.ply", b"hello, I am a text file\n", read_ply, "not a PLY")
    add("empty.ply", b"", read_ply, "empty")
    add("header.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex x\n", read_ply,
        "header")  # fmt: skip
    _ply(tmp_path / "missing.ply", {k: v for k, v in cols.items() if k != "opacity"})
    add("missing.ply", None, read_ply, "lack opacity")
    _ply(tmp_path / "nan.ply", {**cols, "y": np.array([0, 1, np.nan, 2], np.float32)})
    add("nan.ply", None, read_ply, r"'y' holds NaN.*row 2")
    _ply(tmp_path / "rest.ply", {**cols, "f_rest_0": np.zeros(4, np.float32)})
    add("rest.ply", None, read_ply, "SH degree")
    face = PlyElement.describe(np.zeros(2, dtype=[("a", "i4")]), "face")
    buf = io.BytesIO()
    PlyData([face]).write(buf)
    add("face.ply", buf.getvalue(), read_ply, "no 'vertex' element")
    spz = write_spz(tmp_path / "good.spz", s).read_bytes()
    add("truncated.spz", spz[: len(spz) // 2], read_spz, "not a readable SPZ")
    add("garbage.spz", bytes(range(256)) * 4, read_spz, "not a readable SPZ")
    add("empty.spz", b"", read_spz, "empty")
    add("missing_file.spz", None, read_spz, "cannot read")
    seq = write_sequence(tmp_path / "seq.ply", run, [0.0, 1.0]).read_bytes()
    add("short_seq.ply", seq[:-40], read_sequence, "truncated")
    add("single.ply", good, read_sequence, "no delta_vertex")
    short = np.zeros(len(s) - 1, dtype=[(p, "<f4") for p in ("x", "y", "z", "scale_0", "scale_1",
                     "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")])  # fmt: skip
    vertex = PlyData.read(io.BytesIO(good))["vertex"]
    buf = io.BytesIO()
    PlyData([vertex, PlyElement.describe(short, "delta_vertex_0")]).write(buf)
    add("count.ply", buf.getvalue(), read_sequence, f"{len(s) - 1} rows for {len(s)} vertices")
    zbuf = io.BytesIO()
    with zipfile.ZipFile(zbuf, "w") as z:
        z.writestr("frame_0000_t0.0000.ply", good)
        z.writestr("frame_0001_t1.0000.ply", b"ply\nnonsense")
    add("bad_member.zip", zbuf.getvalue(), read_sequence, "frame_0001_t1.0000.ply")
    add("not.zip", b"PK\x03\x04 broken", read_sequence, "not a readable zip")
    for path, reader, match in cases:
        with pytest.raises(ExportError, match=match) as e:
            reader(path)
        assert str(path) in str(e.value), (path, str(e.value))
        assert e.value.__cause__ is None


def test_splats_at_checks_and_defaults(run: Run, tmp_path: Path) -> None:
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            splats_at(run, bad)
    with pytest.raises(ValueError, match="labels"):
        splats_at(run, 0.5, labels=np.zeros(3, np.int64))
    with pytest.raises(ValueError, match="sh_rest"):
        Splats(**{**_fields(splats_at(run, None)), "sh_rest": np.zeros((300, 4, 3))})
    # A bare model: object ids 0; the same Gaussians as through its run.
    bare = splats_at(run.model, 0.5)
    assert not bare.object_ids.any() and np.array_equal(bare.means, splats_at(run, 0.5).means)
    assert np.array_equal(default_times(run), run.times)
    assert np.array_equal(default_times(run, 3), [0.0, 0.5, 1.0])
    phase1 = load_run(run.path / PHASE1_CHECKPOINT_NAME)
    assert phase1.labels is None and not splats_at(phase1, 0.2).object_ids.any()
    train = sorted({c["time"] for c in phase1.cameras if c["split"] == "train"})
    assert default_times(phase1).tolist() == train and len(train) == 4
