//! Bindings of the tracker (`crate::tracking`): UKF / RTS smoother / EM with the GIL released;
//! the progress callback and Ctrl-C checks run between EM iterations with the GIL held.

use super::error::to_py;
use super::{alloc, cameras_from, norm_from, out, view, Arr, IArr, Out, PySkeleton};
use crate::limits::StateMap;
use crate::tracking::{
    buffers::BufferPool, moments, EmOptions, FilterStats, OnlineTracker, Params, SkeletonEmission,
    Tracker, DEFAULT_RELINEARIZE,
};
use numpy::{PyArray1, PyArrayDyn, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::sync::Arc;

/// The tracker of one recording (skeleton emission, measurements, last posterior).
/// Large buffers handed from dropped trackers to new ones (`tracking::buffers`): give one
/// pool to the trackers of a run that builds many in turn (the streaming smoother).
#[pyclass(name = "NativeBufferPool", module = "acm_rs._native", frozen)]
pub(super) struct PyBufferPool {
    inner: Arc<BufferPool>,
}

#[pymethods]
impl PyBufferPool {
    /// A pool keeping at most `max_buffers` vectors.
    #[new]
    #[pyo3(signature = (max_buffers=4))]
    fn new(max_buffers: usize) -> Self {
        Self {
            inner: Arc::new(BufferPool::new(max_buffers)),
        }
    }
    /// Number of vectors kept now.
    fn __len__(&self) -> usize {
        self.inner.len()
    }
}

#[pyclass(name = "NativeTracker", module = "acm_rs._native")]
pub(super) struct PyTracker {
    inner: Tracker<SkeletonEmission>,
    /// A private pool (`threads > 0`), e.g. 1 thread when windows run in parallel.
    pool: Option<rayon::ThreadPool>,
    /// `(returned, stalled, final_stats)` of the last `run_em` (see `EmOutcome`).
    last_em: Option<(Option<usize>, bool, FilterStats)>,
}

/// Runs `f` inside a worker of `pool` if there is one, else of the global pool: the
/// parallel loops in `f` (sigma points, Gram products) then share work between the pool's
/// workers instead of each being injected into the pool from outside and waited for.
/// Measured on a 2,000-frame segment of the rat (2 vCPU): filter 1,750 → 2,250 frames/s.
fn in_pool<R: Send>(pool: &Option<rayon::ThreadPool>, f: impl FnOnce() -> R + Send) -> R {
    match pool {
        Some(p) => p.install(f),
        None => rayon::scope(|_| f()),
    }
}

type ParamArrays<'py> = (Arr<'py>, Arr<'py>, Arr<'py>, Arr<'py>);
/// `(params, history, converged, interrupted)` of `run_em`.
type EmReturn<'py> = (Bound<'py, PyDict>, Vec<Bound<'py, PyDict>>, bool, bool);

impl PyTracker {
    fn params(&self, p: &ParamArrays<'_>) -> PyResult<Params> {
        let n_x = crate::tracking::Emission::n_meas(self.inner.emission());
        params_from(p, self.inner.n_state(), n_x)
    }
}

/// `Θ` from numpy arrays: `mu0 (n,)`, `V0, Vz (n, n)`, `Vx_diag (n_x,)`.
fn params_from(p: &ParamArrays<'_>, n: usize, n_x: usize) -> PyResult<Params> {
    Ok(Params {
        mu0: view(&p.0, "mu0", &[Some(n)])?.to_vec(),
        v0: view(&p.1, "V0", &[Some(n), Some(n)])?.to_vec(),
        vz: view(&p.2, "Vz", &[Some(n), Some(n)])?.to_vec(),
        vx: view(&p.3, "Vx_diag", &[Some(n_x)])?.to_vec(),
    })
}

/// The skeleton emission (Alg. 4 ∘ Alg. 10) from the binding's arguments: camera parameters
/// `(C, 16)` (or `(C, 15)` without skew), joint limits `lower, upper (n_bones, 3)`, normalisation `(c_t, c_r, c_1, c_2)`.
fn emission_from(
    skeleton: &PySkeleton,
    params: &Arr<'_>,
    lower: &Arr<'_>,
    upper: &Arr<'_>,
    norm: (f64, f64, f64, f64),
    joint_limits: bool,
    stretch: &[usize],
) -> PyResult<SkeletonEmission> {
    let sk = skeleton.inner.clone();
    let cams = cameras_from(params)?;
    let nb = sk.n_bones();
    let lo = view(lower, "lower", &[Some(nb), Some(3)])?;
    let hi = view(upper, "upper", &[Some(nb), Some(3)])?;
    let norm = norm_from(norm.0, norm.1, norm.2, norm.3)?;
    let map = StateMap::new(nb, lo, hi, &norm, joint_limits)
        .and_then(|m| m.with_stretch(stretch))
        .map_err(to_py)?;
    SkeletonEmission::new(sk, cams, map, norm).map_err(to_py)
}

/// Bone indices from an optional int64 array (`None`: no bones).
pub(super) fn bone_list(bones: Option<&IArr<'_>>) -> PyResult<Vec<usize>> {
    match bones {
        None => Ok(Vec::new()),
        Some(a) => view(a, "stretch bones", &[None])?
            .iter()
            .map(|&b| {
                usize::try_from(b).map_err(|_| {
                    pyo3::exceptions::PyValueError::new_err(format!("negative bone index {b}"))
                })
            })
            .collect(),
    }
}

/// Counts of one E-step as a dict (`used`, `gated`, `invisible`, `gate_skipped_frames`).
fn stats_dict<'py>(py: Python<'py>, s: &FilterStats) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("used", s.used)?;
    d.set_item("gated", s.gated)?;
    d.set_item("invisible", s.invisible)?;
    d.set_item("gate_skipped_frames", s.gate_skipped_frames)?;
    d.set_item("relinearized_frames", s.relinearized_frames)?;
    d.set_item("relinearizations", s.relinearizations)?;
    d.set_item("log_likelihood", s.log_lik)?;
    Ok(d)
}

