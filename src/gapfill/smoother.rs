//! Random-walk Kalman filter and RTS smoother in the subspace (B&L Algorithm 1, Appendix A),
//! in whitened information form and with memoised covariances.
//!
//! Model (B&L eqs. 1, 2, 4, 5 with `F = I`): `x̃_t = x̃_{t−1} + w_t`, `w_t ~ N(0, Q)`;
//! `z_t = H_t (V̂ x̃_t + m̄) + v_t`, `v_t ~ N(0, r I)`.
//!
//! * **Whitening.** With `Q = L Lᵀ` (Cholesky) the coordinates `x' = L⁻¹ x̃` have `Q' = I` and
//!   basis rows `v_i' = Lᵀ v_i`; filled values are unchanged. Everything below is in these
//!   coordinates.
//! * **Information form.** With `R = r I` the update `K_t = P̂_t Ĥ_tᵀ (Ĥ_t P̂_t Ĥ_tᵀ + R)⁻¹`
//!   (A.5) equals `P_t Ĥ_tᵀ / r` with `P_t = Λ_t⁻¹`, `Λ_t = P̂_t⁻¹ + G_t / r` (A.4) and
//!   `G_t = Ĥ_tᵀ Ĥ_t = Σ_{present i} v_i v_iᵀ`, so each update is a `d̂ × d̂` Cholesky instead of
//!   an `n_present × n_present` inverse.
//! * **One inverse per step.** With `Q = I`, `M_t = (I + Λ_t)⁻¹` gives everything else:
//!   the RTS gain `C_t = P_t (P_t + I)⁻¹ = M_t` (A.6), the next predicted information
//!   `P̂_{t+1}⁻¹ = (P_t + I)⁻¹ = I − M_t` (A.2), and the smoothed covariance (A.8)
//!   `P̃_t = P_t + C_t (P̃_{t+1} − P̂_{t+1}) C_tᵀ = M_t + M_t P̃_{t+1} M_t`
//!   (because `P_t − P_t M_t = M_t`). The filter mean uses the Cholesky factor of `Λ_t`.
//! * **Memoisation.** The covariance recursion does not depend on the measured values, only
//!   on the sequence of missing patterns. A filter covariance is a *state*; the transition
//!   (state, next pattern) → state is computed once and cached. Before a new transition is
//!   computed it is merged with a known state `s` of the same pattern when the bound
//!   `‖P_new − P_s‖₂ ≤ η/(1−η) ‖P_s‖₂`, `η = ‖P_s‖₂ ‖P̂_new⁻¹ − P̂_s⁻¹‖_F`, which follows from
//!   the identity `P_new − P_s = P_new (P̂_s⁻¹ − P̂_new⁻¹) P_s` (A.4, same `G_t`), guarantees
//!   a relative change of at most `memo_tol` (`η ≤ memo_tol`). The recursion is a contraction,
//!   so merged errors do not accumulate. Frames with every marker missing are pure prediction
//!   steps (the published code fails on them).
//! * **Parallel chunks.** The filter covariances of long sequences are computed in one chunk per
//!   thread, each from the prior a burn-in before its start, and stitched where the exact
//!   recursion and the chunk agree within `memo_tol` (`filter_states`).
//! * **RTS gain** `C_t = P_t P̂_{t+1}⁻¹` (A.6; Algorithm 1 prints `P_t P̂_t⁻¹`, which is not the
//!   RTS smoother).

use super::linalg::{
    add_outer, chol_solve_in_place, cholesky_lower, close, dot, spd_inverse_lower, symmetrize,
};
use crate::error::{AcmError, Result};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;
use std::collections::HashMap;

const PRIOR: u32 = u32::MAX;
/// Known states of a pattern tried by the merge test.
const MERGE_CANDIDATES: usize = 8;

/// The linear-Gaussian model of the smoother.
#[derive(Debug, Clone)]
pub struct Model {
    /// Basis rows `v_i` (row-major D × d̂).
    pub v: Vec<f64>,
    /// Mean m̄ (D).
    pub mean: Vec<f64>,
    /// Process noise Q (d̂ × d̂).
    pub q: DMatrix<f64>,
    /// Measurement noise variance r (R = r I).
    pub r: f64,
    /// Prior mean of x̃ at the first frame.
    pub m0: DVector<f64>,
    /// Prior covariance of x̃ at the first frame.
    pub p0: DMatrix<f64>,
}

impl Model {
    /// d̂.
    pub fn k(&self) -> usize {
        self.q.nrows()
    }
    /// D.
    pub fn d(&self) -> usize {
        self.mean.len()
    }
    #[inline]
    fn row(&self, i: usize) -> &[f64] {
        let k = self.k();
        &self.v[i * k..(i + 1) * k]
    }
}

/// Missing-value patterns of a sequence: one id per frame and the missing coordinates of each
/// pattern.
#[derive(Debug, Clone)]
pub struct Patterns {
    /// Pattern id of every frame.
    pub of_frame: Vec<u32>,
    /// Missing coordinates per pattern.
    pub missing: Vec<Vec<u32>>,
}

impl Patterns {
    /// Finds the patterns of the row-major `T × D` sequence `x` (NaN = missing).
    pub fn new(x: &[f64], d: usize) -> Self {
        let t = x.len() / d;
        let mut ids: HashMap<Vec<u32>, u32> = HashMap::new();
        let mut missing = Vec::new();
        let mut of_frame = Vec::with_capacity(t);
        for row in x.chunks_exact(d) {
            let miss: Vec<u32> = (0..d as u32)
                .filter(|&j| row[j as usize].is_nan())
                .collect();
            let next = ids.len() as u32;
            let id = *ids.entry(miss.clone()).or_insert_with(|| {
                missing.push(miss);
                next
            });
            of_frame.push(id);
        }
        Self { of_frame, missing }
    }

