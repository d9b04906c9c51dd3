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

use super::dense::{
    add_a_at, add_gram_rows, add_gram_rows_lower, cholesky, cholesky_into, mirror_lower,
    symmetrize_slice,
};
use super::model::Emission;
use super::Params;
use crate::error::Result;
use crate::kernels::{cholesky_in_place, dot, lower_solve_in_place, lower_tr_solve_in_place};
use crate::team::Team;
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
    /// Frames whose update was relinearised about the posterior (see `relinearize`).
    pub relinearized_frames: usize,
    /// Linearisations beyond each frame's first, over all frames (the iterations of the
    /// relinearised frames; each costs about one update).
    pub relinearizations: usize,
}

/// Scratch buffers of the filter. Sized on the first frame; a frame whose update holds
/// without relinearisation allocates nothing afterwards (the online filter's promise).
#[derive(Debug)]
pub(crate) struct Workspace {
    sigma: Vec<f64>,
    x: Vec<f64>,
    xbar: Vec<f64>,
    /// `X − x̄` (`2n × n_x`, row = sigma point): the deviations the gate and `Ỹ` share.
    dev: Vec<f64>,
    used: Vec<usize>,
    /// `ws.used` as runs of consecutive entries `(first entry, first index in used, length)`.
    runs: Vec<(usize, usize, usize)>,
    ytil: Vec<f64>,
    /// `M = I + ỸỸᵀ`, factorised in place.
    gram: Vec<f64>,
    /// The prediction `(m̄, P)` and the Cholesky factor `L̃` of `P` (`ns`, `ns × ns`).
    mbar: Vec<f64>,
    p: Vec<f64>,
    lfull: Vec<f64>,
    vx_eff: Vec<f64>,
    scale: Vec<f64>,
    nu: Vec<f64>,
    xhat: Vec<f64>,
    gx: Vec<f64>,
    /// `Σ_r dev[r, j] dev[r, j − o]` for the gate's block offsets `o` (`block × n_x`).
    bands: Vec<f64>,
    /// The linear prediction `D s[n..]` of [`linearisation_error`] (`n_p`).
    lin: Vec<f64>,
    /// The gate's rejected blocks, one block of `S` and its whitened innovation.
    rejected: Vec<usize>,
    sb: Vec<f64>,
    sbw: Vec<f64>,
    /// `U = L_M⁻¹ [Wᵀ; 0]` (`2n × ns`) and `Ỹν̃` (`2n`) of [`linear_update`].
    u: Vec<f64>,
    b: Vec<f64>,
    up: Update,
    /// Linearisations of the current frame beyond its first (moved into
    /// [`FilterStats::relinearizations`] at the frame's end).
    relin_steps: usize,
    /// Everything on the calling thread (no hand-off to rayon's pool; see
    /// [`Emission::eval_batch_serial`]).
    pub(crate) serial: bool,
}

impl Workspace {
    pub(crate) fn new(n: usize, n_x: usize) -> Self {
        Self {
            sigma: vec![0.0; 2 * n * n],
            x: vec![0.0; 2 * n * n_x],
            xbar: vec![0.0; n_x],
            dev: vec![0.0; 2 * n * n_x],
            used: Vec::with_capacity(n_x),
            runs: Vec::with_capacity(n_x),
            ytil: Vec::with_capacity(2 * n * n_x),
            gram: vec![0.0; 4 * n * n],
            mbar: Vec::new(),
            p: Vec::new(),
            lfull: Vec::new(),
            vx_eff: Vec::with_capacity(n_x),
            scale: Vec::with_capacity(n_x),
            nu: Vec::with_capacity(n_x),
            xhat: Vec::with_capacity(n_x),
            gx: vec![0.0; n_x],
            bands: Vec::new(),
            lin: Vec::with_capacity(n_x),
            rejected: Vec::with_capacity(n_x),
            sb: Vec::new(),
            sbw: Vec::new(),
            u: Vec::new(),
            b: Vec::new(),
            up: Update::default(),
            relin_steps: 0,
            serial: false,
        }
    }
}

/// `g` of each row of `states` into `out`, on the calling thread alone if `serial`.
fn eval<E: Emission + ?Sized>(em: &E, serial: bool, states: &[f64], out: &mut [f64]) -> Result<()> {
    if serial {
        em.eval_batch_serial(states, out)
    } else {
        em.eval_batch(states, out)
    }
}

/// Writes the `2n` sigma points `m ± √n L_i` (Alg. 5 without the weight-0 centre point) as
/// rows of `out` (`2n × n`).
pub(crate) fn sigma_points(m: &[f64], l: &DMatrix<f64>, out: &mut [f64]) {
    sigma_points_from(m, l.as_slice(), l.nrows(), out);
}

/// [`sigma_points`] with the factor's leading `n × n` block read from the column-major
/// slice `l` of leading dimension `ld` (e.g. the position block of the whole state's).
fn sigma_points_from(m: &[f64], l: &[f64], ld: usize, out: &mut [f64]) {
    let n = m.len();
    let s = (n as f64).sqrt();
    for i in 0..n {
        let (plus, rest) = out[i * n..].split_at_mut(n);
        let minus = &mut rest[(n - 1) * n..n * n];
        let col = &l[i * ld..i * ld + n];
        for r in 0..n {
            let d = s * col[r];
            plus[r] = m[r] + d;
            minus[r] = m[r] - d;
        }
    }
}

