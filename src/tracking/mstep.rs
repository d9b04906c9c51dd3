//! The M-step (ACM supp. Alg. 12, eqs. 77-81) and the convergence measure (Alg. 13).

use super::dense::cholesky;
use super::filter::{sigma_points, status};
use super::model::Emission;
use super::Params;
use crate::error::Result;
use nalgebra::DMatrix;
use rayon::prelude::*;

/// Frames per parallel work item (fixed, so that the reduction order is deterministic).
const CHUNK: usize = 4;

/// `e_tj = E[(x_tj − g_j(z_t))²]` under `N(μ̂_t, V̂_t)` by the sigma points (eq. 81) for the
/// entries of frame `t` used in the E-step, NaN for the others; `sigma` (`2n × n`) and `g`
/// (`2n × n_x`) are scratch.
#[allow(clippy::too_many_arguments)]
fn frame_residual_moments<E: Emission + ?Sized>(
    em: &E,
    means: &[f64],
    covs: &[f64],
    x: &[f64],
    mask: &[u8],
    t: usize,
    sigma: &mut [f64],
    g: &mut [f64],
    out: &mut [f64],
) -> Result<()> {
    let (n, n_x) = (em.n_state(), em.n_meas());
    out.fill(f64::NAN);
    let m = &mask[t * n_x..(t + 1) * n_x];
    if !m.contains(&status::USED) {
        return Ok(());
    }
    let k = t + 1; // moments index (0 = z_0)
    let l = cholesky(&covs[k * n * n..(k + 1) * n * n], n, &|| {
        format!("the smoothed state covariance of frame {t}")
    })?;
    let mean = &means[k * n..(k + 1) * n];
    sigma_points(mean, &l, sigma);
    // on this thread: the callers run frames in parallel already (a spinning team inside
    // would compete with rayon's workers for the cores)
    em.eval_sigma(mean, sigma, true, g)?;
    let xt = &x[t * n_x..(t + 1) * n_x];
    for j in 0..n_x {
        if m[j] != status::USED {
            continue;
        }
        let (mut s, mut cnt) = (0.0, 0usize);
        for i in 0..2 * n {
            let v = g[i * n_x + j];
            if v.is_finite() {
                s += (xt[j] - v) * (xt[j] - v);
                cnt += 1;
            }
        }
        if cnt > 0 {
            out[j] = s / cnt as f64;
        }
    }
    Ok(())
}

/// `V_x,j = sums_j / counts_j` (eq. 81), the previous value for entries never used. A floor
/// keeps `V_x` invertible if a measurement is fitted exactly.
fn vx_from_sums(sums: &[f64], counts: &[f64], prev: &[f64]) -> Vec<f64> {
    sums.iter()
        .zip(counts)
        .zip(prev)
        .map(|((s, &c), &p)| if c > 0.0 { (s / c).max(1e-14) } else { p })
        .collect()
}

/// New parameters from the smoothed moments: `μ0 = μ̂_0`, `V0 = V̂_0` (eqs. 77-78),
/// `V_z = acc / T` (eq. 79, `acc` from the smoother) and the diagonal `V_x` of eq. 81 from the
/// sigma points of every `N(μ̂_t, V̂_t)` through `g`, counting only the entries used in the
/// E-step (`mask == USED`). Entries never used keep their previous value.
///
/// # Errors
/// Numerical error if a smoothed covariance is not positive semi-definite; emission errors.
pub(crate) fn m_step<E: Emission + ?Sized>(
    em: &E,
    means: &[f64],
    covs: &[f64],
    x: &[f64],
    mask: &[u8],
    acc: &DMatrix<f64>,
    prev: &Params,
) -> Result<Params> {
    let n = em.n_state();
    let n_x = em.n_meas();
    let t_len = x.len() / n_x;
    let mu0 = means[..n].to_vec();
    let v0 = covs[..n * n].to_vec();
    let vz: Vec<f64> = acc.iter().map(|v| v / t_len.max(1) as f64).collect();
    // Eq. 81, in parallel over chunks of frames, reduced in chunk order.
    let partial: Vec<Result<(Vec<f64>, Vec<f64>)>> = (0..t_len.div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let mut sums = vec![0.0; n_x];
            let mut counts = vec![0.0; n_x];
            let mut sigma = vec![0.0; 2 * n * n];
            let mut g = vec![0.0; 2 * n * n_x];
            let mut e = vec![0.0; n_x];
            for t in c * CHUNK..((c + 1) * CHUNK).min(t_len) {
                frame_residual_moments(em, means, covs, x, mask, t, &mut sigma, &mut g, &mut e)?;
                for j in 0..n_x {
                    if e[j].is_finite() {
                        sums[j] += e[j];
                        counts[j] += 1.0;
                    }
                }
            }
            Ok((sums, counts))
        })
        .collect();
    let mut sums = vec![0.0; n_x];
    let mut counts = vec![0.0; n_x];
    for p in partial {
        let (s, c) = p?;
        for j in 0..n_x {
            sums[j] += s[j];
            counts[j] += c[j];
        }
    }
    let vx = vx_from_sums(&sums, &counts, &prev.vx);
    Ok(Params { mu0, v0, vz, vx })
}