fn params_out<'py>(py: Python<'py>, p: Params) -> PyResult<Bound<'py, PyDict>> {
    let n = p.mu0.len();
    let n_x = p.vx.len();
    let d = PyDict::new(py);
    d.set_item("mu0", out(py, p.mu0, &[n])?)?;
    d.set_item("V0", out(py, p.v0, &[n, n])?)?;
    d.set_item("Vz", out(py, p.vz, &[n, n])?)?;
    d.set_item("Vx_diag", out(py, p.vx, &[n_x])?)?;
    Ok(d)
}

#[pymethods]
impl PyTracker {
    /// `x (T, n_cams, M, 2)` normalised pixels (eq. 11), NaN = missing.
    /// `relinearize`: maximum iterated posterior linearisations per frame (0 = the paper's
    /// single unscented update). `order`: 1 = the paper's random walk, 2 = position and
    /// velocity (the parameters `mu0, V0, Vz` then have `2 n_state` rows, position first).
    #[new]
    /// `threads`: run this tracker's work on a private pool of that many threads (0: the
    /// global pool), e.g. 1 when several trackers run in parallel.
    /// `stretch`: elastic bones whose log-stretch follows the pose entries in the state
    /// (memoryless transition; issue 28).
    /// `buffers`: a `NativeBufferPool` shared by the trackers of one run, from which this
    /// tracker takes its covariances and to which it gives them back when dropped.
    #[pyo3(signature = (skeleton, params, lower, upper, norm, joint_limits, x, relinearize=DEFAULT_RELINEARIZE, order=1, threads=0, stretch=None, buffers=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        skeleton: &PySkeleton,
        params: Arr<'_>,
        lower: Arr<'_>,
        upper: Arr<'_>,
        norm: (f64, f64, f64, f64),
        joint_limits: bool,
        x: Arr<'_>,
        relinearize: usize,
        order: usize,
        threads: usize,
        stretch: Option<IArr<'_>>,
        buffers: Option<PyRef<'_, PyBufferPool>>,
    ) -> PyResult<Self> {
        let bones = bone_list(stretch.as_ref())?;
        let em = emission_from(
            skeleton,
            &params,
            &lower,
            &upper,
            norm,
            joint_limits,
            &bones,
        )?;
        let shape = [
            None,
            Some(em.cameras.len()),
            Some(em.skeleton.n_markers()),
            Some(2),
        ];
        let xs = view(&x, "x", &shape)?.to_vec();
        let mut inner = Tracker::new(em, xs).map_err(to_py)?;
        inner.set_relinearize(relinearize);
        if let Some(b) = buffers {
            inner.set_buffer_pool(Arc::clone(&b.inner));
        }
        inner.set_order(order).map_err(to_py)?;
        let pool = if threads > 0 {
            let p = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .map_err(|e| pyo3::exceptions::PyRuntimeError::new_err(e.to_string()))?;
            Some(p)
        } else {
            None
        };
        Ok(Self {
            inner,
            pool,
            last_em: None,
        })
    }

    /// Dimension of the pose state `z` (Alg. 10).
    #[getter]
    fn n_state(&self) -> usize {
        self.inner.emission().map.n_state()
    }
    /// Rows of `mu0, V0, Vz`: `order × n_state`.
    #[getter]
    fn n_params_state(&self) -> usize {
        self.inner.n_state()
    }
    #[getter]
    fn n_frames(&self) -> usize {
        self.inner.n_frames()
    }

    /// Runs Alg. 11 then a final E-step. `callback(iteration, delta, seconds, stats_dict)` is
    /// called after every iteration with the GIL held and may return `False` to stop; Ctrl-C
    /// stops the run between iterations (the result is returned with `interrupted = True`).
    /// Returns `(params dict, history list of dicts, converged, interrupted)`.
    /// `patience`: stop after this many E-steps in a row below the best log-likelihood
    /// (`EmOptions::patience`; `None` or 0: run on). `overrelax`: growth factor `α > 1` of
    /// over-relaxed EM (`EmOptions::overrelax`; `None`: plain EM). History entries carry
    /// `step` (1: the plain step) and `rejected`.
    #[pyo3(signature = (mu0, v0, vz, vx, max_iter, tol, gate=None, callback=None, ll_tol=None, dof=None, patience=Some(crate::tracking::DEFAULT_PATIENCE), overrelax=None))]
    #[allow(clippy::too_many_arguments)]
    fn run_em<'py>(
        &mut self,
        py: Python<'py>,
        mu0: Arr<'py>,
        v0: Arr<'py>,
        vz: Arr<'py>,
        vx: Arr<'py>,
        max_iter: usize,
        tol: f64,
        gate: Option<f64>,
        callback: Option<Py<PyAny>>,
        ll_tol: Option<f64>,
        dof: Option<f64>,
        patience: Option<usize>,
        overrelax: Option<f64>,
    ) -> PyResult<EmReturn<'py>> {
        if let Some(a) = overrelax {
            if !(a.is_finite() && a > 1.0) {
                return Err(pyo3::exceptions::PyValueError::new_err(format!(
                    "overrelax must be a growth factor > 1 (or None), got {a}"
                )));
            }
        }
        let init = self.params(&(mu0, v0, vz, vx))?;
        let opts = EmOptions {
            max_iter,
            tol,
            gate,
            ll_tol,
            dof,
            patience: patience.filter(|&p| p > 0),
            overrelax,
        };
        let mut py_err: Option<PyErr> = None;
        let inner = &mut self.inner;
        let res = py.detach(|| {
            inner.run_em(init, &opts, |it| {
                Python::attach(|py| {
                    if let Err(e) = py.check_signals() {
                        py_err = Some(e);
                        return false;
                    }
                    let Some(cb) = &callback else { return true };
                    let fill = || -> PyResult<bool> {
                        let stats = stats_dict(py, &it.stats)?;
                        let r = cb.call1(py, (it.iteration, it.delta, it.seconds, stats))?;
                        Ok(r.is_none(py) || r.is_truthy(py)?)
                    };
                    match fill() {
                        Ok(go) => go,
                        Err(e) => {
                            py_err = Some(e);
                            false
                        }
                    }
                })
            })
        });
        if let Some(e) = py_err {
            // Ctrl-C: keep the results (the run ended with a final E-step) and report it in
            // `interrupted`; any other error from the callback propagates.
            if !e.is_instance_of::<pyo3::exceptions::PyKeyboardInterrupt>(py) {
                return Err(e);
            }
        }
        let outcome = res.map_err(to_py)?;
        self.last_em = Some((outcome.returned, outcome.stalled, outcome.final_stats));
        let history = outcome
            .history
            .iter()
            .map(|it| {
                let d = stats_dict(py, &it.stats)?;
                d.set_item("iteration", it.iteration)?;
                d.set_item("delta", it.delta)?;
                d.set_item("seconds", it.seconds)?;
                d.set_item("step", it.step)?;
                d.set_item("rejected", it.rejected)?;
                Ok(d)
            })
            .collect::<PyResult<Vec<_>>>()?;
        Ok((
            params_out(py, outcome.params)?,
            history,
            outcome.converged,
            outcome.interrupted,
        ))
    }

    /// What the last `run_em` returned: `{"returned_iteration": k or None, "stalled": bool,
    /// "final": stats}`, `k` the iteration whose E-step evaluated the returned parameters when
    /// they are an earlier iterate of higher marginal log-likelihood than the last one (None:
    /// the last M-step's), `stalled` whether `patience` E-steps in a row below the best ended
    /// the run, `final` the counts of the final E-step under them; None before any run.
    fn em_outcome<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some((returned, stalled, stats)) = &self.last_em else {
            return Ok(None);
        };
        let d = PyDict::new(py);
        d.set_item("returned_iteration", *returned)?;
        d.set_item("stalled", *stalled)?;
        d.set_item("final", stats_dict(py, stats)?)?;
        Ok(Some(d))
    }

    /// One E-step (filter + smoother) with the given parameters → stats dict. `smooth=False`:
    /// the filter only; `statistics=False`: without eq. 79's statistic (no M-step may follow).
    #[pyo3(signature = (mu0, v0, vz, vx, gate=None, smooth=true, statistics=true))]
    #[allow(clippy::too_many_arguments)]
    fn e_step<'py>(
        &mut self,
        py: Python<'py>,
        mu0: Arr<'py>,
        v0: Arr<'py>,
        vz: Arr<'py>,
        vx: Arr<'py>,
        gate: Option<f64>,
        smooth: bool,
        statistics: bool,
    ) -> PyResult<Bound<'py, PyDict>> {
        let p = self.params(&(mu0, v0, vz, vx))?;
        let (inner, pool) = (&mut self.inner, &self.pool);
        let s = py
            .detach(|| {
                in_pool(pool, || match (smooth, statistics) {
                    (false, _) => inner.filter(&p, gate),
                    (true, true) => inner.e_step(&p, gate),
                    (true, false) => inner.smooth(&p, gate),
                })
            })
            .map_err(to_py)?;
        stats_dict(py, &s)
    }

    /// The backward pass over the moments of the last `e_step(smooth=False)`, starting from
    /// `end=(mean (ns,), cov (ns, ns))`, the smoothed moments after the last frame as the
    /// next segment of a longer recording computed them (None: the filtered ones); only
    /// `V_z` of the parameters is used (`Tracker::smooth_filtered`).
    #[pyo3(signature = (mu0, v0, vz, vx, end=None))]
    fn smooth_filtered<'py>(
        &mut self,
        py: Python<'py>,
        mu0: Arr<'py>,
        v0: Arr<'py>,
        vz: Arr<'py>,
        vx: Arr<'py>,
        end: Option<(Arr<'py>, Arr<'py>)>,
    ) -> PyResult<()> {
        let p = self.params(&(mu0, v0, vz, vx))?;
        let ns = self.inner.n_state();
        let end = match &end {
            Some((m, c)) => Some((
                view(m, "end mean", &[Some(ns)])?.to_vec(),
                view(c, "end covariance", &[Some(ns), Some(ns)])?.to_vec(),
            )),
            None => None,
        };
        let (inner, pool) = (&mut self.inner, &self.pool);
        py.detach(|| {
            in_pool(pool, || {
                inner.smooth_filtered(&p, end.as_ref().map(|(m, c)| (m.as_slice(), c.as_slice())))
            })
        })
        .map_err(to_py)
    }

    /// The whole-state moments of the last `e_step(smooth=False)` for a spill file:
    /// `(means (T+1, ns), packed (T+1, ns (ns + 1) / 2))`, the covariances' lower triangles
    /// column by column (`Tracker::filtered_packed`).
    fn filtered_packed<'py>(&self, py: Python<'py>) -> PyResult<(Out<'py>, Out<'py>)> {
        let steps = self.inner.n_frames() + 1;
        let ns = self.inner.n_state();
        // written straight into numpy's array (its allocator takes huge pages for large
        // arrays: ~40 kB a frame of the velocity state, written once and saved)
        let packed = alloc(py, &[steps, ns * (ns + 1) / 2]);
        let m = {
            let mut w = packed.readwrite();
            let dst = w.as_slice_mut().expect("contiguous");
            let inner = &self.inner;
            py.detach(|| inner.filtered_packed_into(dst).map(<[f64]>::to_vec))
                .map_err(to_py)?
        };
        Ok((out(py, m, &[steps, ns])?, packed))
    }

    /// Restores a filter pass saved by `filtered_packed()` and `mask()` (e.g. from a spill
    /// file) so that `smooth_filtered` can follow without filtering again.
    fn load_filtered(
        &mut self,
        py: Python<'_>,
        means: Arr<'_>,
        packed: Arr<'_>,
        mask: numpy::PyReadonlyArrayDyn<'_, u8>,
    ) -> PyResult<()> {
        let (steps, ns) = (self.inner.n_frames() + 1, self.inner.n_state());
        let m = view(&means, "means", &[Some(steps), Some(ns)])?.to_vec();
        let p = view(&packed, "packed", &[Some(steps), Some(ns * (ns + 1) / 2)])?.to_vec();
        let em = self.inner.emission();
        let mask_shape = [
            Some(steps - 1),
            Some(em.cameras.len()),
            Some(em.skeleton.n_markers()),
            Some(2),
        ];
        let mk = view(&mask, "mask", &mask_shape)?.to_vec();
        let inner = &mut self.inner;
        py.detach(|| inner.load_filtered(&m, &p, &mk))
            .map_err(to_py)
    }

    /// Moments of the whole state (`ns = order · n`, position first) at row `k` of the last
    /// pass (`0..=T`; negative counts from the end): `(mean (ns,), cov (ns, ns))`; after
    /// `e_step(smooth=False)` the filtered ones (the checkpoint of a long recording).
    fn state_row<'py>(&self, py: Python<'py>, k: isize) -> PyResult<(Out<'py>, Out<'py>)> {
        let rows = self.inner.n_frames() as isize + 1;
        let idx = if k < 0 { rows + k } else { k };
        if idx < 0 {
            return Err(pyo3::exceptions::PyIndexError::new_err(format!(
                "row {k} of {rows}"
            )));
        }
        let (m, c) = self.inner.state_row(idx as usize).map_err(to_py)?;
        let ns = m.len();
        Ok((out(py, m.to_vec(), &[ns])?, out(py, c.to_vec(), &[ns, ns])?))
    }

    /// The M-step from the last E-step (Alg. 12) → params dict.
    fn m_step<'py>(
        &self,
        py: Python<'py>,
        mu0: Arr<'py>,
        v0: Arr<'py>,
        vz: Arr<'py>,
        vx: Arr<'py>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let prev = self.params(&(mu0, v0, vz, vx))?;
        let inner = &self.inner;
        let p = py.detach(|| inner.m_step(&prev)).map_err(to_py)?;
        params_out(py, p)
    }

    /// Position moments `(T+1, n)`, `(T+1, n, n)` near the posterior (e.g. another tracker's
    /// `means()`, `covs()` under the random walk) to linearise about where the prior is too
    /// broad for the unscented transform; `None` removes them.
    #[pyo3(signature = (means=None, covs=None))]
    fn set_linearization_hint(
        &mut self,
        means: Option<Arr<'_>>,
        covs: Option<Arr<'_>>,
    ) -> PyResult<()> {
        let (t, n) = (self.inner.n_frames() + 1, self.n_state());
        let hint = match (means, covs) {
            (Some(m), Some(c)) => Some((
                view(&m, "means", &[Some(t), Some(n)])?.to_vec(),
                view(&c, "covs", &[Some(t), Some(n), Some(n)])?.to_vec(),
            )),
            (None, None) => None,
            _ => {
                return Err(pyo3::exceptions::PyValueError::new_err(
                    "give both means and covs, or neither",
                ))
            }
        };
        self.inner.set_linearization_hint(hint).map_err(to_py)
    }

    /// `(T+1, n)` posterior means of the last E-step (row 0 = `z_0`).
    fn means<'py>(&self, py: Python<'py>) -> PyResult<Out<'py>> {
        let n = self.n_state();
        let a = alloc(py, &[self.inner.n_frames() + 1, n]);
        a.readwrite()
            .as_slice_mut()
            .expect("contiguous")
            .copy_from_slice(self.inner.means());
        Ok(a)
    }

    /// `(T+1, n, n)` posterior covariances of the last E-step.
    fn covs<'py>(&self, py: Python<'py>) -> PyResult<Out<'py>> {
        self.inner.require_covariances().map_err(to_py)?;
        let n = self.n_state();
        let a = alloc(py, &[self.inner.n_frames() + 1, n, n]);
        {
            let mut w = a.readwrite();
            let dst = w.as_slice_mut().expect("contiguous");
            let src = self.inner.covs();
            py.detach(|| dst.copy_from_slice(src));
        }
        Ok(a)
    }

    /// Frees the covariances of the last E-step, keeping the means and the entry statuses
    /// (`Tracker::release_covariances`): the next `e_step` allocates them again; `covs`,
    /// `posterior`, `state_row` and `m_step` raise until then.
    fn release_covariances(&mut self) {
        self.inner.release_covariances();
    }

    /// `(T, n_cams, M, 2)` status of each measurement entry in the last E-step
    /// (0 missing, 1 used, 2 gated, 3 not predictable).
    fn mask<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArrayDyn<u8>>> {
        let em = self.inner.emission();
        PyArray1::from_slice(py, self.inner.mask()).reshape(vec![
            self.inner.n_frames(),
            em.cameras.len(),
            em.skeleton.n_markers(),
            2,
        ])
    }

    /// Posterior of frames `1..T` → `(poses (T, n_pose), joints (T, J, 3), markers (T, M, 3),
    /// joints_std (T, J, 3), markers_std (T, M, 3))`.
    #[allow(clippy::type_complexity)]
    fn posterior<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(Out<'py>, Out<'py>, Out<'py>, Out<'py>, Out<'py>)> {
        self.inner.require_covariances().map_err(to_py)?;
        let em = self.inner.emission();
        let n = em.map.n_state();
        let (means, covs) = (&self.inner.means()[n..], &self.inner.covs()[n * n..]);
        let pool = &self.pool;
        let p = py
            .detach(|| in_pool(pool, || moments::posterior_poses(em, means, covs)))
            .map_err(to_py)?;
        let t = self.inner.n_frames();
        let (nj, nm, np) = (
            em.skeleton.n_joints(),
            em.skeleton.n_markers(),
            em.skeleton.n_pose(),
        );
        Ok((
            out(py, p.poses, &[t, np])?,
            out(py, p.joints, &[t, nj, 3])?,
            out(py, p.markers, &[t, nm, 3])?,
            out(py, p.joints_std, &[t, nj, 3])?,
            out(py, p.markers_std, &[t, nm, 3])?,
        ))
    }
}

