//! Bindings of the calibration objective (`crate::calibration`, ACM supp. eq. 7).

use super::error::to_py;
use super::{alloc, view, Arr, Out};
use crate::calibration::{CalibrationProblem, N_CAM_PARAMS, N_VIEW_PARAMS};
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

/// Eq. 7 residuals and exact CSR Jacobian for a fixed set of detections (layout in
/// `src/calibration.rs`).
#[pyclass(frozen, name = "NativeCalibration", module = "acm_rs._native")]
pub(super) struct PyCalibration {
    inner: CalibrationProblem,
}

#[pymethods]
impl PyCalibration {
    /// `board (P, 3)`, `corners (C, F, P, 2)` with NaN = not detected, `params0 (13 C + 6 F,)`,
    /// `fixed (13 C + 6 F,)` bool.
    #[new]
    fn new(
        board: Arr<'_>,
        corners: Arr<'_>,
        reference: usize,
        params0: Arr<'_>,
        fixed: PyReadonlyArrayDyn<'_, bool>,
    ) -> PyResult<Self> {
        let b = view(&board, "board_points", &[None, Some(3)])?;
        let np = b.len() / 3;
        let shape = corners.shape().to_vec();
        let c = view(&corners, "corners", &[None, None, Some(np), Some(2)])?;
        let (nc, nf) = (shape[0], shape[1]);
        let n_full = N_CAM_PARAMS * nc + N_VIEW_PARAMS * nf;
        let p = view(&params0, "params0", &[Some(n_full)])?;
        let f = view(&fixed, "fixed", &[Some(n_full)])?;
        let inner = CalibrationProblem::new(nc, nf, b, c, reference, p, f).map_err(to_py)?;
        Ok(Self { inner })
    }

    #[getter]
    fn n_free(&self) -> usize {
        self.inner.n_free()
    }
    #[getter]
    fn n_full(&self) -> usize {
        self.inner.n_full()
    }
    #[getter]
    fn n_observations(&self) -> usize {
        self.inner.n_observations()
    }
    #[getter]
    fn nnz(&self) -> usize {
        self.inner.nnz()
    }
    /// Full-layout indices of the free parameters.
    #[getter]
    fn free_indices<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        let v = self
            .inner
            .free_indices()
            .iter()
            .map(|&i| i as i64)
            .collect();
        PyArray1::from_vec(py, v)
    }
    /// Flat `(cam, frame, point)` index of each observation.
    #[getter]
    fn observation_index<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        let v = self
            .inner
            .observation_index()
            .iter()
            .map(|&i| i as i64)
            .collect();
        PyArray1::from_vec(py, v)
    }
    /// CSR row pointer (int32).
    #[getter]
    fn indptr<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i32>> {
        PyArray1::from_slice(py, self.inner.indptr())
    }
    /// CSR column indices (int32, sorted per row).
    #[getter]
    fn indices<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i32>> {
        PyArray1::from_slice(py, self.inner.indices())
    }
    /// Free parameters `(n_free,)` → full parameter vector `(n_full,)`.
    fn full_params<'py>(&self, py: Python<'py>, x: Arr<'py>) -> PyResult<Out<'py>> {
        let s = view(&x, "x", &[Some(self.inner.n_free())])?;
        let v = self.inner.full_params(s).map_err(to_py)?;
        let n = v.len();
        super::out(py, v, &[n])
    }
    /// `x (n_free,)` → `(residuals (2 n_obs,) px, number of detections behind a camera)`.
    fn residuals<'py>(&self, py: Python<'py>, x: Arr<'py>) -> PyResult<(Out<'py>, usize)> {
        let s = view(&x, "x", &[Some(self.inner.n_free())])?;
        let r = alloc(py, &[2 * self.inner.n_observations()]);
        let behind = {
            let mut w = r.readwrite();
            let o = w.as_slice_mut()?;
            py.detach(|| self.inner.residuals_into(s, o))
                .map_err(to_py)?
        };
        Ok((r, behind))
    }
    /// `x (n_free,)` → CSR values `(nnz,)` of the exact Jacobian for `indptr`/`indices`.
    fn jacobian_data<'py>(&self, py: Python<'py>, x: Arr<'py>) -> PyResult<Out<'py>> {
        let s = view(&x, "x", &[Some(self.inner.n_free())])?;
        let d = alloc(py, &[self.inner.nnz()]);
        {
            let mut w = d.readwrite();
            let o = w.as_slice_mut()?;
            py.detach(|| self.inner.jacobian_into(s, o))
                .map_err(to_py)?;
        }
        Ok(d)
    }
}
