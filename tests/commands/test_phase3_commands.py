"""Phase 3 through the command line on a tiny real run: `fit --phases 3`, `query`,
`eval --queries`, `bench phase3`, and the clear errors for runs, encoders and queries that
cannot be used."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from support.datasets import write_blender
from support.scenes import small_synthetic
from sync4d.cli import main
from sync4d.data import synthetic as syn
from sync4d.events import read_events
from sync4d.runs import EVENTS_FILE

SMALL = small_synthetic()

SETTINGS = ["--iters", "12", "--threads", "1", "--set", "phase1.init_points=300",
            "--set", "eval_every=0", "--set", "phase2.iterations=8",
            "--set", "phase2.motion_start=2"]  # fmt: skip


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("phase3_cli")
    write_blender(tmp / "tiny", n=4, size=24)
    assert main(["fit", str(tmp / "tiny"), "--out", str(tmp / "p1"), *SETTINGS,
                 "--phases", "1"]) == 0  # fmt: skip
    assert main(["fit", str(tmp / "tiny"), "--out", str(tmp / "p2"), *SETTINGS]) == 0
    # the embedded scene, small: its masks give every object Gaussians from the first votes
    syn.write_synthetic_scene(tmp / "objects", SMALL)
    assert main(["fit", str(tmp / "objects"), "--out", str(tmp / "objects-run"), *SETTINGS,
                 "--set", "phase1.init_points=3000",
                 "--set", "phase1.init_from=random"]) == 0  # fmt: skip
    return {"data": tmp / "tiny", "p1": tmp / "p1", "p2": tmp / "p2", "tmp": tmp,
            "objects": tmp / "objects-run"}  # fmt: skip


def test_phase3_needs_a_phase2_run(runs, capsys):
    assert main(["fit", "--out", str(runs["p1"]), "--phases", "3", "--threads", "1"]) == 2
    err = capsys.readouterr().err
    assert "needs a Phase 2 checkpoint" in err and "--phases 2" in err
    assert not (runs["p1"] / "phase3").exists()


def test_phase3_refuses_settings_that_do_not_apply(runs, capsys):
    assert main(["fit", "--out", str(runs["p2"]), "--phases", "3",
                 "--set", "phase1.iterations=5"]) == 2
    assert "settings other than phase3.*" in capsys.readouterr().err
    assert main(["fit", "--out", str(runs["p2"]), "--phases", "3", "--set", "phase3.beta=2"]) == 2
    assert "phase3.beta" in capsys.readouterr().err


def test_a_missing_or_broken_encoder_folder_is_named(runs, capsys, tmp_path):
    missing = tmp_path / "no-such-encoder"
    assert main(["fit", "--out", str(runs["p2"]), "--phases", "3", "--encoder", str(missing)]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "encoder convert" in err
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "encoder.json").write_text("{}")
    assert main(["fit", "--out", str(runs["p2"]), "--phases", "3", "--encoder", str(broken)]) == 2
    assert str(broken) in capsys.readouterr().err


def test_query_without_a_field_says_how_to_build_it(runs, capsys):
    assert main(["query", str(runs["p2"]), "red ball"]) == 2
    err = capsys.readouterr().err
    assert "no language field" in err and "--phases 3" in err
    assert main(["query", str(runs["tmp"] / "nowhere"), "red ball"]) == 2
    assert "no such run folder" in capsys.readouterr().err


def test_phases_must_be_contiguous(runs, capsys):
    assert main(["fit", str(runs["data"]), "--out", str(runs["tmp"] / "x"), "--phases", "1,3"]) == 2
    assert "1,3" in capsys.readouterr().err
    assert not (runs["tmp"] / "x").exists()


def test_fit_query_and_eval_with_the_offline_encoder(runs, capsys, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(runs["objects"], run)
    assert main(["fit", "--out", str(run), "--phases", "3",
                 "--encoder", "offline", "--threads", "1"]) == 0
    out, err = capsys.readouterr()
    assert "Phase 3: 3 objects x 6 frames" in out
    assert "fit: Phase 3 encoded " in err and " of 18 object-frames in " in err
    assert (run / "phase3" / "field.safetensors").is_file()
    # The build's events follow the fit's in the run's event log, for another process.
    events = read_events(run / EVENTS_FILE)
    kinds = [e["event"] for e in events]
    build = events[len(kinds) - 1 - kinds[::-1].index("Phase3Started"):]
    assert [e["event"] for e in build if e["event"] not in ("Started", "Advanced", "Finished")
            ] == ["Phase3Started", "PhaseDone", "FieldBuilt", "Skipped"]  # fmt: skip
    assert build[-2]["objects"] == 3 and build[-1]["counts"]["object_frames"] == 18
    assert build[-1]["phase"] == "phase3"
    assert main(["query", str(run), "the blue box", "a green pillar at rest", "--json"]) == 0
    answers = json.loads(capsys.readouterr().out)
    assert [a["query"] for a in answers] == ["the blue box", "a green pillar at rest"]
    assert answers[0]["objects"][0]["name"] == "blue box" and answers[0]["closed_vocabulary"]
    assert answers[1]["motion_phrases"][0]["predicate"] == "at rest"
    assert Path(answers[0]["plot"]).is_file()
    assert main(["query", str(run), "   "]) == 2
    assert "empty query" in capsys.readouterr().err
    queries = tmp_path / "queries.json"
    queries.write_text(json.dumps({"queries": [
        {"query": "the red ball", "object": "red ball", "frames": [[0, 5]]}]}))  # fmt: skip
    assert main(["eval", str(run), "--queries", str(queries), "--scorer", "paper", "names"]) == 0
    table = capsys.readouterr().out
    assert "paper" in table and "names" in table
    rows = json.loads((run / "phase3" / "eval-queries-names.json").read_text())
    assert rows["queries"][0]["query"] == "the red ball"
    assert rows["queries"][0]["object_correct"] is True
    assert rows["queries"][0]["viou"] is not None  # the dataset's masks are the GT masks
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"queries": [{"query": "x", "object": "ghost",
                                            "frames": [[0, 1]]}]}))  # fmt: skip
    assert main(["eval", str(run), "--queries", str(bad)]) == 2
    assert "ghost" in capsys.readouterr().err
    assert main(["bench", "phase3", str(run), "--repeat", "1", "--queries", "the ball",
                 "--out", str(tmp_path / "b.json"), "--threads", "1"]) == 0  # fmt: skip
    res = json.loads((tmp_path / "b.json").read_text())["results"][0]
    built = json.loads((run / "phase3" / "field.json").read_text())["timings"]
    assert res["query_warm_ms"] > 0 and res["crops"] == built["crops"]  # same field, same crops


def test_a_field_of_another_model_is_refused_and_refits_clear_it(runs, capsys, tmp_path):
    """The field records the checkpoint it was built from: `query` and `eval` refuse it once
    the run's checkpoint changed, naming the command that rebuilds it; `--phases 2` and
    `--force` remove it with the model it described."""
    run = tmp_path / "run"
    shutil.copytree(runs["objects"], run)
    build = ["fit", "--out", str(run), "--phases", "3", "--encoder", "offline", "--threads", "1"]
    assert main(build) == 0
    meta = json.loads((run / "phase3" / "field.json").read_text())
    assert meta["checkpoint"]["file"] == "checkpoint.safetensors"
    assert len(meta["checkpoint"]["sha256"]) == 64
    assert main(["query", str(run), "the blue box"]) == 0
    capsys.readouterr()
    # another model under the same name: the Phase 1 checkpoint copied over the Phase 2 one
    shutil.copyfile(run / "phase1.safetensors", run / "checkpoint.safetensors")
    queries = tmp_path / "queries.json"
    queries.write_text(json.dumps({"queries": [
        {"query": "the red ball", "object": "red ball", "frames": [[0, 5]]}]}))  # fmt: skip
    for command in (["query", str(run), "the blue box"], ["eval", str(run), "--queries",
                                                          str(queries)]):  # fmt: skip
        assert main(command) == 2
        err = capsys.readouterr().err
        assert "built from another model" in err and f"fit --out {run} --phases 3" in err
    # a field that does not say what it was built from (an older sync4d) is refused too
    shutil.copyfile(runs["objects"] / "checkpoint.safetensors", run / "checkpoint.safetensors")
    assert main(["query", str(run), "the blue box"]) == 0
    del meta["checkpoint"]
    (run / "phase3" / "field.json").write_text(json.dumps(meta))
    capsys.readouterr()
    assert main(["query", str(run), "the blue box"]) == 2
    assert "does not record the checkpoint" in capsys.readouterr().err
    # redoing Phase 2 removes the field of the old Phase 2 ...
    assert main(build) == 0
    assert main(["fit", "--out", str(run), "--phases", "2", "--threads", "1"]) == 0
    assert not (run / "phase3").exists()
    capsys.readouterr()
    assert main(["query", str(run), "the blue box"]) == 2
    assert "no language field" in capsys.readouterr().err
    # ... and so does starting over with --force, even with Phase 1 alone
    assert main(build) == 0
    assert main(["fit", str(runs["objects"].parent / "objects"), "--out", str(run), "--force",
                 *SETTINGS, "--set", "phase1.init_from=random", "--phases", "1"]) == 0  # fmt: skip
    assert not (run / "phase3").exists()
