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

use super::dense::{chol_solve_mat, cholesky, symmetrize};
use crate::error::Result;
use nalgebra::{DMatrix, DVector};

/// Runs Alg. 9 in place: `means`/`covs` hold the filtered `(T+1)` moments (index 0 = the
/// prior of `z_0`) and are overwritten with the smoothed ones. Returns
/// `Σ_{t=1}^{T} E[(z_t − z_{t-1})(z_t − z_{t-1})ᵀ]` (`n × n`, column-major).
///
/// # Errors
/// Numerical error if some `Ṽ_t + V_z` is not positive definite.
pub(crate) fn smooth_in_place(
    means: &mut [f64],
    covs: &mut [f64],
    vz: &[f64],
    n: usize,
) -> Result<DMatrix<f64>> {
    let steps = means.len() / n;
    let mut acc = DMatrix::zeros(n, n);
    if steps < 2 {
        return Ok(acc);
    }
    let vz = DMatrix::from_column_slice(n, n, vz);
    for t in (0..steps - 1).rev() {
        let (cov_head, cov_tail) = covs.split_at_mut((t + 1) * n * n);
        let vf = DMatrix::from_column_slice(n, n, &cov_head[t * n * n..]);
        let vs_next = DMatrix::from_column_slice(n, n, &cov_tail[..n * n]);
        let (mean_head, mean_tail) = means.split_at_mut((t + 1) * n);
        let mf = DVector::from_column_slice(&mean_head[t * n..]);
        let ms_next = DVector::from_column_slice(&mean_tail[..n]);
        // Alg. 8 lines 3-6.
        let p = &vf + &vz;
        let lp = cholesky(p.as_slice(), n, &|| {
            format!("Ṽ_t + V_z in the smoother at frame {t}")
        })?;
        let mut gt = vf.clone(); // Gᵀ = P⁻¹ Ṽ_t (P and Ṽ_t symmetric)
        chol_solve_mat(&lp, &mut gt);
        let g = gt.transpose();
        // Lines 7-8.
        let ms = &mf + &g * (&ms_next - &mf);
        let mut vs = &vf + &g * (&vs_next - &p) * &gt;
        symmetrize(&mut vs);
        // Eq. 79 term for the pair (t+1, t).
        let d = &ms_next - &ms;
        let cross = &vs_next * &gt; // Cov(z_{t+1}, z_t) = V̂_{t+1} G_tᵀ
        acc += &d * d.transpose() + &vs_next + &vs - &cross - cross.transpose();
        mean_head[t * n..].copy_from_slice(ms.as_slice());
        cov_head[t * n * n..].copy_from_slice(vs.as_slice());
    }
    symmetrize(&mut acc);
    Ok(acc)
}
