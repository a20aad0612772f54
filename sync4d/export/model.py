"""The scene description as one typed model (pydantic, torch-free): `Scene` and its records
(docs/export.md has what each key means).

Design:

* **One shape.** `sync4d.export.describe.describe` returns a `Scene`; `write_scene` writes it
  (`Scene.to_json`); the JSON Schema shipped beside it (``scene.schema.json``) is generated
  from it (`sync4d.export.schema.generate`, rewritten by ``python scripts/gen_docs.py``, a
  test fails when it is not current); `sync4d serve` keeps it in memory and answers with its
  records. Nothing else describes the file.
* **The file's bytes.** A record's fields are in the order of the keys in the file; the keys
  that may be absent (a slot's `margin`, an event's `evidence`, and the `embeddings` of a
  description not yet written) are left out when unset, never written as null; a `Number`
  stays the int or float it was given. So ``dumps(scene.model_dump())`` is the JSON the
  description's dicts were.
* **As strict as the schema.** Records refuse unknown keys where the schema does, and the types
  are strict (no "1" for 1, no true for 1), so what the model accepts the schema accepts
  (the schema, JSON Schema's integers, also takes 48.0 for 48; the model takes what sync4d
  writes, 48).
  Files are checked against the schema (`sync4d.export.schema.validate`: its error names the
  offending key); what `sync4d serve` kept between starts is read back through the model.

Importing it imports pydantic and numpy (through the Phase 3 names below), not torch.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PlainValidator,
    StrictBool,
    StrictInt,
    StrictStr,
    ValidationError,
    WithJsonSchema,
    create_model,
)

from sync4d.phase3.kinematics import FEATURE_DESCRIPTIONS, FEATURE_NAMES
from sync4d.phase3.states import MOTION_STATES

__all__ = ["EVENT_KINDS", "EVIDENCE", "FORMAT", "SEGMENT_STATES", "SLOT_SOURCES", "VERSION",
           "Axes", "Box", "Camera", "CheckpointRef", "EmbeddingsRef", "EncoderRef", "Event",
           "Extent", "Frames", "Interval", "Kinematics", "Metadata", "Number", "NumberOrNull",
           "ObjectRecord", "RunRef", "Scale", "Scene", "Segment", "Slot", "Track", "Units",
           "VocabularyMatch", "dumps", "where"]  # fmt: skip

#: Format name and version of the description (`metadata.format`, `metadata.version`).
FORMAT = "sync4d.scene"
VERSION = 1
#: The motion states of the segments, in their order in the file.
SEGMENT_STATES = MOTION_STATES
#: The pairwise event kinds, in their order in the file.
EVENT_KINDS = ("approach", "contact", "separation")
#: How a contact was found: the gap closed, or the fall turned into a rise (a bounce).
EVIDENCE = ("gap", "rebound")
#: Where a language slot's text comes from: the vocabulary, or a query.
SLOT_SOURCES = ("vocab", "query")


# --------------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------------

def _number(ge: float | None = None, le: float | None = None, null: bool = False) -> Any:
    """A JSON number within [`ge`, `le`] (`null`: or None): an int or a float, kept as given
    (no bool, no string), published as ``{"type": "number", "minimum": ..., ...}``."""

    def check(x: Any) -> Any:
        if x is None and null:
            return x
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise ValueError("should be a number" + (" or null" if null else ""))
        if (ge is not None and x < ge) or (le is not None and x > le):
            raise ValueError(f"should be in [{ge if ge is not None else '-inf'}, "
                             f"{le if le is not None else 'inf'}]")  # fmt: skip
        return x

    schema: dict[str, Any] = {"type": ["number", "null"] if null else "number"}
    schema |= {k: v for k, v in (("minimum", ge), ("maximum", le)) if v is not None}
    kind = int | float | None if null else int | float
    return Annotated[kind, PlainValidator(check), WithJsonSchema(schema)]


def _integer(minimum: int) -> Any:
    return Annotated[StrictInt, Field(ge=minimum)]


def _vector(item: Any, n: int) -> Any:
    return Annotated[list[item], Field(min_length=n, max_length=n)]


#: A number of the description (rounded to its decimals; an int stays an int).
Number = _number()
#: A number that is null where it was not finite (kinematics, event distances).
NumberOrNull = _number(null=True)
_NonNegative = _number(ge=0)
_Time = _number(ge=0, le=1)
_Count = _integer(0)
_Id = _integer(1)
_Vec3 = _vector(Number, 3)
_Vec4 = _vector(Number, 4)
_Sha256 = Annotated[StrictStr, Field(pattern=r"^[0-9a-f]{64}$")]


def _absent(value: object) -> bool:
    return value is None


class _Record(BaseModel):
    """A record of the description: strict, no keys beyond its fields."""

    model_config = ConfigDict(strict=True, extra="forbid", use_attribute_docstrings=True)


# --------------------------------------------------------------------------------------------
# Metadata
# --------------------------------------------------------------------------------------------

class RunRef(_Record):
    """The run the description was made from."""

    name: StrictStr
    """the run folder's name"""
    kind: StrictStr
    """the checkpoint's kind (sync4d.phase2 ...)"""
    iteration: _Count
    """training iterations of the checkpoint"""
    dataset: StrictStr
    """the dataset folder's name (empty when the run does not name one)"""