    fn all_missing(&self, p: u32, d: usize) -> bool {
        self.missing[p as usize].len() == d
    }
}

/// The model in whitened coordinates `x' = L⁻¹ x̃`, `Q = L Lᵀ` (so `Q' = I`).
#[derive(Debug, Clone)]
struct White {
    k: usize,
    d: usize,
    /// Lower Cholesky factor L of Q.
    l: DMatrix<f64>,
    /// Rows `v_i' = Lᵀ v_i` (row-major D × d̂).
    v: Vec<f64>,
    /// `Σ_i v_i' v_i'ᵀ` over all coordinates.
    g_full: DMatrix<f64>,
    /// Prior information `(L⁻¹ P₀ L⁻ᵀ)⁻¹ = Lᵀ P₀⁻¹ L`.
    lam0: DMatrix<f64>,
    /// Prior mean `L⁻¹ m₀`.
    m0: DVector<f64>,
    inv_r: f64,
}

impl White {
    fn new(model: &Model) -> Result<Self> {
        let (d, k) = (model.d(), model.k());
        let mut q = model.q.clone();
        symmetrize(&mut q);
        let l = match cholesky_lower(&q) {
            Some(l) => l,
            None => {
                // Q positive semi-definite only (e.g. the published Q): a relative jitter.
                let j = 1e-12 * (q.trace() / k as f64).max(1e-300);
                for c in 0..k {
                    q[(c, c)] += j;
                }
                cholesky_lower(&q).ok_or_else(|| {
                    AcmError::Numerical("the process noise Q is not positive definite".into())
                })?
            }
        };
        let mut v = vec![0.0; d * k];
        v.par_chunks_mut(k).enumerate().for_each(|(i, out)| {
            let row = model.row(i);
            for (c, o) in out.iter_mut().enumerate() {
                // (Lᵀ v)_c = Σ_a L_ac v_a, a ≥ c
                *o = (c..k).map(|a| l[(a, c)] * row[a]).sum();
            }
        });
        let mut g_full = DMatrix::zeros(k, k);
        add_outer(&mut g_full, &v, k, &(0..d as u32).collect::<Vec<_>>(), 1.0);
        let p0_lam = spd_inverse_lower(&model.p0).ok_or_else(|| {
            AcmError::Numerical("the prior covariance P0 is not positive definite".into())
        })?;
        let mut lam0 = l.transpose() * p0_lam * &l;
        symmetrize(&mut lam0);
        let m0 = l
            .solve_lower_triangular(&model.m0)
            .ok_or_else(|| AcmError::Numerical("singular Cholesky factor of Q".into()))?;
        Ok(Self {
            k,
            d,
            l,
            v,
            g_full,
            lam0,
            m0,
            inv_r: 1.0 / model.r,
        })
    }

    #[inline]
    fn row(&self, i: usize) -> &[f64] {
        &self.v[i * self.k..(i + 1) * self.k]
    }

    /// `G_p / r` of a pattern: `G_full − Σ_{missing}` or `Σ_{present}`, whichever is shorter.
    fn info_gain(&self, miss: &[u32]) -> DMatrix<f64> {
        let mut g = if miss.len() * 2 <= self.d {
            let mut g = self.g_full.clone();
            add_outer(&mut g, &self.v, self.k, miss, -1.0);
            g
        } else {
            let mut present = vec![true; self.d];
            miss.iter().for_each(|&j| present[j as usize] = false);
            let idx: Vec<u32> = (0..self.d as u32)
                .filter(|&j| present[j as usize])
                .collect();
            let mut g = DMatrix::zeros(self.k, self.k);
            add_outer(&mut g, &self.v, self.k, &idx, 1.0);
            g
        };
        g.as_mut_slice().iter_mut().for_each(|x| *x *= self.inv_r);
        g
    }

    /// `vᵀ A v` summed over coordinates `idx` of the rows.
    fn quad_sum(&self, a: &DMatrix<f64>, idx: impl Iterator<Item = usize>) -> f64 {
        let k = self.k;
        let mut s = 0.0;
        let mut av = vec![0.0; k];
        for i in idx {
            let v = self.row(i);
            av.iter_mut().for_each(|x| *x = 0.0);
            for (b, &vb) in v.iter().enumerate() {
                if vb == 0.0 {
                    continue;
                }
                for (o, aab) in av.iter_mut().zip(&a.as_slice()[b * k..(b + 1) * k]) {
                    *o += aab * vb;
                }
            }
            s += dot(v, &av);
        }
        s
    }
}

/// A memoised filter state (whitened coordinates).
#[derive(Debug, Clone)]
struct FState {
    /// The predecessor whose `P̂⁻¹ = I − M_pred` (or the prior) entered `Λ_t` (A.2, A.4).
    pred: u32,
    /// Lower Cholesky factor of the information `Λ_t = P_t⁻¹` (A.4).
    chol: DMatrix<f64>,
    /// `M_t = (I + Λ_t)⁻¹`: RTS gain `C_t` (A.6); `I − M_t = P̂_{t+1}⁻¹` (A.2).
    m: DMatrix<f64>,
    /// Upper bound on `‖P_t‖₂`.
    pnorm: f64,
}

