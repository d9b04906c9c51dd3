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
    add_outer, chol_solve_in_place, cholesky_in_place, cholesky_lower, close, dot,
    inverse_from_cholesky, pack_lower, packed_col, packed_len, spd_inverse_lower,
    sym_matvec_packed_add, symmetrize, unpack_symmetric, unpack_symmetric_into,
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

    pub(super) fn all_missing(&self, p: u32, d: usize) -> bool {
        self.missing[p as usize].len() == d
    }
}

/// The slowest per-frame decay of the smoother with every coordinate observed: the largest
/// steady-state gain `μ_j = 2 / (2 + a_j + √(a_j (4 + a_j)))`, `a_j = g_j / r` over the
/// eigenvalues `g_j` of the whitened `G_full` (see [`super::lowrank`]). A frame `n` frames away
/// moves a smoothed mean by a factor of at most about `μⁿ` through observed stretches.
pub fn slowest_decay(model: &Model) -> Result<f64> {
    let w = White::new(model)?;
    let g = nalgebra::SymmetricEigen::new(w.g_full.clone()).eigenvalues;
    let a = g.iter().cloned().fold(f64::INFINITY, f64::min).max(0.0) * w.inv_r;
    Ok(2.0 / (2.0 + a + (a * (4.0 + a)).sqrt()))
}

/// The model in whitened coordinates `x' = L⁻¹ x̃`, `Q = L Lᵀ` (so `Q' = I`).
#[derive(Debug, Clone)]
pub(super) struct White {
    pub(super) k: usize,
    pub(super) d: usize,
    /// Lower Cholesky factor L of Q.
    pub(super) l: DMatrix<f64>,
    /// Rows `v_i' = Lᵀ v_i` (row-major D × d̂).
    pub(super) v: Vec<f64>,
    /// `Σ_i v_i' v_i'ᵀ` over all coordinates.
    pub(super) g_full: DMatrix<f64>,
    /// Prior information `(L⁻¹ P₀ L⁻ᵀ)⁻¹ = Lᵀ P₀⁻¹ L`, packed lower triangle.
    pub(super) lam0_packed: Vec<f64>,
    /// Prior mean `L⁻¹ m₀`.
    pub(super) m0: DVector<f64>,
    pub(super) inv_r: f64,
    /// `G_p / r` (packed lower triangles) of the patterns seen in more than one frame, at
    /// `gain_slot[p] · packed_len(k)`; empty until [`White::cache_pattern_gains`].
    gains: Vec<f64>,
    gain_slot: Vec<u32>,
}

impl White {
    pub(super) fn new(model: &Model) -> Result<Self> {
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
        let mut lam0_packed = Vec::with_capacity(packed_len(k));
        pack_lower(lam0.as_slice(), k, &mut lam0_packed);
        Ok(Self {
            k,
            d,
            l,
            v,
            g_full,
            lam0_packed,
            m0,
            inv_r: 1.0 / model.r,
            gains: Vec::new(),
            gain_slot: Vec::new(),
        })
    }

    /// Computes `G_p / r` once for every pattern that more than one frame has (within a
    /// 256 MB budget), so that new filter states copy it instead of summing `v_i v_iᵀ` over the
    /// pattern's missing (or present) coordinates each time (85_12: 764 patterns, 4,900 states
    /// per pass). Same values bit for bit as [`Self::info_gain_into`].
    fn cache_pattern_gains(&mut self, pats: &Patterns) {
        const BUDGET: usize = 256 << 20;
        let tri = packed_len(self.k);
        let mut count = vec![0u32; pats.missing.len()];
        for &p in &pats.of_frame {
            count[p as usize] += 1;
        }
        let mut slot = vec![u32::MAX; count.len()];
        let mut cached = Vec::new();
        for (p, &c) in count.iter().enumerate() {
            if c > 1 && pats.missing[p].len() < self.d && (cached.len() + 1) * tri * 8 <= BUDGET {
                slot[p] = cached.len() as u32;
                cached.push(p);
            }
        }
        let mut gains = vec![0.0; cached.len() * tri];
        let this = &*self;
        gains
            .par_chunks_mut(tri.max(1))
            .zip(cached.par_iter())
            .for_each_init(
                || DMatrix::zeros(this.k, this.k),
                |g, (out, &p)| {
                    this.info_gain_into(&pats.missing[p], g);
                    let mut packed = Vec::with_capacity(tri);
                    pack_lower(g.as_slice(), this.k, &mut packed);
                    out.copy_from_slice(&packed);
                },
            );
        self.gains = gains;
        self.gain_slot = slot;
    }

    /// The cached `G_p / r` of pattern `p` (packed lower triangle), if any.
    #[inline]
    fn cached_gain(&self, p: u32) -> Option<&[f64]> {
        let s = *self.gain_slot.get(p as usize)?;
        if s == u32::MAX {
            return None;
        }
        let tri = packed_len(self.k);
        Some(&self.gains[s as usize * tri..(s as usize + 1) * tri])
    }