/// Runs [`crate::tracking::bundle::smooth_file`] (the `acm-smooth` binary's work) on one
/// bundle with the GIL released → `(n_frames, iterations, converged, mean_reprojection_px)`.
#[pyfunction]
#[pyo3(signature = (input, output, keep_cov=true))]
pub(super) fn smooth_bundle(
    py: Python<'_>,
    input: std::path::PathBuf,
    output: std::path::PathBuf,
    keep_cov: bool,
) -> PyResult<(usize, usize, bool, f64)> {
    let s = py
        .detach(|| crate::tracking::bundle::smooth_file(&input, &output, keep_cov, |_| true))
        .map_err(to_py)?;
    Ok((
        s.n_frames,
        s.outcome.history.len(),
        s.outcome.converged,
        s.mean_reprojection_px,
    ))
}

/// [`crate::tracking::extrapolate`]: the parameters `eta` times as far from `a` as the
/// M-step's `b` (over-relaxed EM; each a tuple `(mu0 (n,), V0 (n, n), Vz (n, n), Vx_diag
/// (n_x,))`) → a tuple of the same, or `None` where a covariance is not positive definite.
#[pyfunction]
pub(super) fn extrapolate_params<'py>(
    py: Python<'py>,
    a: ParamArrays<'py>,
    b: ParamArrays<'py>,
    eta: f64,
) -> PyResult<Option<(Out<'py>, Out<'py>, Out<'py>, Out<'py>)>> {
    let n = view(&a.0, "mu0", &[None])?.len();
    let n_x = view(&a.3, "Vx_diag", &[None])?.len();
    let (pa, pb) = (params_from(&a, n, n_x)?, params_from(&b, n, n_x)?);
    if !eta.is_finite() {
        return Err(pyo3::exceptions::PyValueError::new_err(format!(
            "eta must be finite, got {eta}"
        )));
    }
    let Some(p) = py.detach(|| crate::tracking::extrapolate(&pa, &pb, eta)) else {
        return Ok(None);
    };
    Ok(Some((
        out(py, p.mu0, &[n])?,
        out(py, p.v0, &[n, n])?,
        out(py, p.vz, &[n, n])?,
        out(py, p.vx, &[n_x])?,
    )))
}

