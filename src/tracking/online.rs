//! The online filter for closed-loop experiments (issue 16, beyond the paper): one step of
//! Alg. 6 per incoming frame with parameters `Θ` learned offline, optional fixed-lag
//! smoothing over the last `lag` frames (Alg. 8 on a sliding window) and prediction ahead by a
//! given latency (the transition of [`super::filter::predict`], no measurement).
//!
//! Memory is fixed at construction: the filtered moments of the last `lag + 1` frames in a
//! ring of preallocated buffers and the filter's workspace. The smoother's gain of a frame
//! (line 4 of Alg. 8) depends on its filtered covariance only, so it is computed once, the
//! first time the fixed-lag smoother needs it, and kept in the ring with the frame: each
//! `lagged` call factorises one new `F Ṽ Fᵀ + V_z`, not `lag` of them, and without the
//! covariances (`want_cov = false`) the rest is `lag` matrix-vector products.

use super::dense::symmetrize;
use super::filter::{self, predict, FilterStats, Transition, Workspace};
use super::model::Emission;
use super::smoother::{rts_apply, rts_gain};
use super::Params;
use crate::error::{ensure_len, AcmError, Result};
use nalgebra::{DMatrix, DVector};

/// A state mean and covariance (column-major), as returned by [`OnlineTracker::lagged_window`].
pub type Moments = (Vec<f64>, Vec<f64>);

/// Frame-by-frame tracker with fixed parameters.
#[derive(Debug)]
pub struct OnlineTracker<E: Emission> {
    em: E,
    params: Params,
    gate: Option<f64>,
    relinearize: usize,
    lag: usize,
    ns: usize,
    /// Filtered means / covariances of the last `lag + 1` frames (ring; `head` = newest).
    means: Vec<Vec<f64>>,
    covs: Vec<Vec<f64>>,
    /// Per slot: the smoother gain `G_tᵀ` and `P = F Ṽ_t Fᵀ + V_z` of the frame in the slot,
    /// once computed, with that frame's index (`usize::MAX`: none yet).
    gains: Vec<Option<(DMatrix<f64>, DMatrix<f64>)>>,
    gain_frame: Vec<usize>,
    head: usize,
    /// Frames processed so far.
    frames: usize,
    ws: Workspace,
    /// The previous frame's filtered moments, copied out of the ring (the slot may be the
    /// one the step writes).
    prev: Moments,
    mask: Vec<u8>,
    weights: Vec<f64>,
    stats: FilterStats,
}

impl<E: Emission> OnlineTracker<E> {
    /// A tracker starting from the prior `(μ0, V0)` of `params` (state of size
    /// `order · n`, see [`super::Tracker::set_order`]) with fixed-lag window `lag` (0: filter
    /// only).
    ///
    /// # Errors
    /// Invalid parameters or gate; an order other than 1 or 2.
    pub fn new(
        em: E,
        params: Params,
        order: usize,
        gate: Option<f64>,
        relinearize: usize,
        lag: usize,
    ) -> Result<Self> {
        if !(1..=2).contains(&order) {
            return Err(AcmError::Invalid(format!(
                "the motion model's order must be 1 or 2, got {order}"
            )));
        }
        if let Some(g) = gate {
            if g.is_nan() || g <= 0.0 {
                return Err(AcmError::Invalid(format!("the gate must be > 0, got {g}")));
            }
        }
        let (n, n_x) = (em.n_state(), em.n_meas());
        let ns = order * n;
        params.validate(ns, n_x)?;
        let mut t = Self {
            means: vec![vec![0.0; ns]; lag + 1],
            covs: vec![vec![0.0; ns * ns]; lag + 1],
            gains: vec![None; lag + 1],
            gain_frame: vec![usize::MAX; lag + 1],
            head: 0,
            frames: 0,
            ws: Workspace::new(n, n_x),
            prev: (vec![0.0; ns], vec![0.0; ns * ns]),
            mask: vec![0; n_x],
            weights: vec![1.0; n_x],
            stats: FilterStats::default(),
            em,
            params,
            gate,
            relinearize,
            lag,
            ns,
        };
        t.ws.serial = true;
        t.reset();
        Ok(t)
    }

    /// Back to the prior `(μ0, V0)`, no frame seen.
    pub fn reset(&mut self) {
        self.head = 0;
        self.frames = 0;
        self.means[0].copy_from_slice(&self.params.mu0);
        self.covs[0].copy_from_slice(&self.params.v0);
        self.gain_frame.fill(usize::MAX);
        self.stats = FilterStats::default();
    }

