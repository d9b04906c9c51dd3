//! Probabilistic pose estimation (ACM supp. sec. 4): the unscented Kalman filter (Alg. 5-7),
//! the unscented RTS smoother (Alg. 8-9) and expectation maximisation (Alg. 11-13) for the
//! state-space model `z_t = z_{t-1} + ε_z`, `x_t = g(z_t) + ε_x` (eqs. 49-50).
//!
//! | module | paper |
//! |---|---|
//! | [`model`] | Alg. 4 + Alg. 10 (emission `g`), eq. 50 |
//! | [`filter`] | Alg. 5-7 (UKF, missing measurements), innovation gate |
//! | [`smoother`] | Alg. 8-9 (RTS), eqs. 58-65/79 (transition statistics) |
//! | [`mstep`] | Alg. 12-13, eqs. 77-87 |
//! | [`moments`] | posterior of joints and markers (unscented transform of FK) |
//! | [`online`] | frame-by-frame filter, fixed-lag smoother and prediction (beyond the paper) |
//! | [`bundle`] | NPZ bundles of the `acm-smooth` binary |
//!
//! Memory: the E-step keeps `(T+1)` means and covariances (`8 n² (T+1)` bytes: 2 GB for the
//! rat's `n = 50` and `T = 10⁵`) and one status byte per measurement entry.

pub mod buffers;
pub mod bundle;
pub mod dense;
pub mod filter;
pub mod model;
pub mod moments;
pub mod mstep;
pub mod online;
pub mod smoother;
#[cfg(test)]
mod tests;

use crate::error::{ensure_len, AcmError, Result};
use buffers::BufferPool;
pub use filter::{status, FilterStats};
pub use model::{Emission, LinearEmission, SkeletonEmission};
pub use mstep::relative_change;
pub use online::OnlineTracker;
use std::sync::Arc;
use std::time::Instant;

/// Model parameters `Θ = {μ0, V0, V_z, V_x}` (sec. 4.1); `V_x` is diagonal.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// Mean of `z_0` (`n`).
    pub mu0: Vec<f64>,
    /// Covariance of `z_0` (`n × n`).
    pub v0: Vec<f64>,
    /// Transition noise covariance (`n × n`).
    pub vz: Vec<f64>,
    /// Diagonal of the measurement noise covariance (`n_x`).
    pub vx: Vec<f64>,
}

impl Params {
    /// The initialisation of sec. 4.7: `V0 = V_z = V_x = noise · I` around `mu0`.
    pub fn initial(mu0: Vec<f64>, n_x: usize, noise: f64) -> Self {
        let n = mu0.len();
        let mut eye = vec![0.0; n * n];
        for i in 0..n {
            eye[i * n + i] = noise;
        }
        Self {
            mu0,
            v0: eye.clone(),
            vz: eye,
            vx: vec![noise; n_x],
        }
    }

    /// Checks lengths and finiteness, and that `V_x > 0` (the covariances are checked by
    /// their Cholesky factorisation when used).
    ///
    /// # Errors
    /// Shape, non-finite or invalid errors naming the parameter.
    pub fn validate(&self, n: usize, n_x: usize) -> Result<()> {
        ensure_len(self.mu0.len(), n, "mu0")?;
        ensure_len(self.v0.len(), n * n, "V0 (n, n)")?;
        ensure_len(self.vz.len(), n * n, "V_z (n, n)")?;
        ensure_len(self.vx.len(), n_x, "diag(V_x)")?;
        for (v, name) in [
            (&self.mu0, "mu0"),
            (&self.v0, "V0"),
            (&self.vz, "V_z"),
            (&self.vx, "V_x"),
        ] {
            crate::error::ensure_finite(v, name)?;
        }
        if let Some(j) = self.vx.iter().position(|&v| v <= 0.0) {
            return Err(AcmError::Invalid(format!(
                "V_x must be positive, entry {j} is {}",
                self.vx[j]
            )));
        }
        Ok(())
    }
}

/// The log-likelihood stop of [`Tracker::run_em`]: the marginal log-likelihood changed by less
/// than `tol` nats per used measurement entry in each of the last two iterations. One small
/// change is not enough: the unscented E-step's log-likelihood is noisy, and on real rat
/// motion a single step of +2 nats (of 276,000, 68,590 entries) came before further gains of
/// 2,000 nats.
/// With over-relaxation ([`EmOptions::overrelax`]) the last change must be a plain EM step's:
/// the change after an over-relaxed step says little about convergence (past the maximum
/// along its direction it gains ~0 although plain EM would still gain; on 100,000 frames a
/// stop on it ended the windows' velocity EM after 4 iterations, joints 6 % worse). The change
/// before it may be an over-relaxed step's of factor `η`, compared with `η · tol` (to first
/// order `η` times a plain step's change); [`overrelaxed_settled`] makes the step after such
/// a small change a plain one. Rejected steps ([`Iteration::rejected`]) do not count.
pub(crate) fn ll_settled(history: &[Iteration], tol: f64) -> bool {
    let held: Vec<&Iteration> = history.iter().filter(|it| !it.rejected).collect();
    let n = held.len();
    if n < 3 || held[n - 1].step > 1.0 {
        return false;
    }
    let small = |a: &Iteration, b: &Iteration| {
        (b.stats.log_lik - a.stats.log_lik).abs()
            < b.step.max(1.0) * tol * b.stats.used.max(1) as f64
    };
    small(held[n - 3], held[n - 2]) && small(held[n - 2], held[n - 1])
}

