//! Low-rank filter states for the small-gain regime of the subspace smoother (B&L Algorithm 1,
//! Appendix A: the same filter and RTS means as [`super::smoother`], exact up to the memo
//! tolerance, without a `d̂ × d̂` factorisation per state).
//!
//! In whitened coordinates (`Q' = I`, module docs of [`super::smoother`]) rotate once more into
//! the eigenbasis of `G_full = Σ_i v_i v_iᵀ = U diag(g) Uᵀ`. With every coordinate observed the
//! recursion `Λ_t = I − M_{t−1} + G_t / r`, `M_t = (I + Λ_t)⁻¹` (A.2, A.4, A.6) is diagonal and
//! converges per mode to `μ_j = 2 / (2 + a_j + √(a_j (4 + a_j)))`, `a_j = g_j / r`, the root of
//! `μ² − (2 + a) μ + 1 = 0`, with `λ_j = 1/μ_j − 1`. With missing coordinates `p` and
//! `M_{t−1} = diag(μ) − E_{t−1}`:
//!
//! `Λ_t = diag(λ) + W C Wᵀ`, `W = [Z_{t−1}, U_p]`, `C = blockdiag(K_{t−1}, −I)`,
//!
//! where `E_{t−1} = Z K Zᵀ` and the columns of `U_p` are the rows `u_i / √r` of the missing
//! coordinates. Woodbury gives, with `A_δ = Wᵀ diag(δ) W`,
//!
//! * `Λ_t⁻¹ = diag(1/λ) − (W/λ) T₁ (W/λ)ᵀ`, `T₁ = C (I + A_{1/λ} C)⁻¹` (the filter mean, A.4-A.5);
//! * `M_t = (diag(1/μ) + W C Wᵀ)⁻¹ = diag(μ) − Z_t K_t Z_tᵀ`, `Z_t = diag(μ) W`,
//!   `K_t = C (I + A_μ C)⁻¹` (the RTS gain A.6 and the next prediction A.2).
//!
//! The block of `Z_t` inherited from `Z_{t−1}` is scaled by `μ` at every step; it is dropped
//! when the bound `‖δE‖_F ≤ ‖Z_o‖_F (‖K_oo‖_F ‖Z_o‖_F + 2 ‖K_on‖_F ‖Z_n‖_F)` guarantees a
//! relative change of the next covariance of at most `tol` (`‖P_{t+1}‖₂ ≤ 1/(1 − ‖M_t‖₂)`).
//! States of the same pattern are merged with the *canonical* state of the pattern (computed as
//! if `E_{t−1} = 0`) when `‖P‖₂ ‖E_{t−1}‖_F ≤ tol`, the merge bound of the dense smoother.
//! The first frames are dense steps until the prior is forgotten (at most `DENSE_PREFIX`). Frames with every coordinate missing, a state of
//! rank above a cap, or a first state that is not forgotten at once make the attempt give up
//! (`None`): the dense smoother then runs. With the published settings (`r = 10⁻³`) every `μ_j`
//! is below 10⁻³, the rank of `E_t` stays near the number of missing coordinates, and a state
//! costs `O(d̂ q + q³)` instead of `≈ 1.3 d̂³`.

use super::linalg::{chol_solve_in_place, cholesky_lower, dot, gemm_tn, spd_inverse_lower};
use super::smoother::{Model, Patterns, White};
use crate::error::{AcmError, Result};
use nalgebra::{DMatrix, SymmetricEigen};
use rayon::prelude::*;
use std::collections::HashMap;

/// Largest steady-state gain `μ_j` for which the low-rank path is tried.
const MU_MAX: f64 = 0.05;

/// Output of [`smooth_means`].
#[derive(Debug, Clone)]
pub struct LowRankMeans {
    /// Smoothed means in the rotated whitened coordinates, row-major T × d̂
    /// (`m̃_t = L U y_t`).
    pub y: Vec<f64>,
    /// `L U`: rotated whitened → original subspace coordinates (d̂ × d̂).
    pub to_orig: DMatrix<f64>,
    /// Filter states computed.
    pub states: usize,
}

impl LowRankMeans {
    /// Smoothed subspace means `m̃_t`, row-major T × d̂ (original coordinates).
    pub fn means(&self) -> Vec<f64> {
        let n = self.to_orig.nrows();
        let my = DMatrix::from_column_slice(n, self.y.len() / n.max(1), &self.y);
        (&self.to_orig * my).data.into()
    }

    /// Back-projection `x̂_t = V̂ L U y_t + m̄` (Algorithm 1, last loop), row-major `T × D`:
    /// every value, or (`only_missing`) only where `x` is NaN, the observed values copied.
    pub fn back_project(&self, model: &Model, x: &[f64], only_missing: bool) -> Vec<f64> {
        let (d, n) = (model.d(), model.k());
        let t_len = self.y.len() / n;
        // Rows b_i = (V̂ L U)ᵀ v... : B = V̂ (L U), D × n.
        let b = DMatrix::from_row_slice(d, n, &model.v) * &self.to_orig;
        if !only_missing {
            let my = DMatrix::from_column_slice(n, t_len, &self.y);
            let mut out = b * my; // D × T column-major = row-major T × D
            out.as_mut_slice().par_chunks_mut(d).for_each(|row| {
                for (o, m) in row.iter_mut().zip(&model.mean) {
                    *o += m;
                }
            });
            return out.data.into();
        }
        let bt = b.transpose(); // column i = row b_i
        let mut out = x.to_vec();
        out.par_chunks_mut(d)
            .zip(self.y.par_chunks(n))
            .for_each(|(row, yt)| {
                for (i, o) in row.iter_mut().enumerate() {
                    if o.is_nan() {
                        *o = model.mean[i] + dot(&bt.as_slice()[i * n..(i + 1) * n], yt);
                    }
                }
            });
        out
    }
}

