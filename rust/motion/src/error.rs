//! Errors of the motion kernels: one variant, naming the bad argument.

/// A bad input to a motion kernel.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MotionError {
    /// An argument has the wrong length or an out-of-range value.
    #[error("{arg}: {msg}")]
    InvalidArgument {
        /// The argument's name as the caller knows it (e.g. `index`, `table`).
        arg: &'static str,
        /// What is wrong.
        msg: String,
    },
}

impl MotionError {
    /// Build an [`MotionError::InvalidArgument`].
    pub fn invalid(arg: &'static str, msg: impl Into<String>) -> Self {
        MotionError::InvalidArgument {
            arg,
            msg: msg.into(),
        }
    }

    /// The name of the offending argument.
    pub fn arg(&self) -> &'static str {
        match self {
            MotionError::InvalidArgument { arg, .. } => arg,
        }
    }

    /// What is wrong with it.
    pub fn msg(&self) -> &str {
        match self {
            MotionError::InvalidArgument { msg, .. } => msg,
        }
    }
}

/// Result alias for this crate.
pub type Result<T> = std::result::Result<T, MotionError>;

/// Check that `values` has exactly `expected` entries.
pub(crate) fn check_len<T>(arg: &'static str, values: &[T], expected: usize) -> Result<()> {
    if values.len() != expected {
        return Err(MotionError::invalid(
            arg,
            format!("expected {expected} values, got {}", values.len()),
        ));
    }
    Ok(())
}
