"""`sync4d export` as a user runs it, on a tiny real run of the embedded scene: every file it
writes, and one clear message for each thing it cannot do."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from support.scenes import small_synthetic
from sync4d.cli import main
from sync4d.data import synthetic as syn
from sync4d.export import load, read_ply, read_sequence, read_spz

SETTINGS = ["--iters", "12", "--threads", "1", "--set", "phase1.init_points=3000", "--set",
            "phase1.init_from=random", "--set", "eval_every=0", "--set", "phase2.iterations=8",
            "--set", "phase2.motion_start=2"]  # fmt: skip


@pytest.fixture(scope="module", params=["gaussians", "nodes"])
def runs(tmp_path_factory: pytest.TempPathFactory, request) -> dict[str, Path]:
    """Runs of both motion models: D_theta per Gaussian, and control nodes (which take over
    after the first iteration at this budget)."""
    tmp = tmp_path_factory.mktemp("export_cli")
    syn.write_synthetic_scene(tmp / "data", small_synthetic())
    settings = [*SETTINGS, "--set", f"phase1.motion={request.param}", "--set",
                "phase1.nodes.count=64"]  # fmt: skip
    assert main(["fit", str(tmp / "data"), "--out", str(tmp / "run"), *settings,
                 "--phases", "1,2,3"]) == 0  # fmt: skip
    assert main(["fit", str(tmp / "data"), "--out", str(tmp / "p1"), *settings,
                 "--phases", "1"]) == 0  # fmt: skip
    if request.param == "nodes":
        from sync4d.runs import load_run

        assert load_run(tmp / "run").model.motion == "nodes"
    return {"run": tmp / "run", "p1": tmp / "p1", "tmp": tmp}


def test_export_writes_every_file(runs, capsys, tmp_path):
    vocab = tmp_path / "vocab.txt"
    vocab.write_text("# colours\na red ball\n\na blue box\na green pillar\n")
    out = tmp_path / "out"
    out.mkdir()
    args = ["export", str(runs["run"]), "--scene", str(out / "scene.json"),
            "--prompt", str(out / "prompt.txt"), "--vocab", str(vocab),
            "--query", "the red ball while it is falling", "--ply", str(out / "c.ply"),
            "--spz", str(out / "t.spz"), "--time", "0.5", "--sequence", str(out / "seq.zip"),
            "--frames", "3", "--threads", "1"]  # fmt: skip
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "tokens by all-MiniLM-L6-v2 WordPiece" in printed and "seq.zip (3 frames)" in printed
    scene = load(out / "scene.json")
    assert scene.texts == ["a red ball", "a blue box", "a green pillar",
                           "the red ball while it is falling"]  # fmt: skip
    assert scene.embeddings["texts"].shape[0] == 4
    assert [o.name for o in scene.objects] == ["red ball", "blue box", "green pillar"]
    assert "red ball" in (out / "prompt.txt").read_text()
    ply = read_ply(out / "c.ply")
    assert ply.time == 0.5 and set(ply.object_ids.tolist()) <= {0, 1, 2, 3}
    assert len(read_spz(out / "t.spz").means) == len(ply.means)
    times, frames = read_sequence(out / "seq.zip")
    assert len(frames) == 3 and list(times) == pytest.approx([0.0, 0.5, 1.0])
    # the same command again gives the same bytes
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    assert main(args) == 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first


def test_a_phase1_run_exports_splats_but_no_scene(runs, capsys, tmp_path):
    assert main(["export", str(runs["p1"]), "--ply", str(tmp_path / "p1.ply")]) == 0
    assert not read_ply(tmp_path / "p1.ply").object_ids.any()
    assert main(["export", str(runs["p1"]), "--scene", str(tmp_path / "s.json")]) == 2
    err = capsys.readouterr().err
    assert "no language field" in err and "--phases 3" in err
    assert not (tmp_path / "s.json").exists()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ([], "nothing to export: give --scene"),
        (["--ply", "x.ply", "--time", "1.5"], "--time 1.5: times are normalised"),
        (["--ply", "x.ply", "--vocab", "v.txt"], "--vocab and --query fill the scene"),
        (["--scene", "s.json", "--vocab", "missing.txt"], "missing.txt: cannot read"),
        (["--scene", "s.json", "--vocab", "empty.txt"], "empty.txt: the vocabulary file has no"),
        (["--scene", "s.json", "--vocab", "bad.json"], "bad.json: a JSON vocabulary must be"),
    ],
)
def test_bad_requests_get_one_clear_message(runs, capsys, tmp_path, monkeypatch, extra, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty.txt").write_text("# nothing\n\n")
    (tmp_path / "bad.json").write_text(json.dumps(["a ball", 3]))
    assert main(["export", str(runs["run"]), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("export: ") and message in err and "Traceback" not in err


def test_a_missing_4dgs_writer_is_named_with_its_install_line(runs, capsys, tmp_path,
                                                                  monkeypatch):  # fmt: skip
    """`--4dgs` without the optional fourdgs package: one line with the install command."""
    monkeypatch.setitem(sys.modules, "fourdgs", None)  # `import fourdgs` raises ImportError
    assert main(["export", str(runs["run"]), "--4dgs", str(tmp_path / "x.4dgs")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("export: ") and "pip install 'sync4d[4dgs]'" in err, err
    assert "Traceback" not in err and not (tmp_path / "x.4dgs").exists()


def test_missing_run_and_unwritable_output(runs, capsys, tmp_path):
    assert main(["export", str(tmp_path / "nope"), "--ply", str(tmp_path / "a.ply")]) == 2
    assert "no such run folder" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["export", str(runs["run"]), "--ply", str(blocker / "a.ply")]) == 2
    assert str(blocker) in capsys.readouterr().err