/// A filter state: `E_t = Z K Zᵀ` (`Z` column-major `n × q`) and the mean solve data.
struct LState {
    /// Columns of `W`: the first `q_old` are `Z` of state `old`, then the pattern's rows.
    old: Option<u32>,
    q_old: usize,
    pat: u32,
    /// `T₁` (`q' × q'`, column-major).
    t1: Vec<f64>,
    z: Vec<f64>,
    q: usize,
    /// `K` (`q × q`, column-major).
    k: Vec<f64>,
    /// Upper bound of `‖E_t‖₂` (see [`e_spec`]).
    e_norm: f64,
    /// Upper bound of `‖P_t‖₂` (canonical states; infinite otherwise).
    pnorm: f64,
}

/// A dense state of the first frames: Cholesky factor of `Λ_t`, `M_t` and a bound of `‖E_t‖₂`.
struct Dense {
    chol: DMatrix<f64>,
    m: DMatrix<f64>,
    e_norm: f64,
}

/// Frames the dense prefix may take before the attempt gives up.
const DENSE_PREFIX: usize = 64;

/// Canonical states (ids `0..canon.len()`) and the states of one forward run (the ids after).
#[derive(Clone, Copy)]
struct Pool<'a> {
    canon: &'a [LState],
    local: &'a [LState],
}

impl Pool<'_> {
    #[inline]
    fn get(&self, id: u32) -> &LState {
        let id = id as usize;
        if id < self.canon.len() {
            &self.canon[id]
        } else {
            &self.local[id - self.canon.len()]
        }
    }
}

struct Setup<'a> {
    n: usize,
    pats: &'a Patterns,
    mu: Vec<f64>,
    inv_lam: Vec<f64>,
    /// Rows `u_i / √r` in the eigenbasis (row-major D × n).
    us: Vec<f64>,
    /// `u_iᵀ diag(1/λ) u_j / r` and `u_iᵀ diag(μ) u_j / r` (D × D).
    h_lam: Vec<f64>,
    h_mu: Vec<f64>,
    /// `u_iᵀ diag(μ²) u_j / r` and `u_iᵀ diag(1/λ²) u_j / r` (D × D).
    h_mu2: Vec<f64>,
    h_lam2: Vec<f64>,
    mu2: Vec<f64>,
    inv_lam2: Vec<f64>,
    d: usize,
    tol: f64,
    cap: usize,
}

