//! pyo3 bindings of the gap-filling core (`crate::gapfill`).

use pyo3::prelude::*;

/// Adds the gap-filling functions to the native module.
pub fn register(_m: &Bound<'_, PyModule>) -> PyResult<()> {
    Ok(())
}