/// Whether the last kept E-step, an over-relaxed one of factor `η`, changed the
/// log-likelihood by less than `η · tol` nats per used entry (to first order what a plain
/// step below `tol` would give): then [`Tracker::run_em`] takes the next step plain, whose
/// change [`ll_settled`] can count.
pub(crate) fn overrelaxed_settled(history: &[Iteration], tol: f64) -> bool {
    let mut held = history.iter().rev().filter(|it| !it.rejected);
    match (held.next(), held.next()) {
        (Some(b), Some(a)) if b.step > 1.0 => {
            (b.stats.log_lik - a.stats.log_lik).abs() < b.step * tol * b.stats.used.max(1) as f64
        }
        _ => false,
    }
}

/// The parameters `η` times as far from `from` as the M-step's `to` (over-relaxed EM,
/// [`EmOptions::overrelax`]): `μ0` on the straight line, the covariances `V0` and `V_z` on
/// the geodesic of positive-definite matrices, `A^½ (A^-½ B A^-½)^η A^½` (it stays
/// positive definite for any `η`, and keeps a block structure that `A` and `B` share), the
/// diagonal `V_x` as `a^(1-η) b^η`. `None` when a covariance is not positive definite or the
/// result is not finite (then the plain step is taken).
pub fn extrapolate(from: &Params, to: &Params, eta: f64) -> Option<Params> {
    fn geodesic(a: &[f64], b: &[f64], eta: f64) -> Option<Vec<f64>> {
        let n = (a.len() as f64).sqrt().round() as usize;
        if n * n != a.len() || b.len() != a.len() {
            return None;
        }
        let sym = |m: &[f64]| {
            nalgebra::DMatrix::from_fn(n, n, |i, j| 0.5 * (m[i * n + j] + m[j * n + i]))
        };
        let ea = nalgebra::SymmetricEigen::new(sym(a));
        let top = ea.eigenvalues.max();
        if top.is_nan() || top <= 0.0 || ea.eigenvalues.min() <= top * 1e-14 {
            return None;
        }
        let scale = |p: f64| {
            let d = ea.eigenvalues.map(|w| w.powf(p));
            &ea.eigenvectors * nalgebra::DMatrix::from_diagonal(&d) * ea.eigenvectors.transpose()
        };
        let (ah, aih) = (scale(0.5), scale(-0.5));
        let c = &aih * sym(b) * &aih;
        let ec = nalgebra::SymmetricEigen::new(0.5 * (&c + c.transpose()));
        if ec.eigenvalues.min() <= 0.0 {
            return None;
        }
        let d = ec.eigenvalues.map(|w| w.powf(eta));
        let ce =
            &ec.eigenvectors * nalgebra::DMatrix::from_diagonal(&d) * ec.eigenvectors.transpose();
        let r = &ah * ce * &ah;
        let out: Vec<f64> = (0..n * n)
            .map(|k| 0.5 * (r[(k / n, k % n)] + r[(k % n, k / n)]))
            .collect();
        out.iter().all(|v| v.is_finite()).then_some(out)
    }
    if from.mu0.len() != to.mu0.len() || from.vx.len() != to.vx.len() {
        return None;
    }
    let mu0: Vec<f64> = from
        .mu0
        .iter()
        .zip(&to.mu0)
        .map(|(a, b)| a + eta * (b - a))
        .collect();
    let mut vx = Vec::with_capacity(from.vx.len());
    for (&a, &b) in from.vx.iter().zip(&to.vx) {
        if !(a > 0.0 && b > 0.0) {
            return None;
        }
        vx.push(a.powf(1.0 - eta) * b.powf(eta));
    }
    let p = Params {
        mu0,
        v0: geodesic(&from.v0, &to.v0, eta)?,
        vz: geodesic(&from.vz, &to.vz, eta)?,
        vx,
    };
    (p.mu0.iter().chain(&p.vx).all(|v| v.is_finite())).then_some(p)
}

/// Options of the EM run (Alg. 11).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EmOptions {
    /// Maximum number of EM iterations (the authors' `iter_max`, 100).
    pub max_iter: usize,
    /// Convergence threshold `ε_tol` of eq. 87 (0.05).
    pub tol: f64,
    /// Innovation gate (squared Mahalanobis distance per image point), or `None`.
    pub gate: Option<f64>,
    /// Degrees of freedom of a Student-t measurement model per image point (`None`:
    /// Gaussian, the paper's model). Outliers get small weights and do not inflate `V_x`.
    pub dof: Option<f64>,
    /// Stop instead on the marginal log-likelihood: when it changes by less than this many
    /// nats per used measurement entry in each of two successive iterations
    /// ([`ll_settled`]; `None`: Alg. 13 with `tol`).
    pub ll_tol: Option<f64>,
    /// Stop when this many successive E-steps have not raised the marginal log-likelihood
    /// above its best so far (`None`: run on). The unscented E-step does not guarantee a rise:
    /// on a free 87-entry skeleton the velocity model's EM fell from its first iteration on and
    /// ran its remaining 89 iterations to no use, while on real rat motion with a 40-frame gap
    /// the random walk's dipped for 5 iterations and then rose by 1,600 nats
    /// ([`DEFAULT_PATIENCE`] = 10 keeps that; docs/tracking.md, "What is guaranteed").
    pub patience: Option<usize>,
    /// Adaptive over-relaxation of the EM step (Salakhutdinov & Roweis 2003; beyond the
    /// paper): `Some(α)` moves the parameters `η` times as far as the M-step along its
    /// direction ([`extrapolate`]), `η` growing by `α` (up to [`MAX_OVERRELAX`]) while the
    /// extrapolated parameters score at least the log-likelihood of the point they came
    /// from, and falling back to the plain M-step (one E-step more, `η = 1`) when they
    /// do not. `None`: plain EM (Alg. 11).
    pub overrelax: Option<f64>,
}

/// Default of [`EmOptions::patience`].
pub const DEFAULT_PATIENCE: usize = 10;

/// Default growth `α` of [`EmOptions::overrelax`] (measured on real rat motion,
/// docs/tracking.md "Over-relaxed EM").
pub const DEFAULT_OVERRELAX: f64 = 1.5;

