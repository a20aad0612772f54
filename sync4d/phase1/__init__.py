"""Phase 1 (paper Sec. 3.1, Appendix A): deformable 4D Gaussians. Canonical Gaussians
(`gaussians`) deformed by D_theta (`deform`), initialised from a point cloud or a random cube
(`init`), trained on the photometric loss (`losses`) with adaptive density control (`densify`)
by `trainer`, its settings in `config`; later phases plug into the trainer (`plugin`). Imports
only the data, the rasterizer, geometry and metrics.
"""

from sync4d.phase1.config import Phase1Config
from sync4d.phase1.deform import DeformationMLP, DeformConfig
from sync4d.phase1.densify import Densifier, DensifyConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.init import initial_model
from sync4d.phase1.trainer import Phase1Trainer

__all__ = [
    "DeformConfig",
    "DeformableGaussians",
    "DeformationMLP",
    "Densifier",
    "DensifyConfig",
    "Phase1Config",
    "Phase1Trainer",
    "initial_model",
]