crate::kernels::dispatch!(
    /// `dev[r, j] = x[r, j] − x̄[j]` for the row-major rows of `x` (`x̄.len()` entries each).
    fn deviations(x: &[f64], xbar: &[f64], dev: &mut [f64]) -> () {
        let n_x = xbar.len();
        for (d, row) in dev.chunks_exact_mut(n_x).zip(x.chunks_exact(n_x)) {
            for ((d, v), m) in d.iter_mut().zip(row).zip(xbar) {
                *d = v - m;
            }
        }
    }
);

/// `used` (ascending entries) as runs of consecutive entries `(first entry, its index in
/// used, length)`, so that the loops over them are contiguous.
fn used_runs(used: &[usize], runs: &mut Vec<(usize, usize, usize)>) {
    runs.clear();
    for (q, &j) in used.iter().enumerate() {
        match runs.last_mut() {
            Some((j0, _, len)) if *j0 + *len == j => *len += 1,
            _ => runs.push((j, q, 1)),
        }
    }
}

crate::kernels::dispatch!(
    /// Rows `i` and `n + i` of `Ỹ` (`2n × n_p`, `n_p = scale.len()`) from the deviations of the
    /// sigma points `z̄ ± √n L_i` (`a`, `b`: rows `i`, `n + i` of `dev` at the used entries):
    /// `E_i = (a + b) s √(1/4n)`, `D_i = (a − b) s √(1/4n)` (`sq = √(1/4n)`, `s` = `scale`).
    fn whitened_pairs(
        dev: &[f64],
        n: usize,
        n_x: usize,
        runs: &[(usize, usize, usize)],
        scale: &[f64],
        sq: f64,
        ytil: &mut [f64],
    ) -> () {
        let np = scale.len();
        for i in 0..n {
            let (dst_e, rest) = ytil[i * np..].split_at_mut(n * np);
            let (dst_e, dst_d) = (&mut dst_e[..np], &mut rest[..np]);
            let dp = &dev[i * n_x..(i + 1) * n_x];
            let dm = &dev[(n + i) * n_x..(n + i + 1) * n_x];
            for &(j0, q0, len) in runs {
                let pairs = dp[j0..j0 + len].iter().zip(&dm[j0..j0 + len]);
                let outs = dst_e[q0..q0 + len].iter_mut().zip(&mut dst_d[q0..q0 + len]);
                for ((e, d), ((a, b), s)) in outs.zip(pairs.zip(&scale[q0..q0 + len])) {
                    *d = (a - b) * s * sq;
                    *e = (a + b) * s * sq;
                }
            }
        }
    }
);

crate::kernels::dispatch!(
    /// `bands[o, j] = Σ_r dev[r, j] dev[r, j − o]` (`j ≥ o`, summed over the rows `r` in order)
    /// for the offsets `o < k`: the entries `(a, a − o)` of every block of `k` entries of
    /// `Σ_r dev_r dev_rᵀ`, each a contiguous axpy over the row.
    fn band_products(dev: &[f64], n_x: usize, k: usize, bands: &mut [f64]) -> () {
        bands.fill(0.0);
        for row in dev.chunks_exact(n_x) {
            for (o, band) in bands.chunks_exact_mut(n_x).take(k).enumerate() {
                let terms = row[o..].iter().zip(&row[..n_x - o]);
                for (b, (x, y)) in band[o..].iter_mut().zip(terms) {
                    *b += x * y;
                }
            }
        }
    }
);

