//! sync4d-motion: CPU kernels of the node motion model (`sync4d/phase1/nodes.py`).
//!
//! [`blend`]: the fused node-weighted sum of a Gaussian's K nodes' table rows, the weights a
//! softmax of `-|x0 - p|^2 / (2 r^2)` over those nodes, and its exact backward. Parallel over
//! Gaussians with rayon in the calling pool; results do not depend on the pool's size.
//!
//! [`epilogue`]: the linear blend's per-Gaussian epilogue (the blended affine map, rotation
//! and log-scale offset applied to the canonical mean, quaternion and scales) and its exact
//! backward.
//!
//! The crate knows nothing of Python: inputs are flat row-major slices and every bad input is a
//! [`MotionError`] naming the argument.

pub mod blend;
pub mod epilogue;
pub mod error;

pub use blend::{
    node_weighted_sum_backward, node_weighted_sum_forward, NodeBlend, NodeBlendGradsMut, NodeIndex,
};
pub use epilogue::{
    linear_epilogue_backward, linear_epilogue_forward, LinearEpilogue, LinearEpilogueGradsMut,
    LinearEpilogueOut, LINEAR_COLUMNS,
};
pub use error::{MotionError, Result};
pub use sync4d_scalar::Real;
