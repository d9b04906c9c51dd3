//! The unscented RTS smoother (ACM supp. Alg. 8-9) and the transition statistics of the
//! M-step (eqs. 58-65, 79), accumulated during the backward pass.
//!
//! For the random-walk transition the sigma-point moments of Alg. 8 are exact:
//! `z̄ = μ̃_t`, `P = Ṽ_t + V_z` (lines 3-4) and `D = Ṽ_t` (line 5), so
//! `G_t = Ṽ_t P⁻¹`, `μ̂_t = μ̃_t + G_t (μ̂_{t+1} − μ̃_t)`,
//! `V̂_t = Ṽ_t + (G_t V̂_{t+1} − D) G_tᵀ` (lines 6-8).
//!
//! Likewise `z_t − z_{t-1}` is linear in the pair `(z_t, z_{t-1})`, so the pairwise
//! sigma-point sum of eq. 79 equals its closed form
//! `E[(z_t − z_{t-1})(·)ᵀ] = d dᵀ + V̂_t + V̂_{t-1} − V̂_t G_{t-1}ᵀ − G_{t-1} V̂_t`
//! with `d = μ̂_t − μ̂_{t-1}` and the pairwise covariance of eq. 59. (The Python tests check
//! this against the literal sigma-point computation.) No gain needs to be stored.

use super::dense::{chol_solve_mat, cholesky, symmetrize, symmetrize_slice};
use super::filter::{f_left, f_right, Transition};
use crate::error::Result;
use crate::kernels::gemm;
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

/// Runs Alg. 9 in place: `means`/`covs` hold the filtered `(T+1)` moments of the state of
/// size `ns` (index 0 = the prior of `s_0`; `ns = n` for the paper's random walk, `2n` for the
/// position–velocity state of [`super::filter::predict`]) and are overwritten with the
/// smoothed ones. Returns `Σ_{t=1}^{T} E[(s_t − F s_{t-1})(s_t − F s_{t-1})ᵀ]` (`ns × ns`,
/// column-major), the sufficient statistic of eq. 79.
///
/// For a general linear `F`: `P = F Ṽ_t Fᵀ + V_z`, `G_t = Ṽ_t Fᵀ P⁻¹`,
/// `μ̂_t = μ̃_t + G_t (μ̂_{t+1} − F μ̃_t)`, `V̂_t = Ṽ_t + G_t (V̂_{t+1} − P) G_tᵀ`, and with
/// `d = μ̂_{t+1} − F μ̂_t`, `C = V̂_{t+1} G_tᵀ` (eq. 59):
/// `E[(s_{t+1} − F s_t)(·)ᵀ] = d dᵀ + V̂_{t+1} − C Fᵀ − F Cᵀ + F V̂_t Fᵀ`.
///
/// With `statistics = false` (smoothing with fixed parameters) the statistic is not
/// accumulated and the returned matrix is zero.
///
/// # Errors
/// Numerical error if some `F Ṽ_t Fᵀ + V_z` is not positive definite.
pub(crate) fn smooth_in_place(
    means: &mut [f64],
    covs: &mut [f64],
    vz: &[f64],
    ns: usize,
    tr: Transition<'_>,
    statistics: bool,
) -> Result<DMatrix<f64>> {
    let steps = means.len() / ns;
    let mut acc = DMatrix::zeros(ns, ns);
    if steps < 2 {
        return Ok(acc);
    }
    let vz = DMatrix::from_column_slice(ns, ns, vz);
    smooth_pipelined(means, covs, &vz, ns, tr, statistics.then_some(&mut acc))?;
    symmetrize(&mut acc);
    Ok(acc)
}

/// Adds eq. 79's term of the pair `(t+1, t)` to `acc`.
pub(crate) fn add_statistic(
    acc: &mut DMatrix<f64>,
    ms: &DVector<f64>,
    vs: &DMatrix<f64>,
    ms_next: &DVector<f64>,
    vs_next: &DMatrix<f64>,
    gt: &DMatrix<f64>,
    tr: Transition<'_>,
) {
    let ns = ms.len();
    let fms = f_left(&DMatrix::from_column_slice(ns, 1, ms.as_slice()), tr);
    let d = ms_next - fms.column(0);
    let cross = vs_next * gt; // Cov(s_{t+1}, s_t) = V̂_{t+1} G_tᵀ
    let cf = f_right(&cross, tr);
    *acc += &d * d.transpose() + vs_next - &cf - cf.transpose() + f_left(&f_right(vs, tr), tr);
}

/// Frames per block of [`smooth_pipelined`].
const GAIN_BLOCK: usize = 32;