/// One step of Alg. 6: from the filtered `(μ̃_{t-1}, Ṽ_{t-1})` and the measurement `x_t`
/// (NaN = missing) to `(μ̃_t, Ṽ_t)`, writing each entry's [`status`] into `mask`.
///
/// `gate`: reject a block of `emission.block()` entries (one image point) whose squared
/// Mahalanobis innovation under the predicted `S` exceeds this value — unless that would
/// reject more than half of the blocks of the frame (then the prediction, not the
/// measurements, is more likely wrong, and nothing is gated).
///
/// `relinearize`: at most this many iterated posterior linearisations of the update where
/// the first one does not hold (0: the paper's single unscented update). `hint`: a
/// position mean and covariance (`n`, `n × n`) near this frame's posterior, used to
/// linearise where the prior is too broad (see [`hinted_update`]).
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
    relinearize: usize,
    hint: Option<(&[f64], &[f64])>,
    frame: usize,
    ws: &mut Workspace,
    mask: &mut [u8],
    weights: &[f64],
    mu_out: &mut [f64],
    v_out: &mut [f64],
    stats: &mut FilterStats,
) -> Result<()> {
    let n = em.n_state();
    let n_x = x_t.len();
    let ns = mu_prev.len();
    // Alg. 6 lines 2-4 (exact for the linear transition): m̄ = F μ̃_{t-1}, P = F Ṽ_{t-1} Fᵀ + V_z.
    ws.mbar.resize(ns, 0.0);
    ws.p.resize(ns * ns, 0.0);
    predict_into(
        mu_prev,
        v_prev,
        &params.vz,
        Transition::of(em),
        &mut ws.mbar,
        &mut ws.p,
    );
    mask.fill(status::MISSING);
    if x_t.iter().all(|v| v.is_nan()) {
        // No measurement: the filtered distribution is the prediction.
        mu_out.copy_from_slice(&ws.mbar);
        v_out.copy_from_slice(&ws.p);
        return Ok(());
    }
    // L̃ = chol(P); its leading n × n block L is the factor of the position block P_zz.
    ws.lfull.resize(ns * ns, 0.0);
    cholesky_into(&ws.p, ns, &mut ws.lfull, &|| {
        format!("the predicted state covariance P = F Ṽ Fᵀ + V_z of frame {frame}")
    })?;
    // Alg. 6 lines 5-7: sigma points of (z̄, P) through g, and their mean x̄.
    sigma_points_from(&ws.mbar[..n], &ws.lfull, ns, &mut ws.sigma);
    em.eval_sigma(&ws.mbar[..n], &ws.sigma, ws.serial, &mut ws.x)?;
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
    // X − x̄, shared by the gate and Ỹ
    ws.dev.resize(m2 * n_x, 0.0);
    deviations(&ws.x, &ws.xbar, &mut ws.dev);
    // Student-t model: entry j has noise V_x,j / w_j (w = 1: the Gaussian model)
    ws.vx_eff.clear();
    ws.vx_eff
        .extend(params.vx.iter().zip(weights).map(|(v, w)| v / w));
    if let Some(g) = gate {
        apply_gate(em.block(), g, ws, x_t, mask, stats);
    }
    ws.used
        .extend((0..n_x).filter(|&j| mask[j] == status::USED));
    if let Some((hm, hv)) = hint {
        let invisible = mask.iter().filter(|&&m| m == status::INVISIBLE).count();
        let measured = ws.used.len() + invisible;
        let broad = measured > 0 && 5 * invisible > measured;
        // (the other sign of a broad prior, a first update that does not hold, is tested
        // below once that update exists)
        if broad {
            if let Some(up) = hinted(em, x_t, (hm, hv), relinearize, frame, mask, stats, ws)? {
                finish(&up, &ws.used, &ws.vx_eff, stats, mu_out, v_out);
                return Ok(());
            }
        }
    }
    let np = ws.used.len();
    stats.used += np;
    if np == 0 {
        mu_out.copy_from_slice(&ws.mbar);
        v_out.copy_from_slice(&ws.p);
        return Ok(());
    }
    // Whitened deviations Ỹ (2n × n_p, row = sigma point) and innovation ν̃ (`whitened_pairs`
    // writes every entry of Ỹ: no zeroing)
    ws.ytil.resize(m2 * np, 0.0);
    ws.scale.clear();
    ws.scale
        .extend(ws.used.iter().map(|&j| 1.0 / ws.vx_eff[j].sqrt()));
    ws.nu.clear();
    ws.nu.extend(
        ws.used
            .iter()
            .zip(&ws.scale)
            .map(|(&j, sc)| (x_t[j] - ws.xbar[j]) * sc),
    );
    // Rows i and n + i (the sigma points z̄ ± √n L_i) become their scaled sum and difference:
    // E = (Y₊ + Y₋)/√2 (what no linear map explains; rows 0..n of Ỹ) and D = (Y₊ − Y₋)/√2
    // (the linear part, `C = L Dᵀ`; rows n..2n). An orthogonal change of the 2n columns:
    // `ỸỸᵀ` and the update are unchanged, and `W = [L, −L]/√2` becomes `[0, L]` (see
    // [`linear_update`] for why E comes first).
    let sq = (0.5 * inv).sqrt();
    used_runs(&ws.used, &mut ws.runs);
    whitened_pairs(&ws.dev, n, n_x, &ws.runs, &ws.scale, sq, &mut ws.ytil);
    linear_update(
        &ws.mbar,
        &ws.lfull,
        n,
        &ws.ytil,
        &ws.nu,
        &mut ws.gram,
        &mut ws.u,
        &mut ws.b,
        frame,
        !ws.serial,
        Some(&mut *v_out),
        &mut ws.up,
    )?;
    if relinearize > 0 {
        // the whitened prediction of the linear model at z̄: x̄ (first pass)
        ws.xhat.clear();
        ws.xhat.extend(ws.used.iter().map(|&j| ws.xbar[j]));
        let lin = (ws.ytil.as_slice(), ws.used.as_slice());
        let err = linearisation_error(
            em,
            &ws.up,
            &ws.xhat,
            &ws.vx_eff,
            &mut ws.gx,
            lin,
            &mut ws.lin,
            ws.serial,
        )?;
        // (the usual case: the first update holds; the rest allocates and is rare)
        if err.is_nan() || err > RELIN_THRESHOLD {
            if let Some((hm, hv)) = hint {
                stats.used -= np;
                if let Some(better) =
                    hinted(em, x_t, (hm, hv), relinearize, frame, mask, stats, ws)?
                {
                    finish(&better, &ws.used, &ws.vx_eff, stats, mu_out, v_out);
                    return Ok(());
                }
                stats.used += np;
            }
            let mbar = ws.mbar.clone();
            let l_full = DMatrix::from_column_slice(ns, ns, &ws.lfull);
            // (the first update's covariance went straight to `v_out`)
            let mut first = ws.up.clone();
            first.v = v_out.to_vec();
            let (xhat, vx_eff) = (ws.xhat.clone(), ws.vx_eff.clone());
            if let Some(better) = relinearized(
                em,
                &mbar,
                &l_full,
                x_t,
                &vx_eff,
                xhat,
                &first,
                relinearize,
                frame,
                ws,
            )? {
                stats.relinearized_frames += 1;
                stats.relinearizations += std::mem::take(&mut ws.relin_steps);
                finish(&better, &ws.used, &ws.vx_eff, stats, mu_out, v_out);
                ws.up = better;
                return Ok(());
            }
        }
    }
    // (V is in `v_out` already)
    finish_mean(&ws.up, &ws.used, &ws.vx_eff, stats, mu_out);
    Ok(())
}