class CheckpointRef(_Record):
    """The checkpoint the description was made from."""

    file: StrictStr
    sha256: _Sha256 | None
    """its SHA-256 (hex), null when the file was not there"""


class EncoderRef(_Record):
    """The text and image encoder the language field was built with."""

    kind: StrictStr | None
    fingerprint: StrictStr | None
    dim: _integer(1)
    """embedding dimension D"""
    closed_vocabulary: StrictBool
    """true when the encoder only knows a fixed vocabulary (the offline encoder)"""


class Units(_Record):
    """The units of the numbers, in words (more keys may follow, each a string)."""

    model_config = ConfigDict(extra="allow")
    __pydantic_extra__: dict[str, StrictStr] = Field(init=False)

    length: StrictStr
    time: StrictStr
    angle: StrictStr
    velocity: StrictStr


class Axes(_Record):
    """The world's axes: `up` (the vector the motion states use) and `right`, and the
    cameras' conventions."""

    up: _Vec3
    right: _Vec3
    cameras: StrictStr


class Scale(_Record):
    """The size of the foreground: its 1st-99th percentile box and the box's diagonal."""

    bounds: Annotated[list[_Vec3], Field(min_length=2, max_length=2)]
    """[min, max] corners"""
    extent: _NonNegative


class Frames(_Record):
    """The stored frames every per-frame list follows: how many, and their times."""

    count: _integer(1)
    times: Annotated[list[_Time], Field(min_length=1)]
    """normalised times in [0, 1], ascending"""


class Camera(_Record):
    """A stored camera of the run."""

    name: StrictStr
    split: StrictStr
    """train or test"""
    time: Number
    world_to_camera: Annotated[list[_Vec4], Field(min_length=4, max_length=4)]
    """row-major 4x4, OpenCV axes"""
    fx: Number
    fy: Number
    cx: Number
    cy: Number
    width: _integer(1)
    height: _integer(1)


class Metadata(_Record):
    """Where the description comes from and how to read its numbers."""

    format: Literal[FORMAT]  # type: ignore[valid-type]
    version: Literal[VERSION]  # type: ignore[valid-type]
    sync4d: StrictStr
    """the sync4d version that wrote it"""
    run: RunRef
    checkpoint: CheckpointRef
    encoder: EncoderRef
    units: Units
    axes: Axes
    scale: Scale
    frames: Frames
    cameras: list[Camera]
    thresholds: dict[str, Any]
    """the Phase 3 settings the segments, events and slots were found with"""


# --------------------------------------------------------------------------------------------
# Objects
# --------------------------------------------------------------------------------------------

class Interval(_Record):
    """An inclusive range [start, end] of stored frames and its times [t0, t1]."""

    start: _Count
    end: _Count
    t0: Number
    t1: Number


class Segment(_Record):
    """An interval where an object is in a motion state."""

    state: Literal[SEGMENT_STATES]  # type: ignore[valid-type]
    start: _Count
    end: _Count
    t0: Number
    t1: Number


class Slot(_Record):
    """A vocabulary entry or query attached to the object the default scorer ranks first, and
    the intervals where it is active."""

    text: StrictStr
    source: Literal[SLOT_SOURCES]  # type: ignore[valid-type]
    score: Number
    intervals: list[Interval]
    margin: Number = Field(None, exclude_if=_absent)  # type: ignore[assignment]
    """a vocabulary entry's lead of this object's cosine over every other object's (absent
    for a query, or in a scene of one object)"""


class VocabularyMatch(_Record):
    """A vocabulary entry near the object's static embedding."""

    text: StrictStr
    similarity: Number
    """cosine"""


class Box(_Record):
    """An axis-aligned box."""

    min: _Vec3
    max: _Vec3


class Extent(_Record):
    """The 2nd-98th percentile box of an object's Gaussians."""

    canonical: Box
    size_max: _Vec3
    """the box's largest size along each axis over the frames"""


