"""Phase 3's settings (`Phase3Config`): the language field's hyperparameters, the paper's
values as defaults (Sec. 3.5, Appendices A, B, F). `sync4d.config.RunConfig` holds one as its
``phase3`` section; this module imports nothing heavy (the rules and encoders it names come
from their numpy-only registries), so a query reads it without torch.
"""

from __future__ import annotations

import dataclasses

from sync4d.phase3.activation import DEFAULT_RULE, RULES
from sync4d.phase3.encoders.encoder import describe_specs, encoder_problem
from sync4d.settings import choice, ranged

__all__ = ["Phase3Config"]


def _name_problem(text: str) -> str | None:
    """A name must not be empty."""
    return None if text.strip() else "expected a non-empty object name"


@dataclasses.dataclass(frozen=True)
class Phase3Config:
    """The language field (Sec. 3.5, Appendices A, B, F): the paper's values as defaults."""

    #: Encoder (`sync4d.phase3.encoders.encoder.ENCODERS`): "offline" (closed-vocabulary
    #: default), a SigLIP-ONNX model directory, or "" for $SYNC4D_ENCODER (else offline).
    encoder: str = choice("", check=encoder_problem, text=describe_specs('""'))
    #: Crop box: lower percentile of the projected Gaussian centres (App. A: 2nd) ...
    crop_low: float = ranged(2.0, 0.0, 50.0)
    #: ... upper percentile (98th) ...
    crop_high: float = ranged(98.0, 50.0, 100.0)
    #: ... and the margin added on each side, as a fraction of the box's size (12 %).
    crop_margin: float = ranged(0.12, 0.0, 1.0)
    #: An object is observed in a frame when at least this fraction of its Gaussians is visible
    #: (beyond the paper, which leaves the threshold open; docs/phase3.md) ...
    min_visible: float = ranged(0.05, 0.0, 1.0)
    #: ... and its crop box is at least this many pixels on each side.
    min_box: int = ranged(4, 1)
    #: Crop and encode only the observed object-frames, the only ones the field reads; false
    #: also crops and encodes the unobserved ones that have a crop box and discards them (the
    #: same field, at the cost the skip saves: for measuring it).
    skip_unobserved: bool = True
    #: At an object's unobserved frames, clip each standardised kinematic feature to the range
    #: it spans over the observed frames, so the ridge map is not extrapolated (an occluded
    #: object's visible fraction drops to 0; docs/phase3.md); false: Eq. 14 as written.
    clip_unobserved: bool = True
    #: Ridge regularisation lambda (Eq. 13).
    ridge_lambda: float = ranged(0.01, 0.0, lo_open=True)
    #: Blend weight beta between prediction and observation where observed ...
    beta: float = ranged(0.65, 0.0, 1.0)
    #: ... and which side takes it (docs/phase3.md).
    beta_on: str = choice("prediction", ("prediction", "observation"))
    #: Temporal EMA gamma: the weight of the neighbouring smoothed frame (zero phase).
    ema_gamma: float = ranged(0.15, 0.0, 1.0, hi_open=True)
    #: Query score weight w_s of the static similarity (Eq. 15) ...
    w_static: float = ranged(0.35, 0.0)
    #: ... and w_t of the peak temporal similarity.
    w_temporal: float = ranged(0.65, 0.0)
    #: Temporal activation rule, a name of `sync4d.phase3.activation.RULES`: by default
    #: the paper's "half-peak" (Appendix F: above 0.5 of the peak).
    activation: str = choice(DEFAULT_RULE, tuple(RULES))
    #: Static-only ablation: e_sync = e_static at every frame in every scorer (Table 5's
    #: "static only"; `query --scorer static` gives it for one query).
    static_only: bool = False
    #: False: the W = 0 ablation, every ridge map W_k = 0 (e_hat = e_static; the observations
    #: still blended and smoothed): the field without its kinematic conditioning
    #: (`query --scorer no-kinematics` gives it for one query on a field built with it on).
    kinematics: bool = True
    #: Name of the hand object for Appendix B dims 26-27 (zero when no object has this name).
    hand_object: str = choice("hand", check=_name_problem, text="an object name")
    #: World up for the motion phrases: "auto" (mean of the training cameras' up vectors) or
    #: an axis "+x", "-x", "+y", "-y", "+z", "-z".
    up: str = choice("auto", ("auto", "+x", "-x", "+y", "-y", "+z", "-z"))
    #: Motion phrases (beyond the paper): "moving" above this fraction of the scene's
    #: reference speed (the 95th percentile of every object's speed) ...
    moving_speed: float = ranged(0.15, 0.0)
    #: ... "at rest" below this fraction ...
    rest_speed: float = ranged(0.08, 0.0)
    #: ... "rising" / "falling" above this fraction along the up vector ...
    vertical_speed: float = ranged(0.15, 0.0)
    #: ... "approaching" / "moving away" above this fraction of closing speed ...
    closing_speed: float = ranged(0.1, 0.0)
    #: ... touching when the gap is below this fraction of the object's radius, ...
    contact_gap: float = ranged(0.6, 0.0)
    #: ... a fall that turns into a rise touches the surface under the object when the gap
    #: there is at most this many radii (a reconstruction leaves a small ball's lowest
    #: Gaussians above the plate's: bouncingballs' red ball 0.77 radii at its bounces, 1.4-1.9
    #: at its apexes; `sync4d.phase3.states`) ...
    rebound_gap: float = ranged(1.2, 0.0)
    #: ... and the turn is within max(`contact_gap` radii, this fraction of the object's
    #: height range over the clip) of its lowest height ...
    rebound_height: float = ranged(0.25, 0.0, 1.0)
    #: ... and a contact lasts while the gap stays within this many radii of its value at the
    #: turn (onset: it comes within; offset: it leaves) ...
    contact_band: float = ranged(0.05, 0.0)
    #: ... with motion read from centroids smoothed by a Gaussian of this sigma (normalised
    #: time) ...
    phrase_smooth: float = ranged(0.015, 0.0)
    #: ... and states lasting at least this many frames ...
    phrase_min_frames: int = ranged(3, 1)
    #: ... and a predicate matches a query when a phrase occurs in it or the text encoder's
    #: similarity of a query n-gram to a phrase reaches this.
    phrase_match: float = ranged(0.8, -1.0, 1.0)