/// Largest step factor `η` of [`EmOptions::overrelax`].
pub const MAX_OVERRELAX: f64 = 8.0;

impl Default for EmOptions {
    fn default() -> Self {
        Self {
            max_iter: 100,
            tol: 0.05,
            gate: None,
            ll_tol: None,
            dof: None,
            patience: Some(DEFAULT_PATIENCE),
            overrelax: None,
        }
    }
}

/// One EM iteration, for progress reports and the history.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Iteration {
    /// 1-based iteration number.
    pub iteration: usize,
    /// Mean relative parameter change of Alg. 13.
    pub delta: f64,
    /// Wall time of the iteration (E-step + M-step), seconds.
    pub seconds: f64,
    /// Counts of the E-step.
    pub stats: FilterStats,
    /// How far the evaluated parameters were moved along the M-step's direction: 1 for the
    /// plain EM step, `η > 1` for an over-relaxed one ([`EmOptions::overrelax`]).
    pub step: f64,
    /// Whether the E-step evaluated an over-relaxed step that scored below the point it
    /// came from (no M-step followed: the next E-step evaluates the plain step).
    pub rejected: bool,
}

/// Result of [`Tracker::run_em`].
#[derive(Debug, Clone)]
pub struct EmOutcome {
    /// The learned parameters: those of the highest marginal log-likelihood among the
    /// parameters evaluated (see [`Self::returned`]).
    pub params: Params,
    /// Per-iteration record.
    pub history: Vec<Iteration>,
    /// Whether `Δ < tol` was reached (false if `max_iter` or the callback stopped it).
    pub converged: bool,
    /// Whether the callback asked to stop.
    pub interrupted: bool,
    /// Which parameters [`Self::params`] are: `Some(k)` = those evaluated by the E-step of
    /// iteration `k` (1-based; the parameters before its M-step), because their marginal
    /// log-likelihood was higher than the last parameters'; `None` = the last M-step's.
    pub returned: Option<usize>,
    /// Whether the run stopped because [`EmOptions::patience`] E-steps in a row stayed below
    /// the best log-likelihood (then [`Self::params`] are the best ones and `converged` is
    /// false).
    pub stalled: bool,
    /// Counts of the final E-step, under the returned parameters (its `log_lik` is theirs).
    pub final_stats: FilterStats,
}

/// The E-step machinery for one recording: owns the emission model, the measurements and the
/// posterior moments of the last E-step.
#[derive(Debug, Clone)]
pub struct Tracker<E: Emission> {
    em: E,
    x: Vec<f64>,
    n_frames: usize,
    means: Vec<f64>,
    covs: Vec<f64>,
    mask: Vec<u8>,
    /// Per-entry precision weights of the Student-t measurement model (1 = Gaussian):
    /// the filter uses `V_x / w` (see [`mstep::m_step_student`]).
    weights: Vec<f64>,
    acc: nalgebra::DMatrix<f64>,
    stats: FilterStats,
    relinearize: usize,
    /// 1: the paper's random walk; 2: position and velocity (see [`filter::predict`]).
    order: usize,
    /// Position marginals of the last E-step when `order > 1` (`(T+1) × n`, `(T+1) × n × n`).
    zmeans: Vec<f64>,
    zcovs: Vec<f64>,
    /// Position moments `(T+1) × n`, `(T+1) × n × n` to linearise about where the prior is
    /// too broad (see [`Self::set_linearization_hint`]).
    hint: Option<(Vec<f64>, Vec<f64>)>,
    /// Whether `acc` holds the statistic of the last smoother pass.
    has_statistics: bool,
    /// Whether the moments are those of a filter pass (not smoothed yet).
    filtered_only: bool,
    /// How each filter step uses the pool's threads.
    frame_parallelism: FrameParallelism,
    /// Where the covariances come from and go back to (None: allocated and freed).
    buffers: Option<Arc<BufferPool>>,
}

impl<E: Emission> Drop for Tracker<E> {
    fn drop(&mut self) {
        if let Some(pool) = &self.buffers {
            pool.give(std::mem::take(&mut self.covs));
            pool.give(std::mem::take(&mut self.zcovs));
        }
    }
}

/// How a filter step uses the threads of the rayon pool ([`Tracker::set_frame_parallelism`]).
/// Both modes give the same moments bit for bit (each sigma point, Gram entry and solved
/// column is computed by the same operations on either thread).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameParallelism {
    /// Time both modes on [`MODE_TRIAL`] alternating frames each early in every
    /// [`MODE_PERIOD`] frames and keep the faster by median (default). On the 2-vCPU machine of
    /// `benches/README.md`, with rayon's hand-offs, one thread per frame was faster for the
    /// 50-entry rat (2,035 vs 1,790 frames/s) and both 100- and 174-entry velocity states;
    /// two were faster for the 87-entry random walk (770 vs 694). With the spinning
    /// [`crate::team::Team`] two threads are faster for the 100-entry velocity state too
    /// (433-445 vs 487 µs a step).
    Auto,
    /// Every step on the calling thread.
    Serial,
    /// Sigma points, Gram matrix and solves of every step shared between the pool's threads.
    Parallel,
}

/// Frames per mode of each timing trial of [`FrameParallelism::Auto`].
pub const MODE_TRIAL: usize = 16;
/// Frames between two timing trials of [`FrameParallelism::Auto`] (the load of the machine
/// may change during a long recording: the streaming smoother's first trial of each segment
/// falls while the previous one is spilled on the other core; 512 instead of 4,096 ran its
/// velocity forward pass 3-7 % faster, docs/tracking.md).
pub const MODE_PERIOD: usize = 512;
/// Frames of each period before its trial (the first frames of a recording relinearise from
/// the broad prior and are not typical).
const MODE_SKIP: usize = 48;

