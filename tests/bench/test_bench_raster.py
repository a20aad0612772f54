"""``python -m sync4d bench raster``: a tiny run through the CLI entry, the JSON it writes, the
benchmark scene, the table and the reference watchdog. Timing values are never asserted."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest
import torch

from sync4d import cli
from sync4d.bench import raster as bench


def test_cli_quick_run_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bench.json"
    threads_before = torch.get_num_threads()
    argv = ["bench", "raster", "--quick", "--sizes", "2000", "--resolutions", "64x64"]
    argv += ["--thread-counts", "1", "--no-reference", "--out", str(out)]
    assert cli.main(argv) == 0
    assert torch.get_num_threads() == threads_before  # restored

    printed = capsys.readouterr().out
    assert "s4d f+b ms" in printed and "skipped (--no-reference)" in printed

    doc = json.loads(out.read_text())
    assert doc["schema"] == bench.SCHEMA and doc["complete"] is True
    for key in ("cpu_model", "nproc", "torch_version", "sync4d_version", "gsplat_version"):
        assert key in doc["machine"]
    assert doc["machine"]["nproc"] >= 1
    assert set(doc["allocators"]) == {"sync4d", "torch"}
    assert "RasterContext pool" in doc["allocators"]["sync4d"]
    assert isinstance(doc["env"], dict)
    settings = doc["settings"]
    assert settings["sizes"] == [2000] and settings["resolutions"] == ["64x64"]
    assert settings["threads"] == [1]
    assert settings["memory_method"] in ("clear_refs", "subprocess")
    assert settings["reference_enabled"] is False

    (row,) = doc["results"]
    assert (row["n"], row["width"], row["height"], row["threads"]) == (2000, 64, 64, 1)
    assert row["reference"]["status"] == "skipped (--no-reference)"
    assert row["speedup_forward_backward"] is None
    s4d = row["sync4d"]
    for mode in ("forward", "forward_backward"):
        t = s4d[mode]
        assert len(t["times_ms"]) == t["repeats"] >= 1
        assert all(v > 0 for v in t["times_ms"]) and t["median_ms"] > 0
        if t["rss_peak_mb"] is not None:
            assert t["rss_peak_mb"] > 0 and t["rss_baseline_mb"] > 0
    counters = s4d["counters"]
    assert set(counters) >= {"visible", "intersections", "evaluated", "blended"}
    assert counters["visible"] > 0 and counters["blended"] > 0
    assert doc["total_seconds"] > 0 and doc["thread_scaling"] == []
    # wgpu columns: timed when an adapter opens (lavapipe in CI), else a stated skip.
    assert "wgpu f+b ms" in printed
    wg = row["wgpu"]
    if settings["wgpu_adapter"]:
        assert wg["status"] == "ok" and wg["forward_backward"]["median_ms"] > 0
        assert wg["counters"]["blended"] == counters["blended"]
    else:
        assert wg["status"].startswith("skipped") and settings["wgpu_note"]
        assert os.environ.get("SYNC4D_REQUIRE_GPU") != "1"


def test_bench_scene_matches_the_spec() -> None:
    n, w, h = 5000, 96, 54
    s = bench.bench_scene(n, w, h)
    again = bench.bench_scene(n, w, h, seed=0)
    for a, b in zip(s.gaussians(), again.gaussians(), strict=True):
        assert a.dtype == torch.float32 and torch.equal(a, b)
    assert not torch.equal(s.means, bench.bench_scene(n, w, h, seed=1).means)
    assert s.means.shape == (n, 3) and s.quats.shape == (n, 4) and s.scales.shape == (n, 3)
    assert s.opacities.shape == (n,) and s.colors.shape == (n, 3)
    fx, fy = s.K[0, 0].item(), s.K[1, 1].item()
    assert fx == fy == pytest.approx(0.8 * w)
    assert (s.K[0, 2].item(), s.K[1, 2].item()) == (w / 2, h / 2)
    assert torch.equal(s.viewmat, torch.eye(4))
    x, y, z = s.means.unbind(1)
    assert z.min() >= 2 and z.max() <= 6
    assert (x.abs() <= 1.1 * z * w / (2 * fx) + 1e-5).all()
    assert (y.abs() <= 1.1 * z * h / (2 * fy) + 1e-5).all()
    assert (x.abs() > z * w / (2 * fx)).any()  # the frustum is widened
    assert s.opacities.min() >= 0.05 and s.opacities.max() <= 0.95
    assert s.colors.min() >= 0 and s.colors.max() <= 1
    log_s = s.scales.log()
    assert log_s.mean().item() == pytest.approx(math.log(0.012), abs=0.03)
    assert log_s.std().item() == pytest.approx(0.5, abs=0.03)


def test_resolution_argument() -> None:
    args = cli.build_parser().parse_args(["bench", "raster", "--resolutions", "800x800", "960x536"])
    assert args.resolutions == [(800, 800), (960, 536)]
    assert bench.parse_resolution("960x536") == (960, 536)
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["bench", "raster", "--resolutions", "800"])
    with pytest.raises(ValueError):
        bench.parse_resolution("0x5")


def test_table_shows_skipped_reference() -> None:
    timing = {"median_ms": 12.5, "rss_peak_mb": 600.0, "rss_delta_mb": 50.0}
    row = {
        "n": 1_000_000,
        "resolution": "800x800",
        "threads": 2,
        "sync4d": {
            "forward": timing,
            "forward_backward": timing,
            "counters": {"visible": 9, "intersections": 12, "evaluated": 40, "blended": 30},
        },
        "reference": {"status": "skipped (N > 100k)"},
    }
    bench._summarise(row)
    table = bench.format_table([row])
    assert "skipped (N > 100k)" in table and "1,000,000" in table
    assert len({len(line) for line in table.splitlines()[:2]}) == 1  # header and rule align


def test_watchdog_kills_a_child_over_its_memory_limit() -> None:
    job = dict(
        impl="sync4d", n=100, width=16, height=16, seed=0, threads=1,
        modes=["forward"], warmup=0, repeats=1, memory_method="subprocess",
    )  # fmt: skip
    outcome = bench.run_child(job, limit_gb=0.05)  # importing torch alone passes 50 MiB
    assert outcome.status == "aborted (RSS > 0.05 GB limit)"
    assert outcome.result is None


def test_run_job_structure() -> None:
    """What a child process returns (run here in-process, ru_maxrss flavour)."""
    res = bench.run_job(
        impl="sync4d", n=300, width=32, height=24, seed=0, threads=1,
        modes=["forward_backward"], warmup=0, repeats=2, memory_method="subprocess",
    )  # fmt: skip
    t = res["modes"]["forward_backward"]
    assert set(t) == set(bench.Timing.__dataclass_fields__)
    assert len(t["times_ms"]) == 2 and t["rss_peak_mb"] > 0
    assert res["counters"]["visible"] > 0  # counters are filled even without a forward mode


def test_run_mode_times_a_trained_runs_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`bench raster --run RUN`: the run's own Gaussians at its test cameras, a variant beside
    the default, counters that match a direct render of the same frame."""
    from sync4d.bench.raster_run import run_frames
    from sync4d.data.synthetic import SyntheticConfig, write_synthetic_scene
    from sync4d.raster import rasterize

    data = write_synthetic_scene(tmp_path / "scene", SyntheticConfig(
        size=48, frames=6, train_cameras=4, test_cameras=2, test_every=3))  # fmt: skip
    run = tmp_path / "run"
    assert cli.main(["fit", str(data), "--out", str(run), "--phases", "1", "--iters", "20",
                     "--threads", "1", "--set", "eval_every=0",
                     "--set", "phase1.init_points=300",
                     "--set", "phase1.init_from=random"]) == 0  # fmt: skip
    out = tmp_path / "bench.json"
    argv = ["bench", "raster", str(run), "--frames", "2", "--repeats", "1",
            "--thread-counts", "1", "--variant", "aa:antialiased=true", "--out", str(out)]
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "fwd+bwd ms" in printed and "eval/blend" in printed
    doc = json.loads(out.read_text())
    rows = doc["results"]
    assert [r["variant"] for r in rows] == ["default", "aa"] * 2
    assert rows[1]["rasterize_kwargs"] == {"antialiased": True}
    frames = run_frames(run, frames=2)
    assert [f.name for f in frames] == [r["frame"] for r in rows[::2]]
    f = frames[0]
    direct = rasterize(*f.gaussians(), f.viewmat, f.K, f.width, f.height, near=f.near,
                       background=f.background, threads=1).counters  # fmt: skip
    assert rows[0]["counters"] == {k: int(v) for k, v in direct.items()}
    assert rows[0]["counters"]["blended"] > 0
    for r in rows:
        assert r["forward_backward"]["median_ms"] > 0 and r["n"] == f.means.shape[0]


