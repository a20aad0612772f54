"""Phase 2 (paper Sec. 3.2-3.4, Appendices A and C): per-object motion decomposition during
training, on a Phase 1 model. Object labels (`assign`), the shared motion M_phi (`motion`), the
paper's regularisers as loss-term objects (`terms`), the trainer that sums them (`trainer`),
the photometric refinement of M_phi's start (`refine`, not in the paper) and the diagnostics
and motion export (`diagnostics`). Imports Phase 1 and what Phase 1 imports, nothing above.
"""

from sync4d.phase2.assign import AssignConfig, Assignment
from sync4d.phase2.motion import MotionConfig, ObjectMotion
from sync4d.phase2.trainer import Phase2Config, Phase2Trainer

__all__ = [
    "AssignConfig",
    "Assignment",
    "MotionConfig",
    "ObjectMotion",
    "Phase2Config",
    "Phase2Trainer",
]
