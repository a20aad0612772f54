"""A render of the viewer that fails ("Render view" on a checkpoint that is not finite at that
time) is one sentence on the page, not a crash: the watchdog's stop on what the rasterizer
would receive, NaN pixels and the rasterizer's refusal, on the oracle run; nothing is written."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from support.oracle import oracle_run_folder
from support.render import nan_render
from sync4d import watchdog
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.runs import RENDERS_DIR
from sync4d.viewer.app import Viewer
from sync4d.viewer.state import RenderFailed, ViewerState


@pytest.fixture(scope="module")
def state(tmp_path_factory) -> ViewerState:
    return ViewerState(oracle_run_folder(tmp_path_factory.mktemp("viewer-render")))


def _view(st: ViewerState, t: float) -> SimpleNamespace:
    """What `Viewer._render` reads: the state, the time, a markdown box, a client's camera
    (the first test camera's pose)."""
    c = next(c for c in st.run.cameras if c["split"] == "test")
    view = np.asarray(c["viewmat"], np.float64).reshape(4, 4)
    eye = -view[:3, :3].T @ view[:3, 3]
    cam = SimpleNamespace(position=eye, wxyz=np.array([1.0, 0.0, 0.0, 0.0]), fov=0.8,
                          aspect=1.0)  # fmt: skip
    return SimpleNamespace(state=st, t=t, threads=1, render_md=SimpleNamespace(content=""),
                           event=SimpleNamespace(client=SimpleNamespace(camera=cam)))


def test_a_failed_render_is_one_sentence_on_the_page(state, monkeypatch):
    folder = state.run_dir / RENDERS_DIR
    before = sorted(folder.glob("view_*")) if folder.is_dir() else []
    real = DeformableGaussians.render
    shown = []

    def press(t: float) -> str:
        page = _view(state, t)
        Viewer._render(page, page.event)  # type: ignore[arg-type]
        return page.render_md.content

    with watchdog.injected("Rendering", None, "input:means"):
        shown.append(press(0.5))
    monkeypatch.setattr(DeformableGaussians, "render", nan_render(real))
    shown.append(press(0.25))

    def refuse(*args, **kwargs):
        raise ValueError("means: contains NaN or inf")

    monkeypatch.setattr(DeformableGaussians, "render", refuse)
    shown.append(press(0.75))
    for text in shown:
        assert text.startswith("**Render failed.** the render at t = "), text
        sentence = text.removeprefix("**Render failed.** ")
        assert "\n" not in sentence and ". " not in sentence, sentence
    assert "stopped" in shown[0] and "means" in shown[0] and "fit --out RUN --force" in shown[0]
    assert "NaN or inf pixels" in shown[1]
    assert "contains NaN or inf" in shown[2]
    after = sorted(folder.glob("view_*")) if folder.is_dir() else []
    assert after == before  # nothing written
    monkeypatch.setattr(DeformableGaussians, "render", real)
    assert press(0.5).startswith("Wrote ")  # the next render works


def test_render_failed_is_a_value_error():
    e = RenderFailed.of(None, 0.5)
    assert isinstance(e, ValueError) and str(e).startswith("the render at t = 0.500 has NaN")