class ObjectRecord(_Record):
    """A foreground object of the run (the background, id 0, is not listed)."""

    id: _Id
    label: _Id
    """its Phase 2 label (the mask label when masks drove the assignment)"""
    name: StrictStr
    gaussians: _Count
    extent: Extent
    radius: _NonNegative
    rigid_share: Number
    """mean share of its motion that M_phi's rigid part explains"""
    observed_frames: _Count
    vocabulary: list[VocabularyMatch]
    """the vocabulary entries nearest it, nearest first"""
    slots: list[Slot]
    segments: list[Segment]
    """its motion states over time, by start frame"""


# --------------------------------------------------------------------------------------------
# Tracks
# --------------------------------------------------------------------------------------------

#: An object's 28 kinematic dimensions, one list of T numbers (null: not finite) each.
Kinematics = create_model(
    "Kinematics", __base__=_Record, __module__=__name__,
    __doc__="The 28 kinematic dimensions of an object per frame (Appendix B), by name.",
    **{name: (list[NumberOrNull], Field(description=FEATURE_DESCRIPTIONS[name]))
       for name in FEATURE_NAMES},  # type: ignore[call-overload]
)  # fmt: skip


class Track(_Record):
    """An object's pose and motion at each stored frame (T rows each)."""

    id: _Id
    centroid: list[_Vec3]
    """M_phi's predicted centre of its Gaussians"""
    rotation: list[_Vec4]
    """M_phi's rotation, unit quaternion w, x, y, z"""
    translation: list[_Vec3]
    velocity: list[_Vec3]
    acceleration: list[_Vec3]
    visible: list[Number]
    """the fraction of its Gaussians seen in the best view"""
    observed: list[StrictBool]
    box_min: list[_Vec3]
    box_max: list[_Vec3]
    kinematics: Kinematics  # type: ignore[valid-type]


# --------------------------------------------------------------------------------------------
# Events, embeddings, the scene
# --------------------------------------------------------------------------------------------

class Event(_Record):
    """An interval where two objects (or an object and the background, id 0) approach, touch
    or move apart."""

    kind: Literal[EVENT_KINDS]  # type: ignore[valid-type]
    objects: Annotated[list[_Count], Field(min_length=2, max_length=2)]
    start: _Count
    end: _Count
    t0: Number
    t1: Number
    distance: Annotated[list[NumberOrNull], Field(min_length=2, max_length=2)]
    """their distance (or the object's height above the background) at start and end"""
    evidence: Literal[EVIDENCE] = Field(None, exclude_if=_absent)  # type: ignore[valid-type]
    """a contact's: the gap closed, or the fall turned into a rise"""


class EmbeddingsRef(_Record):
    """The embeddings side file (safetensors) beside the description: its name, SHA-256 and
    the shape of each array."""

    file: StrictStr
    sha256: _Sha256
    arrays: dict[str, list[_Count]]
    rows: dict[str, StrictStr]
    """what each array's rows are"""


class Scene(_Record):
    """Objects, tracks, motion segments, pairwise events and language slots of a sync4d run
    (docs/export.md). Times are normalised to [0, 1]; intervals are inclusive frame ranges
    [start, end] of metadata.frames.times."""

    metadata: Metadata
    objects: list[ObjectRecord]
    tracks: list[Track]
    events: list[Event]
    texts: list[StrictStr]
    """the vocabulary entries, then the queries"""
    embeddings: EmbeddingsRef = Field(None, exclude_if=_absent)  # type: ignore[assignment]
    """the embeddings side file (a description in memory has none until `write_scene`)"""

    def to_json(self) -> str:
        """The description as the file holds it (`dumps`, a final newline)."""
        return dumps(self.model_dump()) + "\n"

    @classmethod
    def from_json(cls, text: str | bytes) -> Scene:
        """The description of the JSON `text` (`ValidationError` when it is no description)."""
        return cls.model_validate_json(text)


# --------------------------------------------------------------------------------------------
# JSON text
# --------------------------------------------------------------------------------------------

def _scalar(x: Any) -> bool:
    return not isinstance(x, (dict, list))


def dumps(obj: Any, indent: int = 0) -> str:
    """`obj` as JSON: objects one key per line, lists of scalars on one line, lists of such
    lists one row per line (tracks stay readable and diffable)."""
    pad, inner = " " * indent, " " * (indent + 1)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(k)}: {dumps(v, indent + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list):
        if all(_scalar(v) for v in obj):
            return "[" + ", ".join(json.dumps(v) for v in obj) + "]"
        return "[\n" + ",\n".join(inner + dumps(v, indent + 1) for v in obj) + "\n" + pad + "]"
    return json.dumps(obj)


def where(error: ValidationError) -> str:
    """The first problem of `error` as ``at KEY/0/KEY: message``, keys as in the file."""
    first = error.errors()[0]
    path = "/".join(str(p) for p in first["loc"])
    return f"at {path or '(the top level)'}: {first['msg']}"
