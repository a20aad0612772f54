"""`.4dgs` files (`sync4d.export.fourdgs`, issue 64) through the format's reference package
`fourdgs`: the file validates, reads back with objects, tracks and embeddings, its state by the
format's own object-layer rule renders (sync4d's rasterizer) like the run, a run without Phase 3
exports without embeddings, and `sync4d export --4dgs` / `--4dgs-snapshot` write what they say.

The oracle Phase 2 run of the embedded scene (`support.oracle`): its Gaussians move rigidly with
the objects (D_theta = the truth), M_phi fitted to them, so its tracks alone reproduce the run;
`Wobbling` makes some of them leave their track (a residual the tracks cannot carry).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import torch

fourdgs = pytest.importorskip(
    "fourdgs", reason="the .4dgs tests need fourdgs (pip install 'sync4d[4dgs]'; the test extra "
    "installs it)")  # fmt: skip

from support.oracle import oracle_phase2_run, oracle_run_folder  # noqa: E402
from sync4d.cli import main  # noqa: E402
from sync4d.data import load_scene  # noqa: E402
from sync4d.export import ExportError  # noqa: E402
from sync4d.export import fourdgs as fd  # noqa: E402
from sync4d.export.fourdgs import (  # noqa: E402
    read_4dgs,
    render_4dgs,
    snapshot,
    splats_from_4dgs,
    validate_4dgs,
    write_4dgs,
)
from sync4d.runs import load_run  # noqa: E402

TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)


@pytest.fixture(scope="module")
def oracle(tmp_path_factory: pytest.TempPathFactory):
    torch.set_num_threads(1)
    run, root = oracle_phase2_run(tmp_path_factory.mktemp("fourdgs"))
    return run, load_scene(root)


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def test_writes_a_valid_file_with_objects_and_tracks(oracle, tmp_path: Path) -> None:
    run, _ = oracle
    rep = write_4dgs(tmp_path / "o.4dgs", run)
    assert validate_4dgs(rep.path) == []
    sc = read_4dgs(rep.path)
    g = sc.gaussians
    assert g.count == run.model.num_gaussians and g.sh_degree == run.model.sh_degree
    assert sorted(np.unique(g.object_id).tolist()) == sorted(np.unique(run.labels).tolist())
    names = {e.object_id: e.label for e in sc.objects.table.entries}
    assert names == run.names
    # One track per moving object (the background, 0, has none), at M_phi's stored frames.
    assert sorted(t.object_id for t in sc.objects.tracks) == [1, 2, 3]
    assert all(np.allclose(t.times, run.times) for t in sc.objects.tracks)
    assert sc.objects.tracks[0].interpolation == 0  # linear: lerp and slerp, as SE3Table
    # No Phase 3 field in this run: no embeddings, and the report says why.
    assert sc.objects.table.embedding_dim == 0 and "no embeddings" in rep.note
    assert sc.header.attributes["sync4d.residual"].startswith("none")
    assert sc.duration_sec == 1.0


def test_round_trip_renders_like_the_run(oracle, tmp_path: Path) -> None:
    """The file's state by the format's own rule (base, then the object's track), rendered by
    sync4d's rasterizer, against the run's own render (D_theta) at five times."""
    run, scene = oracle
    cam = scene.test[0].camera
    bg = torch.tensor(run.background, dtype=torch.float32)
    psnr = {}
    for residual in ("none", "all"):
        rep = write_4dgs(tmp_path / f"{residual}.4dgs", run, residual=residual)
        # Rigid objects: no Gaussian leaves its track, so no residual is written either way.
        assert rep.residual_gaussians == 0 and rep.records == run.model.num_gaussians
        sc = read_4dgs(rep.path)
        for t in TIMES:
            with torch.no_grad():
                want = run.model.render(cam, t, background=bg, threads=1).features
            got = render_4dgs(sc, cam, t, near=run.model.near, background=bg, threads=1)
            psnr[residual, t] = _psnr(got, want)
    print({f"{r} t={t}": round(v, 2) for (r, t), v in psnr.items()})
    # The tracks alone reproduce the run up to quantisation (measured 55.2-55.6 dB).
    assert min(psnr.values()) > 50.0


class Wobbling:
    """`model` whose Gaussians `which` [N] bool move off their object's path by `amp` world
    units along z, ``amp sin(2 pi t)`` (a non-rigid residual); everything else is the model's."""

    def __init__(self, model, which: np.ndarray, amp: float) -> None:
        self._model, self._which, self._amp = model, torch.as_tensor(which), amp

    def __getattr__(self, name: str):
        return getattr(self._model, name)

    def at_time(self, t: float, deform: bool = True):
        m, q, s = self._model.at_time(t, deform)
        m = m.clone()
        m[self._which, 2] += self._amp * math.sin(2.0 * math.pi * t)
        return m, q, s

    def render(self, camera, t: float, **kw):
        return self._model.render(camera, t, deformed=self.at_time(t), **kw)


@pytest.fixture(scope="module")
def wobbling(oracle):
    """The oracle run with a quarter of every object's Gaussians (the background's too)
    wobbling by 0.05 units, and which ones."""
    run, scene = oracle
    rng = np.random.default_rng(0)
    which = rng.random(run.model.num_gaussians) < 0.25
    return dataclasses.replace(run, model=Wobbling(run.model, which, 0.05)), which, scene


def test_residual_keeps_each_gaussian_within_the_tolerance(wobbling, tmp_path: Path) -> None:
    """Gaussians that leave their track get piecewise-linear records, those that the tracks
    alone leave further than the tolerance (pixels in the camera that sees them largest,
    times their opacity): the wobbling ones, up to 0.05 units (about a pixel) off, and no
    steady one; a larger tolerance writes fewer records; a faint Gaussian may stray further;
    `background` keeps the objects' Gaussians on their tracks alone."""
    run, which, _ = wobbling
    n = run.model.num_gaussians
    alpha = torch.sigmoid(run.model.opacity_logits).detach().double().numpy()
    reps = {}
    for tol in (0.05, 0.2):
        rep = write_4dgs(tmp_path / f"t{tol}.4dgs", run, tolerance=tol)
        assert validate_4dgs(rep.path) == []
        reps[tol] = rep
        # the wobbling Gaussians, and no steady one, hold a residual
        moving = rep.deviation > rep.limit
        assert moving[which].mean() > 0.9 and not moving[~which].any()
        assert rep.residual_gaussians == int(moving.sum())
    assert reps[0.05].records > reps[0.2].records > n
    # the allowed distance is the tolerance over opacity times pixels per unit
    ratio = reps[0.2].limit / reps[0.05].limit
    assert np.allclose(ratio[np.isfinite(ratio)], 4.0)
    seen = np.isfinite(reps[0.05].limit)
    assert seen.mean() > 0.9
    lim_alpha = reps[0.05].limit[seen] * alpha[seen]  # 0.05 / pixels per unit
    assert lim_alpha.max() < 0.05 and lim_alpha.min() > 0.0
    none = write_4dgs(tmp_path / "none.4dgs", run, residual="none")
    assert none.records == n and none.residual_gaussians == 0
    bg = write_4dgs(tmp_path / "bg.4dgs", run, residual="background", tolerance=0.05)
    labels = np.asarray(run.labels)
    assert bg.residual_gaussians == int(((reps[0.05].deviation > reps[0.05].limit)
                                         & (labels == 0)).sum())  # fmt: skip
    # One live record per Gaussian at every stored time (the windows tile time), and the
    # file renders like the wobbling run only with its residual.
    scene = wobbling[2]
    cam = scene.test[0].camera
    bgc = torch.tensor(run.background, dtype=torch.float32)
    psnr: dict[str, list[float]] = {"all": [], "none": []}
    for name, rep in (("all", reps[0.05]), ("none", none)):
        sc = read_4dgs(rep.path)
        for t in run.times[::2]:
            assert len(sc.state_at(float(t))["indices"]) == n
            with torch.no_grad():
                want = run.model.render(cam, float(t), background=bgc, threads=1).features
            got = render_4dgs(sc, cam, float(t), near=run.model.near, background=bgc, threads=1)
            psnr[name].append(_psnr(got, want))
    print({k: [round(v, 1) for v in vs] for k, vs in psnr.items()})
    assert min(psnr["all"]) > 45.0 and min(psnr["none"]) < 35.0


def test_segments_hold_every_frame_within_its_limit() -> None:
    """`_segments`' piecewise-linear paths: per Gaussian they tile the stored frames end to end,
    and at every frame the state they give (the segment's start state, its centre moved
    linearly) is within the Gaussian's limit of the path, which bends, jumps and scales."""
    rng = np.random.default_rng(3)
    t_n, m = 40, 50
    times = np.sort(np.r_[0.0, rng.random(t_n - 2), 1.0])
    c = np.cumsum(rng.normal(0, 0.01, (t_n, m, 3)), axis=0)
    c[25:, :10] += 0.3  # a jump
    c[:, 10:20] = 0.0  # still
    q = np.tile(fd._matrix_to_quat_xyzw(np.eye(3)), (t_n, m, 1))
    ang = np.linspace(0, 1.0, t_n)[:, None] * rng.random(m)[None]
    q[..., 2], q[..., 3] = np.sin(ang / 2), np.cos(ang / 2)
    s = np.exp(rng.normal(-3, 0.3, (m, 3)))[None] * (1 + 0.2 * np.sin(6 * times))[:, None, None]
    s = np.ascontiguousarray(s)
    limit = np.full(m, 0.02)
    segs = fd._segments(times, c, q, s, limit)
    for g in range(m):
        mine = sorted((a, b) for idx, a, b in segs if g in idx)
        assert mine[0][0] == 0 and mine[-1][1] == t_n - 1
        assert all(mine[i][1] == mine[i + 1][0] for i in range(len(mine) - 1))
        for a, b in mine:
            for j in range(a, b + 1):
                w = (times[j] - times[a]) / (times[b] - times[a])
                lin = c[a, g] + w * (c[b, g] - c[a, g])
                err = fd._state_error(lin, q[a, g], s[a, g], c[j, g], q[j, g], s[j, g])
                assert err <= limit[g] + 1e-12 or b - a == 1, (g, a, b, j, err)
    still = [len([1 for idx, a, b in segs if g in idx]) for g in range(10, 20)]
    assert max(still) < max(len([1 for idx, a, b in segs if g in idx]) for g in range(10))


def test_state_follows_the_tracks(oracle, tmp_path: Path) -> None:
    run, _ = oracle
    sc = read_4dgs(write_4dgs(tmp_path / "o.4dgs", run).path)
    for t in (0.0, 0.5, 1.0):
        s = splats_from_4dgs(sc, t)
        with torch.no_grad():
            want, _, _ = run.model.at_time(t)
        ids = s["object_ids"].numpy()
        # Each object's centre where D_theta has it (order differs: compare per object).
        for k in (1, 2, 3):
            got_c = s["means"][ids == k].double().mean(0)
            want_c = want[torch.as_tensor(run.labels == k)].double().mean(0)
            assert float((got_c - want_c).norm()) < 0.02, (t, k)


def test_embeddings_rank_their_object_first(tmp_path: Path) -> None:
    """An object's embedding read back from the file ranks that object first for its name
    through the run's own text encoder (the field's, "offline")."""
    from sync4d.phase3.encoders.encoder import load_encoder
    from sync4d.phase3.store import load_field

    torch.set_num_threads(1)
    folder = oracle_run_folder(tmp_path, encoder="offline")
    run = load_run(folder)
    rep = write_4dgs(tmp_path / "f.4dgs", run)
    assert validate_4dgs(rep.path) == [] and rep.embeddings
    sc = read_4dgs(rep.path)
    field = load_field(folder)
    assert sc.header.attributes["sync4d.encoder.kind"] == field.encoder["kind"] == "offline"
    assert sc.header.attributes["sync4d.encoder.fingerprint"] == field.encoder["fingerprint"]
    rows = [e for e in sc.objects.table.entries if e.embedding is not None]
    assert sorted(e.object_id for e in rows) == sorted(field.labels)
    assert sc.objects.table.embedding_dim == field.dim
    emb = np.asarray([e.embedding for e in rows], dtype=np.float64)
    emb /= np.linalg.norm(emb, axis=1, keepdims=True)
    enc = load_encoder(sc.header.attributes["sync4d.encoder.kind"])
    for i, e in enumerate(rows):
        text = enc.encode_texts([e.label])[0].astype(np.float64)
        assert int(np.argmax(emb @ text)) == i, e.label


def test_run_without_phase2_or_field(oracle, tmp_path: Path) -> None:
    run, _ = oracle
    p1 = dataclasses.replace(run, motion=None, labels=None, times=None, names={})
    rep = write_4dgs(tmp_path / "p1.4dgs", p1)
    assert validate_4dgs(rep.path) == [] and rep.tracks == 0 and not rep.embeddings
    sc = read_4dgs(rep.path)
    assert not sc.objects and set(np.unique(sc.gaussians.object_id).tolist()) == {0}
    # a Phase 1 run has no stored frames: its canonical Gaussians, still, whatever the residual
    assert "none" in sc.header.attributes["sync4d.residual"]
    with pytest.raises(ExportError, match="give one of all, background, none"):
        write_4dgs(tmp_path / "bad.4dgs", run, residual="some")
    with pytest.raises(ExportError, match="give a number >= 0"):
        write_4dgs(tmp_path / "bad.4dgs", run, tolerance=float("nan"))
    blind = dataclasses.replace(run, cameras=[])  # the tolerance is in pixels: no cameras, no
    with pytest.raises(ExportError, match="no training cameras.*--4dgs-residual none"):
        write_4dgs(tmp_path / "blind.4dgs", blind)
    assert write_4dgs(tmp_path / "blind.4dgs", blind, residual="none").tracks == 3


def _sh_colours(sh_u8: np.ndarray, degree: int, dirs: np.ndarray) -> np.ndarray:
    """The SH rest's colour part [N, 3] of the format's u8 SH codes [N, 3K] toward `dirs`."""
    from sync4d import raster

    n, k = len(sh_u8), sh_u8.shape[1] // 3
    rest = sh_u8.astype(np.float64).reshape(n, 3, k).transpose(0, 2, 1) * (8.0 / 255.0) - 4.0
    coeffs = torch.as_tensor(np.concatenate([np.zeros((n, 1, 3)), rest], axis=1))
    return raster.spherical_harmonics(degree, torch.as_tensor(dirs), coeffs, threads=1).numpy()


def test_gltf_snapshot_composes_the_tracks(oracle, tmp_path: Path) -> None:
    """One instant as glTF, read back by fourdgs' own importer: the tracks composed, z-up baked
    into +y up (positions, orientations and degree-3 SH), so each Gaussian shows toward r d the
    colour it showed toward d; as USD (when usd-core is installed), opened by OpenUSD."""
    run, _ = oracle
    sc = read_4dgs(write_4dgs(tmp_path / "o.4dgs", run).path)
    sc.header.attributes["coordinate_system"] = "z-up-right-handed"
    rng = np.random.default_rng(4)
    g = sc.gaussians
    g.sh_degree, g.sh = 3, rng.integers(96, 160, (g.count, 45)).astype(np.uint8)
    assert snapshot(tmp_path / "s.glb", sc, 0.5) > 0
    got = fourdgs.from_gltf(str(tmp_path / "s.glb")).gaussians
    st = sc.state_at(0.5)
    r = fd._TO_Y_UP["z-up-right-handed"]
    want = np.asarray(st["centers"]) @ r.T
    assert got.count == len(want)
    # the writer's glTF keeps the state's order
    order = back = np.arange(len(want))
    assert np.allclose(got.positions, want, atol=1e-4)
    turned = fd._quat_xyzw_to_matrix(got.rotations[back].astype(np.float64))
    was = r @ fd._quat_xyzw_to_matrix(np.asarray(st["orientations"], np.float64)[order])
    assert np.allclose(np.abs(np.einsum("nij,nij->nj", turned, was)), 1.0, atol=1e-3)
    d = rng.normal(size=(len(want), 3))
    before = _sh_colours(g.sh[st["indices"]][order], 3, d)
    after = _sh_colours(got.sh[back], 3, d @ r.T)
    assert np.abs(after - before).max() < 0.2  # one 8-bit step (8/255) per coefficient
    assert np.abs(after - before).mean() < 0.02
    with pytest.raises(ExportError, match="glTF"):
        snapshot(tmp_path / "s.obj", sc, 0.5)
    if importlib.util.find_spec("pxr") is not None:
        from pxr import Usd

        assert snapshot(tmp_path / "s.usda", sc, 0.5) > 0
        stage = Usd.Stage.Open(str(tmp_path / "s.usda"))
        prims = [p.GetTypeName() for p in stage.Traverse()]
        assert "ParticleField3DGaussianSplat" in prims
        assert fourdgs.from_usd(str(tmp_path / "s.usda")).gaussians.count == len(want)


def test_sh_rotation_turns_the_colours_with_the_gaussian() -> None:
    """`_sh_rotation`: coefficients X c show toward r d what c showed toward d (every band)."""
    from sync4d import raster

    rng = np.random.default_rng(6)
    q = rng.normal(size=4)
    r = fd._quat_xyzw_to_matrix(q)
    c = rng.normal(size=(15, 3))
    x = fd._sh_rotation(3, r)
    d = rng.normal(size=(200, 3))
    full = np.concatenate([np.zeros((1, 3)), c])
    turned = np.concatenate([np.zeros((1, 3)), x @ c])

    def colour(coeffs: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        k = torch.as_tensor(np.broadcast_to(coeffs, (len(dirs), 16, 3)).copy())
        return raster.spherical_harmonics(3, torch.as_tensor(dirs), k, threads=1).numpy()

    assert np.allclose(colour(turned, d @ r.T), colour(full, d), atol=1e-9)


def test_export_command(tmp_path: Path, capsys) -> None:
    torch.set_num_threads(1)
    folder = oracle_run_folder(tmp_path, encoder="offline")
    before = sorted((p.name, p.stat().st_mtime_ns) for p in folder.rglob("*"))
    out = tmp_path / "o.4dgs"
    assert main(["export", str(folder), "--4dgs", str(out), "--4dgs-residual", "background",
                 "--4dgs-tolerance", "0.1", "--threads", "1"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "4dgs:" in printed and "embeddings: 3 objects, offline encoder" in printed
    assert validate_4dgs(out) == []
    assert sorted((p.name, p.stat().st_mtime_ns) for p in folder.rglob("*")) == before
    for extra in (["--4dgs-tolerance", "0.1"], ["--4dgs-residual", "none"]):
        assert main(["export", str(folder), "--ply", str(tmp_path / "c.ply"), *extra]) == 2
        assert "go with --4dgs" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["export", str(folder), "--4dgs", str(out), "--4dgs-tolerance", "-1"])
    assert "expected a finite number >= 0" in capsys.readouterr().err


def test_command_default_tolerance_is_the_writers() -> None:
    from sync4d.commands import export

    assert export.TOLERANCE == fd.TOLERANCE
    assert export.RESIDUAL_CHOICES == fd.RESIDUAL_CHOICES


def test_refined_tracks_fit_d_theta_despite_stray_points() -> None:
    """`_refine_tracks` from poses 0.05 off: the object's points that move rigidly end near
    their refined path, though a tenth of them drift away (a shadow given to the object)."""
    rng = np.random.default_rng(5)
    t_n, n = 12, 300
    rest = rng.normal(0, 0.2, (n, 3))
    angles = np.linspace(0, 1.2, t_n)
    rot = np.stack([fd._quat_xyzw_to_matrix(np.array([0, np.sin(a / 2), 0, np.cos(a / 2)]))
                    for a in angles])  # fmt: skip
    trans = np.stack([np.array([a, 0.5 * a, -a]) for a in angles])
    x = np.einsum("tij,nj->tni", rot, rest) + trans[:, None]
    stray = np.arange(n) < n // 10
    x[:, stray, 2] += np.linspace(0, 0.5, t_n)[:, None]
    labels = np.ones(n, dtype=np.int64)
    noisy_r = rot @ fd._quat_xyzw_to_matrix(np.array([0.03, 0, 0, 1.0]))
    noisy_t = trans + 0.05

    def worst(r: np.ndarray, b: np.ndarray) -> float:
        back = np.einsum("tji,tnj->tni", r, x - b[:, None]).mean(axis=0)
        moved = np.einsum("tij,nj->tni", r, back) + b[:, None]
        return float(np.linalg.norm(moved - x, axis=2)[:, ~stray].max())

    before = worst(noisy_r, noisy_t)
    r2, b2 = fd._refine_tracks(x.astype(np.float32), np.ones(n), labels,
                               noisy_r[None].repeat(2, 0), noisy_t[None].repeat(2, 0), [1])
    after = worst(r2[1], b2[1])
    assert after < 0.1 * before and after < 0.01, (before, after)


def test_colours_out_of_the_grid_move_into_the_sh_rest() -> None:
    """`_fit_into_gamut`: a DC colour beyond [0, 1] is clipped and its SH rest refit, so seen
    from the cameras (and from views between them) it stays nearer its old colour than the
    clip alone leaves it; colours inside the grid keep their rest."""
    from sync4d import raster

    rng = np.random.default_rng(2)
    n = 40
    means = rng.normal(0, 0.3, (n, 3))
    rgb = rng.uniform(-0.3, 1.3, (n, 3))
    rgb[:10] = rng.uniform(0.1, 0.9, (10, 3))  # inside
    rest = rng.normal(0, 0.05, (n, 15, 3))
    phi = rng.uniform(0, 2 * np.pi, 60)
    theta = rng.uniform(0.2, 1.2, 60)
    ring = 4.0 * np.stack([np.cos(phi) * np.sin(theta), np.sin(phi) * np.sin(theta),
                           np.cos(theta)], axis=1)  # fmt: skip
    cams, held = ring[:40], ring[40:]
    new_rgb, new_rest, mask = fd._fit_into_gamut(rgb, rest, means, cams)
    assert np.array_equal(mask, (rgb != np.clip(rgb, 0, 1)).any(axis=1))
    assert np.array_equal(new_rest[~mask], rest[~mask])
    assert 0.0 <= new_rgb.min() and new_rgb.max() <= 1.0

    def colours(dc_rgb: np.ndarray, r: np.ndarray, at: np.ndarray) -> np.ndarray:
        coeffs = torch.as_tensor(np.concatenate([((dc_rgb - 0.5) / fd._SH_C0)[:, None], r], 1))
        out = []
        for c in at:
            dirs = torch.as_tensor(means - c)
            out.append(raster.spherical_harmonics(3, dirs, coeffs, threads=1).numpy() + 0.5)
        return np.stack(out)

    for views in (cams, held):
        want = colours(rgb, rest, views)[:, mask]
        clip_err = np.abs(colours(new_rgb, rest, views)[:, mask] - want).mean()
        fit_err = np.abs(colours(new_rgb, new_rest, views)[:, mask] - want).mean()
        assert fit_err < 0.5 * clip_err, (fit_err, clip_err)


def test_the_example_writes_its_4dgs_files(tmp_path: Path) -> None:
    """examples/export.sh as a user runs it, with fourdgs installed: the .4dgs with the
    residual, its glTF instant, and the one whose objects move by their tracks alone."""
    import os
    import subprocess
    import sys

    from support import ROOT

    folder = oracle_run_folder(tmp_path, encoder="offline")
    out = tmp_path / "out"
    done = subprocess.run(
        ["sh", str(ROOT / "examples" / "export.sh"), str(folder), str(out)], cwd=tmp_path,
        capture_output=True, text=True, timeout=600,
        env={**os.environ, "PYTHON": sys.executable, "OMP_NUM_THREADS": "1"})  # fmt: skip
    assert done.returncode == 0, done.stderr
    for name in ("scene.4dgs", "rigid.4dgs"):
        assert validate_4dgs(out / name) == [], name
    assert (out / "t0.5.glb").stat().st_size > 0
    rigid = read_4dgs(out / "rigid.4dgs").header.attributes["sync4d.residual"]
    assert rigid.startswith("none (background)")  # the oracle's plate stands still