/// The per-frame mode of [`FrameParallelism::Auto`]: in a trial of `2 · MODE_TRIAL` frames
/// after the first [`MODE_SKIP`] of each period, parallel and serial frames alternate; then
/// the faster by median step time (serial before the first trial).
struct ModeChooser {
    fixed: Option<bool>,
    serial_faster: bool,
    times: [[f64; MODE_TRIAL]; 2],
}

impl ModeChooser {
    fn new(mode: FrameParallelism, threads: usize) -> Self {
        let fixed = match mode {
            FrameParallelism::Serial => Some(true),
            FrameParallelism::Parallel => Some(false),
            FrameParallelism::Auto if threads <= 1 => Some(true),
            FrameParallelism::Auto => None,
        };
        Self {
            fixed,
            serial_faster: true,
            times: [[0.0; MODE_TRIAL]; 2],
        }
    }

    /// The position of frame `t` in the trial of its period (`None` outside it).
    fn trial(&self, t: usize) -> Option<usize> {
        let p = (t % MODE_PERIOD).checked_sub(MODE_SKIP)?;
        (self.fixed.is_none() && p < 2 * MODE_TRIAL).then_some(p)
    }

    /// Whether frame `t` runs serially (in a trial: every other frame).
    fn serial(&self, t: usize) -> bool {
        match (self.fixed, self.trial(t)) {
            (Some(s), _) => s,
            (None, Some(p)) => p % 2 == 1,
            (None, None) => self.serial_faster,
        }
    }

    /// Whether frame `t` is timed.
    fn timed(&self, t: usize) -> bool {
        self.trial(t).is_some()
    }

    /// Records the step time of a timed frame `t`.
    fn record(&mut self, t: usize, seconds: f64) {
        let Some(p) = self.trial(t) else { return };
        self.times[p % 2][p / 2] = seconds;
        if p + 1 == 2 * MODE_TRIAL {
            let median = |v: &[f64; MODE_TRIAL]| {
                let mut v = *v;
                v.sort_by(f64::total_cmp);
                v[MODE_TRIAL / 2]
            };
            self.serial_faster = median(&self.times[1]) <= median(&self.times[0]);
        }
    }
}

/// Default maximum number of iterated posterior linearisations per frame (see
/// [`Tracker::set_relinearize`]).
pub const DEFAULT_RELINEARIZE: usize = 10;

impl<E: Emission> Tracker<E> {
    /// Sets up a tracker for measurements `x` (`T × n_x`, NaN = missing, in the layout of the
    /// emission: for the skeleton camera, marker, coordinate in normalised pixels).
    ///
    /// # Errors
    /// Shape error if `x` is not a whole number of frames or empty; non-finite error for ±inf.
    pub fn new(em: E, x: Vec<f64>) -> Result<Self> {
        let (n, n_x) = (em.n_state(), em.n_meas());
        if n == 0 || n_x == 0 {
            return Err(AcmError::Invalid(
                "the model has an empty state or measurement".into(),
            ));
        }
        if x.is_empty() || !x.len().is_multiple_of(n_x) {
            return Err(AcmError::Shape(format!(
                "measurements: {} values is not a positive multiple of n_x = {n_x}",
                x.len()
            )));
        }
        if let Some(i) = x.iter().position(|v| v.is_infinite()) {
            return Err(AcmError::NonFinite(format!(
                "measurement of frame {} entry {} is infinite (use NaN for missing)",
                i / n_x,
                i % n_x
            )));
        }
        let t = x.len() / n_x;
        Ok(Self {
            em,
            mask: vec![status::MISSING; x.len()],
            weights: vec![1.0; x.len()],
            x,
            n_frames: t,
            means: vec![0.0; (t + 1) * n],
            covs: vec![0.0; (t + 1) * n * n],
            acc: nalgebra::DMatrix::zeros(n, n),
            stats: FilterStats::default(),
            relinearize: DEFAULT_RELINEARIZE,
            order: 1,
            zmeans: Vec::new(),
            zcovs: Vec::new(),
            hint: None,
            has_statistics: false,
            filtered_only: false,
            frame_parallelism: FrameParallelism::Auto,
            buffers: None,
        })
    }

    /// Takes the covariances' vectors from `pool` from now on and gives them back when they
    /// are replaced or the tracker is dropped (the streaming smoother's trackers of one run
    /// share one pool: [`buffers`]). The moments do not depend on it.
    pub fn set_buffer_pool(&mut self, pool: Arc<BufferPool>) {
        let len = self.covs.len();
        // (the vector of `new` was never written: freeing it costs no page faults)
        self.covs = pool.zeros(len);
        self.buffers = Some(pool);
    }

    /// `len` zeros from the buffer pool, if any, giving `old` back to it.
    fn fresh(&self, old: Vec<f64>, len: usize) -> Vec<f64> {
        match &self.buffers {
            Some(pool) => {
                pool.give(old);
                pool.zeros(len)
            }
            None => {
                drop(old);
                vec![0.0; len]
            }
        }
    }

    /// The emission model.
    pub fn emission(&self) -> &E {
        &self.em
    }
    /// Number of frames `T`.
    pub fn n_frames(&self) -> usize {
        self.n_frames
    }
    /// Posterior means of the position `z` in the last E-step, `(T+1) × n` (row 0 = `z_0`).
    pub fn means(&self) -> &[f64] {
        if self.order == 1 {
            &self.means
        } else {
            &self.zmeans
        }
    }
    /// Posterior covariances of the position `z` in the last E-step, `(T+1) × n × n`.
    pub fn covs(&self) -> &[f64] {
        if self.order == 1 {
            &self.covs
        } else {
            &self.zcovs
        }
    }
    /// Posterior means and covariances of the whole state (`(T+1) × ns`, `(T+1) × ns × ns`,
    /// `ns = order · n`; for order 2 each row is `(z, ż)`).
    pub fn state_moments(&self) -> (&[f64], &[f64]) {
        (&self.means, &self.covs)
    }
    /// The order of the motion model (1 or 2).
    pub fn order(&self) -> usize {
        self.order
    }
    /// State dimension `ns = order · n` of the parameters `μ0, V0, V_z`.
    pub fn n_state(&self) -> usize {
        self.order * self.em.n_state()
    }