    #[inline]
    fn row(&self, i: usize) -> &[f64] {
        &self.v[i * self.k..(i + 1) * self.k]
    }

    /// `G_p / r` of a pattern into `g` (`k × k`): `G_full − Σ_{missing}` or `Σ_{present}`,
    /// whichever is shorter.
    fn info_gain_into(&self, miss: &[u32], g: &mut DMatrix<f64>) {
        if miss.len() * 2 <= self.d {
            g.copy_from(&self.g_full);
            add_outer(g, &self.v, self.k, miss, -1.0);
        } else {
            let mut present = vec![true; self.d];
            miss.iter().for_each(|&j| present[j as usize] = false);
            let idx: Vec<u32> = (0..self.d as u32)
                .filter(|&j| present[j as usize])
                .collect();
            g.fill(0.0);
            add_outer(g, &self.v, self.k, &idx, 1.0);
        }
        g.as_mut_slice().iter_mut().for_each(|x| *x *= self.inv_r);
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

/// A memoised filter state (whitened coordinates). Its matrix `M_t = (I + Λ_t)⁻¹`, the RTS
/// gain `C_t` (A.6), with `I − M_t = P̂_{t+1}⁻¹` (A.2), is stored packed (lower triangle,
/// column by column, `packed_len(k)` values) at `off` in arena `arena`. The information
/// `Λ_t = P_t⁻¹` (A.4) is not stored: the means need only `M_t` (information filter, see
/// [`smooth`]), and the few explicit filter covariances are rebuilt from the predecessor and
/// the pattern ([`state_cov`]). One contiguous arena per chain avoids an allocation per state
/// (25,000 states of d̂ = 41 take 170 MB; full matrices of `Λ_t` and `M_t` took 680 MB).
#[derive(Debug, Clone, Copy)]
struct FState {
    /// The predecessor whose `P̂⁻¹ = I − M_pred` (or the prior) entered `Λ_t` (A.2, A.4).
    pred: u32,
    /// The missing-value pattern of the state's frames (`G_t` of A.4).
    pat: u32,
    /// Arena holding the matrix.
    arena: u32,
    /// Offset of `M_t` in the arena.
    off: usize,
    /// Upper bound on `‖P_t‖₂`.
    pnorm: f64,
}

/// Packed matrices of the filter states, one arena per chain.
#[derive(Debug, Clone, Default)]
struct Arenas {
    /// Values of one packed triangle.
    tri: usize,
    arenas: Vec<Vec<f64>>,
}

impl Arenas {
    fn new(k: usize) -> Self {
        Self {
            tri: packed_len(k),
            arenas: vec![Vec::new()],
        }
    }
    /// Packed lower triangle of `M_t`.
    #[inline]
    fn m(&self, st: &FState) -> &[f64] {
        &self.arenas[st.arena as usize][st.off..st.off + self.tri]
    }
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
    /// Filter state id per frame.
    state_of_frame: Vec<u32>,
    /// Filter states.
    states: Vec<FState>,
    /// Their matrices.
    mats: Arenas,
    white: White,
    /// Missing coordinates per pattern (rebuilds `Λ_t` of a state, [`state_cov`]).
    missing: Vec<Vec<u32>>,
    /// The memo tolerance of the pass (also the stitching tolerance of [`cov_sums`]).
    tol: f64,
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
        let p = state_cov(&self.white, &self.missing, &self.states, &self.mats, st);
        let l = &self.white.l;
        l * p * l.transpose()
    }
}

/// `‖A − B‖_F` of two predicted informations `P̂⁻¹` given by their predecessor ids
/// (`P̂⁻¹ = I − M_pred`, or the prior information), from the packed lower triangles.
fn lam_dist(states: &[FState], mats: &Arenas, w: &White, a: u32, b: u32) -> f64 {
    if a == b {
        return 0.0;
    }
    let k = w.k;
    let ident = |x: u32| if x == PRIOR { 1.0 } else { 0.0 };
    // For a state id, the stored matrix enters with sign −1 and the identity is added.
    let (sa, sgn_a) = if a == PRIOR {
        (w.lam0_packed.as_slice(), 1.0)
    } else {
        (mats.m(&states[a as usize]), -1.0)
    };
    let (sb, sgn_b) = if b == PRIOR {
        (w.lam0_packed.as_slice(), 1.0)
    } else {
        (mats.m(&states[b as usize]), -1.0)
    };
    // Identity parts cancel unless exactly one side is the prior.
    let id_diff = (1.0 - ident(a)) - (1.0 - ident(b));
    let mut s = 0.0;
    for j in 0..k {
        let (c0, c1) = (packed_col(k, j), packed_col(k, j + 1));
        for (i, (x, y)) in sa[c0..c1].iter().zip(&sb[c0..c1]).enumerate() {
            let mut d = sgn_a * x - sgn_b * y;
            if i == 0 {
                d += id_diff;
                s += d * d;
            } else {
                // Off-diagonal entries count twice in the Frobenius norm.
                s += 2.0 * d * d;
            }
        }
    }
    s.sqrt()
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
    let mut w = White::new(model)?;
    w.cache_pattern_gains(pats);
    let (d, k) = (w.d, w.k);
    let t_len = x.len() / d;

    let (states, mats, state_of_frame) = filter_states(&w, pats, memo_tol)?;
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
    // Means in information form (A.2-A.7 with Q' = I), which need only M_t: with the
    // information vector η_t = Λ_t m_t,
    //   forward   η_t = P̂_t⁻¹ m̂_t + b_t / r = M_{t−1} η_{t−1} + b_t / r
    //             (P̂_t⁻¹ m̂_t = (I − M_{t−1}) P_{t−1} η_{t−1} and (I − M) Λ⁻¹ = (I + Λ)⁻¹ = M);
    //   backward  m̃_t = m_t + M_t (m̃_{t+1} − m_t) = (I − M_t) P_t η_t + M_t m̃_{t+1}
    //             = M_t (η_t + m̃_{t+1}),   m̃_{T−1} = P_{T−1} η_{T−1}.
    // Only the last frame solves with Λ (rebuilt from its predecessor). Before: a Cholesky
    // factor of Λ_t per state and a solve plus G_t m̂_t per frame.
    // The shortcut P̂_t⁻¹ m̂_t = M_{t−1} η_{t−1} holds when frame t's state was computed from
    // frame t−1's. A merged state (memo test) or the first state adopted from a parallel chunk
    // was computed from another, nearby predecessor: there m_{t−1} = Λ_{t−1}⁻¹ η_{t−1} is
    // formed explicitly and P̂_t⁻¹ is the state's own predecessor's, as in the covariance form,
    // so an approximate state perturbs the means by its covariance error times the innovation
    // (not times the mean). The backward step uses only M_t and Λ_t of one state: always exact.
    let pred_info_add = |pred: u32, m: &[f64], out: &mut [f64]| {
        if pred == PRIOR {
            sym_matvec_packed_add(&w.lam0_packed, k, m, out);
        } else {
            // (I − M_pred) m
            let mut mm = vec![0.0; k];
            sym_matvec_packed_add(mats.m(&states[pred as usize]), k, m, &mut mm);
            for ((o, a), b) in out.iter_mut().zip(m).zip(&mm) {
                *o += a - b;
            }
        }
    };
    let mut chols: HashMap<u32, DMatrix<f64>> = HashMap::new();
    let mut eta = bz; // η_t, filled in place over the data terms b_t
    for t in 0..t_len {
        let (done, rest) = eta.split_at_mut(t * k);
        let e_t = &mut rest[..k];
        e_t.iter_mut().for_each(|v| *v *= w.inv_r);
        let pred = states[state_of_frame[t] as usize].pred;
        if t == 0 {
            pred_info_add(pred, w.m0.as_slice(), e_t);
        } else {
            let sp = state_of_frame[t - 1];
            let eta_prev = &done[(t - 1) * k..];
            if pred == sp {
                sym_matvec_packed_add(mats.m(&states[sp as usize]), k, eta_prev, e_t);
            } else {
                let chol = match chols.entry(sp) {
                    std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
                    std::collections::hash_map::Entry::Vacant(e) => e.insert(state_chol(
                        &w,
                        &pats.missing,
                        &states,
                        &mats,
                        &states[sp as usize],
                    )?),
                };
                let mut m_prev = eta_prev.to_vec();
                chol_solve_in_place(chol, &mut m_prev);
                pred_info_add(pred, &m_prev, e_t);
            }
        }
    }
    let mut ms = vec![0.0; t_len * k];
    if t_len > 0 {
        let last = t_len - 1;
        let chol = state_chol(
            &w,
            &pats.missing,
            &states,
            &mats,
            &states[state_of_frame[last] as usize],
        )?;
        let m_last = &mut ms[last * k..];
        m_last.copy_from_slice(&eta[last * k..]);
        chol_solve_in_place(&chol, m_last);
    }
    let mut sum = vec![0.0; k];
    for t in (0..t_len.saturating_sub(1)).rev() {
        let c = mats.m(&states[state_of_frame[t] as usize]);
        let (head, tail) = ms.split_at_mut((t + 1) * k);
        for ((s, e), m) in sum.iter_mut().zip(&eta[t * k..(t + 1) * k]).zip(&tail[..k]) {
            *s = e + m;
        }
        sym_matvec_packed_add(c, k, &sum, &mut head[t * k..]);
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
        state_of_frame,
        states,
        mats,
        white: w,
        missing: pats.missing.clone(),
        tol: memo_tol,
    };
    if want_cov && t_len > 0 {
        smoothed_covariances(&mut sm, memo_tol)?;
    }
    Ok(sm)
}

/// Frames per chunk below which the filter covariances are computed sequentially.
const MIN_CHUNK: usize = 800;
/// Burn-in frames a chunk starts before its first frame (from the prior). On CMU 85_12 and
/// HDM05 (d̂ = 44 / 38) the chunk's states agree with the exact chain at its first frame after
/// 100 frames already; a chunk that does not agree is continued exactly (slower, not wrong).
const BURN_IN: usize = 200;
/// Frames between two junction tests of [`filter_states`].
const TEST_EVERY: usize = 8;

/// Memoised filter states of a stretch of frames.
struct Chain {
    states: Vec<FState>,
    mats: Arenas,
    by_pat: Vec<Vec<u32>>,
    trans: HashMap<(u32, u32), u32>,
    sof: Vec<u32>,
    scratch: Scratch,
}

/// Work matrices of one transition (`k × k` each), reused across states.
struct Scratch {
    ipi: DMatrix<f64>,
    w: Vec<f64>,
    m: DMatrix<f64>,
}

impl Chain {
    fn new(n_pat: usize, k: usize) -> Self {
        let z = || DMatrix::zeros(k, k);
        Self {
            states: Vec::new(),
            mats: Arenas::new(k),
            by_pat: vec![Vec::new(); n_pat],
            trans: HashMap::new(),
            sof: Vec::new(),
            scratch: Scratch {
                ipi: z(),
                w: vec![0.0; k * k],
                m: z(),
            },
        }
    }