/// [`hinted_update`] with the prior of this frame from the workspace (a rare path: copies).
#[allow(clippy::too_many_arguments)]
fn hinted<E: Emission + ?Sized>(
    em: &E,
    x_t: &[f64],
    h: (&[f64], &[f64]),
    relinearize: usize,
    frame: usize,
    mask: &mut [u8],
    stats: &mut FilterStats,
    ws: &mut Workspace,
) -> Result<Option<Update>> {
    let ns = ws.mbar.len();
    let mbar = ws.mbar.clone();
    let l_full = DMatrix::from_column_slice(ns, ns, &ws.lfull);
    let vx_eff = ws.vx_eff.clone();
    // the linearisation overwrites the prior's sigma-point images; kept for the caller's
    // own update if it fails
    let (x, xbar) = (ws.x.clone(), ws.xbar.clone());
    let up = hinted_update(
        em,
        (&mbar, &l_full),
        x_t,
        &vx_eff,
        h,
        relinearize,
        frame,
        mask,
        stats,
        ws,
    )?;
    if up.is_none() {
        ws.x = x;
        ws.xbar = xbar;
    }
    Ok(up)
}

/// Writes an update's moments and adds its `ln N(x; x̂, S)` to the stats (`linear_update`
/// leaves out the `ln |V_x|` term of the `used` entries).
fn finish(
    up: &Update,
    used: &[usize],
    vx_eff: &[f64],
    stats: &mut FilterStats,
    mu_out: &mut [f64],
    v_out: &mut [f64],
) {
    finish_mean(up, used, vx_eff, stats, mu_out);
    v_out.copy_from_slice(&up.v);
}

/// [`finish`] for an update whose covariance [`linear_update`] wrote to the output itself.
fn finish_mean(
    up: &Update,
    used: &[usize],
    vx_eff: &[f64],
    stats: &mut FilterStats,
    mu_out: &mut [f64],
) {
    let log_det_vx: f64 = used.iter().map(|&j| vx_eff[j].ln()).sum();
    stats.log_lik += up.log_lik - 0.5 * log_det_vx;
    mu_out.copy_from_slice(&up.mu);
}

/// The update of a frame whose prior `(m̄, L̃)` is too broad for the unscented transform (e.g. after a
/// stretch without detections under the position-velocity model, whose sigma points then
/// leave the cameras' view): iterated posterior linearisation started from the `hint`
/// `(μ_h, V_h)` of the position (e.g. the random walk's smoothed posterior of this frame)
/// instead of from the prior. The prior itself is unchanged, so the filter and the smoother
/// stay those of the model. Re-derives which measured entries are predictable (statuses in
/// `mask`, counts in `stats`); `None` (nothing changed) if the linearisation fails.
#[allow(clippy::too_many_arguments)]
fn hinted_update<E: Emission + ?Sized>(
    em: &E,
    (mbar, l_full): (&[f64], &DMatrix<f64>),
    x_t: &[f64],
    vx_eff: &[f64],
    (hm, hv): (&[f64], &[f64]),
    relinearize: usize,
    frame: usize,
    mask: &mut [u8],
    stats: &mut FilterStats,
    ws: &mut Workspace,
) -> Result<Option<Update>> {
    let n = em.n_state();
    let n_x = x_t.len();
    let before: Vec<usize> = ws.used.clone();
    ws.used.clear();
    ws.used
        .extend((0..n_x).filter(|&j| mask[j] == status::USED || mask[j] == status::INVISIBLE));
    let measured = ws.used.len();
    let hmu = DVector::from_column_slice(hm);
    let hvm = DMatrix::from_column_slice(n, n, hv);
    let mut xhat = Vec::new();
    let Some(nu) = linearize_about(
        em, mbar, l_full, x_t, vx_eff, &hmu, &hvm, &mut xhat, true, ws,
    )?
    else {
        ws.used = before;
        return Ok(None);
    };
    ws.relin_steps += 1;
    let first = fresh_update(mbar, l_full, n, &nu, frame, ws)?;
    let up = relinearized(
        em,
        mbar,
        l_full,
        x_t,
        vx_eff,
        xhat,
        &first,
        relinearize,
        frame,
        ws,
    )?
    .unwrap_or(first);
    let was_invisible = mask.iter().filter(|&&m| m == status::INVISIBLE).count();
    for m in mask.iter_mut() {
        if *m == status::USED {
            *m = status::INVISIBLE;
        }
    }
    for &j in &ws.used {
        mask[j] = status::USED;
    }
    stats.invisible = stats.invisible + (measured - ws.used.len()) - was_invisible;
    stats.used += ws.used.len();
    stats.relinearized_frames += 1;
    stats.relinearizations += std::mem::take(&mut ws.relin_steps);
    Ok(Some(up))
}

/// The result of one linear(ised) Kalman update.
#[derive(Debug, Clone, Default)]
struct Update {
    /// Posterior mean (`ns`) and covariance (`ns × ns`, column-major).
    mu: Vec<f64>,
    v: Vec<f64>,
    /// `s = M⁻¹ Ỹ ν̃`, whose last `n` entries are the update in the coordinates of `L`.
    s: Vec<f64>,
    log_lik: f64,
}