/// Output of [`smooth`].
#[derive(Debug, Clone)]
pub struct Smoothed {
    /// Smoothed subspace means `m̃_t`, row-major T × d̂ (original coordinates).
    pub m: Vec<f64>,
    /// Smoothed covariance id per frame (if covariances were requested).
    pub cov_of_frame: Vec<u32>,
    /// Distinct smoothed covariances `P̃'` (whitened coordinates).
    covs: Vec<DMatrix<f64>>,
    /// Lag-one terms `X_e = P̃'_{t+1} M_t` per (state, next covariance) pair `e`.
    lags: Vec<DMatrix<f64>>,
    /// Lag pair id per frame `t ≥ 1` (pair of frames t−1, t); index 0 unused.
    lag_of_frame: Vec<u32>,
    /// Filter state id per frame.
    state_of_frame: Vec<u32>,
    /// Filter states.
    states: Vec<FState>,
    white: White,
}

impl Smoothed {
    /// Number of distinct filter covariances computed.
    pub fn distinct_filter_covariances(&self) -> usize {
        self.states.len()
    }

    /// Smoothed covariance `P̃_t = L P̃'_t Lᵀ` of frame `t` (original coordinates).
    pub fn smoothed_cov(&self, t: usize) -> DMatrix<f64> {
        let l = &self.white.l;
        l * &self.covs[self.cov_of_frame[t] as usize] * l.transpose()
    }

    /// Filter covariance `P_t = L Λ_t⁻¹ Lᵀ` of frame `t` (original coordinates).
    pub fn filter_cov(&self, t: usize) -> DMatrix<f64> {
        let st = &self.states[self.state_of_frame[t] as usize];
        let k = self.white.k;
        let mut p = DMatrix::identity(k, k);
        for c in 0..k {
            let mut col = p.column(c).into_owned();
            chol_solve_in_place(&st.chol, col.as_mut_slice());
            p.set_column(c, &col);
        }
        let l = &self.white.l;
        l * p * l.transpose()
    }
}

/// `‖A − B‖_F` of two predicted informations `P̂⁻¹` given by their predecessor ids
/// (`P̂⁻¹ = I − M_pred`, or the prior information).
fn lam_dist(states: &[FState], w: &White, a: u32, b: u32) -> f64 {
    if a == b {
        return 0.0;
    }
    let k = w.k;
    let ident = |x: u32| if x == PRIOR { 1.0 } else { 0.0 };
    // For a state id, the stored matrix enters with sign −1 and the identity is added.
    let (sa, sgn_a) = if a == PRIOR {
        (w.lam0.as_slice(), 1.0)
    } else {
        (states[a as usize].m.as_slice(), -1.0)
    };
    let (sb, sgn_b) = if b == PRIOR {
        (w.lam0.as_slice(), 1.0)
    } else {
        (states[b as usize].m.as_slice(), -1.0)
    };
    // Identity parts cancel unless exactly one side is the prior.
    let id_diff = (1.0 - ident(a)) - (1.0 - ident(b));
    let mut s = 0.0;
    for (idx, (x, y)) in sa.iter().zip(sb).enumerate() {
        let mut d = sgn_a * x - sgn_b * y;
        if idx % (k + 1) == 0 {
            d += id_diff;
        }
        s += d * d;
    }
    s.sqrt()
}

/// `Σ_i c_i M_i` over the entries with `c_i > 0`, in parallel over fixed chunks whose partial
/// sums are added in order (the result does not depend on the thread count).
fn weighted_sum(counts: &[f64], mats: &[DMatrix<f64>], k: usize) -> DMatrix<f64> {
    counts
        .par_chunks(64)
        .zip(mats.par_chunks(64))
        .map(|(cs, ms)| {
            let mut acc = DMatrix::<f64>::zeros(k, k);
            for (&c, m) in cs.iter().zip(ms) {
                if c > 0.0 {
                    acc.iter_mut().zip(m.iter()).for_each(|(a, b)| *a += c * b);
                }
            }
            acc
        })
        .collect::<Vec<_>>()
        .into_iter()
        .fold(DMatrix::zeros(k, k), |a, b| a + b)
}