    /// The motion model: order 1 is the paper's random walk `z_t = z_{t-1} + ε` (eq. 49);
    /// order 2 adds the velocity, `z_t = z_{t-1} + ż_{t-1} + ε`, `ż_t = ż_{t-1} + ε'` (beyond
    /// the paper: fast movements do not lag and gaps are bridged by smooth curves). The
    /// parameters `μ0, V0, V_z` then have `2n` entries / rows, position first.
    ///
    /// # Errors
    /// Invalid for an order other than 1 or 2.
    pub fn set_order(&mut self, order: usize) -> Result<()> {
        if !(1..=2).contains(&order) {
            return Err(AcmError::Invalid(format!(
                "the motion model's order must be 1 (random walk) or 2 (velocity), got {order}"
            )));
        }
        let ns = order * self.em.n_state();
        self.order = order;
        self.means = vec![0.0; (self.n_frames + 1) * ns];
        let old = std::mem::take(&mut self.covs);
        self.covs = self.fresh(old, (self.n_frames + 1) * ns * ns);
        Ok(())
    }

    /// Frees the covariances of the last pass (the whole state's and, for order 2, the
    /// position marginals'), keeping the means and the entry statuses. EM over many windows
    /// (`tracking/long.py`) then holds a window's `8 (T+1) ns²` bytes only while it works on
    /// it: after its M-step, until its next E-step, which allocates them again. Until then
    /// [`Self::covs`] and [`Self::state_moments`] give empty covariances, and the methods
    /// that need them ([`Self::m_step`], [`Self::state_row`], [`Self::smooth_filtered`],
    /// [`Self::filtered_packed`]) return an error.
    pub fn release_covariances(&mut self) {
        let (covs, zcovs) = (
            std::mem::take(&mut self.covs),
            std::mem::take(&mut self.zcovs),
        );
        if let Some(pool) = &self.buffers {
            pool.give(covs);
            pool.give(zcovs);
        }
        self.has_statistics = false;
        self.filtered_only = false;
    }

    /// Checks that the covariances of the last pass are held (not freed by
    /// [`Self::release_covariances`]).
    ///
    /// # Errors
    /// Invalid, naming the fix, if they were released.
    pub fn require_covariances(&self) -> Result<()> {
        if self.covs.is_empty() {
            return Err(AcmError::Invalid(
                "this tracker's covariances were released (release_covariances); run an E-step \
                 first"
                    .into(),
            ));
        }
        Ok(())
    }

    /// Position means `(T+1) × n` and covariances `(T+1) × n × n` (row 0 = `z_0`) near the
    /// posterior, e.g. the random walk's smoothed posterior, used to linearise the update of
    /// frames whose prior is too broad for the unscented transform (after a stretch without
    /// detections under the position-velocity model). The model is unchanged: only where `g`
    /// is linearised. `None` removes it.
    ///
    /// # Errors
    /// Shape error for arrays of the wrong length.
    pub fn set_linearization_hint(&mut self, hint: Option<(Vec<f64>, Vec<f64>)>) -> Result<()> {
        if let Some((m, c)) = &hint {
            let (n, steps) = (self.em.n_state(), self.n_frames + 1);
            ensure_len(m.len(), steps * n, "hint means (T+1, n)")?;
            ensure_len(c.len(), steps * n * n, "hint covariances (T+1, n, n)")?;
        }
        self.hint = hint;
        Ok(())
    }

    /// Copies the position marginals out of the whole-state moments (order > 1).
    fn extract_positions(&mut self) {
        if self.order == 1 {
            return;
        }
        let n = self.em.n_state();
        let ns = self.order * n;
        let steps = self.n_frames + 1;
        self.zmeans.resize(steps * n, 0.0);
        if self.zcovs.len() != steps * n * n {
            let old = std::mem::take(&mut self.zcovs);
            self.zcovs = self.fresh(old, steps * n * n);
        }
        for k in 0..steps {
            self.zmeans[k * n..(k + 1) * n].copy_from_slice(&self.means[k * ns..k * ns + n]);
            for c in 0..n {
                let src = &self.covs[k * ns * ns + c * ns..k * ns * ns + c * ns + n];
                self.zcovs[k * n * n + c * n..k * n * n + (c + 1) * n].copy_from_slice(src);
            }
        }
    }

    /// Replaces `μ0, V0` of an M-step on the position marginals by the whole state's.
    fn with_full_initial(&self, mut p: Params) -> Params {
        if self.order > 1 {
            let ns = self.order * self.em.n_state();
            p.mu0 = self.means[..ns].to_vec();
            p.v0 = self.covs[..ns * ns].to_vec();
        }
        p
    }
    /// Status of every measurement entry in the last E-step (`T × n_x`, see [`status`]).
    pub fn mask(&self) -> &[u8] {
        &self.mask
    }
    /// Counts of the last E-step.
    pub fn stats(&self) -> FilterStats {
        self.stats
    }

    /// At most `k` iterated posterior linearisations per frame where the single unscented
    /// update does not hold (e.g. the first frame with detections after a stretch without
    /// any); 0 gives the paper's filter exactly. Default [`DEFAULT_RELINEARIZE`].
    pub fn set_relinearize(&mut self, k: usize) {
        self.relinearize = k;
    }

    /// Sets how each filter step uses the pool's threads (default
    /// [`FrameParallelism::Auto`]). The moments do not depend on it.
    pub fn set_frame_parallelism(&mut self, mode: FrameParallelism) {
        self.frame_parallelism = mode;
    }

