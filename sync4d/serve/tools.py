"""What `sync4d serve` answers, without the protocol: one run's scene description, queries,
tracks, events and renders as plain data (`RunTools`). `sync4d.serve.server` puts these on the
Model Context Protocol; the tests and other front ends can call them directly.

Design:

* **One source of numbers.** The scene description is the one `sync4d export --scene` writes:
  `sync4d.export.describe.describe` on the run (`load_run`) and its field (`load_field`), a
  `sync4d.export.model.Scene` (rounded, typed), kept in memory; the scene resource is its JSON
  text (`Scene.to_json`, with the side file's record `export` writes beside ``scene.json``,
  computed without writing it) and the prompt `prompt_text` of its data, so the `describe`,
  `track` and `events` tools and the two resources say exactly what the exported files say.
  Queries go through `sync4d.phase3.query.answer`, as `sync4d query` does (whatever that
  learns, the server answers too).
* **Ready at start.** `prepare` (which `sync4d serve` calls as it starts) builds what the
  first calls need on a background thread while the client connects: the scene description
  (the first thing an agent asks for), then the field, and the run (torch) once a first call
  is answered, so that its import does not slow that call. The description is also
  kept outside the run folder (`sync4d.serve.cache`, keyed by the run's files and the code), so
  a server started again on the same run reads it back into the model in milliseconds instead
  of importing torch and describing every frame (seconds); an entry the model refuses is built
  again. A call that needs something still being built waits for that build, never starts a
  second one. Without `prepare` nothing is read at construction: the field (numpy) loads on
  the first query, the run (torch) on the first description or render, and a query never
  imports torch.
* **Clear refusals.** Every argument a caller can get wrong (an unknown object, a time outside
  [0, 1], an interval backwards, an unknown camera, kind or scorer) and every run that cannot
  answer (no Phase 2, no language field: the message names the command to run) raises
  `ToolProblem` with one sentence saying what to do; the server turns it into an error result.
  So does a render that fails: the watchdog's stop on what the rasterizer would receive (a
  NaN or a diverged value in the checkpoint at that time), the rasterizer's refusal, or an
  image with NaN or inf pixels.
* **Read-only and bounded.** Nothing is written to the run folder: the query texts the server
  encodes are kept in memory (at most `TEXT_CACHE_SIZE`, the least recently used dropped
  first; the run's own ``phase3/texts.json`` is read, never written), and the last
  `RENDER_CACHE_SIZE` renders are kept for a repeated call. Nothing else grows per call.
* **Thread-safe.** The protocol runs synchronous tools on worker threads. A lock per resource
  serialises its load (the field, the run, the description: a call waits for the one it
  needs, never loads it twice) and its use (the query text cache, the renders), so a query
  does not wait for a render, nor `track`, `events` or `describe` (which read the finished
  description) for either. Renders are the bottleneck under load (torch and the rasterizer;
  docs/results/benchmarks.md compares it with the single lock of every call it replaced).

Times are the run's normalised times, 0 to 1 (the description's `metadata.units.time`); frames
are the stored frames of the field and M_phi, intervals inclusive [start, end].
"""

from __future__ import annotations

import io
import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import ValidationError

from sync4d.errors import Sync4dError
from sync4d.export.model import EVENT_KINDS, Event, ObjectRecord, Scene, Segment
from sync4d.runs.names import CHECKPOINT_NAME
from sync4d.serve.cache import description_key, read_description, write_description

if TYPE_CHECKING:  # torch-free at run time: the run and the field load on first use
    from sync4d.phase3.encoders.encoder import Encoder
    from sync4d.phase3.query import TextCache
    from sync4d.phase3.store import Field
    from sync4d.runs import Run

__all__ = ["EVENT_KINDS", "PROMPT_URI", "RENDER_CACHE_SIZE", "SCENE_URI", "TEXT_CACHE_SIZE",
           "RunTools", "ToolProblem", "pick_camera"]  # fmt: skip

_log = logging.getLogger(__name__)