/// Alg. 9 (with eq. 79's statistic added to `acc` if given), the gains computed ahead: a frame's gain (line 4, the
/// Cholesky factorisation and solve, ~40 % of a step) depends on its filtered covariance only,
/// so while one thread applies the gains of a block of frames backwards (lines 5-8, the
/// sequential part), the other threads compute the gains of the block before it. The same
/// functions in the same order per frame as [`rts_step`]: the same numbers bit for bit.
fn smooth_pipelined(
    means: &mut [f64],
    covs: &mut [f64],
    vz: &DMatrix<f64>,
    ns: usize,
    tr: Transition<'_>,
    mut acc: Option<&mut DMatrix<f64>>,
) -> Result<()> {
    type Gains = Vec<(DMatrix<f64>, DMatrix<f64>)>;
    let steps = means.len() / ns;
    let nn = ns * ns;
    let gains = |lo: usize, hi: usize, covs: &[f64]| -> Result<Gains> {
        (lo..hi)
            .into_par_iter()
            .map(|t| {
                let vf = DMatrix::from_column_slice(ns, ns, &covs[t * nn..(t + 1) * nn]);
                rts_gain(&vf, vz, tr, t)
            })
            .collect()
    };
    // frames lo..hi of `means`/`covs` backwards, given the smoothed frame hi (and eq. 79's
    // statistic, as in the sequential form)
    let apply = |lo: usize,
                 hi: usize,
                 g: &Gains,
                 means: &mut [f64],
                 covs: &mut [f64],
                 mut acc: Option<&mut DMatrix<f64>>| {
        let mut scratch = (Vec::new(), Vec::new());
        for t in (lo..hi).rev() {
            let (gt, p) = &g[t - lo];
            let (cov_head, cov_tail) = covs.split_at_mut((t + 1 - lo) * nn);
            let (mean_head, mean_tail) = means.split_at_mut((t + 1 - lo) * ns);
            let (vs_next, ms_next) = (&cov_tail[..nn], &mean_tail[..ns]);
            let mf = DVector::from_column_slice(&mean_head[(t - lo) * ns..]);
            let ms = smoothed_mean(&mf, gt, ms_next, tr);
            let cov = &mut cov_head[(t - lo) * nn..];
            smoothed_cov_in_place(cov, gt.as_slice(), p.as_slice(), vs_next, &mut scratch);
            if let Some(acc) = acc.as_deref_mut() {
                let vs = DMatrix::from_column_slice(ns, ns, cov);
                let vn = DMatrix::from_column_slice(ns, ns, vs_next);
                let mn = DVector::from_column_slice(ms_next);
                add_statistic(acc, &ms, &vs, &mn, &vn, gt, tr);
            }
            mean_head[(t - lo) * ns..].copy_from_slice(ms.as_slice());
        }
    };
    let mut hi = steps - 1;
    let mut lo = hi.saturating_sub(GAIN_BLOCK);
    let mut current = gains(lo, hi, covs)?;
    loop {
        let next_lo = lo.saturating_sub(GAIN_BLOCK);
        let (head_m, tail_m) = means.split_at_mut(lo * ns);
        let (head_c, tail_c) = covs.split_at_mut(lo * nn);
        let _ = head_m;
        let acc_here = acc.as_deref_mut();
        let (_, next) = rayon::join(
            || apply(lo, hi, &current, tail_m, tail_c, acc_here),
            || {
                if lo > 0 {
                    gains(next_lo, lo, head_c)
                } else {
                    Ok(Vec::new())
                }
            },
        );
        if lo == 0 {
            return Ok(());
        }
        current = next?;
        hi = lo;
        lo = next_lo;
    }
}

/// One backward step of Alg. 8 (lines 3-8) for the transition of
/// [`super::filter::predict`]: from the filtered `(μ̃_t, Ṽ_t)` and the smoothed
/// `(μ̂_{t+1}, V̂_{t+1})` to `(μ̂_t, V̂_t, G_tᵀ)`.
///
/// # Errors
/// Numerical error if `F Ṽ_t Fᵀ + V_z` is not positive definite.
#[cfg(test)]
pub(crate) fn rts_step(
    mf: &DVector<f64>,
    vf: &DMatrix<f64>,
    ms_next: &DVector<f64>,
    vs_next: &DMatrix<f64>,
    vz: &DMatrix<f64>,
    tr: Transition<'_>,
    t: usize,
) -> Result<(DVector<f64>, DMatrix<f64>, DMatrix<f64>)> {
    let (gt, p) = rts_gain(vf, vz, tr, t)?;
    let (ms, vs) = rts_apply(mf, vf, &gt, &p, ms_next, Some(vs_next), tr);
    Ok((ms, vs.expect("asked for"), gt))
}

