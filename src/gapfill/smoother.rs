//! Random-walk Kalman filter and RTS smoother in the subspace (B&L Algorithm 1, Appendix A),
//! in information form and with memoised covariances.
//!
//! Model (B&L eqs. 1, 2, 4, 5 with `F = I`): `x̃_t = x̃_{t−1} + w_t`, `w_t ~ N(0, Q)`;
//! `z_t = H_t (V̂ x̃_t + m̄) + v_t`, `v_t ~ N(0, r I)`.
//!
//! * **Information form.** With `R = r I` the update `K_t = P̂_t Ĥ_tᵀ (Ĥ_t P̂_t Ĥ_tᵀ + R)⁻¹`
//!   (A.5) equals `P_t Ĥ_tᵀ / r` with `P_t = (P̂_t⁻¹ + G_t / r)⁻¹` and `G_t = Ĥ_tᵀ Ĥ_t =
//!   Σ_{present i} v_i v_iᵀ`, so each update solves a `d̂ × d̂` system instead of inverting the
//!   `n_present × n_present` innovation covariance. `G_t` depends only on the missing pattern.
//! * **Memoisation.** The covariance recursion (A.2, A.4, A.6, A.8) does not depend on the
//!   measured values, only on the sequence of missing patterns. A filter covariance is a *state*;
//!   the transition (state, next pattern) → state is computed once and cached, and a new
//!   covariance within `memo_tol` (relative, max norm) of an earlier one of the same pattern is
//!   merged with it (the recursion is a contraction, so merging does not accumulate). In a stretch
//!   of frames with the same pattern the covariance converges and the per-frame cost drops to the
//!   `O(n_present · d̂ + d̂²)` of the mean update. Frames with every marker missing are pure
//!   prediction steps (the published code fails on them).
//! * **RTS gain** `C_t = P_t P̂_{t+1}⁻¹` (A.6; Algorithm 1 prints `P_t P̂_t⁻¹`, which is not the
//!   RTS smoother).

use super::linalg::{close, spd_inverse, symmetrize};
use crate::error::{AcmError, Result};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;
use std::collections::HashMap;

const PRIOR: u32 = u32::MAX;

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

/// Missing-value patterns of a sequence: one id per frame, the missing coordinates and
/// `G_p = Σ_{present i} v_i v_iᵀ` per pattern.
#[derive(Debug, Clone)]
pub struct Patterns {
    /// Pattern id of every frame.
    pub of_frame: Vec<u32>,
    /// Missing coordinates per pattern.
    pub missing: Vec<Vec<u32>>,
    /// Present-coordinate Gram matrices per pattern.
    pub gram: Vec<DMatrix<f64>>,
}

impl Patterns {
    /// Finds the patterns of the row-major `T × D` sequence `x` (NaN = missing).
    pub fn new(x: &[f64], d: usize, model: &Model) -> Self {
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
        let k = model.k();
        let full = gram_of(model, (0..d).collect::<Vec<_>>().iter().copied(), k);
        let gram = missing
            .par_iter()
            .map(|miss| {
                if miss.len() * 2 <= d {
                    let sub = gram_of(model, miss.iter().map(|&j| j as usize), k);
                    &full - sub
                } else {
                    let mut present = vec![true; d];
                    miss.iter().for_each(|&j| present[j as usize] = false);
                    gram_of(model, (0..d).filter(|&j| present[j]), k)
                }
            })
            .collect();
        Self {
            of_frame,
            missing,
            gram,
        }
    }

    fn all_missing(&self, p: u32, d: usize) -> bool {
        self.missing[p as usize].len() == d
    }
}

fn gram_of(model: &Model, idx: impl Iterator<Item = usize>, k: usize) -> DMatrix<f64> {
    let mut g = DMatrix::zeros(k, k);
    for i in idx {
        let v = model.row(i);
        for a in 0..k {
            let va = v[a];
            if va == 0.0 {
                continue;
            }
            for b in 0..k {
                g[(a, b)] += va * v[b];
            }
        }
    }
    g
}