    /// The state of frame `t` reached from state `prev` (memoised transition).
    fn step(&mut self, w: &White, pats: &Patterns, prev: u32, t: usize, tol: f64) -> Result<u32> {
        let pat = pats.of_frame[t];
        if let Some(&s) = self.trans.get(&(prev, pat)) {
            return Ok(s);
        }
        let s = self.new_transition(w, pats, prev, pat, tol)?;
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
        // At most one new state per frame: reserve once (address space only; pages are
        // touched when written) instead of growing by doubling (copies and refaults).
        let need = frames.len() * self.mats.tri;
        let arena = &mut self.mats.arenas[0];
        arena.reserve(need.saturating_sub(arena.capacity() - arena.len()));
        self.sof.reserve(frames.len());
        for t in frames {
            prev = self.step(w, pats, prev, t, tol)?;
            self.sof.push(prev);
        }
        Ok(())
    }
}

/// `info ← Λ_t = P̂_t⁻¹ + G_t / r` (A.2, A.4; lower triangle and the diagonal; the strict
/// upper triangle is unspecified) of the state reached from `pred` with pattern `pat`.
fn info_into(
    w: &White,
    missing: &[Vec<u32>],
    states: &[FState],
    mats: &Arenas,
    pred: u32,
    pat: u32,
    info: &mut DMatrix<f64>,
) {
    let k = w.k;
    let (add, sign, ident) = if pred == PRIOR {
        (w.lam0_packed.as_slice(), 1.0, 0.0)
    } else {
        (mats.m(&states[pred as usize]), -1.0, 1.0)
    };
    let cached = w.cached_gain(pat);
    if cached.is_none() {
        let miss = &missing[pat as usize];
        if miss.len() == w.d {
            info.fill(0.0);
        } else {
            w.info_gain_into(miss, info);
        }
    }
    let info = info.as_mut_slice();
    for j in 0..k {
        let (c0, c1) = (packed_col(k, j), packed_col(k, j + 1));
        let col = &add[c0..c1];
        let dst = &mut info[j * k + j..(j + 1) * k];
        if let Some(g) = cached {
            for ((o, a), gv) in dst.iter_mut().zip(col).zip(&g[c0..c1]) {
                *o = gv + sign * a;
            }
        } else {
            for (o, a) in dst.iter_mut().zip(col) {
                *o += sign * a;
            }
        }
        info[j * k + j] += ident;
    }
}

/// Lower Cholesky factor of the information `Λ_t` of a state (rebuilt from its predecessor).
fn state_chol(
    w: &White,
    missing: &[Vec<u32>],
    states: &[FState],
    mats: &Arenas,
    st: &FState,
) -> Result<DMatrix<f64>> {
    let mut l = DMatrix::zeros(w.k, w.k);
    info_into(w, missing, states, mats, st.pred, st.pat, &mut l);
    if !cholesky_in_place(l.as_mut_slice(), w.k) {
        return Err(AcmError::Numerical(
            "the filter information matrix is not positive definite".into(),
        ));
    }
    Ok(l)
}

/// Explicit `P = Λ⁻¹` of a state (NaN if `Λ` is not numerically positive definite).
fn state_cov(
    w: &White,
    missing: &[Vec<u32>],
    states: &[FState],
    mats: &Arenas,
    st: &FState,
) -> DMatrix<f64> {
    let k = w.k;
    let Ok(l) = state_chol(w, missing, states, mats, st) else {
        return DMatrix::from_element(k, k, f64::NAN);
    };
    let mut ws = vec![0.0; k * k];
    let mut p = DMatrix::zeros(k, k);
    inverse_from_cholesky(l.as_slice(), k, &mut ws, p.as_mut_slice());
    p
}

/// Filter states of all frames (A.2, A.4). Sequential for short sequences or `tol = 0`; else
/// the frames are split into one chunk per thread, each chunk computed in parallel from the
/// prior `BURN_IN` frames before its start, and stitched: from a chunk's first frame on, the
/// exact recursion continues from the previous chunk's last state until its covariance agrees
/// with the chunk's own within `tol` (relative, max norm — the memo merge criterion); from
/// there the chunk's states are used. The Riccati recursion is a contraction, so the burn-in
/// forgets the prior and the stitched states are those of the sequential recursion up to `tol`.
fn filter_states(w: &White, pats: &Patterns, tol: f64) -> Result<(Vec<FState>, Arenas, Vec<u32>)> {
    let t_len = pats.of_frame.len();
    let n_pat = pats.missing.len();
    let n = if tol > 0.0 {
        rayon::current_num_threads().min(t_len / MIN_CHUNK).max(1)
    } else {
        1
    };
    // Equal work per thread: chunks after the first also compute BURN_IN earlier frames.
    let work = (t_len + (n - 1) * BURN_IN) / n;
    let bound = |c: usize| {
        if c == 0 {
            0
        } else if c == n {
            t_len
        } else {
            c * work - (c - 1) * BURN_IN
        }
    };
    let mut locals = (0..n)
        .into_par_iter()
        .map(|c| {
            let start = if c == 0 {
                0
            } else {
                bound(c).saturating_sub(BURN_IN)
            };
            let mut ch = Chain::new(n_pat, w.k);
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
                        &state_cov(
                            w,
                            &pats.missing,
                            &g.states,
                            &g.mats,
                            &g.states[sid as usize],
                        ),
                        &state_cov(
                            w,
                            &pats.missing,
                            &lc.states,
                            &lc.mats,
                            &lc.states[lsid as usize],
                        ),
                        tol,
                    )
                {
                    adopt = Some(t);
                    break;
                }
            }
            g.sof.push(sid);
        }
        if let (Some(t0), Some((mut lc, start))) = (adopt, local) {
            let base = g.states.len() as u32;
            let arena = g.mats.arenas.len() as u32;
            g.mats.arenas.push(std::mem::take(&mut lc.mats.arenas[0]));
            g.states.extend(lc.states.into_iter().map(|mut st| {
                if st.pred != PRIOR {
                    st.pred += base;
                }
                st.arena = arena;
                st
            }));
            g.sof.extend(lc.sof[t0 - start..].iter().map(|&s| s + base));
            // The chunk's states continue the chain; the global memo table stays valid.
        }
    }
    debug_assert_eq!(g.sof.len(), t_len);
    Ok((g.states, g.mats, g.sof))
}