/// The Kalman update of the prior `(m̄, P = L̃ L̃ᵀ)` of the state (position `z` first, `n`
/// entries, then e.g. velocity) under the whitened linear-Gaussian model
/// `x̃ = x̂ + D L⁻¹ (z − z̄) + E ξ + ε` (`ξ, ε ~ N(0, I)`, `L` the leading `n × n` block of
/// `L̃`), given `Ỹ = [Eᵀ; Dᵀ]` (`2n × n_p`, row-major) and `ν̃ = x̃ − x̂`: with
/// `M = I + ỸỸᵀ`, `s = M⁻¹ Ỹ ν̃` and `W = L̃[:, :n]`, `μ = m̄ + W s[n..]` and
/// `Ṽ = P − W (I − (M⁻¹)_DD) Wᵀ = Uᵀ U + L̃[:, n:] L̃[:, n:]ᵀ` (push-through form of Alg. 6
/// lines 19-26), and `ln N(x; x̂, S)` from `|S| = |V_x| |M|` and `ν̃ᵀν̃ − (Ỹν̃)ᵀ s` (without
/// the `|V_x|` term, which the caller adds).
///
/// Why E first: with `L_M = [[L₁₁, 0], [L₂₁, L₂₂]]` the factor of `M`, `L₂₂ L₂₂ᵀ` is the Schur
/// complement of the E block, `((M⁻¹)_DD)⁻¹`, so `U = L₂₂⁻¹ Wᵀ` (`n × ns`): a triangular
/// solve with the `n × n` block instead of the whole `2n × 2n` factor (a quarter of the
/// work), and `UᵀU` sums over `n` rows instead of `2n` (half).
///
/// `l_full` is `L̃` (column-major `ns × ns`); `gram`, `u`, `b` are scratch (`gram` ends
/// as the factor of `M`); the result goes to `out`, whose buffers are reused, except the
/// covariance when `v_dst` is given: it is written there (e.g. the filter's output row, which
/// saves a copy of `ns²` values) and `out.v` is left as it was.
#[allow(clippy::too_many_arguments)]
fn linear_update(
    mbar: &[f64],
    l_full: &[f64],
    n: usize,
    ytil: &[f64],
    nu: &[f64],
    gram: &mut Vec<f64>,
    u: &mut Vec<f64>,
    b: &mut Vec<f64>,
    frame: usize,
    parallel: bool,
    v_dst: Option<&mut [f64]>,
    out: &mut Update,
) -> Result<()> {
    let ns = mbar.len();
    let m2 = 2 * n;
    let np = nu.len();
    // M = I + Ỹ Ỹᵀ (the dominant product), factorised in place: its lower triangle only,
    // the one the factorisation reads (the same factor bit for bit as from the mirrored,
    // symmetrised M: both triangles are the same sums)
    gram.clear();
    gram.resize(m2 * m2, 0.0);
    for i in 0..m2 {
        gram[i * m2 + i] = 1.0;
    }
    add_gram_rows_lower(ytil, m2, np, gram, parallel);
    if !cholesky_in_place(gram, m2) {
        // (never seen: M ⪰ I) the failed factorisation overwrote part of `gram`: rebuild M,
        // then the allocating path with its jitter and error message
        gram.fill(0.0);
        for i in 0..m2 {
            gram[i * m2 + i] = 1.0;
        }
        add_gram_rows(ytil, m2, np, gram, parallel);
        symmetrize_slice(gram, m2);
        let lm = cholesky(gram, m2, &|| format!("I + ỸᵀỸ of frame {frame}"))?;
        gram.copy_from_slice(lm.as_slice());
    }
    let lm: &[f64] = gram;
    out.s.clear();
    out.s
        .extend((0..m2).map(|i| dot(&ytil[i * np..(i + 1) * np], nu)));
    b.clear();
    b.extend_from_slice(&out.s);
    lower_solve_in_place(lm, m2, &mut out.s);
    lower_tr_solve_in_place(lm, m2, &mut out.s);
    let log_det_m = 2.0 * (0..m2).map(|i| lm[i * m2 + i].ln()).sum::<f64>();
    let maha = dot(nu, nu) - dot(b, &out.s);
    out.log_lik = -0.5 * (np as f64 * (2.0 * std::f64::consts::PI).ln() + log_det_m + maha);
    // μ = m̄ + W s[n..], W = L̃[:, :n]
    out.mu.clear();
    out.mu.extend_from_slice(mbar);
    for c in 0..n {
        let sc = out.s[n + c];
        for (m, l) in out.mu.iter_mut().zip(&l_full[c * ns..(c + 1) * ns]) {
            *m += l * sc;
        }
    }
    // L₂₂, the trailing n × n block of L_M, made contiguous (into `b`, free now)
    b.clear();
    b.resize(n * n, 0.0);
    for c in 0..n {
        b[c * n..(c + 1) * n].copy_from_slice(&lm[(n + c) * m2 + n..(n + c + 1) * m2]);
    }
    // U = L₂₂⁻¹ Wᵀ (n × ns): column r holds row r of W.
    u.resize(n * ns, 0.0); // (every entry written below)
    for r in 0..ns {
        for c in 0..n {
            u[r * n + c] = l_full[c * ns + r];
        }
    }
    // (columns independent: split between two threads when large)
    if parallel && n * n * ns > 400_000 {
        let (u0, u1) = u.split_at_mut(ns / 2 * n);
        let l22: &[f64] = b;
        Team::global().run_pair(rayon::current_num_threads(), [u0, u1], &|_, h| {
            lower_solve_in_place(l22, n, h);
        });
    } else {
        lower_solve_in_place(b, n, u);
    }
    let v = match v_dst {
        Some(v) => v,
        None => {
            out.v.clear();
            out.v.resize(ns * ns, 0.0);
            &mut out.v[..]
        }
    };
    // UᵀU into the lower triangle (columns of U as rows), + L̃[:, n:] L̃[:, n:]ᵀ there too,
    // then mirrored once: exactly symmetric (as `at_a_into` followed by `add_a_at` and a
    // symmetrisation, bit for bit, with two passes over the ns × ns fewer)
    v.fill(0.0);
    add_gram_rows_lower(&u[..n * ns], ns, n, v, parallel);
    if ns > n {
        add_a_at(&l_full[n * ns..], ns, ns - n, v);
    } else {
        mirror_lower(v, ns);
    }
    Ok(())
}