impl Setup<'_> {
    #[inline]
    fn us_row(&self, i: usize) -> &[f64] {
        &self.us[i * self.n..(i + 1) * self.n]
    }

    /// Column `c` of `W` for a state whose inherited block is `z_old` (`q_old` columns).
    #[inline]
    fn w_col<'b>(&'b self, z_old: &'b [f64], q_old: usize, miss: &[u32], c: usize) -> &'b [f64] {
        if c < q_old {
            &z_old[c * self.n..(c + 1) * self.n]
        } else {
            self.us_row(miss[c - q_old] as usize)
        }
    }

    /// The state for pattern `pat` reached from `old` (its `E = Z K Zᵀ`; `None` = `E = 0`).
    /// `Ok(None)` if the rank exceeds the cap.
    fn state(&self, states: Pool<'_>, old: Option<u32>, pat: u32) -> Result<Option<LState>> {
        let n = self.n;
        let miss = &self.pats.missing[pat as usize];
        let (z_old, k_old, q_old): (&[f64], &[f64], usize) = match old {
            Some(s) => {
                let st = states.get(s);
                (&st.z, &st.k, st.q)
            }
            None => (&[], &[], 0),
        };
        let qp = q_old + miss.len();
        if qp > self.cap {
            return Ok(None);
        }
        // C = blockdiag(K_old, −I).
        let mut c = DMatrix::<f64>::zeros(qp, qp);
        for a in 0..q_old {
            for b in 0..q_old {
                c[(a, b)] = k_old[b * q_old + a];
            }
        }
        for a in q_old..qp {
            c[(a, a)] = -1.0;
        }
        // A_δ = Wᵀ diag(δ) W for δ = 1/λ, μ and μ² (the Gram matrix of Z = diag(μ) W);
        // pattern-pattern blocks are looked up.
        let mut a_lam = DMatrix::<f64>::zeros(qp, qp);
        let mut a_mu = DMatrix::<f64>::zeros(qp, qp);
        let mut gram = DMatrix::<f64>::zeros(qp, qp);
        let mut gram_lam = DMatrix::<f64>::zeros(qp, qp);
        // Inherited columns scaled by the four weights, S = [δ_f ∘ w_b] (n × 4 q_old), and
        // R = Wᵀ S (qp × 4 q_old) by one GEMM: R[a, 4b + f] = w_aᵀ diag(δ_f) w_b.
        let weights = [&self.inv_lam, &self.mu, &self.mu2, &self.inv_lam2];
        let mut scaled = vec![0.0; 4 * n * q_old];
        for a in 0..q_old {
            let wa = self.w_col(z_old, q_old, miss, a);
            for (f, wt) in weights.iter().enumerate() {
                let dst = &mut scaled[(4 * a + f) * n..(4 * a + f + 1) * n];
                for ((o, w), x) in dst.iter_mut().zip(wa).zip(wt.iter()) {
                    *o = w * x;
                }
            }
        }
        let mut rgram = vec![0.0; qp * 4 * q_old];
        if q_old > 0 {
            let mut wmat = Vec::with_capacity(n * qp);
            for a in 0..qp {
                wmat.extend_from_slice(self.w_col(z_old, q_old, miss, a));
            }
            gemm_tn(&wmat, &scaled, n, qp, 4 * q_old, &mut rgram);
        }
        for a in 0..qp {
            for b in 0..=a {
                let v = if b >= q_old {
                    let ij = miss[a - q_old] as usize * self.d + miss[b - q_old] as usize;
                    [
                        self.h_lam[ij],
                        self.h_mu[ij],
                        self.h_mu2[ij],
                        self.h_lam2[ij],
                    ]
                } else {
                    let r = |f: usize| rgram[(4 * b + f) * qp + a];
                    [r(0), r(1), r(2), r(3)]
                };
                a_lam[(a, b)] = v[0];
                a_lam[(b, a)] = v[0];
                a_mu[(a, b)] = v[1];
                a_mu[(b, a)] = v[1];
                gram[(a, b)] = v[2];
                gram[(b, a)] = v[2];
                gram_lam[(a, b)] = v[3];
                gram_lam[(b, a)] = v[3];
            }
        }
        let singular =
            || AcmError::Numerical("singular capacitance matrix in the low-rank filter".into());
        let capacitance = |a: &DMatrix<f64>| -> Result<DMatrix<f64>> {
            if q_old == 0 {
                // C = −I: T = −(I − A)⁻¹, and I − A is positive definite (Schur complement of
                // the positive-definite Λ or I + Λ).
                let mut s = -a;
                for i in 0..qp {
                    s[(i, i)] += 1.0;
                }
                return Ok(-spd_inverse_lower(&s).ok_or_else(singular)?);
            }
            // T = C (I + A C)⁻¹ = (I + C A)⁻¹ C (both symmetric forms are equal).
            let t = solve_capacitance(a.as_slice(), k_old, q_old, qp).ok_or_else(singular)?;
            let mut t = DMatrix::from_column_slice(qp, qp, &t);
            for i in 0..qp {
                for j in 0..i {
                    let v = 0.5 * (t[(i, j)] + t[(j, i)]);
                    t[(i, j)] = v;
                    t[(j, i)] = v;
                }
            }
            Ok(t)
        };
        let t1 = capacitance(&a_lam)?;
        let kf = capacitance(&a_mu)?;
        let e_full = e_spec(&kf, &gram);
        let mu_max = self.mu.iter().copied().fold(0.0, f64::max);
        // Drop the inherited block when its contribution to E is below the tolerance:
        // ‖E_full − Z_n K_nn Z_nᵀ‖_F = ‖Z K' Zᵀ‖_F, K' = K outside the nn block.
        let mut keep_from = 0;
        if q_old > 0 {
            let mut kd = kf.clone();
            for a in q_old..qp {
                for b in q_old..qp {
                    kd[(a, b)] = 0.0;
                }
            }
            let slack = (1.0 - mu_max - e_full).max(0.0);
            if e_spec(&kd, &gram) <= self.tol * slack {
                keep_from = q_old;
            }
        }
        let q = qp - keep_from;
        let k = kf.view((keep_from, keep_from), (q, q)).into_owned();
        let e_norm = if keep_from == 0 {
            e_full
        } else {
            e_spec(&k, &gram.view((keep_from, keep_from), (q, q)).into_owned())
        };
        // Z = diag(μ) W (kept columns).
        let mut z = vec![0.0; n * q];
        for a in 0..q {
            let wa = self.w_col(z_old, q_old, miss, keep_from + a);
            for (o, (w, m)) in z[a * n..(a + 1) * n]
                .iter_mut()
                .zip(wa.iter().zip(&self.mu))
            {
                *o = w * m;
            }
        }
        let mut k = k.as_slice().to_vec();
        let (mut z, mut q, mut e_norm) = (z, q, e_norm);
        if q > n {
            // More columns than dimensions: re-factor E = Σ σ v vᵀ and keep the components
            // above the tolerance (their sum is below it in the Frobenius norm).
            let zm = DMatrix::from_column_slice(n, q, &z);
            let km = DMatrix::from_column_slice(q, q, &k);
            let e = &zm * km * zm.transpose();
            let eig = SymmetricEigen::new(0.5 * (&e + e.transpose()));
            let slack = (1.0 - mu_max - e_full).max(0.0);
            let cut = self.tol * slack / (n as f64).sqrt();
            let keep: Vec<usize> = (0..n).filter(|&i| eig.eigenvalues[i].abs() > cut).collect();
            q = keep.len();
            z = keep
                .iter()
                .flat_map(|&i| {
                    eig.eigenvectors
                        .column(i)
                        .iter()
                        .copied()
                        .collect::<Vec<_>>()
                })
                .collect();
            k = vec![0.0; q * q];
            for (a, &i) in keep.iter().enumerate() {
                k[a * q + a] = eig.eigenvalues[i];
            }
            e_norm = keep
                .iter()
                .map(|&i| eig.eigenvalues[i].abs())
                .fold(0.0, f64::max);
        }
        // ‖P‖₂ ≤ max 1/λ + ‖(W/λ) T₁ (W/λ)ᵀ‖₂ (used by the merge test of canonical states).
        let pnorm = if q_old == 0 {
            self.inv_lam.iter().copied().fold(0.0, f64::max) + e_spec(&t1, &gram_lam)
        } else {
            f64::INFINITY
        };
        Ok(Some(LState {
            old: if q_old > 0 { old } else { None },
            q_old,
            pat,
            t1: t1.as_slice().to_vec(),
            z,
            q,
            k,
            e_norm,
            pnorm,
        }))
    }

    /// `h ← Λ⁻¹ h` for a low-rank state.
    fn solve(&self, states: Pool<'_>, st: &LState, h: &mut [f64], tmp: &mut Vec<f64>) {
        let miss = &self.pats.missing[st.pat as usize];
        let z_old: &[f64] = st.old.map_or(&[], |s| &states.get(s).z);
        let qp = st.q_old + miss.len();
        for (x, il) in h.iter_mut().zip(&self.inv_lam) {
            *x *= il;
        }
        // c = T₁ Wᵀ (h/λ)
        tmp.clear();
        for a in 0..qp {
            let wa = self.w_col(z_old, st.q_old, miss, a);
            tmp.push(wa.iter().zip(h.iter()).map(|(w, x)| w * x).sum());
        }
        for a in 0..qp {
            let ca: f64 = (0..qp).map(|b| st.t1[b * qp + a] * tmp[b]).sum();
            if ca != 0.0 {
                let wa = self.w_col(z_old, st.q_old, miss, a);
                for ((x, w), il) in h.iter_mut().zip(wa).zip(&self.inv_lam) {
                    *x -= ca * w * il;
                }
            }
        }
    }

    /// `out = M v = μ ∘ v − Z K Zᵀ v` for a low-rank state.
    fn gain(&self, st: &LState, v: &[f64], out: &mut [f64], tmp: &mut Vec<f64>) {
        let n = self.n;
        for ((o, x), m) in out.iter_mut().zip(v).zip(&self.mu) {
            *o = m * x;
        }
        tmp.clear();
        for a in 0..st.q {
            let za = &st.z[a * n..(a + 1) * n];
            tmp.push(za.iter().zip(v).map(|(z, x)| z * x).sum());
        }
        for a in 0..st.q {
            let ca: f64 = (0..st.q).map(|b| st.k[b * st.q + a] * tmp[b]).sum();
            if ca != 0.0 {
                for (o, z) in out.iter_mut().zip(&st.z[a * n..(a + 1) * n]) {
                    *o -= ca * z;
                }
            }
        }
    }
}