/// Alg. 13: the mean relative change of `(μ0, diag V0, diag V_z, diag V_x)` between two
/// parameter sets (eqs. 82-87). An entry that is exactly zero before and after counts as no
/// change.
pub fn relative_change(prev: &Params, next: &Params) -> f64 {
    let n = prev.mu0.len();
    let rel = |a: f64, b: f64| {
        if a == b {
            0.0
        } else {
            ((b - a) / a).abs()
        }
    };
    let mut sum = 0.0;
    for i in 0..n {
        sum += rel(prev.mu0[i], next.mu0[i]);
        sum += rel(prev.v0[i * n + i], next.v0[i * n + i]);
        sum += rel(prev.vz[i * n + i], next.vz[i * n + i]);
    }
    for (a, b) in prev.vx.iter().zip(&next.vx) {
        sum += rel(*a, *b);
    }
    sum / (3 * n + prev.vx.len()) as f64
}

/// The M-step of a Student-t measurement model (beyond the paper; issue 12): each image point
/// (a block of `em.block()` entries) of frame `t` has noise `V_x / w_tb` with
/// `w ~ Gamma(ν/2, ν/2)`, i.e. a Student-t with `ν = dof` degrees of freedom. With the
/// expected squared residuals `e_tj = E[(x_tj − g_j(z_t))²]` under the smoothed posterior
/// (sigma points, as eq. 81) and `δ²_tb = Σ_{j∈b} e_tj / V_x,j` (previous `V_x`):
///
/// `w_tb = (ν + k) / (ν + δ²_tb)` (k = used entries of the block), and
/// `V_x,j = Σ_t w_tb e_tj / n_j` (the weighted eq. 81).
///
/// `μ0`, `V0` and `V_z` are eqs. 77-79 as in [`m_step`]. Returns the parameters and the
/// per-entry weights (`T × n_x`, 1 where an entry was not used) for the next E-step.
///
/// # Errors
/// As [`m_step`]; an invalid error for `dof <= 0`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn m_step_student<E: Emission + ?Sized>(
    em: &E,
    means: &[f64],
    covs: &[f64],
    x: &[f64],
    mask: &[u8],
    acc: &DMatrix<f64>,
    prev: &Params,
    dof: f64,
) -> Result<(Params, Vec<f64>)> {
    if !(dof.is_finite() && dof > 0.0) {
        return Err(crate::error::AcmError::Invalid(format!(
            "the Student-t degrees of freedom must be > 0, got {dof}"
        )));
    }
    let n = em.n_state();
    let n_x = em.n_meas();
    let k = em.block().max(1);
    let t_len = x.len() / n_x;
    // eqs. 77-79 as in `m_step`
    let mu0 = means[..n].to_vec();
    let v0 = covs[..n * n].to_vec();
    let vz: Vec<f64> = acc.iter().map(|v| v / t_len.max(1) as f64).collect();
    // e_tj for the used entries (NaN elsewhere), frames in parallel
    let mut e = vec![f64::NAN; t_len * n_x];
    e.par_chunks_mut(n_x)
        .enumerate()
        .try_for_each(|(t, et)| -> Result<()> {
            let mut sigma = vec![0.0; 2 * n * n];
            let mut g = vec![0.0; 2 * n * n_x];
            frame_residual_moments(em, means, covs, x, mask, t, &mut sigma, &mut g, et)
        })?;
    let mut w = vec![1.0; t_len * n_x];
    let mut sums = vec![0.0; n_x];
    let mut counts = vec![0.0; n_x];
    for t in 0..t_len {
        for b0 in (0..n_x).step_by(k) {
            let idx = t * n_x + b0;
            let used: Vec<usize> = (0..k.min(n_x - b0))
                .filter(|&a| e[idx + a].is_finite())
                .collect();
            if used.is_empty() {
                continue;
            }
            let d2: f64 = used.iter().map(|&a| e[idx + a] / prev.vx[b0 + a]).sum();
            let wb = (dof + used.len() as f64) / (dof + d2);
            for &a in &used {
                w[idx + a] = wb;
                sums[b0 + a] += wb * e[idx + a];
                counts[b0 + a] += 1.0;
            }
        }
    }
    let vx = vx_from_sums(&sums, &counts, &prev.vx);
    Ok((Params { mu0, v0, vz, vx }, w))
}