/// [`linear_update`] of the prior `(m̄, L̃)` with the linearisation in `ws.ytil` and the
/// innovation `nu` into a new [`Update`] (the rare, relinearised paths).
fn fresh_update(
    mbar: &[f64],
    l_full: &DMatrix<f64>,
    n: usize,
    nu: &DVector<f64>,
    frame: usize,
    ws: &mut Workspace,
) -> Result<Update> {
    let mut up = Update::default();
    let (ytil, gram, u, b) = (&ws.ytil, &mut ws.gram, &mut ws.u, &mut ws.b);
    let l = l_full.as_slice();
    let par = !ws.serial;
    linear_update(
        mbar,
        l,
        n,
        ytil,
        nu.as_slice(),
        gram,
        u,
        b,
        frame,
        par,
        None,
        &mut up,
    )?;
    Ok(up)
}

/// The linear transition `F` of the state (see [`predict`]): `n` position entries (the
/// emission's state), the order given by the state's length (`ns / n`), and position entries
/// whose rows of `F` are 0, with their velocity twins: memoryless entries `z_t = ε_t ~ N(0,
/// V_z)`, e.g. the log-stretch of elastic segments around their mean (issue 28, beyond the
/// paper; `V_z`'s block of them is then their variance, learned by the same M-step).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Transition<'a> {
    /// Number of position entries.
    pub n: usize,
    /// Position entries with a zero row of `F`.
    pub memoryless: &'a [usize],
}

#[cfg(test)]
impl Transition<'static> {
    /// The transition without memoryless entries.
    pub(crate) fn plain(n: usize) -> Self {
        Self { n, memoryless: &[] }
    }
}

impl Transition<'_> {
    /// The transition of an emission's state.
    pub(crate) fn of<E: Emission + ?Sized>(em: &E) -> Transition<'_> {
        Transition {
            n: em.n_state(),
            memoryless: em.memoryless(),
        }
    }
    /// The rows of `F` that are 0 in a state of length `ns` (with velocity twins for order 2).
    fn zero_rows(&self, ns: usize) -> impl Iterator<Item = usize> + '_ {
        let n = self.n;
        self.memoryless
            .iter()
            .flat_map(move |&i| std::iter::once(i).chain((ns > n).then_some(n + i)))
    }
}

/// The prediction of Alg. 6 lines 2-4 for the linear transition `F` of the state's order
/// (`mu_prev.len() / n`): order 1 is the paper's random walk (`F = I`); order 2 is the
/// position–velocity state `(z, ż)` with `z_t = z_{t-1} + ż_{t-1} + ε`, `ż_t = ż_{t-1} + ε`
/// (`F = [[I, I], [0, I]]`, beyond the paper), with the memoryless rows of `tr` zero.
/// Returns `(F μ, F Ṽ Fᵀ + V_z)`.
pub(crate) fn predict(
    mu_prev: &[f64],
    v_prev: &[f64],
    vz: &[f64],
    tr: Transition<'_>,
) -> (DVector<f64>, DMatrix<f64>) {
    let ns = mu_prev.len();
    let (mut m, mut p) = (vec![0.0; ns], vec![0.0; ns * ns]);
    predict_into(mu_prev, v_prev, vz, tr, &mut m, &mut p);
    (DVector::from_vec(m), DMatrix::from_vec(ns, ns, p))
}

/// [`predict`] into caller buffers (`ns`, `ns × ns`), without allocating.
pub(crate) fn predict_into(
    mu_prev: &[f64],
    v_prev: &[f64],
    vz: &[f64],
    tr: Transition<'_>,
    m: &mut [f64],
    p: &mut [f64],
) {
    let (ns, n) = (mu_prev.len(), tr.n);
    m.copy_from_slice(mu_prev);
    p.copy_from_slice(v_prev);
    if ns > n {
        for r in 0..n {
            m[r] += mu_prev[n + r];
        }
        // Ṽ Fᵀ: the position columns gain the velocity columns (still unchanged) ...
        for c in 0..n {
            let (head, tail) = p.split_at_mut((n + c) * ns);
            for (x, y) in head[c * ns..(c + 1) * ns].iter_mut().zip(&tail[..ns]) {
                *x += y;
            }
        }
        // ... then F (Ṽ Fᵀ): the position rows gain the velocity rows.
        for col in p.chunks_exact_mut(ns) {
            let (head, tail) = col.split_at_mut(n);
            for (x, y) in head.iter_mut().zip(&tail[..n]) {
                *x += y;
            }
        }
    }
    // a zero row i of F: (F μ)_i = 0 and row and column i of F Ṽ Fᵀ are 0
    for i in tr.zero_rows(ns) {
        m[i] = 0.0;
        p[i * ns..(i + 1) * ns].fill(0.0);
        for c in 0..ns {
            p[c * ns + i] = 0.0;
        }
    }
    for (x, y) in p.iter_mut().zip(vz) {
        *x += y;
    }
    symmetrize_slice(p, ns);
}

/// `F A` for the transition of [`predict`] (`A` with `ns` rows): the position rows gain the
/// velocity rows; memoryless rows are 0.
pub(crate) fn f_left(a: &DMatrix<f64>, tr: Transition<'_>) -> DMatrix<f64> {
    let n = tr.n;
    let mut out = a.clone();
    if a.nrows() > n {
        for c in 0..a.ncols() {
            for r in 0..n {
                out[(r, c)] += a[(n + r, c)];
            }
        }
    }
    for i in tr.zero_rows(a.nrows()) {
        out.row_mut(i).fill(0.0);
    }
    out
}