/// Runs the forward filter and the RTS smoother (B&L Algorithm 1 with gain A.6) on the
/// row-major `T × D` sequence `x`; with `want_cov` also the smoothed covariances (A.8) and the
/// lag-one terms EM needs.
pub fn smooth(
    x: &[f64],
    model: &Model,
    pats: &Patterns,
    want_cov: bool,
    memo_tol: f64,
) -> Result<Smoothed> {
    let w = White::new(model)?;
    let (d, k) = (w.d, w.k);
    let t_len = x.len() / d;

    let (states, state_of_frame) = filter_states(&w, pats, memo_tol)?;
    // Data term of every frame, in parallel: b_t = Σ_{present i} v_i (z_ti − m̄_i) = Ĥ_tᵀ(z_t − H_t m̄).
    let mut bz = vec![0.0; t_len * k];
    bz.par_chunks_mut(k).enumerate().for_each(|(t, out)| {
        for (i, z) in x[t * d..(t + 1) * d].iter().enumerate() {
            if !z.is_nan() {
                let e = z - model.mean[i];
                for (o, vc) in out.iter_mut().zip(w.row(i)) {
                    *o += e * vc;
                }
            }
        }
    });
    let mut mf = vec![0.0; t_len * k]; // filtered means (whitened)
    let mut g = vec![0.0; k];
    let gf = w.g_full.as_slice();

    for t in 0..t_len {
        let pat = pats.of_frame[t];
        let sid = state_of_frame[t];
        // Mean (A.3, A.5): m̂_t = m_{t−1} (random walk),
        // m_t = m̂_t + P_t Ĥ_tᵀ (z_t − Ĥ_t m̂_t − H_t m̄) / r = m̂_t + P_t (b_t − G_t m̂_t) / r.
        let (done, rest) = mf.split_at_mut(t * k);
        let m_hat: &[f64] = if t == 0 {
            w.m0.as_slice()
        } else {
            &done[(t - 1) * k..]
        };
        let m_t = &mut rest[..k];
        m_t.copy_from_slice(m_hat);
        let miss = &pats.missing[pat as usize];
        if miss.len() < d {
            // g = G_t m̂_t: G_full m̂ − Σ_{missing} v_i (v_iᵀ m̂), or Σ_{present}.
            g.iter_mut().for_each(|v| *v = 0.0);
            if miss.len() * 2 <= d {
                for (col, &mb) in gf.chunks_exact(k).zip(m_hat) {
                    for (o, c) in g.iter_mut().zip(col) {
                        *o += c * mb;
                    }
                }
                for &i in miss {
                    let v = w.row(i as usize);
                    let p = dot(v, m_hat);
                    for (o, vc) in g.iter_mut().zip(v) {
                        *o -= p * vc;
                    }
                }
            } else {
                let row = &x[t * d..(t + 1) * d];
                for (i, z) in row.iter().enumerate() {
                    if !z.is_nan() {
                        let v = w.row(i);
                        let p = dot(v, m_hat);
                        for (o, vc) in g.iter_mut().zip(v) {
                            *o += p * vc;
                        }
                    }
                }
            }
            for (o, b) in g.iter_mut().zip(&bz[t * k..(t + 1) * k]) {
                *o = (b - *o) * w.inv_r;
            }
            chol_solve_in_place(&states[sid as usize].chol, &mut g);
            for (a, b) in m_t.iter_mut().zip(&g) {
                *a += b;
            }
        }
    }

    // Backward pass: m̃_t = m_t + C_t (m̃_{t+1} − m̂_{t+1}), m̂_{t+1} = m_t, C_t = M_t (A.7).
    let mut ms = mf.clone();
    let mut diff = vec![0.0; k];
    for t in (0..t_len.saturating_sub(1)).rev() {
        let c = states[state_of_frame[t] as usize].m.as_slice();
        for a in 0..k {
            diff[a] = ms[(t + 1) * k + a] - mf[t * k + a];
        }
        let out = &mut ms[t * k..(t + 1) * k];
        for (b, &db) in diff.iter().enumerate() {
            for (o, cab) in out.iter_mut().zip(&c[b * k..(b + 1) * k]) {
                *o += cab * db;
            }
        }
    }
    // Back to the original coordinates: m̃ = L m̃'.
    let mut m_orig = vec![0.0; t_len * k];
    m_orig
        .par_chunks_mut(k)
        .zip(ms.par_chunks(k))
        .for_each(|(o, m)| {
            let ls = w.l.as_slice();
            for (b, &mb) in m.iter().enumerate() {
                for (oa, lab) in o[b..].iter_mut().zip(&ls[b * k + b..(b + 1) * k]) {
                    *oa += lab * mb;
                }
            }
        });

    let mut sm = Smoothed {
        m: m_orig,
        cov_of_frame: Vec::new(),
        covs: Vec::new(),
        lags: Vec::new(),
        lag_of_frame: Vec::new(),
        state_of_frame,
        states,
        white: w,
    };
    if want_cov && t_len > 0 {
        smoothed_covariances(&mut sm, memo_tol)?;
    }
    Ok(sm)
}

/// Frames per chunk below which the filter covariances are computed sequentially.
const MIN_CHUNK: usize = 800;
/// Burn-in frames a chunk starts before its first frame (from the prior).
const BURN_IN: usize = 400;
/// Frames between two junction tests of [`filter_states`].
const TEST_EVERY: usize = 8;

/// Memoised filter states of a stretch of frames.
struct Chain {
    states: Vec<FState>,
    by_pat: Vec<Vec<u32>>,
    trans: HashMap<(u32, u32), u32>,
    sof: Vec<u32>,
}

impl Chain {
    fn new(n_pat: usize) -> Self {
        Self {
            states: Vec::new(),
            by_pat: vec![Vec::new(); n_pat],
            trans: HashMap::new(),
            sof: Vec::new(),
        }
    }

    /// The state of frame `t` reached from state `prev` (memoised transition).
    fn step(&mut self, w: &White, pats: &Patterns, prev: u32, t: usize, tol: f64) -> Result<u32> {
        let pat = pats.of_frame[t];
        if let Some(&s) = self.trans.get(&(prev, pat)) {
            return Ok(s);
        }
        let s = new_transition(w, pats, &mut self.states, &mut self.by_pat, prev, pat, tol)?;
        self.trans.insert((prev, pat), s);
        Ok(s)
    }

    fn run(
        &mut self,
        w: &White,
        pats: &Patterns,
        frames: std::ops::Range<usize>,
        tol: f64,
    ) -> Result<()> {
        let mut prev = self.sof.last().copied().unwrap_or(PRIOR);
        for t in frames {
            prev = self.step(w, pats, prev, t, tol)?;
            self.sof.push(prev);
        }
        Ok(())
    }
}

