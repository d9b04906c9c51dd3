//! The one error type of the pure-Rust core.
//!
//! The Python binding layer (`src/python/`) maps every variant to a Python exception in one
//! place; nothing in the core panics on user-reachable input.

use thiserror::Error;

/// Errors raised by the geometry, kinematics and estimation code.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum AcmError {
    /// An input array has the wrong number of elements or the wrong shape.
    #[error("shape error: {0}")]
    Shape(String),
    /// An input contains NaN or infinity where a finite number is required.
    #[error("non-finite input: {0}")]
    NonFinite(String),
    /// An input is finite and well-shaped but not valid (e.g. a non-tree skeleton, an unknown
    /// name, a rotation matrix that is not orthonormal, bounds with lower > upper).
    #[error("invalid input: {0}")]
    Invalid(String),
    /// A numerical failure (e.g. a covariance that is not positive definite).
    #[error("numerical error: {0}")]
    Numerical(String),
}

/// Shorthand for results of the core.
pub type Result<T> = std::result::Result<T, AcmError>;

/// Returns an [`AcmError::NonFinite`] naming `what` if any value is NaN or infinite.
pub fn ensure_finite(values: &[f64], what: &str) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(AcmError::NonFinite(format!(
            "{what} contains a non-finite value ({}) at flat index {i}",
            values[i]
        ))),
    }
}

/// Returns an [`AcmError::Shape`] unless `len == expected`.
pub fn ensure_len(len: usize, expected: usize, what: &str) -> Result<()> {
    if len == expected {
        Ok(())
    } else {
        Err(AcmError::Shape(format!(
            "{what} has {len} elements, expected {expected}"
        )))
    }
}
