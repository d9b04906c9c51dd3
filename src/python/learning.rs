//! Bindings of the skeleton-learning objective (`crate::learning`).

use super::error::to_py;
use super::{cameras_from, norm_from, out, pairs, vec3s, view, Arr, IArr, Out, PySkeleton};
use crate::learning::{LearningProblem, Mode};
use crate::limits::StateMap;
use crate::symmetry::SymmetryMap;
use pyo3::prelude::*;

/// The objective of eq. 9/12 with its exact gradient (see `learning.rs` for the layout).
#[pyclass(frozen, name = "NativeLearning", module = "acm_rs._native")]
pub(super) struct PyLearning {
    inner: LearningProblem,
}

#[pymethods]
impl PyLearning {
    #[new]
    #[pyo3(signature = (skeleton, params, labels, lower, upper, norm, bone_pairs, marker_pairs,
                        length_scale, lengths=None, offsets=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        skeleton: &PySkeleton,
        params: Arr<'_>,
        labels: Arr<'_>,
        lower: Arr<'_>,
        upper: Arr<'_>,
        norm: (f64, f64, f64, f64),
        bone_pairs: IArr<'_>,
        marker_pairs: IArr<'_>,
        length_scale: f64,
        lengths: Option<Arr<'_>>,
        offsets: Option<Arr<'_>>,
    ) -> PyResult<Self> {
        let sk = skeleton.inner.clone();
        let cams = cameras_from(&params)?;
        let (nb, nm) = (sk.n_bones(), sk.n_markers());
        let lab = view(
            &labels,
            "labels",
            &[None, Some(cams.len()), Some(nm), Some(2)],
        )?;
        let lo = view(&lower, "lower", &[Some(nb), Some(3)])?;
        let hi = view(&upper, "upper", &[Some(nb), Some(3)])?;
        let norm = norm_from(norm.0, norm.1, norm.2, norm.3)?;
        let map = StateMap::new(nb, lo, hi, &norm, false).map_err(to_py)?;
        let bp = pairs(&bone_pairs, "bone_pairs")?;
        let mp = pairs(&marker_pairs, "marker_pairs")?;
        let sym = SymmetryMap::new(nb, &bp, nm, &mp).map_err(to_py)?;
        let mode = match (&lengths, &offsets) {
            (Some(l), Some(o)) => Mode::PosesOnly {
                lengths: view(l, "lengths", &[Some(nb)])?.to_vec(),
                offsets: vec3s(view(o, "offsets", &[Some(nm), Some(3)])?),
            },
            (None, None) => Mode::Full,
            _ => {
                return Err(pyo3::exceptions::PyValueError::new_err(
                    "give both fixed lengths and offsets, or neither",
                ))
            }
        };
        let inner =
            LearningProblem::new(sk, cams, norm, map, sym, lab.to_vec(), length_scale, mode)
                .map_err(to_py)?;
        Ok(Self { inner })
    }

    #[getter]
    fn n_params(&self) -> usize {
        self.inner.n_params()
    }
    #[getter]
    fn n_skeleton_params(&self) -> usize {
        self.inner.n_skeleton_params()
    }
    #[getter]
    fn n_labels(&self) -> usize {
        self.inner.n_labels()
    }
    #[getter]
    fn n_frames(&self) -> usize {
        self.inner.n_frames()
    }

    /// `x (n_params,)` → `(value, gradient (n_params,))`, with the GIL released.
    fn value_and_grad<'py>(&self, py: Python<'py>, x: Arr<'py>) -> PyResult<(f64, Out<'py>)> {
        let xs = view(&x, "x", &[Some(self.inner.n_params())])?;
        let (f, g) = py.detach(|| self.inner.value_grad(xs)).map_err(to_py)?;
        let n = g.len();
        Ok((f, out(py, g, &[n])?))
    }

    /// Per-frame box-constrained Levenberg-Marquardt on the poses (skeleton part of `x`
    /// fixed) → `(x, iterations per frame)`, with the GIL released.
    fn fit_poses_lm<'py>(
        &self,
        py: Python<'py>,
        x: Arr<'py>,
        lower: Arr<'py>,
        upper: Arr<'py>,
        max_iter: usize,
    ) -> PyResult<(Out<'py>, Vec<usize>)> {
        let xs = view(&x, "x", &[Some(self.inner.n_params())])?;
        let lo = view(&lower, "lower", &[None])?;
        let hi = view(&upper, "upper", &[None])?;
        let (xo, it) = py
            .detach(|| self.inner.fit_poses_lm(xs, lo, hi, max_iter))
            .map_err(to_py)?;
        let n = xo.len();
        Ok((out(py, xo, &[n])?, it))
    }

    /// E-step of the elastic-segment EM (`crate::learning::elastic`): every frame's MAP state
    /// and log-stretch with their Laplace statistics → `(x, stretch (F, E), stretch_var
    /// (F, E), sq_px (F,), dof (F,), n_px (F,), iterations)`, GIL released.
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn fit_poses_elastic<'py>(
        &self,
        py: Python<'py>,
        x: Arr<'py>,
        lower: Arr<'py>,
        upper: Arr<'py>,
        stretch_bones: IArr<'py>,
        stretch_sd: Arr<'py>,
        stretch0: Arr<'py>,
        noise_px: f64,
        max_iter: usize,
    ) -> PyResult<(
        Out<'py>,
        Out<'py>,
        Out<'py>,
        Out<'py>,
        Out<'py>,
        Vec<usize>,
        Vec<usize>,
    )> {
        let xs = view(&x, "x", &[Some(self.inner.n_params())])?;
        let lo = view(&lower, "lower", &[None])?;
        let hi = view(&upper, "upper", &[None])?;
        let bones = super::tracking::bone_list(Some(&stretch_bones))?;
        let ne = bones.len();
        let f = self.inner.n_frames();
        let sd = view(&stretch_sd, "stretch_sd", &[Some(ne)])?;
        let s0 = view(&stretch0, "stretch0", &[Some(f), Some(ne)])?;
        let fit = py
            .detach(|| {
                self.inner
                    .fit_poses_elastic(xs, lo, hi, &bones, sd, s0, noise_px, max_iter)
            })
            .map_err(to_py)?;
        let n = fit.x.len();
        Ok((
            out(py, fit.x, &[n])?,
            out(py, fit.stretch, &[f, ne])?,
            out(py, fit.stretch_var, &[f, ne])?,
            out(py, fit.sq_px, &[f])?,
            out(py, fit.dof, &[f])?,
            fit.n_px,
            fit.iterations,
        ))
    }

    /// Levenberg-Marquardt on the whole problem (Schur complement over the frames, box
    /// bounds, optional Gaussian prior `w (x − c)` on the skeleton parameters) →
    /// `(x, iterations, value before, value after, message)`, GIL released. Values include
    /// the prior, divided by the number of labels.
    #[pyo3(signature = (x, lower, upper, max_iter, tol, prior_centre=None, prior_weight=None))]
    #[allow(clippy::too_many_arguments)]
    fn fit_full_lm<'py>(
        &self,
        py: Python<'py>,
        x: Arr<'py>,
        lower: Arr<'py>,
        upper: Arr<'py>,
        max_iter: usize,
        tol: f64,
        prior_centre: Option<Arr<'py>>,
        prior_weight: Option<Arr<'py>>,
    ) -> PyResult<(Out<'py>, usize, f64, f64, String)> {
        let n = self.inner.n_params();
        let nsk = self.inner.n_skeleton_params();
        let xs = view(&x, "x", &[Some(n)])?;
        let lo = view(&lower, "lower", &[Some(n)])?;
        let hi = view(&upper, "upper", &[Some(n)])?;
        let prior = match (&prior_centre, &prior_weight) {
            (Some(c), Some(w)) => Some((
                view(c, "prior_centre", &[Some(nsk)])?,
                view(w, "prior_weight", &[Some(nsk)])?,
            )),
            (None, None) => None,
            _ => {
                return Err(pyo3::exceptions::PyValueError::new_err(
                    "give both prior_centre and prior_weight, or neither",
                ))
            }
        };
        let (xo, rep) = py
            .detach(|| self.inner.fit_full_lm(xs, lo, hi, max_iter, tol, prior))
            .map_err(to_py)?;
        Ok((
            out(py, xo, &[n])?,
            rep.iterations,
            rep.initial_value,
            rep.final_value,
            rep.message,
        ))
    }

    /// `x` → diagonal of the Gauss-Newton matrix (for preconditioning), with the GIL released.
    fn gauss_newton_diagonal<'py>(&self, py: Python<'py>, x: Arr<'py>) -> PyResult<Out<'py>> {
        let xs = view(&x, "x", &[Some(self.inner.n_params())])?;
        let d = py
            .detach(|| self.inner.gauss_newton_diagonal(xs))
            .map_err(to_py)?;
        let n = d.len();
        out(py, d, &[n])
    }

    /// `x` → `(projected (F, C, M, 2), lengths (B,), offsets (M, 3), poses (F, 3 + 3B))`.
    fn residuals<'py>(
        &self,
        py: Python<'py>,
        x: Arr<'py>,
    ) -> PyResult<(Out<'py>, Out<'py>, Out<'py>, Out<'py>)> {
        let xs = view(&x, "x", &[Some(self.inner.n_params())])?;
        let res = py.detach(|| self.inner.residuals(xs)).map_err(to_py)?;
        let f = self.inner.n_frames();
        let (nb, nm) = (res.lengths.len(), res.offsets.len() / 3);
        let c = res.projected.len() / (f * nm * 2).max(1);
        let np = res.poses.len() / f.max(1);
        Ok((
            out(py, res.projected, &[f, c, nm, 2])?,
            out(py, res.lengths, &[nb])?,
            out(py, res.offsets, &[nm, 3])?,
            out(py, res.poses, &[f, np])?,
        ))
    }
}