    /// Runs the unscented Kalman filter (Alg. 7) only: afterwards [`Self::means`] and
    /// [`Self::covs`] hold the filtered moments.
    ///
    /// # Errors
    /// Invalid parameters; numerical errors naming the frame.
    pub fn filter(&mut self, params: &Params, gate: Option<f64>) -> Result<FilterStats> {
        let n_x = self.em.n_meas();
        let n = self.n_state();
        params.validate(n, n_x)?;
        if let Some(g) = gate {
            if g.is_nan() || g <= 0.0 {
                return Err(AcmError::Invalid(format!("the gate must be > 0, got {g}")));
            }
        }
        let size = (self.n_frames + 1) * n * n;
        if self.covs.len() != size {
            // after release_covariances
            self.covs = self.fresh(Vec::new(), size);
        }
        self.means[..n].copy_from_slice(&params.mu0);
        self.covs[..n * n].copy_from_slice(&params.v0);
        // The frames run in a worker of the current rayon pool (`rayon::scope` moves there
        // when called from outside it): the parallel loops of each step then share their work
        // between the workers instead of each being injected into the pool from outside and
        // waited for (rat, 2 vCPU: 1,750 → 2,250 frames/s).
        let stats = rayon::scope(|_| self.filter_frames(params, gate))?;
        self.stats = stats;
        self.has_statistics = false;
        self.filtered_only = true;
        self.extract_positions();
        Ok(stats)
    }

    /// The frame loop of [`Self::filter`] (from the prior in row 0).
    fn filter_frames(&mut self, params: &Params, gate: Option<f64>) -> Result<FilterStats> {
        let n_x = self.em.n_meas();
        let n = self.n_state();
        let mut ws = filter::Workspace::new(self.em.n_state(), n_x);
        let mut stats = FilterStats::default();
        let mut mode = ModeChooser::new(self.frame_parallelism, rayon::current_num_threads());
        for t in 0..self.n_frames {
            ws.serial = mode.serial(t);
            let clock = mode.timed(t).then(Instant::now);
            let (mh, mt) = self.means.split_at_mut((t + 1) * n);
            let (ch, ct) = self.covs.split_at_mut((t + 1) * n * n);
            filter::step(
                &self.em,
                params,
                &mh[t * n..],
                &ch[t * n * n..],
                &self.x[t * n_x..(t + 1) * n_x],
                gate,
                self.relinearize,
                self.hint.as_ref().map(|(m, c)| {
                    let n = self.em.n_state();
                    (
                        &m[(t + 1) * n..(t + 2) * n],
                        &c[(t + 1) * n * n..(t + 2) * n * n],
                    )
                }),
                t,
                &mut ws,
                &mut self.mask[t * n_x..(t + 1) * n_x],
                &self.weights[t * n_x..(t + 1) * n_x],
                &mut mt[..n],
                &mut ct[..n * n],
                &mut stats,
            )?;
            if let Some(c) = clock {
                mode.record(t, c.elapsed().as_secs_f64());
            }
        }
        Ok(stats)
    }

    /// The E-step (Alg. 9): filter, then smooth. Afterwards [`Self::means`] and
    /// [`Self::covs`] hold the smoothed moments.
    ///
    /// # Errors
    /// As [`Self::filter`].
    pub fn e_step(&mut self, params: &Params, gate: Option<f64>) -> Result<FilterStats> {
        self.filter_smooth(params, gate, true)
    }

    /// Filter and smoother with fixed parameters: [`Self::e_step`] without the transition
    /// statistic of eq. 79 (about a third of the smoother's work), so no M-step may follow.
    ///
    /// # Errors
    /// As [`Self::filter`].
    pub fn smooth(&mut self, params: &Params, gate: Option<f64>) -> Result<FilterStats> {
        self.filter_smooth(params, gate, false)
    }

    /// The backward pass (Alg. 8, without eq. 79's statistic) over the moments of the last
    /// [`Self::filter`], for one segment of a longer recording (the streaming smoother of long
    /// recordings): it starts from `end` = (mean `ns`, covariance `ns × ns`), the smoothed
    /// moments after the segment's last frame as computed by the next segment, instead of the
    /// last filtered ones (`None`: the last segment). With `params`' `μ0, V0` set to the
    /// filtered moments before the segment's first frame (its checkpoint), the segments
    /// reproduce the smoother of the whole recording exactly.
    ///
    /// # Errors
    /// Invalid if the last pass was not a filter; shape and finiteness errors for `end`;
    /// numerical errors as [`Self::smooth`].
    pub fn smooth_filtered(
        &mut self,
        params: &Params,
        end: Option<(&[f64], &[f64])>,
    ) -> Result<()> {
        if !self.filtered_only {
            return Err(AcmError::Invalid(
                "smooth_filtered needs the moments of a filter pass (run filter first)".into(),
            ));
        }
        let ns = self.n_state();
        ensure_len(params.vz.len(), ns * ns, "V_z (n, n)")?;
        if let Some((m, c)) = end {
            ensure_len(m.len(), ns, "end mean (ns)")?;
            ensure_len(c.len(), ns * ns, "end covariance (ns, ns)")?;
            crate::error::ensure_finite(m, "end mean")?;
            crate::error::ensure_finite(c, "end covariance")?;
            let t = self.n_frames;
            self.means[t * ns..(t + 1) * ns].copy_from_slice(m);
            self.covs[t * ns * ns..(t + 1) * ns * ns].copy_from_slice(c);
        }
        self.backward(params, false)
    }

