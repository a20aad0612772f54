"""The scene description file: deterministic JSON valid against the shipped schema, its
embeddings side file, and `load`, which gives both back as Python objects (docs/export.md).

Same run, same bytes: the `sync4d.export.model.Scene` that `describe` returns has every number
rounded to fixed decimals (-0 written as 0) and its keys in the model's order; it is written
as `Scene.to_json` lays it out (lists of numbers one row per line), and the side file
(``<name>.embeddings.safetensors`` beside the JSON) is referenced by file name and SHA-256
(`with_embeddings`, which `sync4d serve` uses too, without writing anything). Both are
written atomically.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from safetensors import SafetensorError
from safetensors.numpy import load_file, save

from sync4d.export.model import EmbeddingsRef, Scene, dumps
from sync4d.export.schema import SceneError, validate
from sync4d.files import file_sha256, write_atomic, write_text_atomic

__all__ = ["SceneDescription", "SceneError", "SceneObject", "Track", "dumps", "embeddings_path",
           "load", "with_embeddings", "write_scene"]  # fmt: skip


def embeddings_path(scene_path: str | Path) -> Path:
    """The side file of the description at `scene_path`: ``scene.json`` ->
    ``scene.embeddings.safetensors`` in the same folder."""
    p = Path(scene_path)
    return p.with_name(f"{p.stem}.embeddings.safetensors")


def _scalar(x: Any) -> bool:
    return not isinstance(x, (dict, list))


def with_embeddings(scene: Scene, path: str | Path,
                    embeddings: dict[str, np.ndarray]) -> tuple[Scene, bytes]:  # fmt: skip
    """`scene` with the record of its side file for a description written at `path` (the
    file's name, SHA-256 and array shapes), and the side file's bytes (`embeddings` as float32
    safetensors); nothing is written."""
    arrays = {k: np.ascontiguousarray(v, np.float32) for k, v in embeddings.items()}
    data = save(arrays)
    ref = EmbeddingsRef(
        file=embeddings_path(path).name, sha256=hashlib.sha256(data).hexdigest(),
        arrays={k: list(v.shape) for k, v in arrays.items()},
        rows={"static": "objects", "sync": "objects x frames", "texts": "texts"},
    )  # fmt: skip
    return scene.model_copy(update={"embeddings": ref}), data


def write_scene(path: str | Path, scene: Scene, embeddings: dict[str, np.ndarray]) -> Path:
    """Write the description `scene` (`sync4d.export.describe.describe`'s) to `path` and its
    `embeddings` to the side file (`embeddings_path`), both atomically, after checking the
    description against the schema. Returns `path`."""
    path = Path(path)
    scene, data = with_embeddings(scene, path, embeddings)
    write_atomic(embeddings_path(path), lambda tmp: tmp.write_bytes(data))
    text = scene.to_json()
    validate(json.loads(text), path)
    write_text_atomic(path, text)
    return path


@dataclass
class Track:
    """One object's track over the T stored frames (float64 arrays): `centroid`,
    `translation`, `velocity`, `acceleration`, `box_min`, `box_max` [T, 3], `rotation` [T, 4]
    (w, x, y, z), `visible` [T], `observed` [T] bool, `kinematics` name -> [T]."""

    centroid: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    visible: np.ndarray
    observed: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    kinematics: dict[str, np.ndarray]


@dataclass
class SceneObject:
    """One object: its `id` (Phase 2 label; 0 is the background), `name`, Gaussian count,
    `record` (the object's JSON entry: extent, rigid share, vocabulary, slots, segments) and
    its `track`."""

    id: int
    name: str
    gaussians: int
    record: dict
    track: Track

    @property
    def segments(self) -> list[dict]:
        """Motion segments: state, start and end frames, t0 and t1."""
        return self.record["segments"]

    @property
    def slots(self) -> list[dict]:
        """Language slots: text, source, score and active intervals."""
        return self.record["slots"]


@dataclass
class SceneDescription:
    """A loaded description: `metadata`, `objects` (with tracks), `events`, `texts`, the
    frame `times` [T] and the `embeddings` of the side file (name -> array; empty when the
    side file is not beside the JSON). `doc` is the JSON as read."""

    path: Path
    doc: dict
    metadata: dict
    times: np.ndarray
    objects: list[SceneObject]
    events: list[dict]
    texts: list[str]
    embeddings: dict[str, np.ndarray] = field(default_factory=dict)

    def object(self, key: int | str) -> SceneObject:
        """The object with this id or name (KeyError if none)."""
        for o in self.objects:
            if o.id == key or o.name == key:
                return o
        raise KeyError(key)


def _array(x: Any) -> np.ndarray:
    return np.asarray([np.nan if v is None else v for v in x] if x and _scalar(x[0]) else x,
                      dtype=np.float64)  # fmt: skip


def _track(t: dict) -> Track:
    return Track(
        centroid=_array(t["centroid"]), rotation=_array(t["rotation"]),
        translation=_array(t["translation"]), velocity=_array(t["velocity"]),
        acceleration=_array(t["acceleration"]), visible=_array(t["visible"]),
        observed=np.asarray(t["observed"], bool), box_min=_array(t["box_min"]),
        box_max=_array(t["box_max"]),
        kinematics={k: _array(v) for k, v in t["kinematics"].items()},
    )  # fmt: skip


def load(path: str | Path, embeddings: bool = True) -> SceneDescription:
    """The scene description at `path` as Python objects, checked against the schema and for
    consistency (track lengths, the side file's digest); `embeddings`: also read the side
    file when it is there. `SceneError` naming the file for anything malformed."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SceneError(f"{path}: no such scene description") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: cannot read it ({e})") from None
    try:
        doc = json.loads(text)
    except ValueError as e:
        raise SceneError(f"{path}: not valid JSON ({e}); is it truncated? Export it again "
                         "with `sync4d export RUN --scene FILE`") from None  # fmt: skip
    validate(doc, path)
    times = np.asarray(doc["metadata"]["frames"]["times"], np.float64)
    t = len(times)
    tracks = {tr["id"]: tr for tr in doc["tracks"]}
    objects = []
    for o in doc["objects"]:
        if o["id"] not in tracks:
            raise SceneError(f"{path}: object {o['id']} ({o['name']}) has no track")
        tr = _track(tracks[o["id"]])
        for name in ("centroid", "rotation", "translation", "velocity", "visible"):
            if len(getattr(tr, name)) != t:
                raise SceneError(f"{path}: the track of object {o['id']} has "
                                 f"{len(getattr(tr, name))} '{name}' rows for {t} frames")
        objects.append(SceneObject(o["id"], o["name"], o["gaussians"], o, tr))
    scene = SceneDescription(path, doc, doc["metadata"], times, objects, doc["events"],
                             doc["texts"])  # fmt: skip
    side = path.with_name(doc["embeddings"]["file"])
    if embeddings and side.is_file():
        if file_sha256(side) != doc["embeddings"]["sha256"]:
            raise SceneError(f"{side}: the embeddings side file does not match {path.name} "
                             "(its SHA-256 differs); export the scene again")  # fmt: skip
        try:
            scene.embeddings = dict(load_file(str(side)))
        except (SafetensorError, OSError) as e:
            raise SceneError(f"{side}: not a readable safetensors file ({e})") from None
    return scene
