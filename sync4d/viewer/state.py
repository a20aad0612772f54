"""What the viewer shows, without the web server: a run (reloaded when its checkpoint changes),
its Gaussians at a time split by object, each object's track, the answers of the language
field, and renders of a view through sync4d's own rasterizer. `sync4d.viewer.app` puts this on
a viser page; the tests and `bench view` use it directly.

The browser draws splats from centres, covariances, colours and opacities: the colour is the
SH DC band's (view-independent; the browser does not evaluate higher bands), so a render of
the same view through sync4d (`render_view`) can show view-dependent shading the page does not.
A render that fails (the watchdog's stop, the rasterizer's refusal, NaN or inf pixels) is a
`RenderFailed` of one sentence (`sync4d.runs.render_rgb`), which the page shows in place of the
file it would have written.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from sync4d.data.scene import Camera
from sync4d.events import read_events
from sync4d.export.splats import default_times, splats_at
from sync4d.geometry import quat_to_matrix
from sync4d.phase1.gaussians import SH_C0
from sync4d.phase3.query import TextCache, answer
from sync4d.phase3.store import Field, FieldError, load_field
from sync4d.runs import CHECKPOINT_NAME, EVENTS_FILE, RENDERS_DIR, RenderFailed, Run, load_run
from sync4d.runs.render import render_rgb

__all__ = ["HIGHLIGHT", "PALETTE", "ObjectInfo", "RenderFailed", "SplatArrays", "ViewerState"]

#: Object colours in the list and of the tracks (label 1, 2, ...; the background is grey).
PALETTE = (
    (0.90, 0.25, 0.20), (0.20, 0.45, 0.90), (0.20, 0.70, 0.30), (0.95, 0.60, 0.10),
    (0.60, 0.30, 0.80), (0.10, 0.70, 0.75), (0.85, 0.35, 0.60), (0.55, 0.55, 0.20),
)  # fmt: skip
#: The colour a highlighted object's splats are blended towards (60 %).
HIGHLIGHT = (1.0, 0.9, 0.0)
#: Frames of splats kept in memory (time -> arrays), the most recent first out last.
CACHE_FRAMES = 64


@dataclass(frozen=True)
class ObjectInfo:
    """An object of the run: Phase 2 `label` (0: the background), `name`, `colour` (RGB in
    [0, 1]) and its number of Gaussians."""

    label: int
    name: str
    colour: tuple[float, float, float]
    gaussians: int


@dataclass
class SplatArrays:
    """One object's splats as the browser takes them: `centers` [n, 3], `covariances`
    [n, 3, 3], `rgbs` [n, 3] in [0, 1], `opacities` [n, 1] (float32)."""

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray

    def tinted(self, colour: tuple[float, float, float], amount: float = 0.6) -> SplatArrays:
        """The same splats with their colours blended `amount` of the way to `colour`."""
        rgb = (1.0 - amount) * self.rgbs + amount * np.asarray(colour, np.float32)
        return SplatArrays(self.centers, self.covariances, rgb.astype(np.float32),
                           self.opacities)  # fmt: skip


def _covariances(quats: np.ndarray, log_scales: np.ndarray) -> np.ndarray:
    """R diag(s^2) R^T [N, 3, 3] from quaternions w-x-y-z [N, 4] and log-scales [N, 3]."""
    r = quat_to_matrix(torch.as_tensor(quats, dtype=torch.float64)).numpy()
    s2 = np.exp(2.0 * log_scales)
    return np.einsum("nij,nj,nkj->nik", r, s2, r).astype(np.float32)


#: Texts whose embeddings a viewer keeps in memory (the least recently asked dropped beyond it;
#: `ask` still writes new ones to the run's text cache, as `query` does).
TEXT_CACHE_SIZE = 1024


class ViewerState:
    """A run as the viewer shows it. `encoder`: the encoder the field was built with, if it
    moved. Raises `RunError` / `CheckpointError` for a run that cannot be read; a missing or
    stale language field is not an error: `field` is None and `field_message` says why and how
    to build it."""

    def __init__(self, run_dir: str | Path, encoder: str | None = None) -> None:
        self.run_dir = Path(run_dir)
        self.encoder = encoder
        self.run: Run
        self.field: Field | None = None
        self.field_message = ""
        self._cache: TextCache | None = None
        self._splats: OrderedDict[float, dict[int, SplatArrays]] = OrderedDict()
        self.mtime = 0.0
        self.load()

    # -- the run --------------------------------------------------------------------------
    def _checkpoint(self) -> Path:
        return self.run_dir / CHECKPOINT_NAME

    def load(self) -> None:
        """(Re)read the run's checkpoint and its field."""
        self.mtime = self._checkpoint().stat().st_mtime if self._checkpoint().exists() else 0.0
        self.run = load_run(self.run_dir)
        self._splats.clear()
        labels = self.run.labels if self.run.labels is not None \
            else np.zeros(self.run.model.num_gaussians, np.int64)
        self.labels = labels
        present = sorted(set(int(x) for x in np.unique(labels)))
        self.objects = [
            ObjectInfo(k, "background" if k == 0 else self.run.names.get(k, f"object {k}"),
                       self._colour(k), int((labels == k).sum()))
            for k in present
        ]  # fmt: skip
        self.times = np.asarray(default_times(self.run), np.float64)
        try:
            self.field = load_field(self.run_dir)
            self.field_message = ""
            self._cache = TextCache(self.run_dir, self.field, self.encoder, limit=TEXT_CACHE_SIZE)
        except FieldError as e:
            self.field, self._cache = None, None
            self.field_message = str(e)

    def _colour(self, label: int) -> tuple[float, float, float]:
        """Object `label`'s colour in the list and of its track: the opacity-weighted mean base
        colour of its Gaussians, brightened to a full channel of 0.9 (so the legend matches
        what the object looks like); grey for the background, a palette colour for a grey
        object."""
        if label == 0:
            return (0.6, 0.6, 0.6)
        m = self.run.model
        sel = torch.as_tensor(self.labels == label)
        with torch.no_grad():
            rgb = (0.5 + SH_C0 * m.sh_dc[sel, 0]).clamp(0, 1)
            w = torch.sigmoid(m.opacity_logits[sel])[:, None]
            mean = ((rgb * w).sum(0) / w.sum().clamp_min(1e-12)).double().numpy()
        if float(mean.max() - mean.min()) < 0.1:  # grey: no colour of its own to show
            return PALETTE[(label - 1) % len(PALETTE)]
        c = mean * (0.9 / max(float(mean.max()), 1e-6))
        return (float(c[0]), float(c[1]), float(c[2]))

    def changed(self) -> bool:
        """True when the checkpoint was rewritten since `load` (a run still training)."""
        p = self._checkpoint()
        return p.exists() and p.stat().st_mtime != self.mtime

    @property
    def iteration(self) -> int:
        """The checkpoint's iteration (of its phase)."""
        return self.run.iteration

    def training(self) -> str:
        """Where the run's training is, from the events its fit writes (`read_events` on
        ``events.jsonl``): "phase2 1200 / 2000, PSNR 31.20 dB" while a loop runs, "" when the
        last loop finished or the run has no event log."""
        events = read_events(self.run_dir / EVENTS_FILE, ("Started", "Advanced", "Finished"))
        if not events or events[-1]["event"] == "Finished":
            return ""
        started = next((e for e in reversed(events) if e["event"] == "Started"), None)
        last = events[-1]
        if started is None or last["event"] != "Advanced" or last.get("task") != started.get(
                "task") or not isinstance(last.get("stats"), dict):  # fmt: skip
            return ""  # not a loop under way, or lines this version did not write
        psnr = last["stats"].get("psnr")
        shown = f", PSNR {psnr:.2f} dB" if isinstance(psnr, float) and math.isfinite(psnr) else ""
        return f"{last['task']} {last.get('done', '?')} / {started.get('total', '?')}{shown}"

    @property
    def up(self) -> np.ndarray:
        """World up [3]: the field's, else the training cameras' mean up (OpenCV: -y)."""
        if self.field is not None:
            return np.asarray(self.field.up, np.float64)
        ups = [-np.asarray(c["viewmat"], np.float64).reshape(4, 4)[1, :3]
               for c in self.run.cameras if c["split"] == "train"]  # fmt: skip
        m = np.mean(ups, axis=0) if ups else np.array([0.0, 0.0, 1.0])
        n = float(np.linalg.norm(m))
        return m / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])

    # -- splats ---------------------------------------------------------------------------
    def splats(self, t: float) -> dict[int, SplatArrays]:
        """Every object's splats at time `t` in [0, 1] (label -> arrays), cached per time."""
        key = round(float(t), 6)
        hit = self._splats.get(key)
        if hit is not None:
            self._splats.move_to_end(key)
            return hit
        with torch.no_grad():
            s = splats_at(self.run.model, key, self.labels)
        cov = _covariances(s.quats, s.log_scales)
        rgb = np.clip(0.5 + SH_C0 * s.sh_dc, 0.0, 1.0).astype(np.float32)
        op = (1.0 / (1.0 + np.exp(-s.opacity_logits)))[:, None].astype(np.float32)
        out = {}
        for o in self.objects:
            sel = s.object_ids == o.label
            out[o.label] = SplatArrays(s.means[sel], cov[sel], rgb[sel], op[sel])
        self._splats[key] = out
        while len(self._splats) > CACHE_FRAMES:
            self._splats.popitem(last=False)
        return out

    # -- tracks ---------------------------------------------------------------------------
    def tracks(self) -> dict[int, np.ndarray]:
        """Each object's centroid over the stored frames (label -> [T, 3]): M_phi's (the
        field's, or the checkpoint's motion export); empty for a Phase 1 run."""
        if self.field is not None:
            return {lab: self.field.centroids[k] for k, lab in enumerate(self.field.labels)}
        export = self.run.export or {}
        if "centroids" not in export:
            return {}
        return {o.label: export["centroids"][o.label] for o in self.objects if o.label > 0}

    def position(self, track: np.ndarray, t: float) -> np.ndarray:
        """A track [T, 3] at time `t`, linear between the stored frames."""
        times = self.field.times if self.field is not None else self.run.times
        if times is None or len(times) != len(track):
            times = np.linspace(0.0, 1.0, len(track))
        return np.array([np.interp(t, times, track[:, i]) for i in range(3)])

    # -- queries --------------------------------------------------------------------------
    def ask(self, text: str) -> dict:
        """The field's answer to `text` (`sync4d.phase3.query.answer`, default scorer), with
        the top object's label, its activation [T] and the field's frame times; FieldError
        (with the command that builds it) when the run has no usable field."""
        if self.field is None or self._cache is None:
            raise FieldError(self.field_message)
        ans = answer(self.field, text, cache=self._cache)
        self._cache.save()
        top = ans["objects"][0]
        k = self.field.labels.index(top["label"])
        ans["top_label"] = top["label"]
        ans["top_active"] = np.asarray(ans["active"][self.field.names[k]], bool)
        ans["top_timeline"] = np.asarray(ans["timeline"][self.field.names[k]], float)
        return ans

    @staticmethod
    def active_at(ans: dict, t: float) -> bool:
        """Whether the answer's top object is active at time `t` (nearest stored frame)."""
        times = np.asarray(ans["times"], float)
        return bool(ans["top_active"][int(np.argmin(np.abs(times - t)))])

    @staticmethod
    def next_active(ans: dict, t: float) -> float | None:
        """The start time of the answer's next active interval after `t` (wrapping to the
        first), None when it is never active."""
        starts = [iv["t0"] for iv in ans["objects"][0]["intervals"]]
        if not starts:
            return None
        later = [s for s in starts if s > t + 1e-9]
        return float(later[0] if later else starts[0])

    # -- renders --------------------------------------------------------------------------
    def render_view(self, position: np.ndarray, wxyz: np.ndarray, fov: float, aspect: float,
                    t: float, height: int = 480, threads: int | None = None) -> Path:  # fmt: skip
        """Render the camera at `position` [3] with orientation `wxyz` (camera-to-world, OpenCV
        axes: x right, y down, z forward), vertical field of view `fov` (radians) and `aspect`
        (width / height) at time `t` through sync4d's rasterizer; writes and returns
        ``RUN/renders/view_t<t>_<n>.png``. `RenderFailed` (one sentence, nothing written) when
        the watchdog stops the render, the rasterizer refuses it or its image is not finite."""
        r = quat_to_matrix(torch.as_tensor(wxyz, dtype=torch.float64)).numpy()
        view = np.eye(4)
        view[:3, :3] = r.T
        view[:3, 3] = -r.T @ np.asarray(position, np.float64)
        width = max(16, int(round(height * aspect)))
        f = 0.5 * height / math.tan(0.5 * fov)
        cam = Camera(view, f, f, width / 2.0, height / 2.0, width, height)
        bg = torch.as_tensor(self.run.background, dtype=torch.float32)
        rgb = render_rgb(self.run.model, cam, t, bg, threads)
        out = self.run_dir / RENDERS_DIR
        out.mkdir(parents=True, exist_ok=True)
        stem = f"view_t{t:.3f}_{time.strftime('%Y%m%d-%H%M%S')}"
        path, n = out / f"{stem}.png", 1
        while path.exists():
            n += 1
            path = out / f"{stem}_{n}.png"
        Image.fromarray(rgb).save(path)
        return path