/// `T = (I + C A)⁻¹ C` for `C = blockdiag(K_old, −I)` (`q_old` + rest), `A` symmetric
/// `qp × qp` (column-major): Gaussian elimination with partial pivoting on row-major copies
/// (contiguous row operations). Returns `T` column-major, or `None` if singular.
fn solve_capacitance(a: &[f64], k_old: &[f64], q_old: usize, qp: usize) -> Option<Vec<f64>> {
    // S = I + C A and R = C, row-major (A symmetric: row j of A = column j).
    let mut s = vec![0.0; qp * qp];
    let mut r = vec![0.0; qp * qp];
    for i in 0..qp {
        let row = &mut s[i * qp..(i + 1) * qp];
        if i < q_old {
            for l in 0..q_old {
                let c = k_old[l * q_old + i];
                if c != 0.0 {
                    for (o, x) in row.iter_mut().zip(&a[l * qp..(l + 1) * qp]) {
                        *o += c * x;
                    }
                }
            }
            r[i * qp..i * qp + q_old].copy_from_slice(&k_old[i * q_old..(i + 1) * q_old]);
        } else {
            for (o, x) in row.iter_mut().zip(&a[i * qp..(i + 1) * qp]) {
                *o = -x;
            }
            r[i * qp + i] = -1.0;
        }
        row[i] += 1.0;
    }
    for c in 0..qp {
        let p = (c..qp).max_by(|&x, &y| s[x * qp + c].abs().total_cmp(&s[y * qp + c].abs()))?;
        let piv = s[p * qp + c];
        if !(piv.abs() > 0.0 && piv.is_finite()) {
            return None;
        }
        if p != c {
            for j in 0..qp {
                s.swap(p * qp + j, c * qp + j);
                r.swap(p * qp + j, c * qp + j);
            }
        }
        let (top, bottom) = s.split_at_mut((c + 1) * qp);
        let (rtop, rbottom) = r.split_at_mut((c + 1) * qp);
        let prow = &top[c * qp..];
        let rrow = &rtop[c * qp..];
        for (srow, rr) in bottom
            .chunks_exact_mut(qp)
            .zip(rbottom.chunks_exact_mut(qp))
        {
            let f = srow[c] / piv;
            if f != 0.0 {
                for (o, x) in srow[c..].iter_mut().zip(&prow[c..]) {
                    *o -= f * x;
                }
                for (o, x) in rr.iter_mut().zip(rrow) {
                    *o -= f * x;
                }
            }
        }
    }
    // Back substitution, row by row from the bottom.
    for c in (0..qp).rev() {
        let (top, bottom) = r.split_at_mut(c * qp + qp);
        let row = &mut top[c * qp..];
        for j in c + 1..qp {
            let f = s[c * qp + j];
            if f != 0.0 {
                for (o, x) in row.iter_mut().zip(&bottom[(j - c - 1) * qp..(j - c) * qp]) {
                    *o -= f * x;
                }
            }
        }
        let inv = 1.0 / s[c * qp + c];
        row.iter_mut().for_each(|x| *x *= inv);
    }
    // Row-major T → column-major.
    let mut t = vec![0.0; qp * qp];
    for i in 0..qp {
        for j in 0..qp {
            t[j * qp + i] = r[i * qp + j];
        }
    }
    t.iter().all(|v| v.is_finite()).then_some(t)
}