/// The online tracker of one live recording (issue 16): `update` per frame, fixed-lag and
/// predicted poses.
#[pyclass(name = "NativeOnlineTracker", module = "acm_rs._native")]
pub(super) struct PyOnlineTracker {
    inner: OnlineTracker<SkeletonEmission>,
    n_cams: usize,
}

impl PyOnlineTracker {
    /// Joints and their posterior SD `((J, 3), (J, 3))` of state moments.
    fn pose<'py>(
        &self,
        py: Python<'py>,
        mean: &[f64],
        cov: &[f64],
    ) -> PyResult<(Out<'py>, Out<'py>)> {
        let (z, c) = self.inner.position(mean, cov);
        let em = self.inner.emission();
        let p = py
            .detach(|| moments::posterior_poses(em, &z, &c))
            .map_err(to_py)?;
        let nj = em.skeleton.n_joints();
        Ok((
            out(py, p.joints, &[nj, 3])?,
            out(py, p.joints_std, &[nj, 3])?,
        ))
    }
}

#[pymethods]
impl PyOnlineTracker {
    /// Parameters `mu0, v0, vz` of the state of size `order × n_state`, `vx` the diagonal.
    #[new]
    #[pyo3(signature = (skeleton, params, lower, upper, norm, joint_limits, mu0, v0, vz, vx, order=1, gate=None, relinearize=DEFAULT_RELINEARIZE, lag=0, serial=true))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        skeleton: &PySkeleton,
        params: Arr<'_>,
        lower: Arr<'_>,
        upper: Arr<'_>,
        norm: (f64, f64, f64, f64),
        joint_limits: bool,
        mu0: Arr<'_>,
        v0: Arr<'_>,
        vz: Arr<'_>,
        vx: Arr<'_>,
        order: usize,
        gate: Option<f64>,
        relinearize: usize,
        lag: usize,
        serial: bool,
    ) -> PyResult<Self> {
        let em = emission_from(skeleton, &params, &lower, &upper, norm, joint_limits, &[])?;
        let n_cams = em.cameras.len();
        let ns = order * em.map.n_state();
        let p = params_from(
            &(mu0, v0, vz, vx),
            ns,
            crate::tracking::Emission::n_meas(&em),
        )?;
        let mut inner = OnlineTracker::new(em, p, order, gate, relinearize, lag).map_err(to_py)?;
        inner.set_serial(serial);
        Ok(Self { inner, n_cams })
    }

    /// One frame `x (n_cams, M, 2)` in normalised pixels (NaN = missing); the GIL is
    /// released during the step (serial: on this thread alone; else inside rayon's pool).
    fn update(&mut self, py: Python<'_>, x: Arr<'_>) -> PyResult<()> {
        let m = self.inner.emission().skeleton.n_markers();
        let xs = view(&x, "x", &[Some(self.n_cams), Some(m), Some(2)])?;
        let inner = &mut self.inner;
        if inner.serial() {
            py.detach(|| inner.update(xs)).map_err(to_py)
        } else {
            py.detach(|| rayon::scope(|_| inner.update(xs)))
                .map_err(to_py)
        }
    }

    /// Whether every step runs on the calling thread alone.
    #[getter]
    fn serial(&self) -> bool {
        self.inner.serial()
    }

    /// Joints and SD of the last filtered frame.
    fn filtered_pose<'py>(&self, py: Python<'py>) -> PyResult<(Out<'py>, Out<'py>)> {
        let (m, c) = self.inner.filtered();
        self.pose(py, m, c)
    }

    /// Joints and SD of frame `t − k` smoothed with the frames up to `t`, and `k`.
    fn lagged_pose<'py>(&mut self, py: Python<'py>) -> PyResult<(Out<'py>, Out<'py>, usize)> {
        let inner = &mut self.inner;
        let (m, c, k) = py.detach(|| inner.lagged()).map_err(to_py)?;
        let (j, s) = self.pose(py, &m, &c)?;
        Ok((j, s, k))
    }

    /// Joints and SD of every frame `t − k ..= t` smoothed with the frames up to `t` (lists in
    /// time order), and `k`.
    #[allow(clippy::type_complexity)]
    fn lagged_window_poses<'py>(
        &mut self,
        py: Python<'py>,
    ) -> PyResult<(Vec<Out<'py>>, Vec<Out<'py>>, usize)> {
        let inner = &mut self.inner;
        let (win, k) = py.detach(|| inner.lagged_window()).map_err(to_py)?;
        let (mut js, mut ss) = (Vec::with_capacity(win.len()), Vec::with_capacity(win.len()));
        for (m, c) in &win {
            let (j, s) = self.pose(py, m, c)?;
            js.push(j);
            ss.push(s);
        }
        Ok((js, ss, k))
    }

    /// Joints and SD predicted `steps` frames after the last filtered frame.
    fn predicted_pose<'py>(&self, py: Python<'py>, steps: usize) -> PyResult<(Out<'py>, Out<'py>)> {
        let (m, c) = self.inner.predict(steps);
        self.pose(py, &m, &c)
    }

    /// Back to the prior, no frame seen.
    fn reset(&mut self) {
        self.inner.reset();
    }

    /// Frames processed.
    #[getter]
    fn frames(&self) -> usize {
        self.inner.frames()
    }

    /// Counts over the frames processed (`used`, `gated`, ...).
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        stats_dict(py, &self.inner.stats())
    }
}