/// The gain of one backward step of Alg. 8, which depends on the filtered covariance only:
/// `(G_tᵀ, P)` with `P = F Ṽ_t Fᵀ + V_z` and `G_tᵀ = P⁻¹ F Ṽ_t` (line 4).
///
/// # Errors
/// Numerical error if `P` is not positive definite.
pub(crate) fn rts_gain(
    vf: &DMatrix<f64>,
    vz: &DMatrix<f64>,
    tr: Transition<'_>,
    t: usize,
) -> Result<(DMatrix<f64>, DMatrix<f64>)> {
    let ns = vf.nrows();
    let fv = f_left(vf, tr); // F Ṽ_t
    let p = f_right(&fv, tr) + vz;
    let lp = cholesky(p.as_slice(), ns, &|| {
        format!("F Ṽ_t Fᵀ + V_z in the smoother at frame {t}")
    })?;
    let mut gt = fv; // Gᵀ = P⁻¹ F Ṽ_t (P and Ṽ_t symmetric)
    chol_solve_mat(&lp, &mut gt);
    Ok((gt, p))
}

/// Line 7 of Alg. 8: `μ̂_t = μ̃_t + G (μ̂_{t+1} − F μ̃_t)`.
fn smoothed_mean(
    mf: &DVector<f64>,
    gt: &DMatrix<f64>,
    ms_next: &[f64],
    tr: Transition<'_>,
) -> DVector<f64> {
    let ns = mf.len();
    let fm = f_left(&DMatrix::from_column_slice(ns, 1, mf.as_slice()), tr);
    let d = DVector::from_column_slice(ms_next) - fm.column(0);
    mf + gt.tr_mul(&d)
}

/// Line 8 of Alg. 8 in place: `cov` holds `Ṽ_t` (column-major `ns × ns`) and becomes
/// `V̂_t = Ṽ_t + G (V̂_{t+1} − P) Gᵀ`, by two packed GEMMs (the second adds `Gᵀᵀ T` into
/// `cov` directly; no copies), then symmetrised. `scratch` holds `V̂_{t+1} − P` and `T`.
fn smoothed_cov_in_place(
    cov: &mut [f64],
    gt: &[f64],
    p: &[f64],
    vs_next: &[f64],
    scratch: &mut (Vec<f64>, Vec<f64>),
) {
    let nn = cov.len();
    let ns = (nn as f64).sqrt().round() as usize;
    let (a, tmp) = scratch;
    a.clear();
    a.extend(vs_next.iter().zip(p).map(|(v, q)| v - q));
    tmp.clear();
    tmp.resize(nn, 0.0);
    // SAFETY: all operands are ns × ns column-major slices of their own (`cov` is written
    // only by the second product, which reads `gt` and `tmp`).
    unsafe {
        // T = (V̂_{t+1} − P) Gᵀ, then cov += G T with G = (Gᵀ)ᵀ
        gemm(
            (ns, ns, ns),
            1.0,
            (a.as_ptr(), ns, false),
            (gt.as_ptr(), ns),
            0.0,
            (tmp.as_mut_ptr(), ns),
        );
        gemm(
            (ns, ns, ns),
            1.0,
            (gt.as_ptr(), ns, true),
            (tmp.as_ptr(), ns),
            1.0,
            (cov.as_mut_ptr(), ns),
        );
    }
    symmetrize_slice(cov, ns);
}

/// Lines 5-8 of Alg. 8 with the gain of [`rts_gain`]: `μ̂_t = μ̃_t + G (μ̂_{t+1} − F μ̃_t)` and,
/// if `vs_next` is given, `V̂_t = Ṽ_t + G (V̂_{t+1} − P) Gᵀ`.
pub(crate) fn rts_apply(
    mf: &DVector<f64>,
    vf: &DMatrix<f64>,
    gt: &DMatrix<f64>,
    p: &DMatrix<f64>,
    ms_next: &DVector<f64>,
    vs_next: Option<&DMatrix<f64>>,
    tr: Transition<'_>,
) -> (DVector<f64>, Option<DMatrix<f64>>) {
    let ms = smoothed_mean(mf, gt, ms_next.as_slice(), tr);
    let vs = vs_next.map(|vn| {
        let mut vs = vf.clone();
        smoothed_cov_in_place(
            vs.as_mut_slice(),
            gt.as_slice(),
            p.as_slice(),
            vn.as_slice(),
            &mut (Vec::new(), Vec::new()),
        );
        vs
    });
    (ms, vs)
}