#: The resources' addresses: the scene description JSON and the LLM prompt.
SCENE_URI = "sync4d://scene.json"
PROMPT_URI = "sync4d://prompt.txt"
#: Slack on time bounds (rounding of the stored frame times).
_EPS = 1e-6
#: Query texts whose embeddings a server keeps in memory (about 12 kB each at 384 dimensions;
#: the least recently used dropped first).
TEXT_CACHE_SIZE = 1024
#: Renders (PNG and what they show) kept for a repeated call, by time and camera.
RENDER_CACHE_SIZE = 32
#: Seconds `prepare` waits for a first answer before it loads the run anyway.
PRELOAD_AFTER_S = 10.0


class ToolProblem(Sync4dError, ValueError):
    """A call that cannot be answered as asked; the message says why and what to do."""


def _problem(e: BaseException) -> ToolProblem:
    """`e` (a sync4d error whose message names the file and the fix) as a `ToolProblem`."""
    return e if isinstance(e, ToolProblem) else ToolProblem(str(e))


class RunTools:
    """The tools of one run folder `run_dir`: `describe`, `query`, `track`, `events`, `render`,
    and the resources `scene_json` and `prompt`. `encoder`: the encoder the field was built
    with, if it moved (as `query --encoder`; or an `Encoder`); `threads`: torch's threads for
    renders and the description (default: torch's own)."""

    def __init__(
        self, run_dir: str | Path, encoder: str | Encoder | None = None,
        threads: int | None = None, fourdgs: str | Path | None = None,
    ) -> None:  # fmt: skip
        self.run_dir = Path(run_dir)
        #: A `.4dgs` file exported from this run (`sync4d export RUN --4dgs FILE`) that
        #: `describe` names; checked by `check`.
        self.fourdgs = None if fourdgs is None else Path(fourdgs)
        self._files: list[dict] = []
        self.encoder = encoder
        self.threads = threads
        self._field_lock = threading.Lock()
        self._run_lock = threading.Lock()
        self._scene_lock = threading.Lock()
        self._query_lock = threading.Lock()
        self._render_lock = threading.Lock()
        self._field: Field | None = None
        self._cache: TextCache | None = None
        self._run: Run | None = None
        self._scene: Scene | None = None
        self._scene_text: str | None = None
        self._prompt: str | None = None
        #: Where the description came from: "built", "kept" (read back) or None (not yet).
        self.scene_source: str | None = None
        self._renders: OrderedDict[tuple[float, str], tuple[bytes, dict]] = OrderedDict()
        self._prepared: threading.Thread | None = None
        #: Set when a tool has answered (`prepare` then loads the run for renders).
        self._answered = threading.Event()

    # -- loading --------------------------------------------------------------------------
    def check(self) -> None:
        """Refuse a folder that is no run (missing, or no checkpoint), before serving it."""
        if not self.run_dir.is_dir():
            raise ToolProblem(f"{self.run_dir}: no such run folder; train one with "
                              f"`sync4d fit DATA --out {self.run_dir}`")  # fmt: skip
        if not (self.run_dir / CHECKPOINT_NAME).is_file():
            raise ToolProblem(f"{self.run_dir}: no {CHECKPOINT_NAME} (not a run folder, or its "
                              f"training never saved); train it with `sync4d fit DATA --out "
                              f"{self.run_dir}`")  # fmt: skip
        if self.fourdgs is not None:
            self._files = [self._fourdgs_file(self.fourdgs)]

    def _fourdgs_file(self, path: Path) -> dict:
        """What `describe` says of the `.4dgs` file at `path`: ToolProblem unless it is a
        readable `.4dgs` written from this run's checkpoint as it is now."""
        from sync4d.export.errors import ExportError
        from sync4d.export.fourdgs import read_summary
        from sync4d.files import file_sha256

        again = f"`sync4d export {self.run_dir} --4dgs {path}`"
        try:
            info = read_summary(path)
        except ExportError as e:
            raise ToolProblem(f"--4dgs: {e}") from None
        meta = info["metadata"]
        sha = meta.get("sync4d.checkpoint.sha256")
        if sha is None:
            raise ToolProblem(f"--4dgs {path}: not written by sync4d export (no checkpoint "
                              f"hash in its header); write it with {again}")  # fmt: skip
        if sha != file_sha256(self.run_dir / CHECKPOINT_NAME):
            raise ToolProblem(f"--4dgs {path}: written from another checkpoint (another run, or "
                              f"this one before it trained on); write it again with {again}")
        return {
            "format": "4dgs", "path": str(path.resolve()), "bytes": info["bytes"],
            "records": info["records"], "objects": [o["label"] for o in info["objects"]],
            "tracks": len(info["tracks"]),
            "embeddings": meta.get("sync4d.encoder.kind") if any(
                o["embedding"] for o in info["objects"]) else None,
            "residual": meta.get("sync4d.residual", ""),
        }  # fmt: skip

    def prepare(self, renders: bool = True) -> threading.Thread:
        """Build, on a background thread, what the first calls need: the scene description
        (read back when kept, else built and kept), the field, and with `renders` the run
        (torch) once the first call is answered (or after `PRELOAD_AFTER_S`), so that its
        import does not slow the first `describe`. A run that cannot give one is left to the
        call that needs it, which says why. Returns the thread (started once)."""
        if self._prepared is None:
            self._prepared = threading.Thread(target=self._prepare, args=(renders,),
                                              name="sync4d-prepare", daemon=True)  # fmt: skip
            self._prepared.start()
        return self._prepared

    def _prepare(self, renders: bool) -> None:
        for step in (self.scene, self.field):
            _quietly(step)
        if renders:
            self._answered.wait(PRELOAD_AFTER_S)
            _quietly(self.run)

    def field(self) -> Field:
        """The run's language field (`load_field`, numpy only), loaded once."""
        from sync4d.phase3.store import FieldError, load_field

        with self._field_lock:
            if self._field is None:
                try:
                    self._field = load_field(self.run_dir)
                except (FieldError, OSError) as e:
                    raise _problem(e) from None
            return self._field

    def run(self) -> Run:
        """The run (`load_run`: the model, M_phi, labels, cameras; imports torch), loaded once."""
        from sync4d.runs import CheckpointError, RunError, load_run

        with self._run_lock:
            if self._run is None:
                if self.threads:
                    import torch

                    torch.set_num_threads(self.threads)
                try:
                    self._run = load_run(self.run_dir)
                except (RunError, CheckpointError, OSError) as e:
                    raise _problem(e) from None
            return self._run

    def _build_scene(self) -> tuple[Scene, str, str]:
        """The scene description (the model and its JSON text) and the prompt exactly as
        `export --scene scene.json --prompt` writes them, made in memory."""
        from sync4d.export.describe import describe
        from sync4d.export.errors import ExportError
        from sync4d.export.prompt import prompt_text
        from sync4d.export.scene import SceneError, with_embeddings
        from sync4d.phase3.store import FieldError

        field = self.field()  # first: a run without a field is refused before torch loads
        run = self.run()
        try:
            scene, emb = describe(run, field)
        except (SceneError, ExportError, FieldError, OSError) as e:
            raise _problem(e) from None
        scene, _ = with_embeddings(scene, "scene.json", emb)  # the record export writes
        return scene, scene.to_json(), prompt_text(scene.model_dump())

    def scene(self) -> Scene:
        """The scene description (numbers rounded as in the exported file): kept from an
        earlier start of the same run and code (`sync4d.serve.cache`), else built once and
        kept."""
        with self._scene_lock:
            if self._scene is None:
                key = description_key(self.run_dir)
                kept = read_description(key)
                scene = None
                if kept is not None:
                    text, prompt = kept
                    try:
                        scene = Scene.from_json(text)
                        self.scene_source = "kept"
                    except ValidationError:
                        scene = None  # not a description this code reads: built again
                if scene is None:
                    scene, text, prompt = self._build_scene()
                    write_description(key, text, prompt)
                    self.scene_source = "built"
                self._scene, self._scene_text, self._prompt = scene, text, prompt
            return self._scene

    def scene_json(self) -> str:
        """The scene description as the JSON text `export --scene` writes."""
        self.scene()
        assert self._scene_text is not None
        return self._scene_text

    def prompt(self) -> str:
        """The plain-text summary for an LLM that `export --prompt` writes."""
        self.scene()
        assert self._prompt is not None
        return self._prompt

    # -- helpers --------------------------------------------------------------------------
    def _names(self) -> dict[int, str]:
        """Object id -> name, the background (0) included."""
        return {0: "background"} | {o.id: o.name for o in self.scene().objects}

    def _object(self, key: str | int) -> ObjectRecord:
        """The description's object named or numbered `key` (case and spaces ignored)."""
        objects = self.scene().objects
        text = " ".join(str(key).split()).lower()
        for o in objects:
            if text in (str(o.id), o.name.lower()):
                return o
        # "ball" for "red ball", "the red ball" for "red ball": when one object alone fits
        hits = [o for o in objects
                if text and (text in o.name.lower() or o.name.lower() in text)]  # fmt: skip
        if len(hits) == 1:
            return hits[0]
        known = ", ".join(f"{o.id} ({o.name})" for o in objects)
        raise ToolProblem(f"unknown object {key!r}: this run's objects are {known}; give a name "
                          "or an id")  # fmt: skip

    def _interval(self, t0: float | None, t1: float | None) -> tuple[float, float]:
        """[t0, t1] checked: normalised times in [0, 1], t0 <= t1 (None: the bound)."""
        a = 0.0 if t0 is None else float(t0)
        b = 1.0 if t1 is None else float(t1)
        for name, t in (("t0", a), ("t1", b)):
            _check_time(name, t)
        if a > b:
            raise ToolProblem(f"t0 = {a:g} is after t1 = {b:g}: give t0 <= t1")
        return a, b

    # -- the tools ------------------------------------------------------------------------
    def describe(self, full: bool = False) -> dict:
        """The scene in brief: run, frames, units, the objects (extent, motion segments,
        language slots), the number of events, the cameras, the LLM prompt, the files exported
        from the run that the server was given (`--4dgs`); `full`: also the whole scene
        description (tracks of every frame, events, metadata: the `Scene`)."""
        scene = self.scene()
        meta = scene.metadata
        times = meta.frames.times
        splits: dict[str, int] = {"test": 0, "train": 0}
        for c in meta.cameras:
            splits[c.split] = splits.get(c.split, 0) + 1
        out = {
            "run": meta.run.model_dump(),
            "frames": {"count": meta.frames.count, "t0": times[0], "t1": times[-1]},
            "units": meta.units.model_dump(),
            "up": meta.axes.up,
            "objects": [o.model_dump(exclude={"label"}) for o in scene.objects],
            "events": len(scene.events),
            "cameras": splits,
            "prompt": self.prompt(),
            "resources": [SCENE_URI, PROMPT_URI],
            "files": list(self._files),
            "scene": scene if full else None,
        }  # fmt: skip
        self._answered.set()
        return out

    def query(self, text: str, scorer: str | None = None, rule: str | None = None,
              timeline: bool = False) -> dict:  # fmt: skip
        """The answer to `text` as `sync4d query --json` gives it: every object ranked with its
        score and active intervals, the top one as `answer` (None with a `refusal`: what was
        asked for is not there); `timeline`: with each object's per-frame similarity."""
        from sync4d.phase3.encoders.encoder import EncoderError
        from sync4d.phase3.query import DEFAULT_SCORER, QueryError, TextCache, answer

        field = self.field()
        with self._query_lock:
            if self._cache is None:  # read-only: new texts stay in memory, bounded
                self._cache = TextCache(self.run_dir, field, self.encoder,
                                        limit=TEXT_CACHE_SIZE, persist=False)  # fmt: skip
            try:
                ans = answer(field, text, cache=self._cache, scorer=scorer or DEFAULT_SCORER,
                             rule=rule)  # fmt: skip
            except (QueryError, EncoderError, OSError) as e:
                raise _problem(e) from None
        out = {k: v for k, v in ans.items() if k not in ("timeline", "active", "times")}
        # a refusal ("the fifth ball to land" of three) names no object
        out["answer"] = ans["objects"][0] if ans["objects"] and not ans["refusal"] else None
        out["timeline"] = {"times": ans["times"], **ans["timeline"]} if timeline else None
        self._answered.set()
        return out

    def track(self, obj: str | int, t0: float | None = None, t1: float | None = None) -> dict:
        """Object `obj`'s pose over [t0, t1]: at each stored frame in it (or, when none falls
        inside, the frame nearest its middle) the centroid, rotation (quaternion w, x, y, z),
        translation, velocity, speed, acceleration and the box of its Gaussians (2nd-98th
        percentile, world axes), from M_phi and the Gaussians (the description's track)."""
        out = self._track(obj, t0, t1)  # reads the finished description: no turn to wait for
        self._answered.set()
        return out

    def _track(self, obj: str | int, t0: float | None, t1: float | None) -> dict:
        a, b = self._interval(t0, t1)
        o = self._object(obj)
        scene = self.scene()
        times = scene.metadata.frames.times
        tr = next(t for t in scene.tracks if t.id == o.id)
        idx = [i for i, t in enumerate(times) if a - _EPS <= t <= b + _EPS]
        note = None
        if not idx:
            mid = 0.5 * (a + b)
            idx = [min(range(len(times)), key=lambda i: abs(times[i] - mid))]
            note = (f"no stored frame lies in [{a:g}, {b:g}]: the nearest frame, "
                    f"t = {times[idx[0]]:g}")  # fmt: skip
        frames = []
        for i in idx:
            v = tr.velocity[i]
            frames.append({
                "frame": i, "t": times[i], "position": tr.centroid[i],
                "rotation": tr.rotation[i], "translation": tr.translation[i],
                "velocity": v, "speed": float(sum(x * x for x in v) ** 0.5),
                "acceleration": tr.acceleration[i],
                "box_min": tr.box_min[i], "box_max": tr.box_max[i],
                "visible": tr.visible[i], "observed": tr.observed[i],
            })  # fmt: skip
        return {"object": {"id": o.id, "name": o.name}, "t0": a, "t1": b,
                "units": scene.metadata.units.model_dump(), "note": note,
                "frames": frames}  # fmt: skip

    def events(self, obj: str | int | None = None, kind: str | None = None,
               t0: float | None = None, t1: float | None = None) -> dict:  # fmt: skip
        """The contact / approach / separation events and the motion segments of the scene
        description that overlap [t0, t1], of object `obj` if given (as either party of an
        event), of `kind` if given (an event kind, or a motion state for the segments)."""
        out = self._events(obj, kind, t0, t1)  # reads the finished description: no turn to wait for
        self._answered.set()
        return out

    def _events(self, obj: str | int | None, kind: str | None, t0: float | None,
                t1: float | None) -> dict:  # fmt: skip
        a, b = self._interval(t0, t1)
        scene = self.scene()
        names = self._names()
        oid = None if obj is None else self._object(obj).id
        states = sorted({s.state for o in scene.objects for s in o.segments})
        if kind is not None and kind not in EVENT_KINDS and kind not in states:
            raise ToolProblem(f"unknown kind {kind!r}: events are {', '.join(EVENT_KINDS)}; "
                              f"motion segments are {', '.join(states) or 'none'}")  # fmt: skip

        def overlaps(x: Event | Segment) -> bool:
            return x.t0 <= b + _EPS and x.t1 >= a - _EPS

        events = []
        for e in scene.events:
            if overlaps(e) and (oid is None or oid in e.objects) and kind in (None, e.kind):
                events.append({**e.model_dump(),
                               "names": [names.get(i, str(i)) for i in e.objects]})  # fmt: skip
        segments = []
        for o in scene.objects:
            if oid is not None and o.id != oid:
                continue
            for s in o.segments:
                if overlaps(s) and kind in (None, s.state):
                    segments.append({"object": o.id, "name": o.name, **s.model_dump()})
        segments.sort(key=lambda s: (s["start"], s["object"]))
        return {"t0": a, "t1": b, "events": events, "segments": segments}

    def cameras(self) -> list[dict]:
        """The run's stored cameras (checkpoint records: name, split, size)."""
        return list(self.run().cameras)

    def render(self, t: float, camera: str | int | None = None) -> tuple[bytes, dict]:
        """A PNG of the run at time `t` seen by `camera` (``test:K``, ``train:K``, ``K``: the
        K-th test camera, or a frame name; default the first test camera, the run's default
        view) and what was rendered (time, camera, split, width, height). The last
        `RENDER_CACHE_SIZE` renders are kept; a render that fails (the watchdog's stop, the
        rasterizer's refusal, NaN or inf pixels) is a `ToolProblem` of one sentence."""
        _check_time("t", float(t))
        run = self.run()
        rec = pick_camera(run.cameras, camera)
        key = (round(float(t), 6), str(rec["name"]))
        with self._render_lock:
            hit = self._renders.get(key)
            if hit is not None:
                self._renders.move_to_end(key)
                return hit
            import numpy as np
            import torch
            from PIL import Image

            from sync4d.data.scene import Camera

            vm = np.asarray(rec["viewmat"], dtype=np.float64).reshape(4, 4)
            cam = Camera(vm, float(rec["fx"]), float(rec["fy"]), float(rec["cx"]),
                         float(rec["cy"]), int(rec["width"]), int(rec["height"]))  # fmt: skip
            from sync4d.runs.render import RenderFailed, render_rgb

            bg = torch.as_tensor(run.background, dtype=torch.float32)
            check = (f"try another time or camera, or check the run with `sync4d render RUN "
                     f"--time {float(t):g}`")  # fmt: skip
            try:
                rgb = render_rgb(run.model, cam, float(t), bg, self.threads,
                                 name=str(rec["name"]), instead=check)  # fmt: skip
            except RenderFailed as e:
                raise ToolProblem(str(e)) from None
        buf = io.BytesIO()
        Image.fromarray(rgb).save(buf, format="PNG")  # after its turn
        info = {"t": float(t), "camera": rec["name"], "split": rec["split"],
                "width": int(rec["width"]), "height": int(rec["height"])}  # fmt: skip
        out = (buf.getvalue(), info)
        with self._render_lock:
            self._renders[key] = out
            while len(self._renders) > RENDER_CACHE_SIZE:
                self._renders.popitem(last=False)
        return out