/// Explicit `P = Λ⁻¹` of a state.
fn state_cov(st: &FState) -> DMatrix<f64> {
    let wi = super::linalg::lower_inverse(&st.chol);
    let mut p = wi.transpose() * &wi;
    symmetrize(&mut p);
    p
}

/// Filter states of all frames (A.2, A.4). Sequential for short sequences or `tol = 0`; else
/// the frames are split into one chunk per thread, each chunk computed in parallel from the
/// prior `BURN_IN` frames before its start, and stitched: from a chunk's first frame on, the
/// exact recursion continues from the previous chunk's last state until its covariance agrees
/// with the chunk's own within `tol` (relative, max norm — the memo merge criterion); from
/// there the chunk's states are used. The Riccati recursion is a contraction, so the burn-in
/// forgets the prior and the stitched states are those of the sequential recursion up to `tol`.
fn filter_states(w: &White, pats: &Patterns, tol: f64) -> Result<(Vec<FState>, Vec<u32>)> {
    let t_len = pats.of_frame.len();
    let n_pat = pats.missing.len();
    let n = if tol > 0.0 {
        rayon::current_num_threads().min(t_len / MIN_CHUNK).max(1)
    } else {
        1
    };
    let bound = |c: usize| c * t_len / n;
    let mut locals = (0..n)
        .into_par_iter()
        .map(|c| {
            let start = if c == 0 {
                0
            } else {
                bound(c).saturating_sub(BURN_IN)
            };
            let mut ch = Chain::new(n_pat);
            ch.run(w, pats, start..bound(c + 1), tol)
                .map(|_| (ch, start))
        })
        .collect::<Vec<_>>()
        .into_iter();
    let (mut g, _) = locals.next().expect("at least one chunk")?;
    for (c, local) in locals.enumerate() {
        let (a, b) = (bound(c + 1), bound(c + 2));
        // A chunk whose burn-in failed numerically is recomputed sequentially.
        let local = local.ok();
        let mut adopt = None;
        for t in a..b {
            let prev = *g.sof.last().expect("frames before the chunk");
            let sid = g.step(w, pats, prev, t, tol)?;
            if let Some((lc, start)) = &local {
                let lsid = lc.sof[t - start];
                if (t - a) % TEST_EVERY == 0
                    && close(
                        &state_cov(&g.states[sid as usize]),
                        &state_cov(&lc.states[lsid as usize]),
                        tol,
                    )
                {
                    adopt = Some(t);
                    break;
                }
            }
            g.sof.push(sid);
        }
        if let (Some(t0), Some((lc, start))) = (adopt, local) {
            let base = g.states.len() as u32;
            g.states.extend(lc.states.into_iter().map(|mut st| {
                if st.pred != PRIOR {
                    st.pred += base;
                }
                st
            }));
            g.sof.extend(lc.sof[t0 - start..].iter().map(|&s| s + base));
            // The chunk's states continue the chain; the global memo table stays valid.
        }
    }
    debug_assert_eq!(g.sof.len(), t_len);
    Ok((g.states, g.sof))
}

fn new_transition(
    w: &White,
    pats: &Patterns,
    states: &mut Vec<FState>,
    by_pat: &mut [Vec<u32>],
    prev: u32,
    pat: u32,
    tol: f64,
) -> Result<u32> {
    let k = w.k;
    // Merge with a known state of the same pattern if the bound guarantees a relative change
    // of at most tol (module docs).
    if tol > 0.0 {
        for &s in by_pat[pat as usize].iter().rev().take(MERGE_CANDIDATES) {
            let st = &states[s as usize];
            if st.pnorm.is_finite() && st.pnorm * lam_dist(states, w, prev, st.pred) <= tol {
                return Ok(s);
            }
        }
    }
    // A.2 + A.4 in whitened information form: Λ_t = P̂_t⁻¹ + G_t / r, P̂_t⁻¹ = I − M_{t−1}.
    let mut info = if pats.all_missing(pat, w.d) {
        DMatrix::zeros(k, k)
    } else {
        w.info_gain(&pats.missing[pat as usize])
    };
    if prev == PRIOR {
        for (a, b) in info.as_mut_slice().iter_mut().zip(w.lam0.as_slice()) {
            *a += b;
        }
    } else {
        for (a, b) in info
            .as_mut_slice()
            .iter_mut()
            .zip(states[prev as usize].m.as_slice())
        {
            *a -= b;
        }
        for c in 0..k {
            info[(c, c)] += 1.0;
        }
    }
    let chol = cholesky_lower(&info).ok_or_else(|| {
        AcmError::Numerical("the filter information matrix is not positive definite".into())
    })?;
    let mut ipi = info;
    for c in 0..k {
        ipi[(c, c)] += 1.0;
    }
    let m = spd_inverse_lower(&ipi)
        .ok_or_else(|| AcmError::Numerical("I + information is not positive definite".into()))?;
    if !m.iter().all(|v| v.is_finite()) {
        return Err(AcmError::Numerical("non-finite RTS gain".into()));
    }
    let pnorm = if tol > 0.0 { p_norm_bound(&m) } else { 0.0 };
    let id = states.len() as u32;
    states.push(FState {
        pred: prev,
        chol,
        m,
        pnorm,
    });
    by_pat[pat as usize].push(id);
    Ok(id)
}

