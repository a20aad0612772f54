"""The scene description on an oracle Phase 2 run of the embedded scene (Gaussians moved by the
true motion, M_phi fitted in closed form, a colour encoder): valid against the schema, its
segments and events against `ground_truth.json`, byte-identical twice, loaded back to the same
numbers, and one clear error for each malformed file."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import jsonschema
import numpy as np
import pytest

from support.encoders import ColourEncoder
from support.oracle import oracle_phase2_run
from sync4d.data import synthetic as syn
from sync4d.export.describe import SceneSettings, describe, pairwise_events
from sync4d.export.model import Scene
from sync4d.export.prompt import count_tokens, prompt_text
from sync4d.export.scene import SceneError, embeddings_path, load, with_embeddings, write_scene
from sync4d.export.schema import schema
from sync4d.phase3.build import build_field
from sync4d.phase3.config import Phase3Config
from sync4d.phase3.evaluation.query_metrics import temporal_iou
from sync4d.phase3.query import TextCache

#: The objects' colours, then a colour no object has (the colour encoder puts every object at
#: the same similarity to it: no object separates).
VOCAB = ["red", "blue", "green", "yellow"]


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("export")
    run, root = oracle_phase2_run(tmp)
    enc = ColourEncoder()
    field = build_field(run, Phase3Config(), enc, threads=1)
    field.save(run.path)
    cache = TextCache(run.path, field, enc)
    doc, emb = describe(run, field, cache=cache, vocab=VOCAB, queries=["the blue object"])
    path = write_scene(tmp / "out" / "scene.json", doc, emb)
    return {"run": run, "field": field, "cache": cache, "root": root, "path": path,
            "tmp": tmp}  # fmt: skip


def _frames(times: np.ndarray, spans) -> np.ndarray:
    m = np.zeros(len(times), bool)
    for t0, t1 in spans:
        m |= (times >= t0 - 1e-9) & (times <= t1 + 1e-9)
    return m


def _predicted(times: np.ndarray, items: list[dict]) -> np.ndarray:
    m = np.zeros(len(times), bool)
    for s in items:
        m[s["start"]:s["end"] + 1] = True
    return m


def test_the_export_is_valid_against_the_shipped_schema(oracle):
    doc = json.loads(oracle["path"].read_text())
    jsonschema.Draft202012Validator(schema()).validate(doc)
    meta = doc["metadata"]
    assert meta["format"] == "sync4d.scene" and meta["frames"]["count"] == 21
    assert [o["name"] for o in doc["objects"]] == ["red ball", "blue box", "green pillar"]
    assert [t["id"] for t in doc["tracks"]] == [1, 2, 3]
    assert len(doc["tracks"][0]["kinematics"]) == 28
    # each object's nearest vocabulary entry is its colour
    assert [o["vocabulary"][0]["text"] for o in doc["objects"]] == VOCAB[:3]
    # embeddings live in the side file, never inline
    assert embeddings_path(oracle["path"]).is_file()
    assert doc["embeddings"]["arrays"]["sync"] == [3, 21, 4]
    assert "static" not in json.dumps(doc["objects"])


def test_segments_and_events_match_the_ground_truth(oracle):
    scene = load(oracle["path"])
    times = scene.times
    gt = syn.load_ground_truth(oracle["root"])
    # ground truth state -> (object, what the description says)
    said = {
        "rising": lambda o: [s for s in o.segments if s["state"] == "rising"],
        "falling": lambda o: [s for s in o.segments if s["state"] == "falling"],
        "at rest": lambda o: [s for s in o.segments if s["state"] == "at rest"],
        "standing still": lambda o: [s for s in o.segments if s["state"] == "at rest"],
        "sliding": lambda o: [s for s in o.segments if s["state"] == "moving"],
        "rolling on the ground": lambda o: [e for e in scene.events if e["kind"] == "contact"
                                            and e["objects"] == [o.id, 0]],
    }  # fmt: skip
    tious = {}
    for obj_id in (1, 2, 3):
        for state in {s for k, s, _, _ in gt.states if k == obj_id}:
            truth = _frames(times, [(a, b) for k, s, a, b in gt.states
                                    if k == obj_id and s == state])  # fmt: skip
            pred = _predicted(times, said[state](scene.object(obj_id)))
            tious[(obj_id, state)] = temporal_iou(pred, truth)
    assert min(tious.values()) >= 0.75, tious
    # the pillar never moves: at rest throughout, on the ground, nothing else of its own
    pillar = scene.object("green pillar")
    assert [(s["state"], s["start"], s["end"]) for s in pillar.segments] == [("at rest", 0, 20)]
    # the ball and the box approach while their centres draw together
    d = np.linalg.norm(gt.translations[0] - gt.translations[1], axis=1)
    rows = [int(np.argmin(np.abs(gt.times - t))) for t in times]
    closing = np.gradient(d[rows], times) < 0
    approach = _predicted(times, [e for e in scene.events
                                  if e["kind"] == "approach" and e["objects"] == [1, 2]])
    assert approach.sum() >= 0.5 * closing.sum()
    assert (approach & ~closing).sum() == 0, (approach, closing)
    # the hop: the ball leaves the ground, rises away from it, comes back and lands
    hop = [e["kind"] for e in scene.events if e["objects"] == [1, 0]]
    assert hop == ["contact", "separation", "approach", "contact"]


def test_two_exports_are_byte_identical(oracle):
    o = oracle
    doc, emb = describe(o["run"], o["field"], cache=o["cache"], vocab=VOCAB,
                        queries=["the blue object"])  # fmt: skip
    again = write_scene(o["tmp"] / "again" / "scene.json", doc, emb)
    assert again.read_bytes() == o["path"].read_bytes()
    assert embeddings_path(again).read_bytes() == embeddings_path(o["path"]).read_bytes()


def test_the_file_is_the_model_and_reads_back_into_it(oracle):
    """The model `describe` returns is the file: its JSON is the file's bytes, the file reads
    back into the same model, and the record of the side file is computed without writing."""
    o = oracle
    scene, emb = describe(o["run"], o["field"], cache=o["cache"], vocab=VOCAB,
                          queries=["the blue object"])  # fmt: skip
    assert isinstance(scene, Scene) and scene.embeddings is None
    written, data = with_embeddings(scene, o["path"], emb)
    text = o["path"].read_text()
    assert written.to_json() == text and data == embeddings_path(o["path"]).read_bytes()
    again = Scene.from_json(text)
    assert again == written and again.to_json() == text
    # what a file may leave out stays out (no null margin or evidence)
    assert [e.model_dump() for e in again.events] == json.loads(text)["events"]
    assert any(e.evidence is None for e in again.events)


def test_load_gives_back_the_same_numbers(oracle):
    field, scene = oracle["field"], load(oracle["path"])
    for k, obj in enumerate(scene.objects):
        tr = obj.track
        np.testing.assert_allclose(tr.centroid, field.centroids[k], atol=5e-7)
        np.testing.assert_allclose(tr.velocity, field.features[k, :, 6:9], atol=5e-7)
        np.testing.assert_allclose(tr.kinematics["speed"], field.features[k, :, 0], atol=5e-7)
        np.testing.assert_array_equal(tr.observed, field.observed[k])
        np.testing.assert_allclose(np.linalg.norm(tr.rotation, axis=1), 1.0, atol=2e-6)
    np.testing.assert_array_equal(scene.embeddings["static"], field.static)
    np.testing.assert_array_equal(scene.embeddings["sync"], field.sync)
    assert scene.embeddings["texts"].shape == (len(VOCAB) + 1, field.dim)
    # the box turns 45 degrees about z: its last quaternion says so
    w = scene.object("blue box").track.rotation[-1, 0]
    assert np.degrees(2 * np.arccos(w)) == pytest.approx(45.0, abs=2.0)


def test_malformed_descriptions_get_one_clear_error(oracle, tmp_path):
    text = oracle["path"].read_text()
    bad = tmp_path / "truncated.json"
    bad.write_text(text[: len(text) // 2])
    with pytest.raises(SceneError, match="truncated.json.*not valid JSON"):
        load(bad)
    doc = json.loads(text)
    del doc["tracks"][0]["centroid"]
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=r"wrong.json.*at tracks/0.*centroid"):
        load(wrong)
    doc = json.loads(text)
    doc["tracks"][1]["visible"] = doc["tracks"][1]["visible"][:-1]
    short = tmp_path / "short.json"
    short.write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="short.json.*object 2.*20 'visible' rows for 21"):
        load(short)
    # a side file that is not the one the description names
    copy = tmp_path / "scene.json"
    copy.write_text(text)
    side = embeddings_path(copy)
    side.write_bytes(embeddings_path(oracle["path"]).read_bytes()[:-8] + b"x" * 8)
    with pytest.raises(SceneError, match="embeddings side file does not match"):
        load(copy)
    with pytest.raises(SceneError, match="no such scene description"):
        load(tmp_path / "missing.json")


def test_the_prompt_comes_from_the_json_alone(oracle):
    text = oracle["path"].read_text()
    prompt = prompt_text(json.loads(text))
    assert prompt == prompt_text(load(oracle["path"]).doc)
    for name in ("red ball", "blue box", "green pillar"):
        assert f"- {name} (id" in prompt
    assert "green pillar (id 3)" in prompt and "static" in prompt
    assert "red ball touches the background 2 times" in prompt
    assert "rising 0.35-" in prompt
    n, tokenizer = count_tokens(prompt)
    assert 100 < n < 5000 and "WordPiece" in tokenizer


def test_a_vocabulary_entry_is_attached_only_where_it_separates(oracle):
    """Each colour's slot and match sit on its object, by a margin above `slot_margin`; the
    colour no object has is attached to none, and the prompt says so."""
    doc = json.loads(oracle["path"].read_text())
    margin = doc["metadata"]["thresholds"]["slot_margin"]
    assert margin == SceneSettings().slot_margin
    for obj, colour in zip(doc["objects"], VOCAB, strict=False):
        vocab_slots = [s for s in obj["slots"] if s["source"] == "vocab"]
        assert [s["text"] for s in vocab_slots] == [colour]
        assert vocab_slots[0]["margin"] >= margin
        assert [v["text"] for v in obj["vocabulary"]] == [colour]
    assert "yellow" not in json.dumps(doc["objects"])
    assert 'No object matches "yellow"' in prompt_text(doc)
    # with no margin required, the old behaviour: every entry goes to its top object
    field, cache = oracle["field"], oracle["cache"]
    loose, _ = describe(oracle["run"], field, cache=cache, vocab=VOCAB,
                        settings=SceneSettings(slot_margin=-1.0))  # fmt: skip
    assert sum(len(o.slots) for o in loose.objects) == len(VOCAB)


def test_a_phase1_run_has_no_description(oracle):
    run = oracle["run"]
    phase1 = type(run)(path=run.path, checkpoint=Path(run.checkpoint), kind="sync4d.phase1",
                       model=run.model, meta={}, background=[1.0] * 3, cameras=[],
                       settings={})  # fmt: skip
    with pytest.raises(SceneError, match="needs a Phase 2 run"):
        describe(phase1, oracle["field"])


def _bouncing_field(lowest_gap: float):
    """A ball of radius 0.1 bouncing twice on the background (parabolic hops), whose measured
    height above the plate never falls below `lowest_gap`, and a second ball at rest on it."""
    times = np.linspace(0.0, 1.0, 61)
    phase = (times * 2.0) % 1.0  # two hops, bounces at t = 0.5 and t = 1.0
    height = lowest_gap + 1.2 * phase * (1.0 - phase) * 4.0 * 0.25
    centroids = np.zeros((2, len(times), 3))
    centroids[0, :, 2] = 0.1 + height
    centroids[1, :, :] = [1.0, 0.0, 0.1]
    gaps = np.full((2, 3, len(times)), 1.0)
    gaps[0, 0], gaps[1, 0] = height, 0.0
    return SimpleNamespace(times=times, labels=[1, 2], radius=np.array([0.1, 0.1]),
                           centroids=centroids, gaps=gaps, gap_labels=[0, 1, 2],
                           up=np.array([0.0, 0.0, 1.0]))  # fmt: skip


@pytest.mark.parametrize("lowest_gap", [0.0, 0.09])
def test_each_bounce_is_a_contact_with_the_background(lowest_gap):
    """The ball comes down and goes straight back up at t = 0.5: a contact, measured by the gap
    when it closes (0.0) and by the rebound when the reconstruction leaves it open (0.09 is 0.9
    radii, above contact_gap's 0.6): a small ball's bounces on bouncingballs look like that."""
    field = _bouncing_field(lowest_gap)
    events = pairwise_events(field, Phase3Config())
    ball = [e for e in events if e["objects"] == [1, 0]]
    contacts = [e for e in ball if e["kind"] == "contact"]
    bounce = [c for c in contacts if c["t0"] <= 0.5 <= c["t1"]]
    assert len(bounce) == 1 and bounce[0]["t1"] - bounce[0]["t0"] <= 0.1, contacts
    assert bounce[0]["evidence"] == ("gap" if lowest_gap == 0.0 else "rebound")
    kinds = [e["kind"] for e in ball if 0.1 < e["t0"] < 0.9 or 0.1 < e["t1"] < 0.9]
    assert kinds == ["separation", "approach", "contact", "separation", "approach"], ball
    # the ball at rest touches the plate throughout, by its gap
    rest = [e for e in events if e["objects"] == [2, 0]]
    assert [(e["kind"], e["start"], e["end"], e["evidence"]) for e in rest] == [
        ("contact", 0, 60, "gap")]
    # a fall that ends in mid-air with no rise after it is no contact
    field.gaps[0, 0, 31:] = field.gaps[0, 0, 30]
    field.centroids[0, 31:, 2] = field.centroids[0, 30, 2]
    late = [e for e in pairwise_events(field, Phase3Config())
            if e["objects"] == [1, 0] and e["kind"] == "contact" and e["t0"] >= 0.45]
    assert late == [] or lowest_gap == 0.0, late


def _mid_air_field(height: np.ndarray) -> SimpleNamespace:
    """A ball of radius 0.1 whose height above the plate (the background) follows `height`."""
    times = np.linspace(0.0, 1.0, len(height))
    centroids = np.zeros((1, len(times), 3))
    centroids[0, :, 2] = 0.1 + height
    gaps = np.full((1, 2, len(times)), np.inf)
    gaps[0, 0] = height
    return SimpleNamespace(times=times, labels=[1], radius=np.array([0.1]), centroids=centroids,
                           gaps=gaps, gap_labels=[0, 1], up=np.array([0.0, 0.0, 1.0]))


@pytest.mark.parametrize("shape", ["swing", "jump with a dip"])
def test_a_fall_then_rise_in_mid_air_is_no_contact(shape):
    """A swing down and straight back up whose lowest point is 5 radii above the plate, and a
    jump that dips in mid-air (3 radii below its top, 4 above the plate) before landing: each
    is a fall that turns into a rise, neither touches the plate there."""
    t = np.linspace(0.0, 1.0, 61)
    if shape == "swing":  # down from 1.3 to 0.5 at t = 0.5, straight back up: lowest there
        height = 0.5 + 0.8 * np.abs(2.0 * t - 1.0)
    else:  # on the plate, up to 0.7, dips to 0.4 at t = 0.5, up to 0.7, down on the plate
        height = np.interp(t, [0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0],
                           [0.0, 0.0, 0.7, 0.4, 0.7, 0.0, 0.0])  # fmt: skip
    events = pairwise_events(_mid_air_field(height), Phase3Config())
    kinds = [(e["kind"], round(e["t0"], 2), round(e["t1"], 2)) for e in events]
    contacts = [e for e in events if e["kind"] == "contact"]
    assert not [c for c in contacts if c["t0"] <= 0.5 <= c["t1"]], kinds
    assert [e for e in events if e["kind"] == "approach" and e["t1"] <= 0.5], kinds
    assert [e for e in events if e["kind"] == "separation" and e["t0"] >= 0.45], kinds
    if shape == "jump with a dip":  # on the plate at both ends, by its gap
        assert [(c["start"] == 0, c["end"] == 60, c["evidence"]) for c in contacts] == [
            (True, False, "gap"), (False, True, "gap")], kinds
    # without the two conditions (any fall turning into a rise) the turn was a contact
    anywhere = dataclasses.replace(Phase3Config(), rebound_gap=1e9, rebound_height=1.0)
    events = pairwise_events(_mid_air_field(height), anywhere)
    assert [e for e in events if e["kind"] == "contact" and e["t0"] <= 0.5 <= e["t1"]
            and e["evidence"] == "rebound"], kinds
    if shape == "swing":  # the same turn lowered to 0.9 radii above the plate: a bounce
        events = pairwise_events(_mid_air_field(height - height[30] + 0.09), Phase3Config())
        assert [e for e in events if e["kind"] == "contact" and e["t0"] <= 0.5 <= e["t1"]
                and e["evidence"] == "rebound"], kinds