def _quietly(step: Callable[[], object]) -> None:
    """`step()` on the preparing thread: a problem is left to the call that needs it."""
    try:
        step()
    except ToolProblem:
        pass  # the call that needs it says why
    except Exception:  # noqa: BLE001 - the call that needs it reports it
        _log.warning("preparing %s failed", getattr(step, "__name__", step), exc_info=True)


def _check_time(name: str, t: float) -> None:
    """`t` must be a normalised time in [0, 1]."""
    if not (0.0 - _EPS <= t <= 1.0 + _EPS):  # also refuses NaN
        raise ToolProblem(f"{name} = {t:g} is out of range: times are normalised, 0 (first "
                          "frame) to 1 (last frame)")  # fmt: skip


def pick_camera(records: list[dict], spec: str | int | None) -> dict:
    """The camera record `spec` names: ``test:K`` / ``train:K`` (the K-th camera of that
    split), ``K`` (a test camera), or a frame's name; None: the first test camera."""
    if not records:
        raise ToolProblem("the checkpoint stores no cameras (written by an older sync4d?); "
                          "render it with `sync4d render RUN --camera ...` after a refit")
    pools: dict[str, list[dict]] = {"train": [], "test": []}
    for r in records:
        pools.setdefault(r["split"], []).append(r)
    counts = f"{len(pools['test'])} test and {len(pools['train'])} train cameras"
    if spec is None or str(spec).strip() == "":
        return (pools["test"] or pools["train"])[0]
    text = str(spec).strip()
    split, _, index = text.rpartition(":")
    if index.lstrip("-").isdigit() and split in ("", "test", "train"):
        pool = pools[split or "test"] or (pools["train"] if not split else [])
        k = int(index)
        if not 0 <= k < len(pool):
            raise ToolProblem(f"camera {text!r}: no such camera; this run has {counts} "
                              "(test:K or train:K, K from 0)")  # fmt: skip
        return pool[k]
    for r in records:
        if r["name"] == text or Path(r["name"]).stem == text:
            return r
    raise ToolProblem(f"camera {text!r}: no camera of that name; give test:K or train:K (this "
                      f"run has {counts}) or a frame name")  # fmt: skip
