"""What Phase 3 skips (issue 40): only observed object-frames are cropped and encoded, in one
encoder call; `phase3.skip_unobserved = false` encodes the unobserved crops too and the field
does not change; the relational kinematic dims stay computed at every frame (their counters).

On an oracle Phase 2 run of the embedded scene (as `test_phase3_oracle`) in which the red ball
leaves every view for a few frames (carried 50 m below the scene) and hides inside the green
pillar for a few others (occluded: a crop box, no visible Gaussian)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from support.oracle import OracleGaussians, oracle_phase2_run
from support.scenes import small_synthetic
from sync4d.data import synthetic as syn
from sync4d.events import Skipped
from sync4d.phase3.build import build_field, load_field
from sync4d.phase3.config import Phase3Config
from sync4d.phase3.encoders.encoder import Encoder
from sync4d.phase3.encoders.offline import OfflineEncoder
from sync4d.phase3.kinematics import RELATIONAL_DIMS, relational_counts
from sync4d.phase3.query import TextCache, answer
from sync4d.terminal import words

SCENE = small_synthetic(frames=13, train_cameras=3, test_every=4)
#: Frame times (normalised) when the red ball is out of every view, and inside the pillar.
AWAY = (0.4, 0.55)
INSIDE = (0.8, 0.95)
QUERIES = ("the red ball", "the blue box", "the green pillar at rest", "the fastest object",
           "the red ball touching the plate", "approaching the green pillar")  # fmt: skip


class HidingGaussians(OracleGaussians):
    """The oracle, with the red ball (label 1) 50 m below the scene during `AWAY` and shrunk to
    a tenth in the middle of the green pillar (label 3) during `INSIDE`."""

    def at_time(self, t: float, deform: bool = True):
        means, quats, scales = super().at_time(t, deform)
        if not deform:
            return means, quats, scales
        ball = torch.as_tensor(self.truth == 1)
        if AWAY[0] <= t <= AWAY[1]:
            means = means.clone()
            means[ball] += torch.tensor([0.0, 0.0, -50.0])
        elif INSIDE[0] <= t <= INSIDE[1]:
            centre = torch.as_tensor(syn.object_poses(float(t))[3][1], dtype=means.dtype)
            means = means.clone()
            means[ball] = centre + 0.1 * (means[ball] - means[ball].mean(0))
        return means, quats, scales


class Counting(Encoder):
    """An encoder that counts its image calls and images, then asks `inner`."""

    def __init__(self, inner: Encoder) -> None:
        self.inner, self.kind, self.closed_vocabulary = inner, inner.kind, inner.closed_vocabulary
        self.calls: list[int] = []

    @property
    def dim(self) -> int:
        return self.inner.dim

    @property
    def fingerprint(self) -> str:
        return self.inner.fingerprint

    def encode_images(self, images):
        self.calls.append(len(images))
        return self.inner.encode_images(images)

    def encode_texts(self, texts):
        return self.inner.encode_texts(texts)


@pytest.fixture(scope="module")
def hiding(tmp_path_factory):
    """(run, scene root, offline encoder, fields and counting encoders with the skip on, off)."""
    tmp = tmp_path_factory.mktemp("phase3_skips")
    run, root = oracle_phase2_run(tmp, HidingGaussians, SCENE)
    offline = OfflineEncoder()
    built = {}
    for skip in (True, False):
        enc = Counting(offline)
        cfg = Phase3Config(skip_unobserved=skip)
        built[skip] = (build_field(run, cfg, enc, threads=1), enc)
    return run, root, offline, built


def _frames(field, span):
    return (field.times >= span[0] - 1e-9) & (field.times <= span[1] + 1e-9)


def test_invisible_frames_are_neither_cropped_nor_encoded(hiding):
    _, _, _, built = hiding
    field, enc = built[True]
    away, inside = _frames(field, AWAY), _frames(field, INSIDE)
    assert away.sum() >= 2 and inside.sum() >= 2
    ball = field.names.index("red ball")
    # away: no view sees it, no box; inside the pillar: a box, nothing visible
    assert (field.visible[ball, away] == 0).all() and (field.boxes[ball, away] == 0).all()
    assert (field.visible[ball, inside] < 0.05).all()
    assert (field.boxes[ball, inside, 2] > field.boxes[ball, inside, 0]).all()
    assert not field.observed[ball, away | inside].any()
    assert field.observed[ball, ~(away | inside)].all() and field.observed[1:].all()
    assert (field.obs[ball, away | inside] == 0).all()
    # one encoder call holding exactly the observed object-frames
    c = field.counts
    assert enc.calls == [int(field.observed.sum())]
    assert c["encoder_calls"] == 1 and c["crops_encoded"] == c["crops"] == field.observed.sum()
    assert c["object_frames"] == field.observed.size
    assert c["invisible"] == int((away | inside).sum()) and c["below_threshold"] == 0
    assert c["extra_crops"] == 0
    assert c["observed"] + c["invisible"] + c["below_threshold"] == c["object_frames"]
    # an image is read once per frame and view, and only for an observed object's crop
    chosen = {(f, field.views[a][f]) for a, f in zip(*np.nonzero(field.observed), strict=True)}
    assert c["images_loaded"] == len(chosen)


def test_the_switch_changes_what_is_encoded_not_the_field(hiding):
    run, _, offline, built = hiding
    (on, enc_on), (off, enc_off) = built[True], built[False]
    inside = int(_frames(on, INSIDE).sum())
    # off: the occluded frames (a box) are cropped and encoded apart, the far ones cannot be
    assert enc_off.calls == [enc_on.calls[0], inside]
    assert off.counts["crops_encoded"] == on.counts["crops_encoded"] + inside
    assert off.counts["extra_crops"] == inside and off.counts["encoder_calls"] == 2
    assert off.config["skip_unobserved"] is False and on.config["skip_unobserved"] is True
    for name in ("obs", "observed", "static", "features", "standardised", "ridge", "pred",
                 "sync", "visible", "boxes", "gaps", "radius", "centroids"):  # fmt: skip
        np.testing.assert_array_equal(getattr(on, name), getattr(off, name), err_msg=name)
    assert on.views == off.views
    cache = TextCache(run.path, on, offline)
    for q in QUERIES:
        for scorer in ("full", "paper"):
            a, b = (answer(f, q, cache=cache, scorer=scorer) for f in (on, off))
            assert a == b, q


def test_relational_dims_are_kept_where_the_ball_is_unseen(hiding):
    _, _, _, built = hiding
    field, _ = built[True]
    c = field.counts
    ball = field.names.index("red ball")
    unseen = ~field.observed[ball]
    k, t = field.observed.shape
    assert c["relational"] == k * t and c["relational_skipped"] == 0
    assert c["relational_unobserved"] == k * int(unseen.sum())
    # M_phi's centroid of the unseen ball is where the run put it: 50 m down while away, so the
    # others' nearest distance (dim 24) is to each other then, and the ball's own is far
    away = _frames(field, AWAY)
    assert (field.features[ball, away, 24] > 45).all()
    others = np.linalg.norm(field.centroids[1] - field.centroids[2], axis=-1)
    np.testing.assert_allclose(field.features[1, away, 24], others[away])
    assert np.isfinite(field.features[..., list(RELATIONAL_DIMS)]).all()
    assert relational_counts(np.ones((1, 5), bool)) == {
        "relational": 0,
        "relational_skipped": 5,
        "relational_unobserved": 0,
    }


def skip_report(field) -> str:
    """The line `fit` prints for the field's `Skipped("phase3", counts)` event."""
    return words(Skipped.of("phase3", field.counts)).text


def test_counts_are_saved_and_reported(hiding, tmp_path):
    _, _, _, built = hiding
    on, off = built[True][0], built[False][0]
    on.save(tmp_path / "on")
    assert load_field(tmp_path / "on").counts == on.counts
    line = skip_report(on)
    c = on.counts
    assert line.startswith(f"fit: Phase 3 encoded {c['crops_encoded']} of {c['object_frames']} "
                           "object-frames in 1 encoder call")  # fmt: skip
    assert f"{c['invisible']} invisible" in line and "\n" not in line
    assert f"{c['relational_unobserved']} at frames with an unobserved object" in line
    assert "skip_unobserved is off" in skip_report(off) and "2 encoder calls" in skip_report(off)
    old = dataclasses.replace(on, counts={})
    assert "before the counters" in skip_report(old)