/// Upper bound on `‖P‖₂ = ‖Λ⁻¹‖₂` from Gershgorin on `M = (I + Λ)⁻¹` (eigenvalues
/// `μ = 1/(1 + λ)`, `‖P‖₂ = μ_max/(1 − μ_max)`); infinite (no merging) when the bound is ≥ 1/2.
fn p_norm_bound(m: &DMatrix<f64>) -> f64 {
    let k = m.nrows();
    let g = m
        .as_slice()
        .chunks_exact(k.max(1))
        .map(|c| c.iter().map(|v| v.abs()).sum::<f64>())
        .fold(0.0, f64::max);
    if g < 0.5 {
        return g / (1.0 - g);
    }
    f64::INFINITY
}

/// Smoothed covariances (A.8) `P̃_t = M_t + M_t P̃_{t+1} M_t` (whitened, module docs) and the
/// lag-one terms `X = P̃_{t+1} M_t` (`P̃_{t+1,t} = P̃_{t+1} C_tᵀ`), memoised on
/// (filter state, next smoothed covariance).
fn smoothed_covariances(sm: &mut Smoothed, tol: f64) -> Result<()> {
    let states = &sm.states;
    let sof = &sm.state_of_frame;
    let t_len = sof.len();
    let k = sm.white.k;
    let mut covs: Vec<DMatrix<f64>> = Vec::new();
    let mut lags: Vec<DMatrix<f64>> = Vec::new();
    let mut of_frame = vec![0u32; t_len];
    let mut lag_of_frame = vec![0u32; t_len];
    let mut memo: HashMap<(u32, u32), (u32, u32)> = HashMap::new();
    // P̃_T = P_T = Λ_T⁻¹.
    let last = &states[sof[t_len - 1] as usize];
    let mut pt = DMatrix::identity(k, k);
    for c in 0..k {
        let mut col = pt.column(c).into_owned();
        chol_solve_in_place(&last.chol, col.as_mut_slice());
        pt.set_column(c, &col);
    }
    symmetrize(&mut pt);
    covs.push(pt);
    for t in (0..t_len.saturating_sub(1)).rev() {
        let s = sof[t];
        let next = of_frame[t + 1];
        let (id, lag) = match memo.get(&(s, next)) {
            Some(&v) => v,
            None => {
                let mm = &states[s as usize].m;
                let xl = &covs[next as usize] * mm;
                let mut pt = mm * &xl;
                pt += mm;
                symmetrize(&mut pt);
                let id = if tol > 0.0 && sof[t + 1] == s && close(&covs[next as usize], &pt, tol) {
                    next
                } else {
                    covs.push(pt);
                    covs.len() as u32 - 1
                };
                lags.push(xl);
                let v = (id, lags.len() as u32 - 1);
                memo.insert((s, next), v);
                v
            }
        };
        of_frame[t] = id;
        lag_of_frame[t + 1] = lag;
    }
    sm.covs = covs;
    sm.lags = lags;
    sm.cov_of_frame = of_frame;
    sm.lag_of_frame = lag_of_frame;
    Ok(())
}

/// Back-projection `y_t = V̂ m̃_t + m̄` of all frames (Algorithm 1, last loop), row-major T × D.
pub fn back_project(sm: &Smoothed, model: &Model) -> Vec<f64> {
    let d = model.d();
    let k = model.k();
    let t_len = sm.m.len() / k;
    let mut y = vec![0.0; t_len * d];
    y.par_chunks_mut(d)
        .zip(sm.m.par_chunks(k))
        .for_each(|(row, m)| {
            for (i, o) in row.iter_mut().enumerate() {
                let v = model.row(i);
                *o = model.mean[i] + dot(v, m);
            }
        });
    y
}

/// Predictive standard deviation `sqrt(v_iᵀ P̃_t v_i + r)` of every missing value (0 elsewhere),
/// row-major T × D (`v_iᵀ P̃_t v_i = v_i'ᵀ P̃'_t v_i'`). Needs `smooth(.., want_cov = true)`.
pub fn missing_std(x: &[f64], sm: &Smoothed, model: &Model) -> Vec<f64> {
    let d = model.d();
    let w = &sm.white;
    let mut out = vec![0.0; x.len()];
    out.par_chunks_mut(d).enumerate().for_each(|(t, row)| {
        let p = &sm.covs[sm.cov_of_frame[t] as usize];
        for (i, o) in row.iter_mut().enumerate() {
            if !x[t * d + i].is_nan() {
                continue;
            }
            let s = w.quad_sum(p, std::iter::once(i));
            *o = (s.max(0.0) + model.r).sqrt();
        }
    });
    out
}

