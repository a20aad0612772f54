"""What the viewer shows, without a browser, on an oracle run of the embedded scene saved as a
run folder with its language field: splats per object and time, tracks, the answer that lights
up an object while it is active, renders of a view, reloading a run that trains, the latency."""

from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest
import torch

from support.oracle import oracle_run_folder
from sync4d.data.scene import Camera
from sync4d.events import Advanced, EventLog, Finished, Started, Stats
from sync4d.phase3.store import FieldError
from sync4d.runs import CHECKPOINT_NAME, EVENTS_FILE, load_run
from sync4d.viewer.state import HIGHLIGHT, ViewerState

QUERY = "the red ball rising"


@pytest.fixture(scope="module", params=["gaussians", "nodes"])
def run_dir(tmp_path_factory, request):
    """The oracle run, saved with either motion model (D_theta per Gaussian, or nodes)."""
    path = oracle_run_folder(tmp_path_factory.mktemp("viewer"), (QUERY,), motion=request.param)
    assert load_run(path).model.motion == request.param
    return path


def test_splats_per_object_match_the_model(run_dir):
    st = ViewerState(run_dir)
    assert [o.name for o in st.objects] == ["background", "red ball", "blue box", "green pillar"]
    # each object's legend colour is what its Gaussians look like
    red, blue, green = (st.objects[i].colour for i in (1, 2, 3))
    assert np.argmax(red) == 0 and np.argmax(blue) == 2 and np.argmax(green) == 1
    sp = st.splats(0.5)
    assert sum(len(a.centers) for a in sp.values()) == st.run.model.num_gaussians
    m = st.run.model
    with torch.no_grad():
        means, quats, scales = m.at_time(0.5)
    sel = st.labels == 1
    np.testing.assert_allclose(sp[1].centers, means[torch.as_tensor(sel)].numpy(), atol=1e-6)
    # covariance = R diag(s^2) R^T, symmetric positive definite
    q = quats[torch.as_tensor(sel)][0].double()
    w, x, y, z = q.tolist()
    r = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]],
                     dtype=torch.float64)
    s2 = scales[torch.as_tensor(sel)][0].double() ** 2
    np.testing.assert_allclose(sp[1].covariances[0], ((r * s2) @ r.T).numpy(), rtol=1e-4,
                               atol=1e-9)
    assert ((sp[1].opacities > 0) & (sp[1].opacities < 1)).all()
    assert st.splats(0.5) is sp  # cached
    lit = sp[1].tinted(HIGHLIGHT)
    assert np.abs(lit.rgbs - sp[1].rgbs).max() > 0.1 and lit.centers is sp[1].centers


def test_the_answer_lights_up_the_top_object_while_it_is_active(run_dir):
    st = ViewerState(run_dir)
    ans = st.ask(QUERY)
    assert ans["objects"][0]["name"] == "red ball" and ans["top_label"] == 1
    assert st.active_at(ans, 0.45) and not st.active_at(ans, 0.1)  # the hop: 0.35-0.55
    start = st.next_active(ans, 0.0)
    assert start == pytest.approx(ans["objects"][0]["intervals"][0]["t0"])
    assert st.next_active(ans, 0.95) == start  # wraps to the first interval
    tracks = st.tracks()
    assert set(tracks) == {1, 2, 3} and tracks[1].shape == (21, 3)
    mid = st.position(tracks[1], 0.45)
    assert mid[2] > tracks[1][0, 2] + 0.1  # the ball is in the air


def test_a_run_without_a_field_says_how_to_build_it(run_dir, tmp_path):
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(run_dir, bare, ignore=shutil.ignore_patterns("phase3"))
    st = ViewerState(bare)
    assert st.field is None and "--phases 3" in st.field_message
    with pytest.raises(FieldError, match="--phases 3"):
        st.ask(QUERY)


def test_render_view_is_the_checkpoint_render_of_that_camera(run_dir):
    st = ViewerState(run_dir)
    c = st.run.cameras[0]
    view = np.asarray(c["viewmat"], np.float64).reshape(4, 4)
    r, eye = view[:3, :3].T, -view[:3, :3].T @ view[:3, 3]
    tr = np.trace(r)
    w = math.sqrt(1.0 + tr) / 2.0
    wxyz = np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w),
                     (r[1, 0] - r[0, 1]) / (4 * w)])  # fmt: skip
    fov = 2 * math.atan(c["height"] / (2 * c["fy"]))
    path = st.render_view(eye, wxyz, fov, c["width"] / c["height"], 0.3, height=c["height"],
                          threads=1)  # fmt: skip
    from PIL import Image

    got = np.asarray(Image.open(path)).astype(float) / 255.0
    cam = Camera(view, c["fy"], c["fy"], c["width"] / 2, c["height"] / 2, c["width"], c["height"])
    with torch.no_grad():
        ref = st.run.model.render(cam, 0.3, background=torch.tensor(st.run.background),
                                  threads=1).features.clamp(0, 1).numpy()  # fmt: skip
    assert path.parent == run_dir / "renders" and got.shape == ref.shape
    assert np.abs(got - ref).max() <= 1.0 / 255.0 + 1e-6  # the same image, 8-bit rounded
    assert (np.abs(ref - 1.0).max(-1) > 0.1).mean() > 0.01  # and not an empty one


def test_a_run_that_trains_is_reloaded(run_dir):
    st = ViewerState(run_dir)
    assert not st.changed()
    ckpt = run_dir / CHECKPOINT_NAME
    later = time.time() + 5
    os.utime(ckpt, (later, later))
    assert st.changed()
    st.load()
    assert not st.changed() and st.iteration == load_run(run_dir).iteration


def test_the_status_follows_the_fits_event_log(run_dir):
    """While a fit runs, the viewer reads where it is from the run folder's `events.jsonl`
    (the fit's own typed events), not from the terminal."""
    st = ViewerState(run_dir)
    path = run_dir / EVENTS_FILE
    assert st.training() == ""  # no event log: nothing to say
    log = EventLog(path)
    try:
        log(Started("phase2", 2000, start=1000, log_every=100))
        log(Advanced("phase2", 1200, Stats(loss=0.01, psnr=31.2, gaussians=900)))
        assert st.training() == "phase2 1200 / 2000, PSNR 31.20 dB"
        log(Finished("phase2"))
        assert st.training() == ""
        with path.open("a") as f:  # a foreign or older line: said nothing about, no error
            f.write('{"event": "Started", "task": "x"}\n{"event": "Advanced", "task": "x"}\n')
        assert st.training() == ""
    finally:
        log.close()
        path.unlink()
