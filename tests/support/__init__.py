"""What the tests share, by theme; every test folder imports it as `support` (pytest's
`pythonpath = ["tests"]`). No test imports another test file or conftest.py.

- `scenes`: seeded random Gaussians (raster inputs, Phase 1 models), the orbit scene rendered
  from known Gaussians, small configurations of the embedded synthetic scene.
- `cameras`: look-at poses (OpenGL camera-to-world, OpenCV world-to-camera).
- `datasets`: tiny dataset folders in each loader's layout (Blender, COLMAP, HyperNeRF,
  nerfstudio, Panoptic).
- `oracle`: the oracle Phase 1 (the synthetic scene's true motion) and an oracle Phase 2 run.
- `readme`: the README's command blocks, as a user reads them.
- `render`: running the standalone renderer `sync4d-render`, and the Python render it matches.
- `training`: stepping a trainer N times (the library's one loop is the pipeline's).
"""

from __future__ import annotations

from pathlib import Path

#: The repository.
ROOT = Path(__file__).resolve().parents[2]
#: The datasets shared beside the repository (`../shared/data`; absent in a user's clone).
SHARED_DATA = ROOT.parent / "shared" / "data"