/// One EM update (Shumway & Stoffer M-step with `F = I`) of Q and (if `learn_r`) r from a
/// smoothed pass with covariances:
/// `Q = 1/(T−1) Σ_t E[(x̃_t − x̃_{t−1})(x̃_t − x̃_{t−1})ᵀ]` with the lag-one covariance
/// `P̃_{t,t−1} = P̃_t C_{t−1}ᵀ`, and
/// `r = Σ_t Σ_{present i} [(z_ti − m̄_i − v_iᵀ m̃_t)² + v_iᵀ P̃_t v_i] / N_present`.
/// The covariance terms are summed in whitened coordinates and mapped back with `L · Lᵀ`.
pub fn em_update(
    x: &[f64],
    model: &Model,
    pats: &Patterns,
    sm: &Smoothed,
    learn_r: bool,
) -> (DMatrix<f64>, f64) {
    let d = model.d();
    let k = model.k();
    let t_len = x.len() / d;
    let w = &sm.white;
    // Mean terms, accumulated in parallel over frames.
    let (dd, res2, nobs) = (1..t_len)
        .into_par_iter()
        .fold(
            || (DMatrix::<f64>::zeros(k, k), 0.0, 0usize),
            |(mut acc, r2, n), t| {
                let a = &sm.m[(t - 1) * k..t * k];
                let b = &sm.m[t * k..(t + 1) * k];
                for j in 0..k {
                    let dj = b[j] - a[j];
                    for (i, o) in acc.column_mut(j).iter_mut().enumerate() {
                        *o += (b[i] - a[i]) * dj;
                    }
                }
                let (r2b, nb) = if t == 1 {
                    let (x0, n0) = frame_residual(x, model, &sm.m[..k], 0);
                    let (x1, n1) = frame_residual(x, model, b, t);
                    (x0 + x1, n0 + n1)
                } else {
                    frame_residual(x, model, b, t)
                };
                (acc, r2 + r2b, n + nb)
            },
        )
        .reduce(
            || (DMatrix::<f64>::zeros(k, k), 0.0, 0usize),
            |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2),
        );
    // Covariance terms through counts over memoised ids.
    let mut cnt_cov = vec![0.0; sm.covs.len()];
    let mut cnt_lag = vec![0.0; sm.lags.len()];
    let mut cnt_tr: HashMap<(u32, u32), f64> = HashMap::new();
    for t in 0..t_len {
        let c = sm.cov_of_frame[t];
        cnt_cov[c as usize] += if t == 0 || t == t_len - 1 { 1.0 } else { 2.0 };
        if t > 0 {
            cnt_lag[sm.lag_of_frame[t] as usize] += 1.0;
        }
        *cnt_tr.entry((pats.of_frame[t], c)).or_default() += 1.0;
    }
    let sc = weighted_sum(&cnt_cov, &sm.covs, k);
    let sl = weighted_sum(&cnt_lag, &sm.lags, k);
    let white_sum = sc - &sl - sl.transpose();
    let mut s = dd + &w.l * white_sum * w.l.transpose();
    s /= t_len as f64 - 1.0;
    let mut q = s;
    symmetrize(&mut q);
    let floor = 1e-9 * (q.trace() / k as f64).max(1e-12);
    for c in 0..k {
        q[(c, c)] = q[(c, c)].max(0.0) + floor;
    }
    let r = if learn_r && nobs > 0 {
        // tr(G_p P̃) = tr(G_full P̃) − Σ_{missing i} v_iᵀ P̃ v_i (or Σ_{present}), whitened.
        let pairs: Vec<((u32, u32), f64)> = cnt_tr.into_iter().collect();
        let tr: f64 = pairs
            .par_iter()
            .map(|&((p, c), wt)| {
                let miss = &pats.missing[p as usize];
                let pc = &sm.covs[c as usize];
                let v = if miss.len() * 2 <= d {
                    w.g_full.dot(pc) - w.quad_sum(pc, miss.iter().map(|&j| j as usize))
                } else {
                    let mut present = vec![true; d];
                    miss.iter().for_each(|&j| present[j as usize] = false);
                    w.quad_sum(pc, (0..d).filter(|&j| present[j]))
                };
                wt * v
            })
            .sum();
        ((res2 + tr) / nobs as f64).max(1e-12)
    } else {
        model.r
    };
    (q, r)
}

fn frame_residual(x: &[f64], model: &Model, m: &[f64], t: usize) -> (f64, usize) {
    let d = model.d();
    let mut s = 0.0;
    let mut n = 0;
    for (i, z) in x[t * d..(t + 1) * d].iter().enumerate() {
        if z.is_nan() {
            continue;
        }
        let v = model.row(i);
        let e = z - model.mean[i] - dot(v, m);
        s += e * e;
        n += 1;
    }
    (s, n)
}