/// Upper bound of the spectral norm of `E = Z K Zᵀ` (`K` symmetric) from the Gram matrix
/// `G = ZᵀZ`: `‖E‖₂ ≤ (tr E⁴)^{1/4} = (tr (K G)⁴)^{1/4}` (the Schatten-4 norm; tighter than the
/// Frobenius norm by up to `rank^{1/4}`).
fn e_spec(k: &DMatrix<f64>, g: &DMatrix<f64>) -> f64 {
    if k.is_empty() {
        return 0.0;
    }
    let kg = k * g;
    let kg2 = &kg * &kg;
    // tr(A²) for A = (KG)², which is similar to a symmetric matrix: Σ_ij A_ij A_ji.
    kg2.iter()
        .zip(kg2.transpose().iter())
        .map(|(a, b)| a * b)
        .sum::<f64>()
        .max(0.0)
        .sqrt()
        .sqrt()
}

/// Frames below which the forward pass runs on one thread.
const MIN_FORWARD: usize = 1000;
/// Frames the second forward run starts before its first frame (from the prior).
const FORWARD_BURN_IN: usize = 64;

/// What every forward run shares.
struct Ctx<'a> {
    setup: &'a Setup<'a>,
    canon: Vec<LState>,
    /// Data terms `b_t` (n × T).
    b: &'a DMatrix<f64>,
    gdiag: Vec<f64>,
    inv_r: f64,
    /// Prior information and mean in the rotated whitened coordinates.
    lam0y: DMatrix<f64>,
    m0y: Vec<f64>,
}

/// The forward pass over frames `a..a + sof.len()`, started from the prior at frame `a`.
struct Run {
    a: usize,
    /// Non-canonical states (ids `canon.len()..`).
    states: Vec<LState>,
    /// Dense states of the frames `a..a + dense.len()`.
    dense: Vec<Dense>,
    /// State id per frame (`u32::MAX` in the dense prefix).
    sof: Vec<u32>,
    /// Filtered means, row-major (frames × n).
    mf: Vec<f64>,
    trans: HashMap<(u32, u32), u32>,
}

impl Run {
    /// Takes the frames `from..` of `other` (a run that agrees with this one at `from − 1`,
    /// [`Ctx::agree`]); `self` must end at `from`.
    fn append(&mut self, other: Run, from: usize, n_canon: usize) {
        let n = self.mf.len() / self.sof.len().max(1);
        let base = self.states.len() as u32;
        let remap = |id: u32| {
            if (id as usize) < n_canon || id == u32::MAX {
                id
            } else {
                id + base
            }
        };
        let skip = from - other.a;
        self.states.extend(other.states.into_iter().map(|mut st| {
            st.old = st.old.map(remap);
            st
        }));
        self.sof
            .extend(other.sof[skip..].iter().map(|&id| remap(id)));
        self.mf.extend_from_slice(&other.mf[skip * n..]);
    }
}

