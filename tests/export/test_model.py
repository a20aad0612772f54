"""The scene model (`sync4d.export.model`): the shipped JSON Schema is the one generated from
it, it imports no torch, and it accepts and refuses the documents the schema does, keeping
every number's int or float and leaving absent keys out."""

from __future__ import annotations

import copy
import json
import subprocess
import sys

import pytest
from pydantic import ValidationError

from sync4d.export.model import EVENT_KINDS, SEGMENT_STATES, Scene, dumps
from sync4d.export.schema import SCHEMA_FILE, SceneError, generate, schema_text, validate
from sync4d.phase3.kinematics import FEATURE_NAMES


def test_the_shipped_schema_is_generated_from_the_model():
    assert SCHEMA_FILE.read_text(encoding="utf-8") == schema_text(), (
        "sync4d/export/scene.schema.json is out of date: run python scripts/gen_docs.py")
    s = generate()
    assert s["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert s["required"] == ["metadata", "objects", "tracks", "events", "texts", "embeddings"]
    assert s["$defs"]["Event"]["properties"]["kind"]["enum"] == list(EVENT_KINDS)
    assert s["$defs"]["Segment"]["properties"]["state"]["enum"] == list(SEGMENT_STATES)
    assert s["$defs"]["Kinematics"]["required"] == list(FEATURE_NAMES)
    assert "title" not in json.dumps(s["$defs"])  # pydantic's titles are not kept


def test_the_model_imports_no_torch():
    code = "import sys, sync4d.export.model; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)  # fmt: skip
    assert out.stdout.strip() == "False"


def test_event_kinds_are_defined_once():
    from sync4d.export import describe
    from sync4d.serve import tools

    assert describe.EVENT_KINDS is EVENT_KINDS and tools.EVENT_KINDS is EVENT_KINDS


def _interval(a: int, b: int) -> dict:
    return {"start": a, "end": b, "t0": a / 2, "t1": b / 2}


def _doc() -> dict:
    """A small valid description: one object over three frames, one contact."""
    vec = [[0.0, 0.0, 1.0]] * 3
    return {
        "metadata": {
            "format": "sync4d.scene", "version": 1, "sync4d": "0.1.0",
            "run": {"name": "r", "kind": "sync4d.phase2", "iteration": 10, "dataset": ""},
            "checkpoint": {"file": "checkpoint.safetensors", "sha256": None},
            "encoder": {"kind": None, "fingerprint": None, "dim": 4, "closed_vocabulary": False},
            "units": {"length": "m", "time": "0 to 1", "angle": "rad", "velocity": "m per 1",
                      "acceleration": "m per 1 squared"},
            "axes": {"up": [0.0, 0.0, 1.0], "right": [1.0, 0.0, 0.0], "cameras": "OpenCV"},
            "scale": {"bounds": [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], "extent": 1.7},
            "frames": {"count": 3, "times": [0.0, 0.5, 1.0]},
            "cameras": [{"name": "r_0.png", "split": "test", "time": 0.0,
                         "world_to_camera": [[1.0, 0.0, 0.0, 0.0]] * 4, "fx": 50, "fy": 50.5,
                         "cx": 24.0, "cy": 24, "width": 48, "height": 48}],
            "thresholds": {"moving_speed": 0.15, "activation": "half-peak"},
        },
        "objects": [{
            "id": 1, "label": 1, "name": "red ball", "gaussians": 300,
            "extent": {"canonical": {"min": [0.0, 0.0, 0.0], "max": [0.2, 0.2, 0.2]},
                       "size_max": [0.2, 0.2, 0.2]},
            "radius": 0.1, "rigid_share": 0.95, "observed_frames": 3,
            "vocabulary": [{"text": "red", "similarity": 0.8}],
            "slots": [{"text": "red", "source": "vocab", "score": 0.9,
                       "intervals": [_interval(0, 2)], "margin": 0.3},
                      {"text": "the ball", "source": "query", "score": 0.7, "intervals": []}],
            "segments": [{"state": "at rest", **_interval(0, 2)}],
        }],
        "tracks": [{
            "id": 1, "centroid": vec, "rotation": [[1.0, 0.0, 0.0, 0.0]] * 3,
            "translation": vec, "velocity": vec, "acceleration": vec, "visible": [1.0, 0.5, 1],
            "observed": [True, False, True], "box_min": vec, "box_max": vec,
            "kinematics": {name: [0.0, None, 1] for name in FEATURE_NAMES},
        }],
        "events": [{"kind": "contact", "objects": [1, 0], **_interval(0, 2),
                    "distance": [0.0, None], "evidence": "gap"},
                   {"kind": "approach", "objects": [1, 0], **_interval(0, 1),
                    "distance": [0.2, 0.0]}],
        "texts": ["red", "the ball"],
        "embeddings": {"file": "s.embeddings.safetensors", "sha256": "0" * 64,
                       "arrays": {"static": [1, 4]}, "rows": {"static": "objects"}},
    }  # fmt: skip


def test_a_valid_description_is_the_model_byte_for_byte():
    doc = _doc()
    validate(doc, "s.json")
    scene = Scene.model_validate(doc)
    assert scene.model_dump() == doc  # no key added (no null margin, evidence), none lost
    text = dumps(doc) + "\n"
    assert scene.to_json() == text and Scene.from_json(text).to_json() == text
    assert scene.metadata.cameras[0].fx == 50 and isinstance(scene.metadata.cameras[0].fx, int)
    assert scene.metadata.units.model_dump()["acceleration"] == "m per 1 squared"
    # a description in memory has no side file yet; a file always has one
    del doc["embeddings"]
    assert "embeddings" not in Scene.model_validate(doc).model_dump()
    with pytest.raises(SceneError, match="'embeddings' is a required property"):
        validate(doc, "s.json")


def _set(path: str, value: object):
    def change(doc: dict) -> None:
        *keys, last = [int(k) if k.isdigit() else k for k in path.split("/")]
        node = doc
        for k in keys:
            node = node[k]
        if value is KeyError:
            del node[last]
        else:
            node[last] = value

    return change


@pytest.mark.parametrize("path, value", [
    ("tracks/0/centroid", KeyError),  # a required key missing
    ("tracks/0/centroid/1/2", None),  # null where a number is required
    ("tracks/0/rotation/0", [1.0, 0.0, 0.0]),  # a quaternion of 3
    ("events/0/kind", "hug"),
    ("events/0/evidence", None),
    ("objects/0/slots/1/margin", None),
    ("objects/0/segments/0/state", "dancing"),
    ("objects/0/id", 0),  # the background is not listed
    ("objects/0/gaussians", -1),
    ("objects/0/name", 3),
    ("objects/0/radius", -0.1),
    ("objects/0/extra", 1),  # an unknown key
    ("tracks/0/observed/0", 1),  # a number for a bool
    ("tracks/0/visible/0", True),  # a bool for a number
    ("metadata/frames/times/2", 1.5),
    ("metadata/units/extra", 1),
    ("metadata/version", 2),
    ("metadata/cameras/0/width", 48.5),
    ("embeddings/sha256", "abc"),
])  # fmt: skip
def test_the_model_refuses_what_the_schema_refuses(path, value):
    doc = copy.deepcopy(_doc())
    _set(path, value)(doc)
    with pytest.raises(SceneError, match="not a sync4d scene description"):
        validate(doc, "s.json")
    with pytest.raises(ValidationError):
        Scene.model_validate(doc)
