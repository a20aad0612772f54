"""`sync4d serve RUN` on the Model Context Protocol (docs/mcp.md): the tools of
`sync4d.serve.tools.RunTools` and the scene description and prompt as resources, through the
official `mcp` SDK's `MCPServer`, over stdio (the default: a desktop client starts the server)
or HTTP (streamable HTTP at ``/mcp``, or the older SSE transport).

Design:

* **Typed results.** Each tool but `render` declares a pydantic model as its result, so its
  output schema is published with the tool list and every answer carries
  ``structuredContent`` (and the same as JSON text, for clients that read text only). What
  comes from the scene description is typed by its model (`sync4d.export.model`): `describe`'s
  full scene is the `Scene`, its objects, `events`' events and segments are views of the
  description's records (their fields, in the order the answers give them), so the two cannot
  drift apart. The query answer's models allow extra keys (its plan may grow), so what
  `sync4d query` learns reaches the agent without a change here. `render`
  answers an image (PNG) and a line of JSON saying what it shows.
* **Errors as results.** A `ToolProblem` (a bad argument, a run that cannot answer) becomes a
  tool error result whose text is the problem's one sentence (the SDK prefixes the tool's
  name); the caller can read it and correct the call. A resource that cannot be read answers
  a protocol error with that sentence (`ResourceError`). Anything else is a crash: logged
  here, reported to the caller without its text (the SDK's rule).
* **Render errors as results.** A render the watchdog stops (a NaN or a diverged value in
  what the rasterizer would receive), that the rasterizer refuses, or whose image is not
  finite is a `ToolProblem` too (`sync4d.runs.render_rgb`): one sentence, not a
  crash.
* **Fast start.** Importing this module imports the SDK, pydantic and the query registries
  (numpy: the scorers' and rules' names become the schema's choices), not torch; `serve`
  starts `RunTools.prepare` (the description, kept between starts, then the field and the
  run, on a background thread) before it accepts the client, so the first `describe` (an
  agent's first call) does not wait for torch. `build_server` alone prepares nothing.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from typing import Annotated, Any, Literal, TypeVar

from mcp.server.mcpserver import Image, MCPServer
from mcp.server.mcpserver.exceptions import ResourceError, ToolError
from mcp_types import ImageContent, TextContent, ToolAnnotations
from pydantic import BaseModel, ConfigDict, Field, create_model

from sync4d import __version__
from sync4d.export import model as scene_model
from sync4d.export.model import Interval, ObjectRecord, RunRef, Scene, Units
from sync4d.phase3.activation import RULES
from sync4d.phase3.query import DEFAULT_SCORER, SCORER_TABLE, SCORERS
from sync4d.serve.tools import PROMPT_URI, SCENE_URI, RunTools, ToolProblem

__all__ = ["build_server", "serve"]

_T = TypeVar("_T")

INSTRUCTIONS = """\
A 4D reconstruction of a dynamic scene by sync4d: objects that move over time, with a language
field that says which object matches a text and when. Times are normalised: 0 is the first
frame, 1 the last; lengths are in the scene's world units. Start with `describe` (objects,
what each does, the cameras), then `query` a text, `track` an object, list `events`, or
`render` a view. The resources hold the full scene description (JSON) and a text summary."""


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------

class _Open(BaseModel):
    """A record that may carry more keys than it names (sync4d's data may grow)."""

    model_config = ConfigDict(extra="allow")


def _fields(record: type[BaseModel], *names: str) -> dict[str, Any]:
    """The fields `names` of the scene description's `record` (type, constraints,
    description), in that order, as `create_model` takes them."""
    return {n: (record.model_fields[n].annotation, record.model_fields[n]) for n in names}


class RankedObject(_Open):
    """An object of a query's answer: its label, name, score and active intervals."""

    label: int
    name: str
    score: float
    intervals: list[Interval]
    active_frames: int


class QueryResult(_Open):
    """`sync4d query --json`'s answer: the top object (`answer`) and every object ranked."""

    query: str
    scorer: str
    rule: str
    answer: RankedObject | None
    objects: list[RankedObject]
    motion_phrases: list[dict[str, Any]] = []
    timeline: dict[str, list[float]] | None = Field(
        None, description="with timeline=true: 'times' and each object's per-frame similarity")


#: An object of the scene: the description's record (`ObjectRecord`) without `label` (its id).
ObjectSummary = create_model(
    "ObjectSummary", __base__=_Open, __module__=__name__,
    __doc__="An object of the scene: id (Phase 2 label), name, Gaussians, extent, motion "
            "segments, language slots, nearest vocabulary entries.",
    **_fields(ObjectRecord, "id", "name", "gaussians", "extent", "segments", "slots", "radius",
              "rigid_share", "observed_frames", "vocabulary"),
)  # fmt: skip


class Frames(BaseModel):
    """The stored frames: how many, and the first and last time."""

    count: int
    t0: float
    t1: float


class ExportedFile(BaseModel):
    """A file exported from this run that the server was started with (`--4dgs`)."""

    format: str = Field(description="'4dgs': the open .4dgs container (objects, tracks, "
                        "embeddings; fourdgs reads it)")
    path: str = Field(description="absolute path on the server's machine")
    bytes: int
    records: int = Field(description="Gaussian records (a Gaussian with a residual has several)")
    objects: list[str] = Field(description="names in its object table")
    tracks: int = Field(description="objects with a rigid track")
    embeddings: str | None = Field(description="the encoder of its object embeddings, or null")
    residual: str = Field(description="what of D_theta's non-rigid motion it keeps")


class DescribeResult(BaseModel):
    """The scene in brief, the LLM prompt, the files exported from the run the server names,
    and (full=true) the whole scene description."""

    run: RunRef
    frames: Frames
    units: Units
    up: list[float]
    objects: list[ObjectSummary]  # type: ignore[valid-type]
    events: int = Field(description="number of events (the events tool lists them)")
    cameras: dict[str, int] = Field(description="stored cameras per split (render's camera)")
    prompt: str
    resources: list[str]
    files: list[ExportedFile] = []
    scene: Scene | None = None


class ObjectRef(BaseModel):
    """An object by id and name."""

    id: int
    name: str


class TrackFrame(BaseModel):
    """An object's pose and motion at one stored frame (world units, normalised time)."""

    frame: int
    t: float
    position: list[float] = Field(description="M_phi's centroid [x, y, z]")
    rotation: list[float] = Field(description="unit quaternion [w, x, y, z]")
    translation: list[float]
    velocity: list[float] = Field(description="length per unit of normalised time")
    speed: float
    acceleration: list[float]
    box_min: list[float] = Field(description="2nd-percentile corner of its Gaussians")
    box_max: list[float] = Field(description="98th-percentile corner of its Gaussians")
    visible: float | None = None
    observed: bool


class TrackResult(BaseModel):
    """An object's track over [t0, t1], one entry per stored frame in it."""

    object: ObjectRef
    t0: float
    t1: float
    units: Units
    note: str | None = None
    frames: list[TrackFrame]


#: A pairwise event of the description (`sync4d.export.model.Event`) with its objects' names.
Event = create_model(
    "Event", __base__=_Open, __module__=__name__,
    __doc__="A pairwise event: kind, the two objects (0: the background) and when.",
    **_fields(scene_model.Event, "kind", "objects"),
    names=(list[str], Field(description="the two objects' names")),
    **_fields(scene_model.Event, "start", "end", "t0", "t1", "distance", "evidence"),
)  # fmt: skip

#: A motion segment of the description (`sync4d.export.model.Segment`) with its object.
Segment = create_model(
    "Segment", __base__=_Open, __module__=__name__,
    __doc__="A motion segment: an object in a state (at rest, moving, rising, ...) and when.",
    object=(int, Field(description="the object's id")), name=(str, ...),
    **_fields(scene_model.Segment, "state", "start", "end", "t0", "t1"),
)  # fmt: skip


class EventsResult(BaseModel):
    """The events and motion segments that overlap [t0, t1]."""

    t0: float
    t1: float
    events: list[Event]  # type: ignore[valid-type]
    segments: list[Segment]  # type: ignore[valid-type]


# --------------------------------------------------------------------------------------------
# The server
# --------------------------------------------------------------------------------------------

def _answers(fn: Callable[..., _T]) -> Callable[..., _T]:
    """`fn` with a `ToolProblem` turned into the SDK's `ToolError` (an error result)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> _T:
        try:
            return fn(*args, **kwargs)
        except ToolProblem as e:
            raise ToolError(str(e)) from None

    return wrapper


_READ_ONLY = ToolAnnotations(read_only_hint=True, destructive_hint=False, idempotent_hint=True,
                             open_world_hint=False)  # fmt: skip

Time = Annotated[float, Field(description="normalised time: 0 first frame, 1 last frame")]
ObjectKey = Annotated[str | int, Field(description="an object's name (e.g. 'red ball') or id")]
#: The scorers and activation rules of their registries (`sync4d query --scorer`, `--rule`).
ScorerName = Annotated[Literal[SCORERS] | None, Field(  # type: ignore[valid-type]
    description="; ".join(f"{n}: {s.summary}" for n, s in SCORER_TABLE.items())
    + f" (default {DEFAULT_SCORER})")]
RuleName = Annotated[Literal[tuple(RULES)] | None, Field(  # type: ignore[valid-type]
    description="; ".join(f"{n}: {r.summary}" for n, r in RULES.items())
    + " (default: the field's)")]


def build_server(tools: RunTools) -> MCPServer:
    """The MCP server of `tools`' run: five tools and two resources."""
    server = MCPServer(
        name="sync4d", title=f"sync4d: {tools.run_dir.name}", version=__version__,
        instructions=INSTRUCTIONS, log_level="WARNING",
    )  # fmt: skip

    @server.tool(annotations=_READ_ONLY)
    @_answers
    def describe(
        full: Annotated[bool, Field(description="also the whole scene description: every "
                                    "frame's track, the events, metadata")] = False,
    ) -> DescribeResult:  # fmt: skip
        """The scene: the objects (size, Gaussians, motion segments such as 'at rest' or
        'falling' with their times), how many events, the cameras, and a plain-text summary
        for reading. Call it first."""
        return DescribeResult.model_validate(tools.describe(full))

    @server.tool(annotations=_READ_ONLY)
    @_answers
    def query(
        text: Annotated[str, Field(description="what to look for, e.g. 'the red ball while "
                                   "it is falling'")],
        scorer: ScorerName = None,
        rule: RuleName = None,
        timeline: Annotated[bool, Field(description="also each object's per-frame "
                                        "similarity")] = False,
    ) -> QueryResult:  # fmt: skip
        """Which object matches a text, and when: every object ranked by score with the
        intervals (frames and times) where it is active; `answer` is the top one. As the
        command `sync4d query RUN TEXT --json`, which also reads relational questions ('which
        ball lands first') into a plan over the objects' states and events when it can."""
        return QueryResult.model_validate(tools.query(text, scorer, rule, timeline))

    @server.tool(annotations=_READ_ONLY)
    @_answers
    def track(object: ObjectKey, t0: Time = 0.0, t1: Time = 1.0) -> TrackResult:
        """An object's pose, velocity and box over [t0, t1]: at each stored frame in it the
        centroid, rotation quaternion (w, x, y, z), translation, velocity, speed,
        acceleration and the box of its Gaussians, from the run's per-object motion (M_phi)."""
        return TrackResult.model_validate(tools.track(object, t0, t1))

    @server.tool(annotations=_READ_ONLY)
    @_answers
    def events(
        object: Annotated[str | int | None,
                          Field(description="only this object's (name or id)")] = None,
        kind: Annotated[str | None, Field(description="an event kind (approach, contact, "
                                          "separation) or a motion state (at rest, moving, "
                                          "rising, falling, turning)")] = None,
        t0: Time = 0.0, t1: Time = 1.0,
    ) -> EventsResult:  # fmt: skip
        """When objects approach, touch and move away from each other or the ground (object
        0, the background), and each object's motion segments (at rest, moving, rising,
        falling, turning), that overlap [t0, t1]."""
        return EventsResult.model_validate(tools.events(object, kind, t0, t1))

    @server.tool(annotations=_READ_ONLY)
    @_answers
    def render(
        t: Time,
        camera: Annotated[str | int | None, Field(
            description="test:K or train:K (the K-th camera of that split, from 0), K (a test "
            "camera) or a frame name; default: the first test camera")] = None,
    ) -> list[ImageContent | TextContent]:  # fmt: skip
        """An image (PNG) of the scene at time t from one of the run's cameras, and a line of
        JSON saying which (camera, split, width, height)."""
        png, info = tools.render(t, camera)
        return [Image(data=png, format="png").to_image_content(),
                TextContent(type="text", text=json.dumps(info))]  # fmt: skip

    @server.resource(SCENE_URI, name="scene", title="Scene description (JSON)",
                     mime_type="application/json",
                     description="the scene description `sync4d export --scene` writes")
    def scene_json() -> str:
        try:
            return tools.scene_json()
        except ToolProblem as e:
            raise ResourceError(str(e)) from None

    @server.resource(PROMPT_URI, name="prompt", title="Scene summary for an LLM",
                     mime_type="text/plain",
                     description="the plain-text summary `sync4d export --prompt` writes")
    def prompt() -> str:
        try:
            return tools.prompt()
        except ToolProblem as e:
            raise ResourceError(str(e)) from None

    return server


def serve(tools: RunTools, http: tuple[str, int] | None = None, sse: bool = False) -> None:
    """Serve `tools`' run: over stdio, or with `http` (host, port) over streamable HTTP at
    ``/mcp`` (`sse`: the SSE transport at ``/sse``). What the first calls need is prepared
    on a background thread from the start (`RunTools.prepare`). Returns when the client
    disconnects (stdio) or on Ctrl-C (HTTP)."""
    tools.prepare()
    server = build_server(tools)
    if http is None:
        server.run("stdio")
    elif sse:
        server.run("sse", host=http[0], port=http[1])
    else:
        server.run("streamable-http", host=http[0], port=http[1])