/// A memoised filter covariance `P_t` with what the next step and the backward pass need.
#[derive(Debug, Clone)]
struct FState {
    p: DMatrix<f64>,
    /// `P̂_{t+1} = P_t + Q` (A.2).
    p_pred: DMatrix<f64>,
    /// `P̂_{t+1}⁻¹`.
    lam_pred: DMatrix<f64>,
    /// RTS gain `C_t = P_t P̂_{t+1}⁻¹` (A.6).
    c: DMatrix<f64>,
}

/// Output of [`smooth`].
#[derive(Debug, Clone)]
pub struct Smoothed {
    /// Smoothed subspace means `m̃_t`, row-major T × d̂.
    pub m: Vec<f64>,
    /// Smoothed covariance id per frame (if covariances were requested).
    pub cov_of_frame: Vec<u32>,
    /// Distinct smoothed covariances `P̃`.
    pub covs: Vec<DMatrix<f64>>,
    /// Filter state id per frame.
    state_of_frame: Vec<u32>,
    /// Filter states.
    states: Vec<FState>,
}

impl Smoothed {
    /// Number of distinct filter covariances computed.
    pub fn distinct_filter_covariances(&self) -> usize {
        self.states.len()
    }
}

/// Runs the forward filter and the RTS smoother (B&L Algorithm 1 with gain A.6) on the
/// row-major `T × D` sequence `x`; with `want_cov` also the smoothed covariances (A.8).
pub fn smooth(
    x: &[f64],
    model: &Model,
    pats: &Patterns,
    want_cov: bool,
    memo_tol: f64,
) -> Result<Smoothed> {
    let d = model.d();
    let k = model.k();
    let t_len = x.len() / d;
    let inv_r = 1.0 / model.r;
    let prior_lam = spd_inverse(&model.p0, "the prior covariance P0")?;

    let mut states: Vec<FState> = Vec::new();
    let mut by_pat: Vec<Vec<u32>> = vec![Vec::new(); pats.missing.len()];
    let mut trans: HashMap<(u32, u32), u32> = HashMap::new();
    let mut state_of_frame = Vec::with_capacity(t_len);
    let mut mf = vec![0.0; t_len * k]; // filtered means
    let mut prev = PRIOR;
    let mut g = DVector::zeros(k);

    for t in 0..t_len {
        let pat = pats.of_frame[t];
        let sid = match trans.get(&(prev, pat)) {
            Some(&s) => s,
            None => {
                let s = new_transition(
                    model,
                    pats,
                    &mut states,
                    &mut by_pat,
                    prev,
                    pat,
                    &prior_lam,
                    inv_r,
                    memo_tol,
                )?;
                trans.insert((prev, pat), s);
                s
            }
        };
        state_of_frame.push(sid);
        // Mean: m̂_t = m_{t−1} (random walk), m_t = m̂_t + P_t Ĥ_tᵀ (z_t − Ĥ_t m̂_t − H_t m̄) / r.
        let (done, rest) = mf.split_at_mut(t * k);
        let m_hat: &[f64] = if t == 0 {
            model.m0.as_slice()
        } else {
            &done[(t - 1) * k..]
        };
        let m_t = &mut rest[..k];
        m_t.copy_from_slice(m_hat);
        if !pats.all_missing(pat, d) {
            g.fill(0.0);
            let row = &x[t * d..(t + 1) * d];
            for (i, z) in row.iter().enumerate() {
                if z.is_nan() {
                    continue;
                }
                let v = model.row(i);
                let pred: f64 = v.iter().zip(m_hat).map(|(a, b)| a * b).sum();
                let e = (z - model.mean[i] - pred) * inv_r;
                for (gc, vc) in g.iter_mut().zip(v) {
                    *gc += e * vc;
                }
            }
            let p = &states[sid as usize].p;
            for a in 0..k {
                let mut s = 0.0;
                for b in 0..k {
                    s += p[(a, b)] * g[b];
                }
                m_t[a] += s;
            }
        }
        prev = sid;
    }

    // Backward pass: m̃_t = m_t + C_t (m̃_{t+1} − m̂_{t+1}), m̂_{t+1} = m_t (A.7).
    let mut ms = mf.clone();
    let mut diff = vec![0.0; k];
    for t in (0..t_len.saturating_sub(1)).rev() {
        let c = &states[state_of_frame[t] as usize].c;
        for a in 0..k {
            diff[a] = ms[(t + 1) * k + a] - mf[t * k + a];
        }
        for a in 0..k {
            let mut s = 0.0;
            for b in 0..k {
                s += c[(a, b)] * diff[b];
            }
            ms[t * k + a] = mf[t * k + a] + s;
        }
    }

    let (cov_of_frame, covs) = if want_cov {
        smoothed_covariances(&states, &state_of_frame, memo_tol)
    } else {
        (Vec::new(), Vec::new())
    };
    Ok(Smoothed {
        m: ms,
        cov_of_frame,
        covs,
        state_of_frame,
        states,
    })
}