impl Chain {
    /// Computes the state reached from `prev` with pattern `pat` (A.2 + A.4 in whitened
    /// information form), or merges it with a known state of the same pattern.
    fn new_transition(
        &mut self,
        w: &White,
        pats: &Patterns,
        prev: u32,
        pat: u32,
        tol: f64,
    ) -> Result<u32> {
        let k = w.k;
        // Merge with a known state of the same pattern if the bound guarantees a relative
        // change of at most tol (module docs).
        if tol > 0.0 {
            for &s in self.by_pat[pat as usize]
                .iter()
                .rev()
                .take(MERGE_CANDIDATES)
            {
                let st = &self.states[s as usize];
                if st.pnorm.is_finite()
                    && st.pnorm * lam_dist(&self.states, &self.mats, w, prev, st.pred) <= tol
                {
                    return Ok(s);
                }
            }
        }
        let sc = &mut self.scratch;
        // Λ_t = P̂_t⁻¹ + G_t / r, P̂_t⁻¹ = I − M_{t−1} (lower triangle; Cholesky reads no more).
        // Λ_t itself is not factored: the means need only M_t (see `smooth`).
        info_into(
            w,
            &pats.missing,
            &self.states,
            &self.mats,
            prev,
            pat,
            &mut sc.ipi,
        );
        // M_t = (I + Λ_t)⁻¹.
        for c in 0..k {
            sc.ipi[(c, c)] += 1.0;
        }
        if !cholesky_in_place(sc.ipi.as_mut_slice(), k) {
            return Err(AcmError::Numerical(
                "I + information is not positive definite".into(),
            ));
        }
        inverse_from_cholesky(sc.ipi.as_slice(), k, &mut sc.w, sc.m.as_mut_slice());
        if !sc.m.iter().all(|v| v.is_finite()) {
            return Err(AcmError::Numerical("non-finite RTS gain".into()));
        }
        let pnorm = if tol > 0.0 { p_norm_bound(&sc.m) } else { 0.0 };
        let arena = &mut self.mats.arenas[0];
        let off = arena.len();
        pack_lower(sc.m.as_slice(), k, arena);
        let id = self.states.len() as u32;
        self.states.push(FState {
            pred: prev,
            pat,
            arena: 0,
            off,
            pnorm,
        });
        self.by_pat[pat as usize].push(id);
        Ok(id)
    }
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

/// Smoothed covariances (A.8) `P̃_t = M_t + M_t P̃_{t+1} M_t` of every frame (whitened, module
/// docs), memoised on (filter state, next smoothed covariance). EM uses [`cov_sums`] instead.
fn smoothed_covariances(sm: &mut Smoothed, tol: f64) -> Result<()> {
    let states = &sm.states;
    let mats = &sm.mats;
    let sof = &sm.state_of_frame;
    let t_len = sof.len();
    let k = sm.white.k;
    let mut covs: Vec<DMatrix<f64>> = Vec::new();
    let mut of_frame = vec![0u32; t_len];
    let mut memo: HashMap<(u32, u32), u32> = HashMap::new();
    // P̃_T = P_T = Λ_T⁻¹.
    let last = &states[sof[t_len - 1] as usize];
    covs.push(state_cov(&sm.white, &sm.missing, states, mats, last));
    for t in (0..t_len.saturating_sub(1)).rev() {
        let s = sof[t];
        let next = of_frame[t + 1];
        let id = match memo.get(&(s, next)) {
            Some(&v) => v,
            None => {
                let mm = &unpack_symmetric(mats.m(&states[s as usize]), k);
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
                memo.insert((s, next), id);
                id
            }
        };
        of_frame[t] = id;
    }
    sm.covs = covs;
    sm.cov_of_frame = of_frame;
    Ok(())
}

/// Back-projection `y_t = V̂ m̃_t + m̄` of all frames (Algorithm 1, last loop), row-major T × D.
pub fn back_project(sm: &Smoothed, model: &Model) -> Vec<f64> {
    back_project_means(&sm.m, model)
}

/// Back-projection `y_t = V̂ m̃_t + m̄` of the row-major `T × d̂` means `m` (one matrix
/// product), row-major `T × D`.
pub fn back_project_means(m: &[f64], model: &Model) -> Vec<f64> {
    let d = model.d();
    let k = model.k();
    let t_len = m.len() / k;
    // Column-major D × T = row-major T × D.
    let mt = DMatrix::from_column_slice(k, t_len, m);
    let v = DMatrix::from_row_slice(d, k, &model.v);
    let mut y = v * mt;
    y.as_mut_slice().par_chunks_mut(d).for_each(|row| {
        for (o, mb) in row.iter_mut().zip(&model.mean) {
            *o += mb;
        }
    });
    y.data.into()
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

/// Sums of the smoothed second moments the M-step needs (whitened coordinates).
struct CovSums {
    /// `Σ_t c_t P̃_t`, `c_t = 1` at the first and last frame and 2 inside.
    cov: DMatrix<f64>,
    /// `Σ_t X_t`, `X_t = P̃_{t+1} M_t` (`P̃_{t+1,t} = X_tᵀ`).
    lag: DMatrix<f64>,
    /// `Σ_t tr(G_{p_t} P̃_t)` (`Σ_{present i} v_iᵀ P̃_t v_i`).
    tr: f64,
}

/// Frames of a backward chunk below which [`cov_sums`] runs sequentially.
const MIN_BWD_CHUNK: usize = 600;
/// Frames a backward chunk starts after its last frame, from the filter covariance.
const BWD_BURN_IN: usize = 200;

/// The smoothed covariances (A.8) `P̃_t = M_t + M_t P̃_{t+1} M_t`, `P̃_{T−1} = P_{T−1}`, and
/// lag-one terms `X_t = P̃_{t+1} M_t`, summed on the fly (nothing per frame is stored).
/// One chunk of frames per thread: the last chunk is exact; every other chunk starts
/// `BWD_BURN_IN` frames after its end from the filter covariance (an upper bound of the
/// smoothed one) and is used if its `P̃` at the next chunk's first frame agrees with the exact
/// one within the memo tolerance (relative, max norm), else it is recomputed from the exact
/// value. The backward recursion contracts like `M_t ⊗ M_t`, so the start is forgotten.
fn cov_sums(sm: &Smoothed, pats: &Patterns) -> Result<CovSums> {
    let t_len = sm.state_of_frame.len();
    let k = sm.white.k;
    let n = if sm.tol > 0.0 {
        rayon::current_num_threads()
            .min(t_len / MIN_BWD_CHUNK)
            .max(1)
    } else {
        1
    };
    // Equal work per thread: chunks before the last also run BWD_BURN_IN later frames.
    let work = (t_len + (n - 1) * BWD_BURN_IN) / n;
    let bound = |c: usize| {
        if c == n {
            t_len
        } else {
            // (n > 1 implies work >= MIN_BWD_CHUNK > BWD_BURN_IN; with n = 1 only c = 0 here)
            c * work.saturating_sub(BWD_BURN_IN)
        }
    };
    let last_frame = |c: usize| {
        if c + 1 == n {
            t_len - 1
        } else {
            (bound(c + 1) + BWD_BURN_IN).min(t_len - 1)
        }
    };
    let start_cov = |t: usize| {
        let st = &sm.states[sm.state_of_frame[t] as usize];
        state_cov(&sm.white, &sm.missing, &sm.states, &sm.mats, st)
    };
    let mut parts: Vec<Chunk> = (0..n)
        .into_par_iter()
        .map(|c| {
            let from = last_frame(c);
            backward_chunk(sm, pats, bound(c), bound(c + 1), from, start_cov(from))
        })
        .collect();
    // Join from the end: chunk c is kept if its P̃ at bound(c + 1) matches the (exact) first
    // value of chunk c + 1, else recomputed from that value.
    for c in (0..n.saturating_sub(1)).rev() {
        let exact = parts[c + 1].at_lo.clone();
        let ok = parts[c]
            .at_hi
            .as_ref()
            .is_some_and(|p| close(p, &exact, sm.tol));
        if !ok {
            parts[c] = backward_chunk(sm, pats, bound(c), bound(c + 1), bound(c + 1), exact);
        }
    }
    let mut out = CovSums {
        cov: DMatrix::zeros(k, k),
        lag: DMatrix::zeros(k, k),
        tr: 0.0,
    };
    for p in parts {
        out.cov += p.sums.cov;
        out.lag += p.sums.lag;
        out.tr += p.sums.tr;
    }
    if !(out.cov.iter().all(|v| v.is_finite()) && out.tr.is_finite()) {
        return Err(AcmError::Numerical(
            "non-finite smoothed covariance in the EM step".into(),
        ));
    }
    Ok(out)
}

/// `acc += a · m`.
fn add_scaled(acc: &mut DMatrix<f64>, a: f64, m: &DMatrix<f64>) {
    acc.iter_mut().zip(m.iter()).for_each(|(o, v)| *o += a * v);
}

/// One backward chunk of [`cov_sums`].
struct Chunk {
    /// Sums over the frames `lo..hi`.
    sums: CovSums,
    /// `P̃_lo`.
    at_lo: DMatrix<f64>,
    /// `P̃_hi` as computed by this chunk (from its burn-in), if `hi` was visited.
    at_hi: Option<DMatrix<f64>>,
}

/// Runs the backward recursion from frame `from` (with `P̃_from = p_from`) down to `lo`,
/// summing the terms of the frames `lo..hi` (`from ≥ hi − 1`).
fn backward_chunk(
    sm: &Smoothed,
    pats: &Patterns,
    lo: usize,
    hi: usize,
    from: usize,
    p_from: DMatrix<f64>,
) -> Chunk {
    let t_len = sm.state_of_frame.len();
    let w = &sm.white;
    let (k, d) = (w.k, w.d);
    let weight = |t: usize| if t == 0 || t + 1 == t_len { 1.0 } else { 2.0 };
    // tr(G_p P̃) = tr(G_full P̃) − Σ_{missing i} v_iᵀ P̃ v_i (or Σ_{present}), whitened.
    let tr_term = |t: usize, pc: &DMatrix<f64>| -> f64 {
        let miss = &pats.missing[pats.of_frame[t] as usize];
        if miss.len() * 2 <= d {
            w.g_full.dot(pc) - w.quad_sum(pc, miss.iter().map(|&j| j as usize))
        } else {
            let mut present = vec![true; d];
            miss.iter().for_each(|&j| present[j as usize] = false);
            w.quad_sum(pc, (0..d).filter(|&j| present[j]))
        }
    };
    let mut sums = CovSums {
        cov: DMatrix::zeros(k, k),
        lag: DMatrix::zeros(k, k),
        tr: 0.0,
    };
    let mut at_hi = (from == hi).then(|| p_from.clone());
    let mut cur = p_from;
    if from < hi {
        add_scaled(&mut sums.cov, weight(from), &cur);
        sums.tr += tr_term(from, &cur);
    }
    let mut x = DMatrix::zeros(k, k);
    let mut next = DMatrix::zeros(k, k);
    let mut mm = DMatrix::zeros(k, k);
    for t in (lo..from).rev() {
        unpack_symmetric_into(
            sm.mats.m(&sm.states[sm.state_of_frame[t] as usize]),
            k,
            mm.as_mut_slice(),
        );
        // X_t = P̃_{t+1} M_t, P̃_t = M_t + M_t X_t (A.8, module docs).
        x.gemm(1.0, &cur, &mm, 0.0);
        next.copy_from(&mm);
        next.gemm(1.0, &mm, &x, 1.0);
        symmetrize(&mut next);
        std::mem::swap(&mut cur, &mut next);
        if t == hi {
            at_hi = Some(cur.clone());
        }
        if t < hi {
            add_scaled(&mut sums.cov, weight(t), &cur);
            sums.lag += &x;
            sums.tr += tr_term(t, &cur);
        }
    }
    Chunk {
        sums,
        at_lo: cur,
        at_hi,
    }
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
) -> Result<(DMatrix<f64>, f64)> {
    let d = model.d();
    let k = model.k();
    let t_len = x.len() / d;
    let w = &sm.white;
    // Mean terms, accumulated in parallel over fixed blocks of frames and summed in block
    // order (a work-stealing reduce would sum in a different order on every run).
    const BLOCK: usize = 1024;
    let blocks: Vec<(DMatrix<f64>, f64, usize)> = (0..(t_len - 1).div_ceil(BLOCK))
        .into_par_iter()
        .map(|blk| {
            let (mut acc, mut r2, mut n) = (DMatrix::<f64>::zeros(k, k), 0.0, 0usize);
            for t in 1 + blk * BLOCK..(1 + (blk + 1) * BLOCK).min(t_len) {
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
                r2 += r2b;
                n += nb;
            }
            (acc, r2, n)
        })
        .collect();
    let (dd, res2, nobs) = blocks
        .into_iter()
        .fold((DMatrix::<f64>::zeros(k, k), 0.0, 0usize), |a, b| {
            (a.0 + b.0, a.1 + b.1, a.2 + b.2)
        });
    // Covariance terms (A.8 recursion, summed on the fly in parallel chunks).
    let sums = cov_sums(sm, pats)?;
    let (sc, sl) = (sums.cov, sums.lag);
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
        ((res2 + sums.tr) / nobs as f64).max(1e-12)
    } else {
        model.r
    };
    Ok((q, r))
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
        let sm = smooth(x, model, pats, false, memo_tol)?;
        let (q, r) = em_update(x, model, pats, &sm, learn_r)?;
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
    fn chunked_em_sums_match_the_sequential_recursion() {
        // Fast forgetting (chunks kept) and slow forgetting (r ≫ Q: the chunk start is not
        // forgotten within the burn-in, so chunks are recomputed): both equal the sums over the
        // stored sequential smoothed covariances.
        for r in [2e-3, 1e3] {
            let (x, mut model) = toy(2 * MIN_BWD_CHUNK + 150, 12, 4, 33);
            model.r = r;
            let pats = Patterns::new(&x, 12);
            let seq = smooth(&x, &model, &pats, true, 0.0).unwrap();
            let k = 4;
            let t_len = seq.cov_of_frame.len();
            let mut cov = DMatrix::zeros(k, k);
            let mut lag = DMatrix::zeros(k, k);
            let mut tr = 0.0;
            for t in 0..t_len {
                let p = &seq.covs[seq.cov_of_frame[t] as usize];
                let wt = if t == 0 || t + 1 == t_len { 1.0 } else { 2.0 };
                cov += p * wt;
                let present: Vec<usize> = (0..12).filter(|&i| !x[t * 12 + i].is_nan()).collect();
                tr += seq.white.quad_sum(p, present.into_iter());
                if t + 1 < t_len {
                    let mm = unpack_symmetric(
                        seq.mats.m(&seq.states[seq.state_of_frame[t] as usize]),
                        k,
                    );
                    lag += &seq.covs[seq.cov_of_frame[t + 1] as usize] * mm;
                }
            }
            let seq_sums = cov_sums(&seq, &pats).unwrap();
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .unwrap();
            let par = pool.install(|| smooth(&x, &model, &pats, false, 1e-9).unwrap());
            let par_sums = pool.install(|| cov_sums(&par, &pats).unwrap());
            for sums in [&seq_sums, &par_sums] {
                assert!(close(&sums.cov, &cov, 1e-7), "r = {r}");
                assert!(close(&sums.lag, &lag, 1e-7), "r = {r}");
                assert!((sums.tr - tr).abs() <= 1e-7 * tr.abs(), "r = {r}");
            }
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