impl Ctx<'_> {
    /// Dense step (A.2, A.4 in the eigenbasis) from the predicted information `lam_pred`.
    fn dense_step(&self, lam_pred: &DMatrix<f64>, pat: u32) -> Result<Dense> {
        let n = self.setup.n;
        let mut lam = lam_pred.clone();
        for c in 0..n {
            lam[(c, c)] += self.gdiag[c] * self.inv_r;
        }
        for &i in &self.setup.pats.missing[pat as usize] {
            let r = self.setup.us_row(i as usize);
            for bb in 0..n {
                for a in 0..n {
                    lam[(a, bb)] -= r[a] * r[bb];
                }
            }
        }
        let chol = cholesky_lower(&lam).ok_or_else(|| {
            AcmError::Numerical("the filter information matrix is not positive definite".into())
        })?;
        for c in 0..n {
            lam[(c, c)] += 1.0;
        }
        let m = spd_inverse_lower(&lam).ok_or_else(|| {
            AcmError::Numerical("I + information is not positive definite".into())
        })?;
        let mut e = -m.clone();
        for c in 0..n {
            e[(c, c)] += self.setup.mu[c];
        }
        // ‖E‖₂ ≤ (tr E⁴)^{1/4} = ‖E²‖_F^{1/2}.
        let e2 = &e * &e;
        Ok(Dense {
            chol,
            e_norm: e2.norm().sqrt(),
            m,
        })
    }

    /// The forward pass over frames `a..b` from the prior at frame `a`; `None` outside the
    /// small-gain regime.
    fn run(&self, a: usize, b: usize) -> Result<Option<Run>> {
        let run = Run {
            a,
            states: Vec::new(),
            dense: Vec::new(),
            sof: Vec::with_capacity(b - a),
            mf: Vec::with_capacity((b - a) * self.setup.n),
            trans: HashMap::new(),
        };
        self.extend(run, b)
    }

    /// Continues `run` up to frame `b` (exclusive).
    fn extend(&self, mut run: Run, b: usize) -> Result<Option<Run>> {
        let setup = self.setup;
        let pats = setup.pats;
        let n = setup.n;
        let tol = setup.tol;
        let mut h = vec![0.0; n];
        let mut tmp = Vec::new();
        let mut m_hat = vec![0.0; n];
        for t in run.a + run.sof.len()..b {
            let local = t - run.a;
            let pat = pats.of_frame[t];
            if local == 0 {
                m_hat.copy_from_slice(&self.m0y);
            } else {
                m_hat.copy_from_slice(&run.mf[(local - 1) * n..local * n]);
            }
            // h = (b_t − G_t m̂) / r, G_t m̂ = g ∘ m̂ − Σ_missing v_y,i (v_y,iᵀ m̂).
            for c in 0..n {
                h[c] = self.b[(c, t)] - self.gdiag[c] * m_hat[c];
            }
            for &i in &pats.missing[pat as usize] {
                // v_y,i (v_y,iᵀ m̂) = r · us_i (us_iᵀ m̂), us_i = v_y,i / √r.
                let r = setup.us_row(i as usize);
                let p: f64 = dot(r, &m_hat) / self.inv_r;
                for (hc, rc) in h.iter_mut().zip(r) {
                    *hc += p * rc;
                }
            }
            for hc in h.iter_mut() {
                *hc *= self.inv_r;
            }
            let prev = run.sof.last().copied().filter(|&s| s != u32::MAX);
            if local == 0 {
                run.dense.push(self.dense_step(&self.lam0y, pat)?);
                chol_solve_in_place(&run.dense[0].chol, &mut h);
                run.sof.push(u32::MAX);
            } else {
                let key = (prev.unwrap_or(u32::MAX), pat);
                let known = prev.and_then(|_| run.trans.get(&key).copied());
                let sid = match known {
                    Some(s) => Some(s),
                    None => {
                        let pool = Pool {
                            canon: &self.canon,
                            local: &run.states,
                        };
                        let c_id = pat;
                        let e_prev = match prev {
                            Some(p) => pool.get(p).e_norm,
                            None => run.dense[local - 1].e_norm,
                        };
                        if pool.get(c_id).pnorm * e_prev <= tol {
                            Some(c_id)
                        } else if let Some(p) = prev {
                            match setup.state(pool, Some(p), pat)? {
                                Some(st) => {
                                    run.states.push(st);
                                    Some((self.canon.len() + run.states.len() - 1) as u32)
                                }
                                None => return Ok(None),
                            }
                        } else {
                            None
                        }
                    }
                };
                match sid {
                    Some(s) => {
                        if prev.is_some() {
                            run.trans.insert(key, s);
                        }
                        run.sof.push(s);
                        let pool = Pool {
                            canon: &self.canon,
                            local: &run.states,
                        };
                        setup.solve(pool, pool.get(s), &mut h, &mut tmp);
                    }
                    None => {
                        // Still in the dense prefix: P̂⁻¹ = I − M_{t−1}.
                        if local >= DENSE_PREFIX {
                            return Ok(None);
                        }
                        let mut lam_pred = -run.dense[local - 1].m.clone();
                        for c in 0..n {
                            lam_pred[(c, c)] += 1.0;
                        }
                        run.dense.push(self.dense_step(&lam_pred, pat)?);
                        chol_solve_in_place(&run.dense[local].chol, &mut h);
                        run.sof.push(u32::MAX);
                    }
                }
            }
            for (a, hc) in m_hat.iter_mut().zip(&h) {
                *a += hc;
            }
            run.mf.extend_from_slice(&m_hat);
        }
        Ok(Some(run))
    }

    /// Whether two runs agree at frame `t`: the same canonical state (so the same future
    /// recursion) and filtered means within the tolerance (relative, max norm).
    fn agree(&self, first: &Run, second: &Run, t: usize) -> bool {
        let n = self.setup.n;
        let (i, j) = (t - first.a, t - second.a);
        let (s1, s2) = (first.sof[i], second.sof[j]);
        if s1 != s2 || (s1 as usize) >= self.canon.len() {
            return false;
        }
        let (m1, m2) = (
            &first.mf[i * n..(i + 1) * n],
            &second.mf[j * n..(j + 1) * n],
        );
        let scale = m1.iter().fold(1.0_f64, |a, v| a.max(v.abs()));
        m1.iter()
            .zip(m2)
            .all(|(x, y)| (x - y).abs() <= self.setup.tol * scale)
    }
}