/// Learns Q and r by `iters` EM iterations (stops early when both change by < 1e-4
/// relatively). Returns the number of iterations run.
pub fn em(
    x: &[f64],
    model: &mut Model,
    pats: &Patterns,
    iters: usize,
    learn_r: bool,
    memo_tol: f64,
) -> Result<usize> {
    for it in 0..iters {
        let sm = smooth(x, model, pats, true, memo_tol)?;
        let (q, r) = em_update(x, model, pats, &sm, learn_r);
        let dq = (&q - &model.q).norm() / model.q.norm().max(1e-300);
        let dr = (r - model.r).abs() / model.r;
        model.q = q;
        model.r = r;
        if dq < 1e-4 && dr < 1e-4 {
            return Ok(it + 1);
        }
    }
    Ok(iters)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Covariance-form Kalman filter + RTS (B&L Appendix A with the A.6 gain), inverting the
    /// innovation covariance per frame: the reference for the information form.
    fn naive(x: &[f64], m: &Model) -> Vec<f64> {
        let (d, k) = (m.d(), m.k());
        let t_len = x.len() / d;
        let vfull = DMatrix::from_row_slice(d, k, &m.v);
        let (mut mean, mut p) = (m.m0.clone(), m.p0.clone());
        let mut mfs = Vec::new();
        let mut pfs: Vec<DMatrix<f64>> = Vec::new();
        let mut pps: Vec<DMatrix<f64>> = Vec::new();
        for t in 0..t_len {
            if t > 0 {
                p = &p + &m.q;
            }
            pps.push(p.clone());
            let pres: Vec<usize> = (0..d).filter(|&i| !x[t * d + i].is_nan()).collect();
            if !pres.is_empty() {
                let h = DMatrix::from_fn(pres.len(), k, |r, c| vfull[(pres[r], c)]);
                let z = DVector::from_iterator(
                    pres.len(),
                    pres.iter().map(|&i| x[t * d + i] - m.mean[i]),
                );
                let s = &h * &p * h.transpose() + DMatrix::identity(pres.len(), pres.len()) * m.r;
                let kg = &p * h.transpose() * s.try_inverse().unwrap();
                mean = &mean + &kg * (z - &h * &mean);
                p = (DMatrix::identity(k, k) - &kg * &h) * &p;
            }
            mfs.push(mean.clone());
            pfs.push(p.clone());
        }
        let mut ms = mfs.clone();
        for t in (0..t_len - 1).rev() {
            let c = &pfs[t] * pps[t + 1].clone().try_inverse().unwrap();
            ms[t] = &mfs[t] + c * (&ms[t + 1] - &mfs[t]);
        }
        ms.iter()
            .flat_map(|v| v.iter().copied().collect::<Vec<_>>())
            .collect()
    }

    fn toy(t_len: usize, d: usize, k: usize, seed: u64) -> (Vec<f64>, Model) {
        let mut rng = crate::gapfill::combine::SplitMix(seed);
        let mut u = || (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
        let a = DMatrix::from_fn(d, k, |_, _| u());
        let basis = a.qr().q();
        let v: Vec<f64> = (0..d)
            .flat_map(|i| (0..k).map(move |c| (i, c)))
            .map(|(i, c)| basis[(i, c)])
            .collect();
        let mut x = Vec::new();
        let mut state = vec![0.0; k];
        for t in 0..t_len {
            for s in state.iter_mut() {
                *s += u();
            }
            for i in 0..d {
                let val: f64 = (0..k).map(|c| basis[(i, c)] * state[c]).sum::<f64>() + 0.01 * u();
                // gaps: coordinate-dependent windows, and frame 7 entirely missing
                let miss = t == 7 || (t % 11 < 3 && i % 4 == 1) || (t > 20 && t < 30 && i < 3);
                x.push(if miss { f64::NAN } else { val + i as f64 });
            }
        }
        let model = Model {
            v,
            mean: (0..d).map(|i| i as f64).collect(),
            q: DMatrix::identity(k, k) * 0.08 + DMatrix::from_element(k, k, 0.01),
            r: 2e-3,
            m0: DVector::zeros(k),
            p0: DMatrix::identity(k, k) * 10.0,
        };
        (x, model)
    }

    #[test]
    fn information_form_equals_covariance_form() {
        let (x, model) = toy(60, 12, 4, 3);
        let pats = Patterns::new(&x, 12);
        let reference = naive(&x, &model);
        for tol in [0.0, 1e-9] {
            let sm = smooth(&x, &model, &pats, true, tol).unwrap();
            let err =
                sm.m.iter()
                    .zip(&reference)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
            assert!(err < 1e-7, "tol {tol}: max difference {err}");
        }
        // memoisation reuses covariances
        let sm = smooth(&x, &model, &pats, false, 1e-9).unwrap();
        assert!(sm.distinct_filter_covariances() < 60);
    }

    #[test]
    fn chunked_filter_matches_sequential() {
        // Long enough for two chunks: the parallel, stitched filter states give the smoothed
        // means and covariances of the sequential recursion.
        let (x, model) = toy(2 * MIN_CHUNK + 100, 12, 4, 21);
        let pats = Patterns::new(&x, 12);
        let seq = smooth(&x, &model, &pats, true, 0.0).unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let par = pool.install(|| smooth(&x, &model, &pats, true, 1e-9).unwrap());
        let scale = seq.m.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
        let err = seq
            .m
            .iter()
            .zip(&par.m)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(err <= 1e-7 * scale, "max difference {err} (scale {scale})");
        for t in [0, MIN_CHUNK + 3, 2 * MIN_CHUNK + 99] {
            assert!(close(&seq.smoothed_cov(t), &par.smoothed_cov(t), 1e-6));
        }
    }

    #[test]
    fn smoothed_covariance_matches_two_pass_definition() {
        // With no memo merging, covariances are symmetric positive semi-definite and smaller
        // than the filter covariance in the trace.
        let (x, model) = toy(40, 9, 3, 5);
        let pats = Patterns::new(&x, 9);
        let sm = smooth(&x, &model, &pats, true, 0.0).unwrap();
        for (t, &c) in sm.cov_of_frame.iter().enumerate() {
            let _ = c;
            let ps = &sm.smoothed_cov(t);
            let pf = &sm.filter_cov(t);
            assert!(ps.trace() <= pf.trace() * (1.0 + 1e-9));
            assert!(ps.clone().cholesky().is_some());
        }
    }

    #[test]
    fn em_increases_fit_and_stays_positive() {
        let (x, mut model) = toy(200, 12, 4, 9);
        model.r = 1.0;
        model.q = DMatrix::identity(4, 4);
        let pats = Patterns::new(&x, 12);
        let n = em(&x, &mut model, &pats, 30, true, 1e-9).unwrap();
        assert!(n >= 1);
        // true noise: r = 0.01² / 12 ≈ 8e-6, q = 1/12 ≈ 0.083 per axis
        assert!(model.r < 1e-3, "learned r {}", model.r);
        let qd = model.q.trace() / 4.0;
        assert!(qd > 0.04 && qd < 0.17, "learned q {qd}");
    }
}
