//! The unscented Kalman filter (ACM supp. Alg. 5-7) for the random-walk state-space model of
//! eqs. 49-50, with missing measurements and an optional innovation gate.
//!
//! # How the update is computed
//! With `α = 1, κ = 0` (eq. 42) the centre sigma point has weight 0 and the others `1/(2n)`
//! (eqs. 46-47). For the random-walk transition the sigma-point prediction of Alg. 6
//! lines 2-4 is exact: `z̄ = μ̃_{t-1}`, `P = Ṽ_{t-1} + V_z`. From `P = L Lᵀ` the sigma points
//! are `z̄ ± √n L_i` (Alg. 5, line 5 of Alg. 6) and go through `g` (line 6). Write the
//! centred, scaled deviations as `W = [L, −L] / √2` (`n × 2n`, so `W Wᵀ = P`) and
//! `Y = (X − x̄) / √(2n)` (`n_p × 2n`, present rows only), so that `S = V_x + Y Yᵀ` and
//! `C = W Yᵀ` (lines 8 and 15). Alg. 6 sets the rows/columns of missing entries to the
//! identity/zero, which is the same as dropping them. Because `V_x` is diagonal, whiten
//! `Ỹ = V_x^{-1/2} Y`, `ν̃ = V_x^{-1/2}(x_t − x̄)` and use the push-through identity:
//!
//! `K ν = W M⁻¹ Ỹᵀ ν̃`,  `Ṽ_t = P − K Cᵀ = W M⁻¹ Wᵀ`,  with `M = I_{2n} + ỸᵀỸ`.
//!
//! This is algebraically identical to lines 19-26 but factors a `2n × 2n` matrix instead of
//! `n_p × n_p` (`n_p` up to 344 for the rat with 4 cameras), never forms `S`, and yields a
//! filtered covariance that is positive semi-definite by construction. The cost per frame
//! is dominated by the Gram matrix `ỸᵀỸ` (`(2n)² n_p` multiply-adds) and the emission of `2n`
//! sigma points.

use super::dense::{add_gram_rows, cholesky, symmetrize};
use super::model::Emission;
use super::Params;
use crate::error::Result;
use nalgebra::{DMatrix, DVector};

/// Status of one measurement entry in one frame, as used by the last E-step.
pub mod status {
    /// No measurement (NaN input, e.g. below `pcutoff`).
    pub const MISSING: u8 = 0;
    /// Used in the update.
    pub const USED: u8 = 1;
    /// Rejected by the innovation gate.
    pub const GATED: u8 = 2;
    /// Measured, but the model cannot predict it (e.g. a marker behind the camera).
    pub const INVISIBLE: u8 = 3;
}

/// Counts of one forward pass.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FilterStats {
    /// Measurement entries used.
    pub used: usize,
    /// Entries rejected by the innovation gate.
    pub gated: usize,
    /// Entries the model could not predict (NaN emission).
    pub invisible: usize,
    /// Frames in which the gate would have rejected more than half of the blocks and was
    /// therefore not applied.
    pub gate_skipped_frames: usize,
    /// Marginal log-likelihood `Σ_t ln N(x_t; x̄_t, S_t)` of the used entries under the
    /// predicted distributions (from the innovations; normalised-pixel units).
    pub log_lik: f64,
}

/// Scratch buffers of the filter (allocated once per pass).
pub(crate) struct Workspace {
    sigma: Vec<f64>,
    x: Vec<f64>,
    xbar: Vec<f64>,
    used: Vec<usize>,
    ytil: Vec<f64>,
    gram: Vec<f64>,
}

impl Workspace {
    pub(crate) fn new(n: usize, n_x: usize) -> Self {
        Self {
            sigma: vec![0.0; 2 * n * n],
            x: vec![0.0; 2 * n * n_x],
            xbar: vec![0.0; n_x],
            used: Vec::with_capacity(n_x),
            ytil: Vec::with_capacity(2 * n * n_x),
            gram: vec![0.0; 4 * n * n],
        }
    }
}

/// Writes the `2n` sigma points `m ± √n L_i` (Alg. 5 without the weight-0 centre point) as
/// rows of `out` (`2n × n`).
pub(crate) fn sigma_points(m: &[f64], l: &DMatrix<f64>, out: &mut [f64]) {
    let n = m.len();
    let s = (n as f64).sqrt();
    for i in 0..n {
        let (plus, rest) = out[i * n..].split_at_mut(n);
        let minus = &mut rest[(n - 1) * n..n * n];
        for r in 0..n {
            let d = s * l[(r, i)];
            plus[r] = m[r] + d;
            minus[r] = m[r] - d;
        }
    }
}