/// Filter and RTS smoother means with low-rank states (module docs), or `None` when the model
/// is outside the small-gain regime (the caller then runs the dense smoother).
pub fn smooth_means(
    x: &[f64],
    model: &Model,
    pats: &Patterns,
    tol: f64,
) -> Result<Option<LowRankMeans>> {
    if tol <= 0.0 {
        return Ok(None);
    }
    let w = White::new(model)?;
    let (d, n) = (w.d, w.k);
    let t_len = x.len() / d;
    if t_len < 2 || (0..pats.missing.len() as u32).any(|p| pats.all_missing(p, d)) {
        return Ok(None);
    }
    let eig = SymmetricEigen::new(w.g_full.clone());
    let (g, u) = (eig.eigenvalues, eig.eigenvectors);
    let mu: Vec<f64> = g
        .iter()
        .map(|&gj| {
            let a = gj.max(0.0) * w.inv_r;
            2.0 / ((2.0 + a) + (a * (4.0 + a)).sqrt())
        })
        .collect();
    if mu.iter().any(|&m| m.is_nan() || m > MU_MAX) {
        return Ok(None);
    }
    let inv_lam: Vec<f64> = mu.iter().map(|&m| m / (1.0 - m)).collect();
    let mu2: Vec<f64> = mu.iter().map(|&m| m * m).collect();
    let inv_lam2: Vec<f64> = inv_lam.iter().map(|&m| m * m).collect();
    // Rows in the eigenbasis: v_y,i = Uᵀ v_i'.
    let vw = DMatrix::from_row_slice(d, n, &w.v);
    let vy = &vw * &u; // D × n
    let sr = w.inv_r.sqrt();
    let mut us = vec![0.0; d * n];
    for i in 0..d {
        for c in 0..n {
            us[i * n + c] = vy[(i, c)] * sr;
        }
    }
    let scaled = |delta: &[f64]| -> Vec<f64> {
        let mut out = vec![0.0; d * d];
        out.par_chunks_mut(d).enumerate().for_each(|(i, row)| {
            let ui = &us[i * n..(i + 1) * n];
            for (j, o) in row.iter_mut().enumerate() {
                let uj = &us[j * n..(j + 1) * n];
                *o = (0..n).map(|c| ui[c] * uj[c] * delta[c]).sum();
            }
        });
        out
    };
    let setup = Setup {
        n,
        pats,
        h_lam: scaled(&inv_lam),
        h_mu: scaled(&mu),
        h_mu2: scaled(&mu2),
        h_lam2: scaled(&inv_lam2),
        mu2,
        inv_lam2,
        mu,
        inv_lam,
        us,
        d,
        tol,
        cap: 2 * n + d,
    };
    // Data terms b_t = Σ_present v_y,i (z_ti − m̄_i): B = V_yᵀ Z_c (n × T), written in place
    // by column blocks on the threads (one GEMM per block; Z_c exists only per block).
    let mut b = DMatrix::<f64>::zeros(n, t_len);
    let per = t_len
        .div_ceil(4 * rayon::current_num_threads().max(1))
        .max(1);
    b.as_mut_slice()
        .par_chunks_mut(per * n)
        .enumerate()
        .for_each(|(blk, out)| {
            let t0 = blk * per;
            let cols = out.len() / n;
            let mut zc = vec![0.0; cols * d];
            for (tt, row) in zc.chunks_exact_mut(d).enumerate() {
                let xr = &x[(t0 + tt) * d..(t0 + tt + 1) * d];
                for ((o, &z), m) in row.iter_mut().zip(xr).zip(&model.mean) {
                    *o = if z.is_nan() { 0.0 } else { z - m };
                }
            }
            // out (n × cols) = V_yᵀ (n × D) · zc (D × cols), all column-major: entry (c, i)
            // of V_yᵀ is vy[(i, c)] at i + c·D (row stride D, column stride 1).
            // SAFETY: the pointers address `vy` (D × n), `zc` (D × cols) and `out` (n × cols)
            // with the strides given, all in bounds; `out` is exclusively borrowed.
            unsafe {
                matrixmultiply::dgemm(
                    n,
                    d,
                    cols,
                    1.0,
                    vy.as_ptr(),
                    d as isize,
                    1,
                    zc.as_ptr(),
                    1,
                    d as isize,
                    0.0,
                    out.as_mut_ptr(),
                    1,
                    n as isize,
                );
            }
        });
    let gdiag: Vec<f64> = g.iter().map(|&v| v.max(0.0)).collect();

    let lam0 = super::linalg::unpack_symmetric(&w.lam0_packed, n);
    // Canonical states of every pattern (independent of the history: in parallel).
    let canonical: Vec<Option<LState>> = (0..pats.missing.len() as u32)
        .into_par_iter()
        .map(|p| {
            setup.state(
                Pool {
                    canon: &[],
                    local: &[],
                },
                None,
                p,
            )
        })
        .collect::<Result<_>>()?;
    if canonical.iter().any(Option::is_none) {
        return Ok(None);
    }
    let ctx = Ctx {
        setup: &setup,
        canon: canonical.into_iter().flatten().collect(),
        b: &b,
        gdiag,
        inv_r: w.inv_r,
        lam0y: u.transpose() * lam0 * &u,
        m0y: (u.transpose() * &w.m0).as_slice().to_vec(),
    };
    // Forward pass: one run, or two in parallel stitched where they agree.
    let split = t_len / 2;
    let run = if rayon::current_num_threads() >= 2 && t_len >= 2 * MIN_FORWARD {
        let (first, second) = rayon::join(
            || ctx.run(0, split),
            || ctx.run(split - FORWARD_BURN_IN, t_len),
        );
        let mut first = match first? {
            Some(r) => r,
            None => return Ok(None),
        };
        match second? {
            Some(second) if ctx.agree(&first, &second, split - 1) => {
                first.append(second, split, ctx.canon.len());
                first
            }
            _ => match ctx.extend(first, t_len)? {
                Some(r) => r,
                None => return Ok(None),
            },
        }
    } else {
        match ctx.run(0, t_len)? {
            Some(r) => r,
            None => return Ok(None),
        }
    };
    let pool = Pool {
        canon: &ctx.canon,
        local: &run.states,
    };
    // Backward pass (A.7): m̃_t = m_t + M_t (m̃_{t+1} − m_t), frames `lo..=start` from
    // m̃_start = `init` (returned from `lo` on).
    let mf = &run.mf;
    let backward = |lo: usize, start: usize, init: &[f64]| -> Vec<f64> {
        let mut ms = mf[lo * n..(start + 1) * n].to_vec();
        ms[(start - lo) * n..].copy_from_slice(init);
        let (mut diff, mut corr, mut tmp) = (vec![0.0; n], vec![0.0; n], Vec::new());
        for t in (lo..start).rev() {
            let i = t - lo;
            for c in 0..n {
                diff[c] = ms[(i + 1) * n + c] - mf[t * n + c];
            }
            if t < run.dense.len() {
                let v = &run.dense[t].m * nalgebra::DVector::from_column_slice(&diff);
                corr.copy_from_slice(v.as_slice());
            } else {
                setup.gain(pool.get(run.sof[t]), &diff, &mut corr, &mut tmp);
            }
            for (o, cc) in ms[i * n..(i + 1) * n].iter_mut().zip(&corr) {
                *o += cc;
            }
        }
        ms
    };
    let last = &mf[(t_len - 1) * n..];
    let ms = if rayon::current_num_threads() >= 2 && t_len >= 2 * MIN_FORWARD {
        // Two halves in parallel: the second exact from the last frame, the first started
        // FORWARD_BURN_IN frames after the split from the filter mean. The error at the split
        // is carried into earlier frames by products of M_t (‖M_t‖₂ < 1), so the first half
        // is kept when it agrees with the exact value at the split within the tolerance, and
        // recomputed from that value otherwise.
        let split = t_len / 2;
        let from = (split + FORWARD_BURN_IN).min(t_len - 1);
        let (first, second) = rayon::join(
            || backward(0, from, &mf[from * n..(from + 1) * n]),
            || backward(split, t_len - 1, last),
        );
        let exact = &second[..n];
        let approx = &first[split * n..(split + 1) * n];
        let scale = exact.iter().fold(1.0_f64, |a, v| a.max(v.abs()));
        let ok = exact
            .iter()
            .zip(approx)
            .all(|(x, y)| (x - y).abs() <= setup.tol * scale);
        let mut ms = if ok { first } else { backward(0, split, exact) };
        ms.truncate(split * n);
        ms.extend_from_slice(&second);
        ms
    } else {
        backward(0, t_len - 1, last)
    };
    Ok(Some(LowRankMeans {
        y: ms,
        to_orig: &w.l * &u,
        states: ctx.canon.len() + run.states.len() + run.dense.len(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gapfill::combine::SplitMix;
    use crate::gapfill::smoother::smooth;

    /// A random-walk sequence in a `k`-dimensional subspace of `d` coordinates with gaps of
    /// several lengths (no frame entirely missing).
    fn toy(t_len: usize, d: usize, k: usize, r: f64, seed: u64) -> (Vec<f64>, Model) {
        let mut rng = SplitMix(seed);
        let mut u = || (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
        let basis = DMatrix::from_fn(d, k, |_, _| u()).qr().q();
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
                let miss = (t % 13 < 4 && i % 5 == 2)
                    || (t > 40 && t < 90 && i < 3)
                    || (t % 7 == 3 && i == d - 1);
                x.push(if miss { f64::NAN } else { val + i as f64 });
            }
        }
        let model = Model {
            v,
            mean: (0..d).map(|i| i as f64).collect(),
            q: DMatrix::identity(k, k) * 0.08 + DMatrix::from_element(k, k, 0.01),
            r,
            m0: nalgebra::DVector::zeros(k),
            p0: DMatrix::identity(k, k) * 10.0,
        };
        (x, model)
    }

    #[test]
    fn low_rank_means_equal_the_dense_smoother_in_the_small_gain_regime() {
        // μ ≈ r / eig(Q) between 1e-4 and 1e-3, as with the published r = 1e-3 mm².
        for (r, seed) in [(1e-5, 1), (1e-4, 2), (3e-5, 3)] {
            let (x, model) = toy(300, 15, 6, r, seed);
            let pats = Patterns::new(&x, 15);
            let dense = smooth(&x, &model, &pats, false, 0.0).unwrap();
            let lr = smooth_means(&x, &model, &pats, 1e-8)
                .unwrap()
                .expect("small-gain regime");
            let scale = dense.m.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
            let err = dense
                .m
                .iter()
                .zip(&lr.means())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(
                err <= 1e-6 * scale,
                "r = {r}: max difference {err} (scale {scale})"
            );
            assert!(lr.states < 300, "states {}", lr.states);
            // Sparse back-projection: the gaps as in the full one, observed values copied.
            let full = lr.back_project(&model, &x, false);
            let sparse = lr.back_project(&model, &x, true);
            for ((f, sp), v) in full.iter().zip(&sparse).zip(&x) {
                if v.is_nan() {
                    assert!((f - sp).abs() <= 1e-9 * scale.max(1.0));
                } else {
                    assert_eq!(sp, v);
                }
            }
        }
    }

    #[test]
    fn parallel_forward_and_backward_runs_equal_the_sequential_smoother() {
        // Long enough for two forward and two backward runs (each stitched after a burn-in).
        let (x, model) = toy(2 * MIN_FORWARD + 300, 15, 6, 3e-5, 7);
        let pats = Patterns::new(&x, 15);
        let dense = smooth(&x, &model, &pats, false, 0.0).unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let lr = pool
            .install(|| smooth_means(&x, &model, &pats, 1e-8))
            .unwrap()
            .expect("small-gain regime");
        let scale = dense.m.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
        let err = dense
            .m
            .iter()
            .zip(&lr.means())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(err <= 1e-6 * scale, "max difference {err} (scale {scale})");
    }

    #[test]
    fn large_gains_and_empty_frames_fall_back_to_the_dense_smoother() {
        // r ≫ Q: the steady-state gains are close to 1.
        let (x, model) = toy(200, 15, 6, 10.0, 4);
        let pats = Patterns::new(&x, 15);
        assert!(smooth_means(&x, &model, &pats, 1e-6).unwrap().is_none());
        // A frame with every coordinate missing.
        let (mut x, model) = toy(200, 15, 6, 1e-3, 5);
        x[50 * 15..51 * 15].iter_mut().for_each(|v| *v = f64::NAN);
        let pats = Patterns::new(&x, 15);
        assert!(smooth_means(&x, &model, &pats, 1e-6).unwrap().is_none());
        // memo_tol = 0 asks for the exact dense recursion.
        let (x, model) = toy(200, 15, 6, 1e-3, 6);
        let pats = Patterns::new(&x, 15);
        assert!(smooth_means(&x, &model, &pats, 0.0).unwrap().is_none());
    }
}
