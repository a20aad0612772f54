"""Phase 3 end to end on an oracle Phase 2 run of the embedded scene: Gaussians sampled in the
objects, moved by the scene's true motion, M_phi fitted in closed form. Everything Phase 3 adds
(crops, visibility, kinematics, field, queries, motion phrases, evaluation) is then checked
against the scene's ground truth, with a small deterministic colour encoder standing in for an
image-text model (the real encoders have their own tests)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from support.encoders import ColourEncoder
from support.oracle import oracle_phase2_run
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.phase3 import motion_phrases as mp
from sync4d.phase3.build import FieldError, build_field, load_field
from sync4d.phase3.config import Phase3Config
from sync4d.phase3.encoders.encoder import EncoderError
from sync4d.phase3.evaluation.annotations import frame_number
from sync4d.phase3.evaluation.query_eval import evaluate_queries, state_queries
from sync4d.phase3.evaluation.query_metrics import temporal_iou
from sync4d.phase3.query import QueryError, TextCache, answer


@pytest.fixture(scope="module")
def oracle_run(tmp_path_factory):
    run, root = oracle_phase2_run(tmp_path_factory.mktemp("phase3"))
    run_dir = run.path
    enc = ColourEncoder()
    field = build_field(run, Phase3Config(), enc, threads=1)
    field.save(run_dir)
    return run, field, enc, root


def _gt(field, spans):
    gt = np.zeros(len(field.times), bool)
    for t0, t1 in spans:
        gt |= (field.times >= t0 - 1e-9) & (field.times <= t1 + 1e-9)
    return gt


def test_crops_visibility_and_views(oracle_run):
    run, field, enc, _ = oracle_run
    assert field.names == ["red ball", "blue box", "green pillar"]
    assert field.observed.all() and enc.images == field.observed.sum()
    assert (field.visible > 0.9).all()  # nothing occludes the objects from the best view
    x0, y0, x1, y1 = (field.boxes[..., i] for i in range(4))
    assert ((x1 > x0) & (y1 > y0) & (x0 >= 0) & (y0 >= 0) & (x1 <= 48) & (y1 <= 48)).all()
    assert all(v.endswith(".png") for row in field.views for v in row)
    np.testing.assert_allclose(field.up, [0.0, 0.0, 1.0], atol=1e-6)  # ring cameras, z up
    # each object's static embedding is its colour
    q = enc.encode_texts(["red", "blue", "green"])
    assert list(np.argmax(field.static @ q.T, axis=0)) == [0, 1, 2]


def test_kinematics_follow_the_true_motion(oracle_run):
    _, field, _, root = oracle_run
    gt = syn.load_ground_truth(root)
    speed = field.features[..., 0]
    assert speed[2].max() < 1e-3  # the pillar never moves
    moving = (field.times > 0.25) & (field.times < 0.75)
    assert (speed[1, moving] > 0.2).all() and speed[1, field.times < 0.15].max() < 1e-3
    vz = field.features[0, :, 8]
    rising = (field.times > syn.HOP[0] + 0.03) & (field.times < syn.HOP[1] - 0.03)
    falling = (field.times > syn.HOP[1] + 0.03) & (field.times < syn.HOP[2] - 0.03)
    assert (vz[rising] > 0.5).all() and (vz[falling] < -0.5).all()
    # M_phi explains the true motion: residuals near 0, rigid share near 1 once the object has
    # moved (Phase 2's share is 0 where nothing moved: |x~ - x0| = 0)
    assert field.features[..., 3].max() < 0.02
    assert field.features[0, 1:, 4].min() > 0.95 and field.features[1, moving, 4].min() > 0.95
    assert field.features[2, :, 4].max() < 0.05
    box_turn = field.features[1, -1, 16]
    true_turn = np.arccos((np.trace(gt.rotations[1, -1] @ gt.rotations[1, 0].T) - 1) / 2)
    assert box_turn == pytest.approx(true_turn, abs=0.02)


def test_state_queries_find_the_object_and_the_interval(oracle_run):
    run, field, enc, root = oracle_run
    cache = TextCache(run.path, field, enc)
    queries = state_queries(root / "ground_truth.json")["queries"]
    assert len(queries) == 6
    tious = []
    for q in queries:
        ans = answer(field, q["query"], cache=cache, scorer="full")
        assert ans["objects"][0]["name"] == q["object"], q["query"]
        act = np.asarray(ans["active"][q["object"]])
        tious.append(temporal_iou(act, _gt(field, q["times"])))
    assert min(tious) >= 0.75 and np.mean(tious) >= 0.85, tious


def test_motion_phrases_and_relations(oracle_run):
    run, field, enc, _ = oracle_run
    cache = TextCache(run.path, field, enc)
    ans = answer(field, "the fastest object", cache=cache, scorer="motion")
    assert ans["objects"][0]["name"] == "red ball"
    ans = answer(field, "the red ball touching the plate", cache=cache, scorer="full")
    assert ans["motion_phrases"][0]["target"] == 0
    act = np.asarray(ans["active"]["red ball"])
    air = (field.times > syn.HOP[0] + 0.05) & (field.times < syn.HOP[2] - 0.05)
    assert not act[air].any() and act[field.times < 0.3].all()
    ans = answer(field, "approaching the green pillar", cache=cache, scorer="motion")
    assert ans["motion_phrases"][0]["target"] == 3
    assert ans["objects"][-1]["name"] == "green pillar"  # never approaches itself
    with pytest.raises(QueryError, match="empty query"):
        answer(field, "   ", cache=cache)
    with pytest.raises(QueryError, match="unknown scorer"):
        answer(field, "red", cache=cache, scorer="psychic")


def test_phrase_matching_is_literal_first_longest_first():
    found, rest = mp.match_predicates("the ball rolling on the ground")
    assert [m.predicate.name for m in found] == ["moving", "touching"]
    assert found[1].target == 0 and rest == "the ball"
    found, rest = mp.match_predicates("the red ball moving up")
    assert [m.predicate.name for m in found] == ["rising"] and rest == "the red ball"
    found, rest = mp.match_predicates("a box on the table")
    assert found[0].predicate.name == "touching" and found[0].target_text == "the table"
    found, rest = mp.match_predicates("the blue box")
    assert found == [] and rest == "the blue box"
    # fallback: the encoder's n-gram similarity, only when nothing matches literally
    def sim(grams, phrases):
        return np.array([[1.0 if (g, p) == ("plummeting", "falling") else 0.0 for p in phrases]
                         for g in grams])  # fmt: skip
    found, rest = mp.match_predicates("the ball plummeting", sim, 0.8)
    assert found[0].predicate.name == "falling" and found[0].similarity == 1.0


def test_second_query_encodes_nothing(oracle_run):
    run, field, _, _ = oracle_run
    enc = ColourEncoder()
    answer(field, "a tall green pillar at rest", cache=TextCache(run.path, field, enc))
    assert enc.texts > 0
    fresh = ColourEncoder()
    answer(field, "a tall green pillar at rest", cache=TextCache(run.path, field, fresh))
    assert fresh.texts == 0  # read from RUN/phase3/texts.json


def test_static_only_ablation_activates_every_frame(oracle_run):
    run, field, enc, _ = oracle_run
    ans = answer(field, "red", cache=TextCache(run.path, field, enc), scorer="static")
    assert ans["objects"][0]["name"] == "red ball"
    assert all(ans["active"]["red ball"])


def test_eval_on_the_ground_truth_and_a_saved_field(oracle_run, monkeypatch):
    run, field, enc, root = oracle_run
    loaded = load_field(run.path)
    np.testing.assert_array_equal(loaded.sync, field.sync)
    assert loaded.names == field.names and loaded.encoder == field.encoder
    monkeypatch.setattr("sync4d.phase3.evaluation.query_eval.load_run", lambda _: run)
    summary = evaluate_queries(run.path, root / "ground_truth.json", scorers=("full", "static"),
                               encoder=enc)  # fmt: skip
    assert summary["full"]["tiou"] >= 0.85 and summary["full"]["object_accuracy"] == 1.0
    assert summary["static"]["tiou"] < summary["full"]["tiou"]
    rows = json.loads((run.path / "phase3" / "eval-ground_truth-full.json").read_text())
    assert len(rows["queries"]) == 6
    assert (run.path / "phase3" / "eval-ground_truth-full.csv").read_text().count("\n") == 8


def test_bad_field_and_run_inputs(oracle_run, tmp_path):
    run, field, enc, _ = oracle_run
    with pytest.raises(FieldError, match="no language field"):
        load_field(tmp_path)
    phase1 = dataclasses.replace(run, kind="sync4d.phase1", motion=None)
    with pytest.raises(FieldError, match="needs a Phase 2 run"):
        build_field(phase1, Phase3Config(), enc)
    out = field.save(tmp_path / "copy")
    (out / "field.json").write_text("{not json")
    with pytest.raises(FieldError, match="field.json"):
        load_field(tmp_path / "copy")


def test_states_are_intervals_and_smoothing_keeps_the_mean():
    act = np.array([[1, 1, 0, 1, 1, 0, 0, 1, 0, 0, 1, 1, 1]], bool)
    # the one-frame gap at 2 closes; the lone frame at 7 goes; the 3-frame run at 10-12 stays
    np.testing.assert_array_equal(
        mp.clean_runs(act, 3)[0], [1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 1, 1, 1])
    times = np.sort(np.random.default_rng(4).uniform(0, 1, 30))
    line = np.stack([times, 2 * times, np.zeros(30)], -1)[None]
    sm = mp.smooth_in_time(line, times, 0.02)
    mid = (times > 0.1) & (times < 0.9)  # a line is kept away from the ends
    np.testing.assert_allclose(sm[0, mid], line[0, mid], atol=0.01)
    np.testing.assert_array_equal(mp.smooth_in_time(line, times, 0.0), line)


def test_eval_reads_4d_langsplat_annotations(oracle_run, monkeypatch, tmp_path):
    """A 4D LangSplat-style annotation folder (COCO polygons + video_annotations.json) for the
    red ball's hop: the polygons are the bounding boxes of its instance mask in each frame's
    first view, so vIoU compares the rendered label mask with them. Each image is named by
    that view's own file number (frames are mapped by name when the dataset is known)."""
    run, field, enc, root = oracle_run
    scene = load_scene(root)
    ann = tmp_path / "annotations"
    (ann / "train").mkdir(parents=True)
    images, annotations = [], []
    for f, t in enumerate(field.times):
        view = next(fr for fr in scene.train if abs(fr.time - t) < 1e-6)
        ys, xs = np.nonzero(view.load_mask() == 1)
        x0, y0, x1, y1 = int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1
        number = frame_number(view.image_path.name)
        images.append({"id": f, "file_name": f"{number:06d}.png", "width": 48, "height": 48})
        annotations.append({"id": f, "image_id": f, "category_id": 1, "bbox": [0, 0, 1, 1],
                            "segmentation": [[x0, y0, x1, y0, x1, y1, x0, y1]]})
    (ann / "train" / "_annotations.coco.json").write_text(json.dumps({
        "images": images, "annotations": annotations,
        "categories": [{"id": 1, "name": "red ball"}]}))  # fmt: skip
    hop = [int(np.argmax(field.times >= syn.HOP[0])), int(np.argmax(field.times >= syn.HOP[2]))]
    (ann / "video_annotations.json").write_text(json.dumps(
        {"red ball": {"the red ball in the air": [hop]}}))  # fmt: skip
    monkeypatch.setattr("sync4d.phase3.evaluation.query_eval.load_run", lambda _: run)
    summary = evaluate_queries(run.path, ann, scorers=("paper",), encoder=enc)
    row = json.loads((run.path / "phase3" / "eval-annotations-paper.json").read_text())
    q = row["queries"][0]
    assert q["query"] == "the red ball in the air" and q["object_correct"] is True
    assert q["gt_intervals"] == [hop]
    assert summary["paper"]["viou"] is not None and 0.0 < summary["paper"]["viou"] <= 1.0


def test_another_encoder_than_the_fields_is_refused(oracle_run):
    run, field, _, _ = oracle_run

    class Other(ColourEncoder):
        @property
        def fingerprint(self) -> str:
            return "another-model"

    with pytest.raises(EncoderError, match="was built with encoder test-colour"):
        answer(field, "a purple thing nobody asked before", cache=TextCache(run.path, field,
                                                                           Other()))


def test_the_static_only_switch_applies_to_every_scorer(oracle_run):
    run, field, enc, _ = oracle_run
    cfg = Phase3Config(static_only=True)
    ans = answer(field, "red", cache=TextCache(run.path, field, enc), scorer="paper", cfg=cfg)
    assert all(ans["active"]["red ball"])
    sims = np.asarray(ans["timeline"]["red ball"])
    np.testing.assert_allclose(sims, sims[0])
