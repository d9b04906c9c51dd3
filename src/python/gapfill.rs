//! pyo3 bindings of the gap-filling core (`crate::gapfill`).

use super::error::to_py;
use crate::gapfill::{self, Combine, Criterion, Method, Options};

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

type Out<'py> = Bound<'py, PyArrayDyn<f64>>;

fn out<'py>(py: Python<'py>, data: Vec<f64>, shape: &[usize]) -> PyResult<Out<'py>> {
    PyArray1::from_vec(py, data).reshape(shape.to_vec())
}

/// Fills a `(T, D)` float64 C-contiguous array (NaN = missing) with the given method.
/// Returns `(filled (T, D), std (T, D) or None, info dict)`; the heavy work runs with the GIL
/// released.
#[pyfunction]
#[pyo3(signature = (x, method, gamma, criterion, dim, r, em_iters, paper_q, subspace_iters,
    min_complete, combine, short_gap, keep_original, want_std, memo_tol, seed, window=None))]
#[allow(clippy::too_many_arguments)]
fn gapfill_fill<'py>(
    py: Python<'py>,
    x: PyReadonlyArrayDyn<'py, f64>,
    method: &str,
    gamma: f64,
    criterion: &str,
    dim: Option<usize>,
    r: Option<f64>,
    em_iters: usize,
    paper_q: bool,
    subspace_iters: usize,
    min_complete: usize,
    combine: &str,
    short_gap: Option<usize>,
    keep_original: bool,
    want_std: bool,
    memo_tol: f64,
    seed: u64,
    window: Option<usize>,
) -> PyResult<(Out<'py>, Option<Out<'py>>, Bound<'py, PyDict>)> {
    let shape = x.shape().to_vec();
    if shape.len() != 2 {
        return Err(PyValueError::new_err(format!(
            "x must have shape (n_frames, n_coords), got {shape:?}"
        )));
    }
    let (t, d) = (shape[0], shape[1]);
    let data = x
        .as_slice()
        .map_err(|_| PyValueError::new_err("x must be C-contiguous"))?;
    let method = Method::parse(method).map_err(to_py)?;
    let criterion = match criterion {
        "energy" => Criterion::Energy,
        "singular-values" | "paper" => Criterion::SingularValues,
        _ => {
            return Err(PyValueError::new_err(format!(
                "criterion must be 'energy' or 'singular-values', got {criterion:?}"
            )))
        }
    };
    let combine = match combine {
        "none" => Combine::None,
        "residual" => Combine::Residual,
        "auto" => Combine::Auto,
        _ => {
            return Err(PyValueError::new_err(format!(
                "combine must be 'none', 'residual' or 'auto', got {combine:?}"
            )))
        }
    };
    let opts = Options {
        method,
        gamma,
        criterion,
        dim,
        r,
        em_iters,
        paper_q,
        subspace_iters,
        min_complete,
        combine,
        short_gap,
        keep_original,
        want_std,
        memo_tol,
        seed,
        window,
    };
    let res = py
        .detach(|| gapfill::fill(data, t, d, &opts))
        .map_err(to_py)?;
    let info = PyDict::new(py);
    info.set_item("dim", res.info.dim)?;
    info.set_item("r", res.info.r)?;
    info.set_item("q_trace", res.info.q_trace)?;
    info.set_item("complete_frames", res.info.complete_frames)?;
    info.set_item("iterated_subspace", res.info.iterated_subspace)?;
    info.set_item("distinct_covariances", res.info.distinct_covariances)?;
    info.set_item("short_gap", res.info.short_gap)?;
    info.set_item("em_iters", res.info.em_iters)?;
    info.set_item("low_rank", res.info.low_rank)?;
    info.set_item("windows", res.info.windows)?;
    info.set_item("window_margin", res.info.window_margin)?;
    let filled = out(py, res.x, &[t, d])?;
    let std = match res.std {
        Some(s) => Some(out(py, s, &[t, d])?),
        None => None,
    };
    Ok((filled, std, info))
}

/// The rows of a `(T, d)` float64 array as text, each value as Python's `repr`, NaN as
/// `nan_text`, joined by `sep` (one string per row; `gapfill/text_stream.py` writes TRC and
/// CSV files with it). Formatting runs with the GIL released.
#[pyfunction]
fn gapfill_format_rows(
    py: Python<'_>,
    x: PyReadonlyArrayDyn<'_, f64>,
    sep: &str,
    nan_text: &str,
) -> PyResult<Vec<String>> {
    let shape = x.shape().to_vec();
    if shape.len() != 2 {
        return Err(PyValueError::new_err(format!(
            "expected a 2-D array, got shape {shape:?}"
        )));
    }
    if shape[1] == 0 {
        return Ok(vec![String::new(); shape[0]]);
    }
    let data = x.as_slice()?.to_vec(); // C-contiguous required
    let (sep, nan_text) = (sep.to_string(), nan_text.to_string());
    Ok(py.detach(|| gapfill::io::format_rows(&data, shape[1], &sep, &nan_text)))
}

/// Adds the gap-filling functions to the native module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(gapfill_format_rows, m)?)?;
    m.add_function(wrap_pyfunction!(gapfill_fill, m)?)?;
    m.add("GAPFILL_AUTO_WINDOW", gapfill::AUTO_WINDOW)?;
    Ok(())
}