    /// The emission model.
    pub fn emission(&self) -> &E {
        &self.em
    }
    /// Frames processed since the start (or [`Self::reset`]).
    pub fn frames(&self) -> usize {
        self.frames
    }
    /// The fixed-lag window.
    pub fn lag(&self) -> usize {
        self.lag
    }
    /// Counts over all frames processed.
    pub fn stats(&self) -> FilterStats {
        self.stats
    }
    /// Status of each measurement entry in the last frame (see [`filter::status`]).
    pub fn mask(&self) -> &[u8] {
        &self.mask
    }
    /// Serial mode (the default): every step runs on the calling thread alone (the sigma
    /// points and the Gram products are not handed to rayon's pool). From a thread outside
    /// the pool (e.g. Python's), each hand-off pushes a job on rayon's queue, which allocates
    /// a block every 63 jobs and wakes a worker; in serial mode a step allocates nothing at
    /// all, and the other cores stay free (e.g. for the 2D network). On the rat with 4
    /// cameras (2 vCPU) serial and parallel steps took the same time (p99 0.69-1.02 ms
    /// against 0.74-1.07 ms).
    pub fn set_serial(&mut self, serial: bool) {
        self.ws.serial = serial;
    }
    /// Whether [`Self::set_serial`] is on.
    pub fn serial(&self) -> bool {
        self.ws.serial
    }

    /// One step of Alg. 6 with the measurement `x_t` (`n_x`, NaN = missing). Once the first
    /// frames have sized the buffers, a step whose update holds without relinearisation
    /// allocates nothing in serial mode or on a worker of rayon's pool (`tests/no_alloc.rs`;
    /// see [`Self::set_serial`] for calls from other threads).
    ///
    /// # Errors
    /// Shape error; ±inf; numerical errors of the step (the state is then unchanged).
    pub fn update(&mut self, x_t: &[f64]) -> Result<()> {
        ensure_len(x_t.len(), self.em.n_meas(), "measurement (n_x)")?;
        if let Some(i) = x_t.iter().position(|v| v.is_infinite()) {
            return Err(AcmError::NonFinite(format!(
                "measurement entry {i} is infinite (use NaN for missing)"
            )));
        }
        // before the first frame the ring holds the prior in slot 0
        let prev = self.head;
        let next = if self.frames == 0 {
            0
        } else {
            (self.head + 1) % (self.lag + 1)
        };
        self.prev.0.copy_from_slice(&self.means[prev]);
        self.prev.1.copy_from_slice(&self.covs[prev]);
        let (mu_out, v_out) = (&mut self.means[next], &mut self.covs[next]);
        let mut stats = self.stats;
        filter::step(
            &self.em,
            &self.params,
            &self.prev.0,
            &self.prev.1,
            x_t,
            self.gate,
            self.relinearize,
            None,
            self.frames,
            &mut self.ws,
            &mut self.mask,
            &self.weights,
            mu_out,
            v_out,
            &mut stats,
        )?;
        self.stats = stats;
        self.head = next;
        self.gain_frame[next] = usize::MAX; // a new frame in this slot
        self.frames += 1;
        Ok(())
    }

    /// The filtered moments `(μ̃_t, Ṽ_t)` of the last frame (state of size `ns`).
    pub fn filtered(&self) -> (&[f64], &[f64]) {
        (&self.means[self.head], &self.covs[self.head])
    }

    /// The fixed-lag smoothed moments of frame `t − k` given the frames up to `t`, with
    /// `k = min(lag, frames − 1)` (Alg. 8 backwards over the window): `(mean, cov, k)`.
    ///
    /// # Errors
    /// Invalid before the first frame; numerical errors of the smoother.
    pub fn lagged(&mut self) -> Result<(Vec<f64>, Vec<f64>, usize)> {
        let (mut all, k) = self.backward(false, true)?;
        let (m, v) = all.pop().expect("one frame at least");
        Ok((m, v.expect("asked for"), k))
    }

    /// The smoothed mean of frame `t − k` as [`Self::lagged`], without its covariance: `lag`
    /// matrix-vector products once the gains are cached (one new gain per frame).
    ///
    /// # Errors
    /// As [`Self::lagged`].
    pub fn lagged_mean(&mut self) -> Result<(Vec<f64>, usize)> {
        let (mut all, k) = self.backward(false, false)?;
        Ok((all.pop().expect("one frame at least").0, k))
    }