/// One step of Alg. 6: from the filtered `(μ̃_{t-1}, Ṽ_{t-1})` and the measurement `x_t`
/// (NaN = missing) to `(μ̃_t, Ṽ_t)`, writing each entry's [`status`] into `mask`.
///
/// `gate`: reject a block of `emission.block()` entries (one image point) whose squared
/// Mahalanobis innovation under the predicted `S` exceeds this value — unless that would
/// reject more than half of the blocks of the frame (then the prediction, not the
/// measurements, is more likely wrong, and nothing is gated).
///
/// # Errors
/// Numerical error if `P` is not positive definite; emission errors.
#[allow(clippy::too_many_arguments)]
pub(crate) fn step<E: Emission + ?Sized>(
    em: &E,
    params: &Params,
    mu_prev: &[f64],
    v_prev: &[f64],
    x_t: &[f64],
    gate: Option<f64>,
    frame: usize,
    ws: &mut Workspace,
    mask: &mut [u8],
    weights: &[f64],
    mu_out: &mut [f64],
    v_out: &mut [f64],
    stats: &mut FilterStats,
) -> Result<()> {
    let n = mu_prev.len();
    let n_x = x_t.len();
    // Alg. 6 lines 2-4 (exact for the random walk): z̄ = μ̃_{t-1}, P = Ṽ_{t-1} + V_z.
    let p: Vec<f64> = v_prev.iter().zip(&params.vz).map(|(a, b)| a + b).collect();
    mask.fill(status::MISSING);
    if x_t.iter().all(|v| v.is_nan()) {
        // No measurement: the filtered distribution is the prediction.
        mu_out.copy_from_slice(mu_prev);
        v_out.copy_from_slice(&p);
        let mut pm = DMatrix::from_column_slice(n, n, v_out);
        symmetrize(&mut pm);
        v_out.copy_from_slice(pm.as_slice());
        return Ok(());
    }
    let l = cholesky(&p, n, &|| {
        format!("the predicted state covariance P = Ṽ + V_z of frame {frame}")
    })?;
    // Alg. 6 lines 5-7: sigma points of (z̄, P) through g, and their mean x̄.
    sigma_points(mu_prev, &l, &mut ws.sigma);
    em.eval_batch(&ws.sigma, &mut ws.x)?;
    let m2 = 2 * n;
    let inv = 1.0 / m2 as f64;
    ws.used.clear();
    // x̄ row by row (contiguous); a NaN emission anywhere in a column makes x̄_j NaN.
    ws.xbar.fill(0.0);
    for row in ws.x.chunks_exact(n_x) {
        for (a, v) in ws.xbar.iter_mut().zip(row) {
            *a += v;
        }
    }
    for j in 0..n_x {
        ws.xbar[j] *= inv;
        if x_t[j].is_nan() {
            continue;
        }
        if ws.xbar[j].is_finite() {
            mask[j] = status::USED;
        } else {
            mask[j] = status::INVISIBLE;
            stats.invisible += 1;
        }
    }
    // Student-t model: entry j has noise V_x,j / w_j (w = 1: the Gaussian model)
    let vx_eff: Vec<f64> = params.vx.iter().zip(weights).map(|(v, w)| v / w).collect();
    if let Some(g) = gate {
        apply_gate(em.block(), g, ws, x_t, &vx_eff, mask, stats);
    }
    ws.used
        .extend((0..n_x).filter(|&j| mask[j] == status::USED));
    let np = ws.used.len();
    stats.used += np;
    if np == 0 {
        mu_out.copy_from_slice(mu_prev);
        v_out.copy_from_slice(&p);
        return Ok(());
    }
    // Whitened deviations Ỹ (2n × n_p, row = sigma point) and innovation ν̃.
    ws.ytil.clear();
    ws.ytil.resize(m2 * np, 0.0);
    let mut nu = DVector::zeros(np);
    let scale: Vec<f64> = ws.used.iter().map(|&j| 1.0 / vx_eff[j].sqrt()).collect();
    for (q, &j) in ws.used.iter().enumerate() {
        nu[q] = (x_t[j] - ws.xbar[j]) * scale[q];
    }
    let sq = inv.sqrt();
    for i in 0..m2 {
        let row = &ws.x[i * n_x..(i + 1) * n_x];
        let dst = &mut ws.ytil[i * np..(i + 1) * np];
        for (q, &j) in ws.used.iter().enumerate() {
            dst[q] = (row[j] - ws.xbar[j]) * scale[q] * sq;
        }
    }
    // M = I + Ỹ Ỹᵀ (the dominant product).
    ws.gram.fill(0.0);
    for i in 0..m2 {
        ws.gram[i * m2 + i] = 1.0;
    }
    add_gram_rows(&ws.ytil, m2, np, &mut ws.gram);
    let lm = cholesky(&ws.gram, m2, &|| format!("I + ỸᵀỸ of frame {frame}"))?;
    // s = M⁻¹ Ỹ ν̃ (here Ỹ is stored transposed: row i = sigma point i).
    let mut s = DVector::zeros(m2);
    for i in 0..m2 {
        let row = &ws.ytil[i * np..(i + 1) * np];
        s[i] = row.iter().zip(nu.iter()).map(|(a, b)| a * b).sum();
    }
    let b = s.clone();
    super::dense::chol_solve_vec(&lm, &mut s);
    // ln N(x; x̄, S) with S = V_x^{1/2} (I + Ỹ Ỹᵀ) V_x^{1/2}: |I + ỸỸᵀ| = |M| (Sylvester),
    // νᵀS⁻¹ν = ν̃ᵀν̃ − bᵀM⁻¹b with b = Ỹᵀν̃ (Woodbury).
    let log_det = ws.used.iter().map(|&j| vx_eff[j].ln()).sum::<f64>()
        + 2.0 * (0..m2).map(|i| lm[(i, i)].ln()).sum::<f64>();
    let maha = nu.norm_squared() - b.dot(&s);
    stats.log_lik -= 0.5 * (np as f64 * (2.0 * std::f64::consts::PI).ln() + log_det + maha);
    // μ̃ = z̄ + W s with W = [L, −L]/√2.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let d: DVector<f64> = DVector::from_fn(n, |i, _| h * (s[i] - s[n + i]));
    let upd = &l * d;
    for r in 0..n {
        mu_out[r] = mu_prev[r] + upd[r];
    }
    // Ṽ = W M⁻¹ Wᵀ = Uᵀ U with U = L_M⁻¹ Wᵀ.
    let mut u = DMatrix::zeros(m2, n);
    for i in 0..n {
        for r in 0..n {
            let v = h * l[(r, i)];
            u[(i, r)] = v;
            u[(n + i, r)] = -v;
        }
    }
    lm.solve_lower_triangular_mut(&mut u);
    let mut vt = super::dense::at_a(&u);
    symmetrize(&mut vt);
    v_out.copy_from_slice(vt.as_slice());
    Ok(())
}