#[allow(clippy::too_many_arguments)]
fn new_transition(
    model: &Model,
    pats: &Patterns,
    states: &mut Vec<FState>,
    by_pat: &mut [Vec<u32>],
    prev: u32,
    pat: u32,
    prior_lam: &DMatrix<f64>,
    inv_r: f64,
    tol: f64,
) -> Result<u32> {
    let d = model.d();
    let (p_hat, lam_hat) = if prev == PRIOR {
        (&model.p0, prior_lam)
    } else {
        let s = &states[prev as usize];
        (&s.p_pred, &s.lam_pred)
    };
    // A.4 in information form: P_t = (P̂_t⁻¹ + G_t / r)⁻¹.
    let p_new = if pats.all_missing(pat, d) {
        p_hat.clone()
    } else {
        let info = lam_hat + &pats.gram[pat as usize] * inv_r;
        spd_inverse(&info, "the filter information matrix")?
    };
    // Merge with a converged covariance of the same pattern.
    if tol > 0.0 {
        if let Some(&s) = by_pat[pat as usize]
            .iter()
            .rev()
            .take(4)
            .find(|&&s| close(&states[s as usize].p, &p_new, tol))
        {
            return Ok(s);
        }
    }
    let mut p_pred = &p_new + &model.q;
    symmetrize(&mut p_pred);
    let lam_pred = spd_inverse(&p_pred, "the predicted covariance P + Q")?;
    let c = &p_new * &lam_pred;
    if !c.iter().all(|v| v.is_finite()) {
        return Err(AcmError::Numerical("non-finite RTS gain".into()));
    }
    let id = states.len() as u32;
    states.push(FState {
        p: p_new,
        p_pred,
        lam_pred,
        c,
    });
    by_pat[pat as usize].push(id);
    Ok(id)
}

