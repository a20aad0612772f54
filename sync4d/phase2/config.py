"""Phase 2's settings (Appendix A; the paper's values as defaults) and ablations, the section
``[phase2]`` of a run config. Every iteration count a shorter budget scales is declared
`ranged(..., scales=floor)` (`sync4d.config.phase2_budget`); ranges are checked by the config,
once, when a file or an override is read.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sync4d.phase2.assign import AssignConfig
from sync4d.phase2.motion import MotionConfig
from sync4d.settings import ranged

__all__ = ["Phase2Config"]


@dataclass(frozen=True)
class Phase2Config:
    """Phase 2 hyperparameters (Appendix A; the paper's values as defaults) and ablations.

    Settings that must go together (checked when the config is read, `combination_problem`):
    `warmup_end` is not below `warmup_start`; and unless `simultaneous`, with `iterations` >
    0 and `use_motion`, `motion_start` and the start of every term whose weight is above 0
    (`velocity_start` for `lambda_vel`, `residual_start` for `lambda_res`) are at most
    `iterations` (else M_phi, or that term, never acts)."""

    #: Phase 2 iterations after Phase 1 (Appendix A: 20k; 0: only M_phi's start, its
    #: closed-form fit and refinement).
    iterations: int = ranged(20_000, 0)
    motion: MotionConfig = field(default_factory=MotionConfig)
    assign: AssignConfig = field(default_factory=AssignConfig)
    #: Weight of the modulated residual energy (Eq. 8).
    lambda_res: float = ranged(0.02, 0.0)
    #: Weight of the rigid-share hinge (Eq. 9).
    lambda_share: float = ranged(0.01, 0.0)
    #: Target rigid share of the hinge: mean rho below tau is penalised (Eq. 9).
    tau: float = ranged(0.35, 0.0, 1.0)
    #: Weight of the velocity coherence term (Eq. 10).
    lambda_vel: float = ranged(0.01, 0.0)
    #: Weight of M_phi's temporal smoothness (Eq. 11).
    lambda_smooth: float = ranged(0.01, 0.0)
    #: Weight of the identity prior on static objects (Eq. 12).
    lambda_id: float = ranged(0.001, 0.0)
    #: EMA factor of the per-Gaussian residual magnitude (Appendix A's modulation).
    eta: float = ranged(0.95, 0.0, 1.0)
    #: Epsilon in the rigid share's denominator (metres).
    share_eps: float = ranged(1e-6, 0.0, lo_open=True)
    #: Iteration from which M_phi trains and the smoothness, rigid-share and identity terms act
    #: (at most `iterations`; like every term's start, checked when the config is read).
    motion_start: int = ranged(200, 0, scales=0)
    #: Iteration from which the velocity coherence term acts.
    velocity_start: int = ranged(300, 0, scales=0)
    #: Start of the linear warm-up of the auxiliary terms' gradient into the scene.
    warmup_start: int = ranged(500, 0, scales=0)
    #: End of that warm-up (full weight from here; not below `warmup_start`).
    warmup_end: int = ranged(1000, 0, scales=0)
    #: Iteration from which the modulated residual energy acts.
    residual_start: int = ranged(600, 0, scales=0)
    #: Keep densifying (clone/split/prune, opacity reset) on Phase 1's schedule, counted from
    #: Phase 2's first iteration; every change re-runs the assignment. Off by default: Phase 1's
    #: densification window is over when Phase 2 starts.
    densify: bool = False
    #: An object whose Gaussians' mean Phase 1 displacement stays below this fraction of the
    #: scene extent is static (it gets the identity prior); background always is.
    static_fraction: float = ranged(0.005, 0.0)
    #: Hold the objects that do not move (`still_position`, `still_rotation`) at their
    #: constant transform: their M_phi rows get no update (masked: zero gradients; Adam
    #: moments cleared) and the refinement skips them. Decided after the assignment and on
    #: every re-assignment. Not in the paper, which trains every object's transform and pulls
    #: the static ones to the identity (lambda_id). Off by default because it changes moving
    #: objects too, through Eq. 9 alone: the rigid share is a mean over all Gaussians, where a
    #: held Gaussian counts its constant transform's share (0 for one D_theta leaves in place)
    #: while a trained static row, which Adam moves by about its rate per step on noise
    #: gradients, makes its Gaussians count about 0.5 (oracle scene, init fit: mean rho 0.37
    #: held vs 0.73; moving rows differ by up to 2e-3 after 10 steps, and are bit-identical
    #: without the hinge and the modulation: tests/phase2/test_phase2_static.py).
    freeze_static: bool = False
    #: When no object moves (each passes the test below), hold every object at its constant
    #: transform and skip Phase 2's loop: its checkpoint is Phase 1's model with those
    #: transforms. No moving object exists to be changed; the Gaussians miss Phase 2's
    #: photometric iterations, which a scene without motion can get from a longer Phase 1.
    #: Not in the paper.
    skip_still_scene: bool = True
    #: An object is still when none of its Gaussians strays farther than this fraction of the
    #: scene extent from its mean D_theta position over the training times (a constant offset
    #: is not motion; it goes into the held transform, the closed-form fit of the canonical
    #: positions onto the mean ones). 1e-3 is Phase 1's static threshold
    #: (`phase1.static.position`): under a pixel at the usual framing (an image spans about the
    #: extent in a few hundred pixels), so the images cannot tell the held transform from the
    #: object's D_theta motion. The largest spread, not the mean: one Gaussian that moves keeps
    #: its object trained. (Measured: a still synthetic scene after 1000 default Phase 1
    #: iterations spreads at most 0.9e-3 of the extent about offsets of up to 3.3e-2.)
    still_position: float = ranged(1e-3, 0.0)
    #: And the closed-form rotation (Kabsch) of its Gaussians from their mean positions to
    #: those at each training time stays below this (radians): the position test alone lets a
    #: small object turn by `still_position * extent / radius`. 0.01 is Phase 1's
    #: `phase1.static.rotation`.
    still_rotation: float = ranged(0.01, 0.0)
    # Ablation switches.
    #: Ablation: false trains Phase 2 without M_phi and its terms.
    use_motion: bool = True
    #: Ablation: false drops the residual modulation m_i (every residual penalised).
    modulation: bool = True
    #: Ablation: false drops the rigid-share hinge.
    hinge: bool = True
    #: Ablation: every term from iteration 0, no warm-up (the paper's failing variant).
    simultaneous: bool = False

    def combination_problem(self) -> str | None:
        """What is wrong with these settings together (each is within its own range), or None;
        `sync4d.config.validate` calls it once all overrides are applied."""
        from sync4d.phase2.terms import TERMS  # the terms' weight and start keys

        if self.warmup_end < self.warmup_start:
            return (f"warmup_end = {self.warmup_end} is below warmup_start = "
                    f"{self.warmup_start}, so there is no warm-up; raise phase2.warmup_end")
        if self.simultaneous or not self.use_motion or self.iterations == 0:
            return None
        it = self.iterations
        if self.motion_start > it:
            return (f"motion_start = {self.motion_start} is after iterations = {it}, so M_phi "
                    "never trains; lower phase2.motion_start")
        for term in TERMS:
            weight, start = getattr(self, term.weight_key), getattr(self, term.start_key)
            if weight > 0 and start > it:
                return (f"{term.start_key} = {start} is after iterations = {it}, so "
                        f"{term.weight_key} never acts; lower phase2.{term.start_key} or set "
                        f"phase2.{term.weight_key} = 0")
        return None