/// The innovation gate: per block of entries (one image point), the squared Mahalanobis
/// distance `νᵀ S_b⁻¹ ν` with `S_b` the block of `S = V_x + Y Yᵀ`.
fn apply_gate(
    block: usize,
    gate: f64,
    ws: &Workspace,
    x_t: &[f64],
    vx: &[f64],
    mask: &mut [u8],
    stats: &mut FilterStats,
) {
    let n_x = x_t.len();
    let m2 = ws.x.len() / n_x;
    let inv = 1.0 / m2 as f64;
    let k = block;
    let n_blocks = n_x / k;
    // Blocks of S (lower triangles, k(k+1)/2 entries each), accumulated row by row.
    let tri = k * (k + 1) / 2;
    let mut sb_all = vec![0.0; n_blocks * tri];
    for row in ws.x.chunks_exact(n_x) {
        for (b, acc) in sb_all.chunks_exact_mut(tri).enumerate() {
            let b0 = b * k;
            let mut e = 0;
            for a in 0..k {
                let da = row[b0 + a] - ws.xbar[b0 + a];
                for c in 0..=a {
                    acc[e] += da * (row[b0 + c] - ws.xbar[b0 + c]);
                    e += 1;
                }
            }
        }
    }
    let mut rejected = Vec::new();
    let mut blocks = 0;
    for (b, acc) in sb_all.chunks_exact(tri).enumerate() {
        let b0 = b * k;
        if (b0..b0 + k).any(|j| mask[j] != status::USED) {
            continue;
        }
        blocks += 1;
        let mut sb = DMatrix::zeros(k, k);
        let mut e = 0;
        for a in 0..k {
            for c in 0..=a {
                sb[(a, c)] = inv * acc[e];
                sb[(c, a)] = inv * acc[e];
                e += 1;
            }
            sb[(a, a)] += vx[b0 + a];
        }
        let nu = DVector::from_fn(k, |a, _| x_t[b0 + a] - ws.xbar[b0 + a]);
        let d2 = match sb.cholesky() {
            Some(c) => {
                let w = c.l().solve_lower_triangular(&nu).unwrap_or(nu.clone());
                w.norm_squared()
            }
            None => 0.0,
        };
        if d2 > gate {
            rejected.push(b0);
        }
    }
    if rejected.is_empty() {
        return;
    }
    if 2 * rejected.len() > blocks {
        stats.gate_skipped_frames += 1;
        return;
    }
    for b0 in rejected {
        for m in mask.iter_mut().skip(b0).take(k) {
            *m = status::GATED;
            stats.gated += 1;
        }
    }
}
