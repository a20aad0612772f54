"""Phase 2 (paper Sec. 3.2-3.4, Appendices A and C): per-object motion decomposition during
training, on a Phase 1 model. Its settings (`config`), object labels (`assign`), the shared
motion M_phi (`motion`), the paper's regularisers as loss-term objects (`terms`), the motion
strategy that plugs all of it into Phase 1's trainer (`strategy`), the builder that makes that
trainer and starts M_phi (`trainer`), the photometric refinement of M_phi's start (`refine`,
not in the paper) and the Appendix C diagnostics (`diagnostics`). Imports Phase 1 and what
Phase 1 imports, nothing above.
"""

from sync4d.phase2.assign import AssignConfig, Assignment
from sync4d.phase2.config import Phase2Config
from sync4d.phase2.motion import MotionConfig, ObjectMotion
from sync4d.phase2.strategy import MotionStrategy
from sync4d.phase2.trainer import phase2_from_state, phase2_trainer

__all__ = [
    "AssignConfig",
    "Assignment",
    "MotionConfig",
    "MotionStrategy",
    "ObjectMotion",
    "Phase2Config",
    "phase2_from_state",
    "phase2_trainer",
]
