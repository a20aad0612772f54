"""The viewer's page on a viser server: the run's splats at the chosen time (one node per object),
the dataset's cameras, each object's track and current position, and the panel: time slider,
play / pause and speed, the object list (show, isolate, highlight), the query box with its
ranked answer, timeline and "next active" jump, "render this view", and the run's status.

Every change of the time, the objects or the answer calls `Viewer.update`, which sends the new
splats; `Viewer.latency` keeps how long each took (slider change to splats sent). A run that is
still training is watched: when its checkpoint is rewritten the page reloads it.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from sync4d.errors import Sync4dError
from sync4d.geometry import matrix_to_rotvec
from sync4d.runs import CheckpointError, CheckpointKind, RunError
from sync4d.viewer.state import HIGHLIGHT, ViewerState

__all__ = ["PLAY_SECONDS", "Viewer"]

#: Seconds the whole clip takes to play at speed 1.
PLAY_SECONDS = 5.0
#: Training cameras drawn at most (evenly chosen).
MAX_CAMERAS = 24
#: Slider latencies kept in `Viewer.latency` (the latest ones).
LATENCIES_KEPT = 1000


def _rgb255(c: tuple[float, float, float]) -> tuple[int, int, int]:
    return tuple(int(round(255 * x)) for x in c)  # type: ignore[return-value]


def _wxyz(r: np.ndarray) -> np.ndarray:
    """Unit quaternion w-x-y-z of a rotation matrix [3, 3]."""
    w = matrix_to_rotvec(r)
    angle = float(np.linalg.norm(w))
    axis = w / angle if angle > 1e-12 else np.zeros(3)
    return np.r_[math.cos(angle / 2.0), math.sin(angle / 2.0) * axis]


class Viewer:
    """The page of `state` on `server` (a `viser.ViserServer`); `threads`: torch and rasterizer
    threads of "render this view"."""

    def __init__(self, server: Any, state: ViewerState, threads: int | None = None) -> None:
        self.server = server
        self.state = state
        self.threads = threads
        self.t = 0.0
        self.answer: dict | None = None
        self.latency: deque[float] = deque(maxlen=LATENCIES_KEPT)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        server.scene.set_up_direction(tuple(float(x) for x in state.up))
        self._initial_camera()
        self._build_panel()
        self._draw_static()
        self.update()
        threading.Thread(target=self._play_loop, daemon=True, name="sync4d-play").start()
        threading.Thread(target=self._watch_loop, daemon=True, name="sync4d-watch").start()

    # -- the panel -----------------------------------------------------------------------
    def _build_panel(self) -> None:
        gui, st = self.server.gui, self.state
        self.status = gui.add_markdown(self._status_text())
        with gui.add_folder("Time"):
            self.time = gui.add_slider("time", 0.0, 1.0, 0.001, 0.0)
            self.play = gui.add_button("Play", icon=None)
            self.speed = gui.add_slider("speed", 0.1, 4.0, 0.1, 1.0,
                                        hint=f"1: the whole clip in {PLAY_SECONDS:g} s")
        self.time.on_update(lambda _: self._set_time(float(self.time.value)))
        self.play.on_click(lambda _: self._toggle_play())
        self.playing = False
        names = [o.name for o in st.objects]
        with gui.add_folder("Objects"):
            gui.add_markdown("  \n".join(
                f"<span style='color:rgb{_rgb255(o.colour)}'>&#9632;</span> {o.name} "
                f"({o.gaussians:,} Gaussians)" for o in st.objects))  # fmt: skip
            self.shown = {}
            for o in st.objects:
                box = gui.add_checkbox(o.name, True)
                box.on_update(lambda _: self.update())
                self.shown[o.label] = box
            self.isolate = gui.add_dropdown("isolate", ["none", *names], initial_value="none")
            self.highlight = gui.add_dropdown("highlight", ["none", *names], initial_value="none")
            self.show_tracks = gui.add_checkbox("tracks", True)
            for handle in (self.isolate, self.highlight, self.show_tracks):
                handle.on_update(lambda _: self.update())
        with gui.add_folder("Query"):
            self.query = gui.add_text("query", "")
            self.ask = gui.add_button("Ask", disabled=st.field is None)
            self.answer_md = gui.add_markdown(
                "" if st.field is not None else f"**No language field.** {st.field_message}")
            self.timeline = gui.add_uplot(
                data=(st.times, np.zeros_like(st.times), np.zeros_like(st.times)),
                series=({"label": "time"}, {"label": "similarity", "stroke": "#1f77b4"},
                        {"label": "active", "stroke": "#e6b800", "fill": "#e6b80040"}),
                scales={"x": {"time": False}, "y": {"auto": True}}, height=140,
                visible=False,
            )  # fmt: skip
            self.next = gui.add_button("Next active", disabled=True)
        self.ask.on_click(lambda _: self._ask())
        self.next.on_click(lambda _: self._next_active())
        self.render_btn = gui.add_button("Render view")
        self.render_md = gui.add_markdown("")
        self.render_btn.on_click(self._render)

    def _status_text(self) -> str:
        st = self.state
        kind = "Phase 2" if st.run.kind == CheckpointKind.PHASE2 else "Phase 1"
        field = "language field ready" if st.field is not None else "no language field"
        return (f"**{st.run_dir.name}**: {kind} checkpoint at iteration {st.iteration}, "
                f"{len(st.objects)} objects, {len(st.times)} frames; {field}")

    # -- the scene -----------------------------------------------------------------------
    def _draw_static(self) -> None:
        """Cameras and tracks (they do not change with time)."""
        scene, st = self.server.scene, self.state
        cams = [c for c in st.run.cameras if c["split"] == "train"]
        step = max(1, math.ceil(len(cams) / MAX_CAMERAS))
        extent = self._extent()
        for i, c in enumerate(cams[::step]):
            view = np.asarray(c["viewmat"], np.float64).reshape(4, 4)
            r, t = view[:3, :3].T, -view[:3, :3].T @ view[:3, 3]
            scene.add_camera_frustum(
                f"/cameras/{i}", fov=2 * math.atan(c["height"] / (2 * c["fy"])),
                aspect=c["width"] / c["height"], scale=0.03 * extent, thickness=0.002 * extent,
                color=(120, 120, 120), wxyz=_wxyz(r), position=t,
            )  # fmt: skip
        self.tracks = st.tracks()
        self._track_nodes, self._markers = {}, {}
        for o in st.objects:
            tr = self.tracks.get(o.label)
            if tr is None or o.label == 0:
                continue
            self._track_nodes[o.label] = scene.add_spline_catmull_rom(
                f"/tracks/{o.label}", points=tr, color=_rgb255(o.colour),
                thickness=0.004 * extent)  # fmt: skip
            self._markers[o.label] = scene.add_icosphere(
                f"/markers/{o.label}", radius=0.015 * extent, color=_rgb255(o.colour),
                position=st.position(tr, 0.0))  # fmt: skip

    def _initial_camera(self) -> None:
        """Start the browser at the first test camera (else training camera) of the run,
        looking at the objects' centre."""
        cams = ([c for c in self.state.run.cameras if c["split"] == "test"]
                or list(self.state.run.cameras))  # fmt: skip
        if not cams:
            return
        view = np.asarray(cams[0]["viewmat"], np.float64).reshape(4, 4)
        eye = -view[:3, :3].T @ view[:3, 3]
        x = self.state.run.model.means.detach().numpy()
        fg = x[self.state.labels > 0] if (self.state.labels > 0).any() else x
        self.server.initial_camera.position = tuple(float(v) for v in eye)
        self.server.initial_camera.look_at = tuple(float(v) for v in np.median(fg, axis=0))
        self.server.initial_camera.up = tuple(float(v) for v in self.state.up)

    def _extent(self) -> float:
        x = self.state.run.model.means.detach().numpy()
        lo, hi = np.percentile(x, 2, axis=0), np.percentile(x, 98, axis=0)
        return float(np.linalg.norm(hi - lo)) or 1.0

    def highlighted(self) -> int | None:
        """The label drawn highlighted now: the panel's choice, else the answer's top object
        while it is active."""
        if self.highlight.value != "none":
            return next(o.label for o in self.state.objects if o.name == self.highlight.value)
        if self.answer is not None and self.state.active_at(self.answer, self.t):
            return int(self.answer["top_label"])
        return None

    def visible(self, label: int) -> bool:
        """Whether object `label` is shown (the isolate choice, else its checkbox)."""
        if self.isolate.value != "none":
            return self.isolate.value == next(o.name for o in self.state.objects
                                              if o.label == label)  # fmt: skip
        return bool(self.shown[label].value)

    def update(self) -> float:
        """Send the splats, markers and visibility of the current time; the seconds it took."""
        t0 = time.perf_counter()
        with self._lock:
            st, scene = self.state, self.server.scene
            splats = st.splats(self.t)
            lit = self.highlighted()
            with self.server.atomic():
                for o in st.objects:
                    arr = splats[o.label]
                    if lit == o.label:
                        arr = arr.tinted(HIGHLIGHT)
                    scene.add_gaussian_splats(
                        f"/splats/{o.label}", centers=arr.centers, covariances=arr.covariances,
                        rgbs=arr.rgbs, opacities=arr.opacities, visible=self.visible(o.label),
                    )  # fmt: skip
                    if o.label in self._markers:
                        show = self.visible(o.label) and bool(self.show_tracks.value)
                        self._markers[o.label].position = st.position(self.tracks[o.label], self.t)
                        self._markers[o.label].visible = show
                        self._track_nodes[o.label].visible = show
            self.server.flush()
        dt = time.perf_counter() - t0
        self.latency.append(dt)
        return dt

    def _set_time(self, t: float) -> None:
        self.t = min(1.0, max(0.0, t))
        self.update()

    # -- playing and watching ------------------------------------------------------------
    def _toggle_play(self) -> None:
        self.playing = not self.playing
        self.play.label = "Pause" if self.playing else "Play"

    def _play_loop(self) -> None:
        last = time.perf_counter()
        while not self._stop.wait(0.05):
            now = time.perf_counter()
            if self.playing:
                t = (self.t + (now - last) * float(self.speed.value) / PLAY_SECONDS) % 1.0
                self.time.value = round(t, 3)  # its on_update sends the frame
            last = now

    def _watch_loop(self) -> None:
        while not self._stop.wait(2.0):
            try:
                if not self.state.changed():
                    continue
                with self._lock:
                    self.state.load()
                    self.answer = None
                training = self.state.training()
                where = f": {training}" if training else ""
                self.status.content = (self._status_text()
                                       + f" (reloaded: the run is training{where})")  # fmt: skip
                self.update()
            except (RunError, CheckpointError, OSError):
                continue  # a save in progress: the next poll reads it

    def stop(self) -> None:
        """End the play and watch threads."""
        self._stop.set()

    # -- queries and renders -------------------------------------------------------------
    def _ask(self) -> None:
        text = self.query.value.strip()
        if not text:
            self.answer_md.content = "Type a query first, e.g. *the red ball while it is falling*."
            return
        try:
            ans = self.state.ask(text)
        except Sync4dError as e:
            self.answer_md.content = f"**Cannot answer.** {e}"
            return
        if ans.get("refusal"):
            self.answer = None
            self.answer_md.content = f"**{ans['query']}**\n\nNo object: {ans['refusal']}."
            self.update()
            return
        self.answer = ans
        rows = ["| # | object | score | active (times) |", "|---|---|---|---|"]
        for i, o in enumerate(ans["objects"], 1):
            spans = ", ".join(f"{iv['t0']:.2f}-{iv['t1']:.2f}" for iv in o["intervals"]) or "-"
            rows.append(f"| {i} | {o['name']} | {o['score']:.3f} | {spans} |")
        self.answer_md.content = f"**{ans['query']}**\n\n" + "\n".join(rows)
        sims = ans["top_timeline"]
        peak = float(np.max(np.abs(sims))) or 1.0
        times = np.asarray(ans["times"], float)
        self.timeline.data = (times, sims, ans["top_active"].astype(float) * peak)
        self.timeline.visible = True
        self.next.disabled = not ans["objects"][0]["intervals"]
        self.update()

    def _next_active(self) -> None:
        if self.answer is None:
            return
        t = self.state.next_active(self.answer, self.t)
        if t is not None:
            self.time.value = round(t, 3)

    def _render(self, event: Any) -> None:
        client = event.client
        if client is None:
            return
        cam = client.camera
        try:
            path = self.state.render_view(np.asarray(cam.position), np.asarray(cam.wxyz),
                                          float(cam.fov), float(cam.aspect), self.t,
                                          threads=self.threads)  # fmt: skip
        except (OSError, ValueError) as e:
            self.render_md.content = f"**Render failed.** {e}"
            return
        self.render_md.content = f"Wrote `{path}`"