    /// The fixed-lag smoothed moments of every frame of the window, `t − k ..= t` in time
    /// order, given the frames up to `t` (`k` as in [`Self::lagged`]): with `lag ≥ T − 1`, after
    /// the last frame, the RTS smoother (Alg. 8) of the whole recording with `Θ` fixed.
    ///
    /// # Errors
    /// As [`Self::lagged`].
    pub fn lagged_window(&mut self) -> Result<(Vec<Moments>, usize)> {
        let (all, k) = self.backward(true, true)?;
        let all = all
            .into_iter()
            .rev()
            .map(|(m, v)| (m, v.expect("asked for")))
            .collect();
        Ok((all, k))
    }

    /// Alg. 8 backwards over the window: the moments of frame `t − k` (last), and with
    /// `keep_all` those of every frame from `t` down to `t − k`; covariances if `want_cov`.
    #[allow(clippy::type_complexity)]
    fn backward(
        &mut self,
        keep_all: bool,
        want_cov: bool,
    ) -> Result<(Vec<(Vec<f64>, Option<Vec<f64>>)>, usize)> {
        if self.frames == 0 {
            return Err(AcmError::Invalid("no frame processed yet".into()));
        }
        let k = self.lag.min(self.frames - 1);
        let ns = self.ns;
        let tr = Transition::of(&self.em);
        let vz = DMatrix::from_column_slice(ns, ns, &self.params.vz);
        // the gains of the frames t − k .. t − 1 not computed yet (normally only t − 1)
        for back in 1..=k {
            let slot = (self.head + self.lag + 1 - back) % (self.lag + 1);
            let frame = self.frames - 1 - back;
            if self.gain_frame[slot] != frame {
                let vf = DMatrix::from_column_slice(ns, ns, &self.covs[slot]);
                self.gains[slot] = Some(rts_gain(&vf, &vz, tr, frame)?);
                self.gain_frame[slot] = frame;
            }
        }
        let mut ms = DVector::from_column_slice(&self.means[self.head]);
        let mut vs = want_cov.then(|| DMatrix::from_column_slice(ns, ns, &self.covs[self.head]));
        let row = |m: &DVector<f64>, v: &Option<DMatrix<f64>>| {
            (
                m.as_slice().to_vec(),
                v.as_ref().map(|v| v.as_slice().to_vec()),
            )
        };
        let mut out = Vec::with_capacity(if keep_all { k + 1 } else { 1 });
        if keep_all {
            out.push(row(&ms, &vs));
        }
        for back in 1..=k {
            let slot = (self.head + self.lag + 1 - back) % (self.lag + 1);
            let mf = DVector::from_column_slice(&self.means[slot]);
            let (gt, p) = self.gains[slot].as_ref().expect("computed above");
            let (m, v) = if let Some(vn) = vs.as_ref() {
                let vf = DMatrix::from_column_slice(ns, ns, &self.covs[slot]);
                rts_apply(&mf, &vf, gt, p, &ms, Some(vn), tr)
            } else {
                let empty = DMatrix::zeros(0, 0);
                rts_apply(&mf, &empty, gt, p, &ms, None, tr)
            };
            ms = m;
            vs = v;
            if keep_all {
                out.push(row(&ms, &vs));
            }
        }
        if !keep_all {
            out.push(row(&ms, &vs));
        }
        Ok((out, k))
    }

    /// The prediction `steps` frames ahead of the last filtered frame (no measurement):
    /// `(mean, cov)` of the state, e.g. to cover the latency of a closed loop.
    pub fn predict(&self, steps: usize) -> (Vec<f64>, Vec<f64>) {
        let tr = Transition::of(&self.em);
        let (mut m, mut v) = (self.means[self.head].clone(), self.covs[self.head].clone());
        for _ in 0..steps {
            let (pm, mut pv) = predict(&m, &v, &self.params.vz, tr);
            symmetrize(&mut pv);
            m = pm.as_slice().to_vec();
            v = pv.as_slice().to_vec();
        }
        (m, v)
    }

    /// The position part `(z, V_zz)` (`n`, `n × n`) of a state's moments.
    pub fn position(&self, mean: &[f64], cov: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let (n, ns) = (self.em.n_state(), self.ns);
        let mut c = vec![0.0; n * n];
        for j in 0..n {
            c[j * n..(j + 1) * n].copy_from_slice(&cov[j * ns..j * ns + n]);
        }
        (mean[..n].to_vec(), c)
    }
}
