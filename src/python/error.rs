//! The one place where core errors become Python exceptions.

use crate::error::AcmError;
use pyo3::exceptions::{PyArithmeticError, PyValueError};
use pyo3::PyErr;

pyo3::create_exception!(
    acm_rs,
    AcmNumericalError,
    PyArithmeticError,
    "A numerical failure, e.g. a covariance that is not positive definite."
);

/// Maps an [`AcmError`] to a Python exception: input errors → `ValueError`, numerical
/// failures → `AcmNumericalError` (a subclass of `ArithmeticError`).
pub fn to_py(e: AcmError) -> PyErr {
    match e {
        AcmError::Numerical(_) => AcmNumericalError::new_err(e.to_string()),
        AcmError::Shape(_) | AcmError::NonFinite(_) | AcmError::Invalid(_) => {
            PyValueError::new_err(e.to_string())
        }
    }
}