/// `A Fᵀ` for the transition of [`predict`] (`A` with `ns` columns); memoryless columns
/// are 0.
pub(crate) fn f_right(a: &DMatrix<f64>, tr: Transition<'_>) -> DMatrix<f64> {
    let n = tr.n;
    let mut out = a.clone();
    if a.ncols() > n {
        for c in 0..n {
            for r in 0..a.nrows() {
                out[(r, c)] += a[(r, n + c)];
            }
        }
    }
    for i in tr.zero_rows(a.ncols()) {
        out.column_mut(i).fill(0.0);
    }
    out
}

/// Mean squared whitened linearisation error above which the update is relinearised
/// (1 = one measurement SD per entry).
const RELIN_THRESHOLD: f64 = 0.1;

/// Iterated posterior linearisation (García-Fernández et al. 2015, beyond the paper): when the
/// posterior mean lies where the statistical linearisation of `g` about the prior no longer
/// holds (after a stretch without detections the prior is broad and one unscented update
/// lands off), `g` is linearised again by the unscented transform about the current posterior
/// `(μ, Ṽ)` — slope `A`, residual covariance `Ω` — and the prior is updated afresh with
/// `x = A z + b + N(0, V_x + Ω)`. Repeats at most `max_iter` times while the whitened
/// linearisation error at `μ` exceeds [`RELIN_THRESHOLD`]. Returns `None` when the first
/// update already holds (the usual case: one extra evaluation of `g` per frame).
#[allow(clippy::too_many_arguments)]
fn relinearized<E: Emission + ?Sized>(
    em: &E,
    mbar: &[f64],
    l_full: &DMatrix<f64>,
    x_t: &[f64],
    vx_eff: &[f64],
    mut xhat: Vec<f64>,
    first: &Update,
    max_iter: usize,
    frame: usize,
    ws: &mut Workspace,
) -> Result<Option<Update>> {
    let n = em.n_state();
    let mut gx = vec![0.0; x_t.len()];
    let mut best: Option<Update> = None;
    for _ in 0..max_iter {
        let cur = best.as_ref().unwrap_or(first);
        let lin = (ws.ytil.as_slice(), ws.used.as_slice());
        let mean_err =
            linearisation_error(em, cur, &xhat, vx_eff, &mut gx, lin, &mut ws.lin, ws.serial)?;
        if mean_err.is_nan() || mean_err <= RELIN_THRESHOLD {
            break; // NaN: a marker is no longer predictable; keep what we have
        }
        let ns = cur.mu.len();
        let vzz = DMatrix::from_fn(n, n, |r, c| cur.v[c * ns + r]);
        let mu_j = DVector::from_column_slice(&cur.mu[..n]);
        let Some(nu) = linearize_about(
            em, mbar, l_full, x_t, vx_eff, &mu_j, &vzz, &mut xhat, false, ws,
        )?
        else {
            break;
        };
        ws.relin_steps += 1;
        best = Some(fresh_update(mbar, l_full, n, &nu, frame, ws)?);
    }
    Ok(best)
}

/// Mean squared whitened error of the linearisation in `ws.ytil` / `xhat` at the posterior
/// mean of `up`: `g(μ)` against `x̂ + D s[n..]`, over the entries of `ws.used`.
#[allow(clippy::too_many_arguments)]
fn linearisation_error<E: Emission + ?Sized>(
    em: &E,
    up: &Update,
    xhat: &[f64],
    vx_eff: &[f64],
    gx: &mut [f64],
    (ytil, used): (&[f64], &[usize]),
    lin: &mut Vec<f64>,
    serial: bool,
) -> Result<f64> {
    let n = em.n_state();
    let np = used.len();
    eval(em, serial, &up.mu[..n], gx)?;
    // D s[n..], row by row of Dᵀ (contiguous)
    lin.clear();
    lin.resize(np, 0.0);
    for i in 0..n {
        let si = up.s[n + i];
        for (l, y) in lin.iter_mut().zip(&ytil[(n + i) * np..(n + i + 1) * np]) {
            *l += y * si;
        }
    }
    let mut err = 0.0;
    for ((&j, &x), l) in used.iter().zip(xhat).zip(lin.iter()) {
        let e = (gx[j] - x) / vx_eff[j].sqrt() - l;
        err += e * e;
    }
    Ok(err / np.max(1) as f64)
}