    /// The whole-state moments of the last [`Self::filter`] in compact form, for a spill file
    /// of the streaming smoother (stored once instead of recomputed in the backward pass):
    /// means `(T+1) × ns` and the lower triangles of the covariances, column by column,
    /// `(T+1) × ns (ns + 1) / 2`. The filter's covariances are exactly symmetric, so
    /// [`Self::load_filtered`] restores them bit for bit.
    ///
    /// # Errors
    /// Invalid if the last pass was not a filter.
    pub fn filtered_packed(&self) -> Result<(&[f64], Vec<f64>)> {
        let ns = self.n_state();
        let mut packed = vec![0.0; (self.n_frames + 1) * ns * (ns + 1) / 2];
        let means = self.filtered_packed_into(&mut packed)?;
        Ok((means, packed))
    }

    /// [`Self::filtered_packed`] into `dst` (`(T+1) · ns (ns + 1) / 2` values, e.g. an array
    /// of the caller's that is written to disk next); returns the means.
    ///
    /// # Errors
    /// Invalid if the last pass was not a filter; shape error for `dst`.
    pub fn filtered_packed_into(&self, dst: &mut [f64]) -> Result<&[f64]> {
        if !self.filtered_only {
            return Err(AcmError::Invalid(
                "filtered_packed needs the moments of a filter pass (run filter first)".into(),
            ));
        }
        let ns = self.n_state();
        let tri = ns * (ns + 1) / 2;
        ensure_len(
            dst.len(),
            (self.n_frames + 1) * tri,
            "packed filtered covariances (T+1, ns(ns+1)/2)",
        )?;
        for (dst, cov) in dst
            .chunks_exact_mut(tri)
            .zip(self.covs.chunks_exact(ns * ns))
        {
            let mut e = 0;
            for c in 0..ns {
                dst[e..e + ns - c].copy_from_slice(&cov[c * ns + c..(c + 1) * ns]);
                e += ns - c;
            }
        }
        Ok(&self.means)
    }

    /// Restores the moments and entry statuses of a filter pass saved by
    /// [`Self::filtered_packed`] and [`Self::mask`], e.g. from a spill file, so that
    /// [`Self::smooth_filtered`] can follow without filtering again.
    ///
    /// # Errors
    /// Shape errors for lengths that do not fit this tracker's frames, state and
    /// measurements; non-finite error for NaN or infinite moments; invalid for a status
    /// code that does not exist.
    pub fn load_filtered(&mut self, means: &[f64], packed: &[f64], mask: &[u8]) -> Result<()> {
        let ns = self.n_state();
        let tri = ns * (ns + 1) / 2;
        let steps = self.n_frames + 1;
        ensure_len(means.len(), steps * ns, "filtered means (T+1, ns)")?;
        ensure_len(
            packed.len(),
            steps * tri,
            "packed filtered covariances (T+1, ns(ns+1)/2)",
        )?;
        ensure_len(mask.len(), self.x.len(), "entry statuses (T, n_x)")?;
        crate::error::ensure_finite(means, "filtered means")?;
        crate::error::ensure_finite(packed, "packed filtered covariances")?;
        if let Some(bad) = mask.iter().find(|&&m| m > status::INVISIBLE) {
            return Err(AcmError::Invalid(format!(
                "entry status {bad} is not one of 0 (missing), 1 (used), 2 (gated), 3 (invisible)"
            )));
        }
        self.means.copy_from_slice(means);
        if self.covs.len() != steps * ns * ns {
            // after release_covariances
            self.covs = self.fresh(Vec::new(), steps * ns * ns);
        }
        for (cov, src) in self
            .covs
            .chunks_exact_mut(ns * ns)
            .zip(packed.chunks_exact(tri))
        {
            let mut e = 0;
            for c in 0..ns {
                for r in c..ns {
                    cov[c * ns + r] = src[e];
                    cov[r * ns + c] = src[e];
                    e += 1;
                }
            }
        }
        self.mask.copy_from_slice(mask);
        self.filtered_only = true;
        self.has_statistics = false;
        Ok(())
    }

    /// Moments of the whole state at row `k` of the last pass (`0..=T`; row 0 = the prior of
    /// `z_0`, row `t` = after frame `t`): `(mean ns, covariance ns × ns)`.
    ///
    /// # Errors
    /// Invalid for `k > T`.
    pub fn state_row(&self, k: usize) -> Result<(&[f64], &[f64])> {
        self.require_covariances()?;
        if k > self.n_frames {
            return Err(AcmError::Invalid(format!(
                "row {k} is beyond the last frame {}",
                self.n_frames
            )));
        }
        let ns = self.n_state();
        Ok((
            &self.means[k * ns..(k + 1) * ns],
            &self.covs[k * ns * ns..(k + 1) * ns * ns],
        ))
    }

    fn filter_smooth(
        &mut self,
        params: &Params,
        gate: Option<f64>,
        statistics: bool,
    ) -> Result<FilterStats> {
        let stats = self.filter(params, gate)?;
        self.backward(params, statistics)?;
        Ok(stats)
    }

    fn backward(&mut self, params: &Params, statistics: bool) -> Result<()> {
        let ns = self.n_state();
        self.acc = smoother::smooth_in_place(
            &mut self.means,
            &mut self.covs,
            &params.vz,
            ns,
            filter::Transition::of(&self.em),
            statistics,
        )?;
        self.has_statistics = statistics;
        self.filtered_only = false;
        self.extract_positions();
        Ok(())
    }

    /// The M-step (Alg. 12) from the moments of the last [`Self::e_step`].
    ///
    /// # Errors
    /// Numerical errors for a smoothed covariance that is not positive semi-definite.
    pub fn m_step(&self, prev: &Params) -> Result<Params> {
        self.require_covariances()?;
        if !self.has_statistics {
            return Err(AcmError::Invalid(
                "the M-step needs an E-step with statistics (not smooth())".into(),
            ));
        }
        let p = mstep::m_step(
            &self.em,
            self.means(),
            self.covs(),
            &self.x,
            &self.mask,
            &self.acc,
            prev,
        )?;
        Ok(self.with_full_initial(p))
    }

    /// Per-entry precision weights of the last robust M-step (`T × n_x`; 1 = Gaussian).
    pub fn weights(&self) -> &[f64] {
        &self.weights
    }