def test_run_mode_names_a_missing_run_and_a_bad_variant(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["bench", "raster", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err
    argv = ["bench", "raster", str(tmp_path), "--variant", "x:speed=fast"]
    assert cli.main(argv) == 2
    assert "alpha_max" in capsys.readouterr().err


def test_run_mode_names_a_moved_dataset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run whose dataset folder is gone: one line naming it and --data, no traceback."""
    from sync4d.data.synthetic import SyntheticConfig, write_synthetic_scene

    data = write_synthetic_scene(tmp_path / "scene", SyntheticConfig(
        size=32, frames=4, train_cameras=2, test_cameras=1, test_every=2))  # fmt: skip
    run = tmp_path / "run"
    assert cli.main(["fit", str(data), "--out", str(run), "--phases", "1", "--iters", "5",
                     "--threads", "1", "--set", "eval_every=0",
                     "--set", "phase1.init_points=100",
                     "--set", "phase1.init_from=random"]) == 0  # fmt: skip
    data.rename(tmp_path / "moved")
    capsys.readouterr()
    assert cli.main(["bench", "raster", str(run), "--repeats", "1"]) == 2
    err = capsys.readouterr().err
    assert "is not there any more" in err and "--data" in err and "Traceback" not in err
    argv = ["bench", "raster", str(run), "--data", str(tmp_path / "moved"),
            "--frames", "1", "--repeats", "1", "--out", str(tmp_path / "b.json")]
    assert cli.main(argv) == 0