/// Statistical linearisation of `g` by the unscented transform about `N(μ_j, V_j)` (position
/// part), expressed for the update of the prior `(m̄, L̃)`: fills `ws.ytil` with
/// `Ỹ = [Eᵀ; Dᵀ]` (whitened; `A = F L_j⁻¹` the slope, `D = A L`, `E` the residual's factor)
/// and `xhat` with `x̂ = x̄_j + A (z̄ − μ_j)` for the entries of `ws.used`, and returns
/// `ν̃ = (x − x̂) / √V_x`. With `drop_invisible`, entries that `g` cannot predict at some
/// sigma point are first removed from `ws.used` (and returned to the caller by the changed
/// `ws.used`); otherwise such an entry makes the linearisation fail (`None`).
#[allow(clippy::too_many_arguments)]
fn linearize_about<E: Emission + ?Sized>(
    em: &E,
    mbar: &[f64],
    l_full: &DMatrix<f64>,
    x_t: &[f64],
    vx_eff: &[f64],
    mu_j: &DVector<f64>,
    v_j: &DMatrix<f64>,
    xhat: &mut Vec<f64>,
    drop_invisible: bool,
    ws: &mut Workspace,
) -> Result<Option<DVector<f64>>> {
    let n = em.n_state();
    let n_x = x_t.len();
    let m2 = 2 * n;
    let Ok(lj) = cholesky(v_j.as_slice(), n, &String::new) else {
        return Ok(None);
    };
    sigma_points(mu_j.as_slice(), &lj, &mut ws.sigma);
    em.eval_sigma(mu_j.as_slice(), &ws.sigma, ws.serial, &mut ws.x)?;
    let inv = 1.0 / m2 as f64;
    ws.xbar.fill(0.0);
    for row in ws.x.chunks_exact(n_x) {
        for &j in &ws.used {
            ws.xbar[j] += row[j];
        }
    }
    for &j in &ws.used {
        ws.xbar[j] *= inv;
    }
    if drop_invisible {
        let xbar = &ws.xbar;
        ws.used.retain(|&j| xbar[j].is_finite());
    } else if ws.used.iter().any(|&j| !ws.xbar[j].is_finite()) {
        return Ok(None);
    }
    let np = ws.used.len();
    if np == 0 {
        return Ok(None);
    }
    if (0..n).any(|i| lj[(i, i)] == 0.0) {
        return Ok(None);
    }
    // G = L_j⁻¹ L and c = L_j⁻¹ (z̄ − μ_j) by the column kernel (L: a contiguous copy)
    let mut g = l_full.view((0, 0), (n, n)).into_owned();
    lower_solve_in_place(lj.as_slice(), n, g.as_mut_slice());
    let mut c = DVector::from_fn(n, |r, _| mbar[r] - mu_j[r]);
    lower_solve_in_place(lj.as_slice(), n, c.as_mut_slice());
    ws.ytil.clear();
    ws.ytil.resize(m2 * np, 0.0);
    // F (rows: sigma-point pairs, whitened; stored as Fᵀ, np × n, so that each pair's row
    // is written contiguously) and E as in `step`, about (μ_j, V_j).
    let sq = (0.5 * inv).sqrt();
    let mut ft = DMatrix::zeros(np, n);
    for i in 0..n {
        let xp = &ws.x[i * n_x..(i + 1) * n_x];
        let xm = &ws.x[(n + i) * n_x..(n + i + 1) * n_x];
        let dst_e = &mut ws.ytil[i * np..(i + 1) * np];
        let dst_f = &mut ft.as_mut_slice()[i * np..(i + 1) * np];
        for (q, &j) in ws.used.iter().enumerate() {
            let scale = 1.0 / vx_eff[j].sqrt();
            dst_f[q] = (xp[j] - xm[j]) * scale * sq;
            dst_e[q] = (xp[j] + xm[j] - 2.0 * ws.xbar[j]) * scale * sq;
        }
    }
    // A = F L_j⁻¹ (whitened); D = A L, so Dᵀ = Gᵀ F with G = L_j⁻¹ L: row i of Dᵀ is
    // column i of Fᵀ G.
    let dt = &ft * &g;
    ws.ytil[n * np..].copy_from_slice(dt.as_slice());
    let f = ft;
    // x̂ = x̄_j + A (z̄ − μ_j); ν̃ = (x − x̂) / √V_x.
    let shift = f * c;
    xhat.clear();
    let mut nu = DVector::zeros(np);
    for (q, &j) in ws.used.iter().enumerate() {
        let sd = vx_eff[j].sqrt();
        xhat.push(ws.xbar[j] + shift[q] * sd);
        nu[q] = (x_t[j] - xhat[q]) / sd;
    }
    Ok(Some(nu))
}

/// The innovation gate: per block of entries (one image point), the squared Mahalanobis
/// distance `νᵀ S_b⁻¹ ν` with `S_b` the block of `S = V_x + Y Yᵀ`.
fn apply_gate(
    block: usize,
    gate: f64,
    ws: &mut Workspace,
    x_t: &[f64],
    mask: &mut [u8],
    stats: &mut FilterStats,
) {
    let n_x = x_t.len();
    let m2 = ws.dev.len() / n_x;
    let inv = 1.0 / m2 as f64;
    let k = block;
    let n_blocks = n_x / k;
    // The blocks of S's sample part, as bands of offsets 0..k (row by row, in row order).
    ws.bands.resize(k * n_x, 0.0);
    band_products(&ws.dev, n_x, k, &mut ws.bands);
    let vx = &ws.vx_eff;
    let rejected = &mut ws.rejected;
    rejected.clear();
    let mut blocks = 0;
    let (sb, w) = (&mut ws.sb, &mut ws.sbw);
    sb.clear();
    sb.resize(k * k, 0.0);
    w.clear();
    w.resize(k, 0.0);
    for b in 0..n_blocks {
        let b0 = b * k;
        if (b0..b0 + k).any(|j| mask[j] != status::USED) {
            continue;
        }
        blocks += 1;
        for a in 0..k {
            for c in 0..=a {
                let acc = ws.bands[(a - c) * n_x + b0 + a];
                sb[c * k + a] = inv * acc;
                sb[a * k + c] = inv * acc;
            }
            sb[a * k + a] += vx[b0 + a];
        }
        for (a, wa) in w.iter_mut().enumerate() {
            *wa = x_t[b0 + a] - ws.xbar[b0 + a];
        }
        // νᵀ S_b⁻¹ ν = |L⁻¹ ν|² (a block whose S_b is not positive definite is not gated)
        let d2 = if cholesky_in_place(sb, k) {
            lower_solve_in_place(sb, k, w);
            w.iter().map(|v| v * v).sum()
        } else {
            0.0
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
    for &b0 in rejected.iter() {
        for m in mask.iter_mut().skip(b0).take(k) {
            *m = status::GATED;
            stats.gated += 1;
        }
    }
}