/// Smoothed covariances (A.8) `P̃_t = P_t + C_t (P̃_{t+1} − P̂_{t+1}) C_tᵀ`
/// `= P_t − P_t C_tᵀ + C_t P̃_{t+1} C_tᵀ`, memoised on (filter state, next smoothed state).
fn smoothed_covariances(
    states: &[FState],
    state_of_frame: &[u32],
    tol: f64,
) -> (Vec<u32>, Vec<DMatrix<f64>>) {
    let t_len = state_of_frame.len();
    let mut covs: Vec<DMatrix<f64>> = Vec::new();
    let mut of_frame = vec![0u32; t_len];
    let mut memo: HashMap<(u32, u32), u32> = HashMap::new();
    covs.push(states[state_of_frame[t_len - 1] as usize].p.clone());
    of_frame[t_len - 1] = 0;
    for t in (0..t_len.saturating_sub(1)).rev() {
        let s = state_of_frame[t];
        let next = of_frame[t + 1];
        let id = match memo.get(&(s, next)) {
            Some(&id) => id,
            None => {
                let st = &states[s as usize];
                let mut pt = &st.p - &st.p * st.c.transpose()
                    + &st.c * &covs[next as usize] * st.c.transpose();
                symmetrize(&mut pt);
                let id = if tol > 0.0
                    && state_of_frame[t + 1] == s
                    && close(&covs[next as usize], &pt, tol)
                {
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
    (of_frame, covs)
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
                *o = model.mean[i] + v.iter().zip(m).map(|(a, b)| a * b).sum::<f64>();
            }
        });
    y
}

/// Predictive standard deviation `sqrt(v_iᵀ P̃_t v_i + r)` of every missing value (0 elsewhere),
/// row-major T × D. Needs `smooth(.., want_cov = true)`.
pub fn missing_std(x: &[f64], sm: &Smoothed, model: &Model) -> Vec<f64> {
    let d = model.d();
    let k = model.k();
    let mut out = vec![0.0; x.len()];
    out.par_chunks_mut(d).enumerate().for_each(|(t, row)| {
        let p = &sm.covs[sm.cov_of_frame[t] as usize];
        for (i, o) in row.iter_mut().enumerate() {
            if !x[t * d + i].is_nan() {
                continue;
            }
            let v = model.row(i);
            let mut s = 0.0;
            for a in 0..k {
                let mut pa = 0.0;
                for b in 0..k {
                    pa += p[(a, b)] * v[b];
                }
                s += v[a] * pa;
            }
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
    // Mean terms, accumulated in parallel over frames.
    let (dd, res2, nobs) = (1..t_len)
        .into_par_iter()
        .fold(
            || (DMatrix::<f64>::zeros(k, k), 0.0, 0usize),
            |(mut acc, r2, n), t| {
                let a = &sm.m[(t - 1) * k..t * k];
                let b = &sm.m[t * k..(t + 1) * k];
                for i in 0..k {
                    let di = b[i] - a[i];
                    for j in 0..k {
                        acc[(i, j)] += di * (b[j] - a[j]);
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
    let mut cnt_cov: HashMap<u32, f64> = HashMap::new();
    let mut cnt_lag: HashMap<(u32, u32), f64> = HashMap::new();
    let mut cnt_tr: HashMap<(u32, u32), f64> = HashMap::new();
    for t in 0..t_len {
        let c = sm.cov_of_frame[t];
        let w = if t == 0 || t == t_len - 1 { 1.0 } else { 2.0 };
        *cnt_cov.entry(c).or_default() += w;
        if t > 0 {
            *cnt_lag.entry((c, sm.state_of_frame[t - 1])).or_default() += 1.0;
        }
        *cnt_tr.entry((pats.of_frame[t], c)).or_default() += 1.0;
    }
    let mut s = dd;
    for (c, w) in cnt_cov {
        s += &sm.covs[c as usize] * w;
    }
    for ((c, st), w) in cnt_lag {
        let lag = &sm.covs[c as usize] * sm.states[st as usize].c.transpose();
        s -= (&lag + lag.transpose()) * w;
    }
    let mut q = s / (t_len as f64 - 1.0);
    symmetrize(&mut q);
    let floor = 1e-9 * (q.trace() / k as f64).max(1e-12);
    for c in 0..k {
        q[(c, c)] = q[(c, c)].max(0.0) + floor;
    }
    let r = if learn_r && nobs > 0 {
        let mut tr = 0.0;
        for ((p, c), w) in cnt_tr {
            tr += w * pats.gram[p as usize].dot(&sm.covs[c as usize]);
        }
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
        let e = z - model.mean[i] - v.iter().zip(m).map(|(a, b)| a * b).sum::<f64>();
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
        let pats = Patterns::new(&x, 12, &model);
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
    fn smoothed_covariance_matches_two_pass_definition() {
        // With no memo merging, covariances are symmetric positive semi-definite and smaller
        // than the filter covariance in the trace.
        let (x, model) = toy(40, 9, 3, 5);
        let pats = Patterns::new(&x, 9, &model);
        let sm = smooth(&x, &model, &pats, true, 0.0).unwrap();
        for (t, &c) in sm.cov_of_frame.iter().enumerate() {
            let ps = &sm.covs[c as usize];
            let pf = &sm.states[sm.state_of_frame[t] as usize].p;
            assert!(ps.trace() <= pf.trace() * (1.0 + 1e-9));
            assert!(ps.clone().cholesky().is_some());
        }
    }

    #[test]
    fn em_increases_fit_and_stays_positive() {
        let (x, mut model) = toy(200, 12, 4, 9);
        model.r = 1.0;
        model.q = DMatrix::identity(4, 4);
        let pats = Patterns::new(&x, 12, &model);
        let n = em(&x, &mut model, &pats, 30, true, 1e-9).unwrap();
        assert!(n >= 1);
        // true noise: r = 0.01² / 12 ≈ 8e-6, q = 1/12 ≈ 0.083 per axis
        assert!(model.r < 1e-3, "learned r {}", model.r);
        let qd = model.q.trace() / 4.0;
        assert!(qd > 0.04 && qd < 0.17, "learned q {qd}");
    }
}