    /// Alg. 11 followed by a final E-step with the learned parameters (sec. 4.7), so that the
    /// moments afterwards are the smoothed posterior under the returned parameters.
    ///
    /// The unscented E-step and the innovation gate make EM's marginal log-likelihood
    /// non-monotone (it may fall between iterations). The run therefore keeps the parameters
    /// of the highest log-likelihood it evaluated: when the last M-step's parameters score
    /// lower than those of an earlier E-step by more than the stop tolerance (`ll_tol` per
    /// used entry, else 1e-6 per entry), those earlier parameters are returned
    /// ([`EmOutcome::returned`]) and the final E-step runs under them.
    ///
    /// `on_iteration` is called after every iteration; returning `false` stops the run (e.g.
    /// on Ctrl-C), which still ends with the final E-step.
    ///
    /// # Errors
    /// As [`Self::e_step`] and [`Self::m_step`].
    pub fn run_em(
        &mut self,
        init: Params,
        opts: &EmOptions,
        mut on_iteration: impl FnMut(&Iteration) -> bool,
    ) -> Result<EmOutcome> {
        let mut params = init;
        let mut history: Vec<Iteration> = Vec::new();
        let (mut converged, mut interrupted, mut stalled) = (false, false, false);
        // (log-likelihood, iteration, parameters) of the best E-step so far
        let mut best: Option<(f64, usize, Params)> = None;
        // over-relaxation: the factor of the evaluated step, the next step's, and (for an
        // over-relaxed step) the plain M-step it came with and the log-likelihood to beat
        let (mut step, mut eta) = (1.0, 1.0);
        let mut fallback: Option<(Params, f64)> = None;
        for k in 1..=opts.max_iter {
            let t0 = Instant::now();
            let stats = self.e_step(&params, opts.gate)?;
            if stats.log_lik.is_finite() && best.as_ref().is_none_or(|b| stats.log_lik > b.0) {
                best = Some((stats.log_lik, k, params.clone()));
            }
            if let Some((plain, ll_from)) = fallback.take() {
                // (a NaN log-likelihood is a rejection too)
                if stats.log_lik.is_nan() || stats.log_lik < ll_from {
                    let it = Iteration {
                        iteration: k,
                        delta: relative_change(&params, &plain),
                        seconds: t0.elapsed().as_secs_f64(),
                        stats,
                        step,
                        rejected: true,
                    };
                    history.push(it);
                    (params, step, eta) = (plain, 1.0, 1.0);
                    if !on_iteration(&it) {
                        interrupted = true;
                        break;
                    }
                    continue;
                }
            }
            let next = match opts.dof {
                Some(dof) => {
                    let (next, w) = mstep::m_step_student(
                        &self.em,
                        self.means(),
                        self.covs(),
                        &self.x,
                        &self.mask,
                        &self.acc,
                        &params,
                        dof,
                    )?;
                    self.weights = w;
                    self.with_full_initial(next)
                }
                None => self.m_step(&params)?,
            };
            let delta = relative_change(&params, &next);
            let it = Iteration {
                iteration: k,
                delta,
                seconds: t0.elapsed().as_secs_f64(),
                stats,
                step,
                rejected: false,
            };
            history.push(it);
            if !on_iteration(&it) {
                params = next;
                interrupted = true;
                break;
            }
            let done = match opts.ll_tol {
                // the log-likelihood of E-step k is that of the parameters of step k - 1
                Some(tol) => ll_settled(&history, tol),
                None => delta < opts.tol,
            };
            if done {
                // (the plain step: the final E-step should not risk a rejection)
                params = next;
                converged = true;
                break;
            }
            // E-steps k - p + 1 ..= k all scored below the best (that of E-step k - p or earlier)
            if let (Some(p), Some((_, kb, _))) = (opts.patience, &best) {
                if p > 0 && k >= kb + p {
                    params = next;
                    stalled = true;
                    break;
                }
            }
            let settling = opts
                .ll_tol
                .is_some_and(|tol| overrelaxed_settled(&history, tol));
            match opts.overrelax {
                Some(alpha) if opts.dof.is_none() && stats.log_lik.is_finite() && !settling => {
                    // η grows after every step that held (the first plain one included)
                    eta = if step > 1.0 {
                        (eta * alpha).min(MAX_OVERRELAX)
                    } else {
                        alpha
                    };
                    match extrapolate(&params, &next, eta) {
                        Some(far) => {
                            fallback = Some((next, stats.log_lik));
                            (params, step) = (far, eta);
                        }
                        None => (params, step) = (next, 1.0),
                    }
                }
                _ => (params, step) = (next, 1.0),
            }
        }
        if let Some((plain, _)) = fallback.take() {
            // max_iter ended on an over-relaxed step that was never evaluated
            params = plain;
        }
        if stalled {
            // straight to the best parameters: the last M-step's were not evaluated
            let (_, k, p) = best.expect("stalled implies a best iteration");
            let final_stats = self.e_step(&p, opts.gate)?;
            return Ok(EmOutcome {
                params: p,
                history,
                converged,
                interrupted,
                returned: Some(k),
                stalled,
                final_stats,
            });
        }
        let mut final_stats = self.e_step(&params, opts.gate)?;
        let mut returned = None;
        if let Some((ll, k, p)) = best {
            let margin = opts.ll_tol.unwrap_or(1e-6) * final_stats.used.max(1) as f64;
            // (a NaN final log-likelihood also falls back to the best parameters)
            let holds = final_stats.log_lik >= ll - margin;
            if !holds {
                final_stats = self.e_step(&p, opts.gate)?;
                params = p;
                returned = Some(k);
            }
        }
        Ok(EmOutcome {
            params,
            history,
            converged,
            interrupted,
            returned,
            stalled,
            final_stats,
        })
    }
}
