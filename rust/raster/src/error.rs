//! Errors returned by the rasterizer: every bad input names the argument and the problem.

/// Error raised for invalid rasterizer input. `arg` names the offending argument.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RasterError {
    /// An argument has the wrong length, a non-finite value, or an out-of-range value.
    #[error("{arg}: {msg}")]
    InvalidArgument {
        /// The argument's name as the caller knows it (e.g. `means`, `viewmat`).
        arg: &'static str,
        /// What is wrong and, where possible, what to do.
        msg: String,
    },
}

impl RasterError {
    /// Build an [`RasterError::InvalidArgument`].
    pub fn invalid(arg: &'static str, msg: impl Into<String>) -> Self {
        RasterError::InvalidArgument {
            arg,
            msg: msg.into(),
        }
    }

    /// The name of the offending argument.
    pub fn arg(&self) -> &'static str {
        match self {
            RasterError::InvalidArgument { arg, .. } => arg,
        }
    }
}

/// Result alias for this crate.
pub type Result<T> = std::result::Result<T, RasterError>;

/// Check that `values` has exactly `expected` entries.
pub fn check_len<T>(arg: &'static str, values: &[T], expected: usize) -> Result<()> {
    if values.len() != expected {
        return Err(RasterError::invalid(
            arg,
            format!("expected {expected} values, got {}", values.len()),
        ));
    }
    Ok(())
}

/// Check that every value is finite; report the first offending index.
pub fn check_finite<F: num_traits::Float>(arg: &'static str, values: &[F]) -> Result<()> {
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(RasterError::invalid(
            arg,
            format!("non-finite value (NaN or inf) at flat index {i}"),
        ));
    }
    Ok(())
}
