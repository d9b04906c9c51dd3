//! Golden tests: on a linear-Gaussian model the UKF/RTS must equal the closed-form Kalman
//! filter and RTS smoother (written here in the textbook covariance form with `S⁻¹`).

use super::filter::Transition;
use super::*;
use nalgebra::{DMatrix, DVector};

struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }
}

fn linear_problem(seed: u64) -> (LinearEmission, Vec<f64>, Params, usize, usize, usize) {
    let (n, n_x, t) = (3, 6, 40);
    let mut rng = Lcg(seed);
    let h: Vec<f64> = (0..n_x * n).map(|_| rng.next()).collect();
    let b: Vec<f64> = (0..n_x).map(|_| rng.next()).collect();
    let em = LinearEmission { h, b, n_z: n };
    let mut z = vec![0.2, -0.1, 0.3];
    let mut x = vec![0.0; t * n_x];
    let mut out = vec![0.0; n_x];
    for k in 0..t {
        for v in z.iter_mut() {
            *v += 0.1 * rng.next();
        }
        em.eval_batch(&z, &mut out).unwrap();
        for j in 0..n_x {
            x[k * n_x + j] = out[j] + 0.05 * rng.next();
        }
    }
    // Missing entries, a frame with nothing, and a frame with one entry.
    for k in 0..t {
        for j in 0..n_x {
            if (k * 7 + j * 3) % 5 == 0 {
                x[k * n_x + j] = f64::NAN;
            }
        }
    }
    for j in 0..n_x {
        x[10 * n_x + j] = f64::NAN;
        if j > 0 {
            x[11 * n_x + j] = f64::NAN;
        }
    }
    let mut p = Params::initial(vec![0.1, 0.0, 0.2], n_x, 0.01);
    p.vz[1] = 0.002; // correlated transition noise
    p.vz[n] = 0.002;
    p.vx = (0..n_x).map(|j| 0.002 + 0.001 * j as f64).collect();
    (em, x, p, n, n_x, t)
}

/// Textbook Kalman filter + RTS smoother of the random walk; returns smoothed (means, covs)
/// for t = 0..T.
fn kalman_rts(
    em: &LinearEmission,
    x: &[f64],
    p: &Params,
    n: usize,
    n_x: usize,
    t_len: usize,
) -> (Vec<DVector<f64>>, Vec<DMatrix<f64>>) {
    let (ms, vs, _) = kalman_rts_order(em, x, p, n, n_x, t_len, 1);
    (ms, vs)
}

#[test]
fn ukf_rts_equals_kalman_on_linear_model() {
    let (em, x, p, n, n_x, t_len) = linear_problem(7);
    let (ms, vs) = kalman_rts(&em, &x, &p, n, n_x, t_len);
    let mut tr = Tracker::new(em, x).unwrap();
    tr.e_step(&p, None).unwrap();
    for k in 0..=t_len {
        for i in 0..n {
            let got = tr.means()[k * n + i];
            assert!((got - ms[k][i]).abs() < 1e-10, "mean t={k} i={i}");
            for j in 0..n {
                let got = tr.covs()[k * n * n + j * n + i];
                assert!((got - vs[k][(i, j)]).abs() < 1e-10, "cov t={k}");
            }
        }
    }
    let stats = tr.stats();
    let present = tr.mask().iter().filter(|&&m| m == status::USED).count();
    assert_eq!(stats.used, present);
    assert!(tr.mask()[10 * n_x..11 * n_x]
        .iter()
        .all(|&m| m == status::MISSING));
}

#[test]
fn em_increases_fit_and_converges_on_linear_model() {
    let (em, x, p, _, _, _) = linear_problem(11);
    let mut tr = Tracker::new(em, x).unwrap();
    let opts = EmOptions {
        max_iter: 300,
        tol: 5e-3,
        gate: None,
        ll_tol: None,
        dof: None,
        patience: None,
        overrelax: None,
    };
    let out = tr.run_em(p, &opts, |_| true).unwrap();
    assert!(out.converged, "{:?}", out.history.last());
    // Δ falls below tol; V_x approaches the true noise variance (uniform ±0.05 → 8.3e-4).
    let mean_vx: f64 = out.params.vx.iter().sum::<f64>() / out.params.vx.len() as f64;
    assert!(mean_vx > 2e-4 && mean_vx < 3e-3, "V_x {mean_vx}");
    // Uniform ±0.1 steps → variance 3.3e-3 per coordinate.
    let n = 3;
    for i in 0..n {
        let v = out.params.vz[i * n + i];
        assert!(v > 1e-3 && v < 1e-2, "V_z[{i}] {v}");
    }
}

#[test]
fn bad_inputs_are_errors() {
    let (em, x, p, n, n_x, _) = linear_problem(3);
    let mut bad = x.clone();
    bad[5] = f64::INFINITY;
    assert!(matches!(
        Tracker::new(em.clone(), bad),
        Err(AcmError::NonFinite(_))
    ));
    assert!(matches!(
        Tracker::new(em.clone(), x[..n_x + 1].to_vec()),
        Err(AcmError::Shape(_))
    ));
    let mut tr = Tracker::new(em, x).unwrap();
    let mut q = p.clone();
    q.vz[0] = -1.0; // not positive definite
    assert!(matches!(tr.e_step(&q, None), Err(AcmError::Numerical(_))));
    let mut q = p.clone();
    q.vx[2] = 0.0;
    assert!(matches!(tr.e_step(&q, None), Err(AcmError::Invalid(_))));
    let mut q = p;
    q.mu0 = vec![0.0; n + 1];
    assert!(matches!(tr.e_step(&q, None), Err(AcmError::Shape(_))));
}

#[test]
fn gate_rejects_gross_outliers_only() {
    let (em, mut x, p, _, n_x, t_len) = linear_problem(5);
    // Gross outliers in a few entries.
    let bad = [(20usize, 1usize), (25, 4), (30, 2)];
    for &(k, j) in &bad {
        x[k * n_x + j] = 50.0;
    }
    let mut tr = Tracker::new(em, x).unwrap();
    let stats = tr.e_step(&p, Some(25.0)).unwrap();
    for &(k, j) in &bad {
        assert_eq!(tr.mask()[k * n_x + j], status::GATED, "frame {k} entry {j}");
    }
    assert_eq!(stats.gated, bad.len());
    assert!(t_len > 30);
}

#[test]
fn log_likelihood_equals_the_kalman_innovation_likelihood() {
    // Σ_t ln N(x_t; H z̄_t + b, H P_t Hᵀ + V_x) of the textbook filter (present entries only)
    let (em, x, p, n, n_x, t_len) = linear_problem(5);
    let h = DMatrix::from_row_slice(n_x, n, &em.h);
    let vz = DMatrix::from_row_slice(n, n, &p.vz);
    let mut m = DVector::from_column_slice(&p.mu0);
    let mut v = DMatrix::from_row_slice(n, n, &p.v0);
    let mut ll = 0.0;
    for k in 0..t_len {
        let pp = &v + &vz;
        let idx: Vec<usize> = (0..n_x).filter(|&j| !x[k * n_x + j].is_nan()).collect();
        if idx.is_empty() {
            v = pp;
            continue;
        }
        let hs = DMatrix::from_fn(idx.len(), n, |a, c| h[(idx[a], c)]);
        let mut s = &hs * &pp * hs.transpose();
        for (a, &j) in idx.iter().enumerate() {
            s[(a, a)] += p.vx[j];
        }
        let nu = DVector::from_fn(idx.len(), |a, _| {
            x[k * n_x + idx[a]] - em.b[idx[a]] - (hs.row(a) * &m)[0]
        });
        let sinv = s.clone().try_inverse().unwrap();
        ll -= 0.5
            * (idx.len() as f64 * (2.0 * std::f64::consts::PI).ln()
                + s.determinant().ln()
                + (nu.transpose() * &sinv * &nu)[0]);
        let gain = &pp * hs.transpose() * &sinv;
        m = &m + &gain * nu;
        v = &pp - &gain * &hs * &pp;
    }
    let mut tr = Tracker::new(em, x).unwrap();
    let stats = tr.filter(&p, None).unwrap();
    assert!(
        (stats.log_lik - ll).abs() < 1e-8 * (1.0 + ll.abs()),
        "{} vs {ll}",
        stats.log_lik
    );
}

#[test]
fn student_t_weights_keep_outliers_out_of_the_noise_estimate() {
    // 3 % of the entries moved by ±1 (20 x the noise range): the Gaussian M-step inflates V_x,
    // the Student-t weights learn the inlier noise (uniform ±0.05 → 8.3e-4) and mark them.
    let (em, mut x, p, _, n_x, _) = linear_problem(11);
    let mut rng = Lcg(99);
    let mut bad = Vec::new();
    for (i, v) in x.iter_mut().enumerate() {
        if v.is_finite() && rng.next() > 0.94 {
            *v += if rng.next() > 0.0 { 1.0 } else { -1.0 };
            bad.push(i);
        }
    }
    assert!(!bad.is_empty());
    let run = |dof: Option<f64>| {
        let mut tr = Tracker::new(em.clone(), x.clone()).unwrap();
        let opts = EmOptions {
            max_iter: 60,
            tol: 1e-4,
            gate: None,
            ll_tol: None,
            dof,
            patience: None,
            overrelax: None,
        };
        let out = tr.run_em(p.clone(), &opts, |_| true).unwrap();
        let vx = out.params.vx.iter().sum::<f64>() / n_x as f64;
        (vx, tr.weights().to_vec())
    };
    let (vx_gauss, w_gauss) = run(None);
    let (vx_t, w_t) = run(Some(4.0));
    let truth = 0.05f64.powi(2) / 3.0;
    assert!(w_gauss.iter().all(|&w| w == 1.0));
    assert!(vx_gauss > 10.0 * truth, "Gaussian V_x {vx_gauss}");
    assert!(
        vx_t < 3.0 * truth && vx_t > 0.3 * truth,
        "Student-t V_x {vx_t} vs {truth}"
    );
    let w_bad = bad.iter().map(|&i| w_t[i]).sum::<f64>() / bad.len() as f64;
    let good: Vec<f64> = (0..x.len())
        .filter(|i| x[*i].is_finite() && !bad.contains(i))
        .map(|i| w_t[i])
        .collect();
    let w_good = good.iter().sum::<f64>() / good.len() as f64;
    assert!(
        w_bad < 0.1 * w_good,
        "outlier weights {w_bad} vs inliers {w_good}"
    );
}

/// Textbook Kalman filter + RTS smoother (covariance form with `S⁻¹`) for the random walk
/// (`order` 1, `F = I`) or the position–velocity state `s = (z, ż)` (`order` 2,
/// `F = [[I, I], [0, I]]`), `x = H z + b`; returns the smoothed moments and
/// `Σ_t E[(s_t − F s_{t-1})(·)ᵀ]` computed from the pairwise covariances.
#[allow(clippy::type_complexity)]
fn kalman_rts_order(
    em: &LinearEmission,
    x: &[f64],
    p: &Params,
    n: usize,
    n_x: usize,
    t_len: usize,
    order: usize,
) -> (Vec<DVector<f64>>, Vec<DMatrix<f64>>, DMatrix<f64>) {
    let ns = order * n;
    let h0 = DMatrix::from_row_slice(n_x, n, &em.h);
    let h = DMatrix::from_fn(n_x, ns, |r, c| if c < n { h0[(r, c)] } else { 0.0 });
    let f = DMatrix::from_fn(ns, ns, |r, c| {
        if r == c || (r < n && c == r + n) {
            1.0
        } else {
            0.0
        }
    });
    let q = DMatrix::from_row_slice(ns, ns, &p.vz);
    let mut mf = vec![DVector::from_column_slice(&p.mu0)];
    let mut vf = vec![DMatrix::from_row_slice(ns, ns, &p.v0)];
    for k in 0..t_len {
        let mp = &f * &mf[k];
        let pp = &f * &vf[k] * f.transpose() + &q;
        let idx: Vec<usize> = (0..n_x).filter(|&j| !x[k * n_x + j].is_nan()).collect();
        if idx.is_empty() {
            mf.push(mp);
            vf.push(pp);
            continue;
        }
        let hs = DMatrix::from_fn(idx.len(), ns, |a, c| h[(idx[a], c)]);
        let r = DMatrix::from_fn(idx.len(), idx.len(), |a, c| {
            if a == c {
                p.vx[idx[a]]
            } else {
                0.0
            }
        });
        let s = &hs * &pp * hs.transpose() + r;
        let k_gain = &pp * hs.transpose() * s.try_inverse().unwrap();
        let nu = DVector::from_fn(idx.len(), |a, _| {
            x[k * n_x + idx[a]] - em.b[idx[a]] - (hs.row(a) * &mp)[0]
        });
        mf.push(&mp + &k_gain * nu);
        vf.push(&pp - &k_gain * &hs * &pp);
    }
    let mut ms = mf.clone();
    let mut vs = vf.clone();
    let mut acc = DMatrix::zeros(ns, ns);
    for k in (0..t_len).rev() {
        let pp = &f * &vf[k] * f.transpose() + &q;
        let g = &vf[k] * f.transpose() * pp.clone().try_inverse().unwrap();
        ms[k] = &mf[k] + &g * (&ms[k + 1] - &f * &mf[k]);
        vs[k] = &vf[k] + &g * (&vs[k + 1] - &pp) * g.transpose();
        // E[(s_{k+1} − F s_k)(·)ᵀ] from the joint Gaussian of (s_{k+1}, s_k)
        let cross = &vs[k + 1] * g.transpose();
        let d = &ms[k + 1] - &f * &ms[k];
        acc += &d * d.transpose() + &vs[k + 1] - &cross * f.transpose() - &f * cross.transpose()
            + &f * &vs[k] * f.transpose();
    }
    (ms, vs, acc)
}

#[test]
fn velocity_state_equals_the_textbook_kalman_smoother() {
    let (em, x, p1, n, n_x, t_len) = linear_problem(11);
    let ns = 2 * n;
    // position–velocity parameters: μ0 = (z0, ż0), correlated V0 and V_z
    let mut mu0 = p1.mu0.clone();
    mu0.extend([0.01, -0.02, 0.0]);
    let mut rng = Lcg(3);
    let a = DMatrix::from_fn(ns, ns, |_, _| 0.05 * rng.next());
    let v0 = DMatrix::identity(ns, ns) * 0.01 + &a * a.transpose();
    let b = DMatrix::from_fn(ns, ns, |_, _| 0.02 * rng.next());
    let vz = DMatrix::identity(ns, ns) * 0.001 + &b * b.transpose();
    let p = Params {
        mu0,
        v0: v0.as_slice().to_vec(),
        vz: vz.as_slice().to_vec(),
        vx: p1.vx.clone(),
    };
    let (ms, vs, acc) = kalman_rts_order(&em, &x, &p, n, n_x, t_len, 2);
    let mut tr = Tracker::new(em, x).unwrap();
    tr.set_order(2).unwrap();
    assert_eq!(tr.n_state(), ns);
    tr.e_step(&p, None).unwrap();
    let (means, covs) = tr.state_moments();
    for k in 0..=t_len {
        for i in 0..ns {
            assert!(
                (means[k * ns + i] - ms[k][i]).abs() < 1e-9,
                "mean t={k} i={i}"
            );
            for j in 0..ns {
                let got = covs[k * ns * ns + j * ns + i];
                assert!((got - vs[k][(i, j)]).abs() < 1e-9, "cov t={k} ({i}, {j})");
            }
        }
        // the position marginals
        for i in 0..n {
            assert_eq!(tr.means()[k * n + i], means[k * ns + i]);
            assert_eq!(
                tr.covs()[k * n * n + i * n + i],
                covs[k * ns * ns + i * ns + i]
            );
        }
    }
    for (got, want) in tr.acc.iter().zip(acc.iter()) {
        assert!(
            (got - want).abs() < 1e-9 * (1.0 + want.abs()),
            "{got} vs {want}"
        );
    }
    // the M-step keeps the whole state's μ0, V0 and learns V_z = acc / T
    let next = tr.m_step(&p).unwrap();
    assert_eq!(next.mu0.len(), ns);
    assert_eq!(next.v0.len(), ns * ns);
    assert!((next.vz[ns + 1] - acc[(1, 1)] / t_len as f64).abs() < 1e-12);
    assert!(tr.set_order(3).is_err());
}

/// `x = (exp(z₀), exp(z₁), z₀ z₁, z₀ + z₁)`: smooth but far from linear over a broad prior.
#[derive(Debug, Clone)]
struct ExpEmission;
impl Emission for ExpEmission {
    fn n_state(&self) -> usize {
        2
    }
    fn n_meas(&self) -> usize {
        4
    }
    fn eval_batch(&self, states: &[f64], out: &mut [f64]) -> Result<()> {
        for (z, o) in states.chunks_exact(2).zip(out.chunks_exact_mut(4)) {
            o.copy_from_slice(&[z[0].exp(), z[1].exp(), z[0] * z[1], z[0] + z[1]]);
        }
        Ok(())
    }
}

#[test]
fn relinearisation_recovers_from_a_broad_prior() {
    // One precise measurement of z = (1.4, −0.9) under the prior N(0, I) (as after a long
    // stretch without detections): the single unscented update lands far off, the iterated
    // posterior linearisation near the truth.
    let truth = [1.4, -0.9];
    let mut x = vec![0.0; 4];
    ExpEmission.eval_batch(&truth, &mut x).unwrap();
    let p = Params {
        mu0: vec![0.0, 0.0],
        v0: vec![1.0, 0.0, 0.0, 1.0],
        vz: vec![1e-9, 0.0, 0.0, 1e-9],
        vx: vec![1e-4; 4],
    };
    let err = |relin: usize| {
        let mut tr = Tracker::new(ExpEmission, x.clone()).unwrap();
        tr.set_relinearize(relin);
        let stats = tr.filter(&p, None).unwrap();
        let m = &tr.means()[2..4];
        (
            ((m[0] - truth[0]).powi(2) + (m[1] - truth[1]).powi(2)).sqrt(),
            stats.relinearized_frames,
            stats.relinearizations,
        )
    };
    let (plain, n0, k0) = err(0);
    let (iterated, n1, k1) = err(10);
    let (_, n2, k2) = err(1);
    assert_eq!((n0, n1, n2), (0, 1, 1));
    // the iterations are counted: none without relinearisation, at most `relinearize`, and
    // this broad prior needs more than one
    assert_eq!((k0, k2), (0, 1));
    assert!((2..=10).contains(&k1), "{k1} relinearisations");
    assert!(plain > 0.1, "the single update is off: {plain}");
    assert!(
        iterated < 0.01,
        "relinearised error {iterated} (single update {plain})"
    );
}

/// [`ExpEmission`] whose first three entries are unpredictable beyond |z| > 3 (like a marker
/// behind a camera) and the last beyond |z| > `last_beyond`.
#[derive(Debug, Clone)]
struct LimitedEmission {
    last_beyond: f64,
}
impl Emission for LimitedEmission {
    fn n_state(&self) -> usize {
        2
    }
    fn n_meas(&self) -> usize {
        4
    }
    fn eval_batch(&self, states: &[f64], out: &mut [f64]) -> Result<()> {
        ExpEmission.eval_batch(states, out)?;
        for (z, o) in states.chunks_exact(2).zip(out.chunks_exact_mut(4)) {
            let far = z.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
            if far > 3.0 {
                o[..3].fill(f64::NAN);
            }
            if far > self.last_beyond {
                o[3] = f64::NAN;
            }
        }
        Ok(())
    }
}

#[test]
fn a_hint_linearises_where_the_prior_is_too_broad() {
    // Prior N(0, 25 I): every sigma point (±√2 · 5) is unpredictable, so the plain update
    // sees nothing; linearised about a hint near the posterior, the same prior and
    // measurement give the posterior near the truth. The prior (the model) is unchanged.
    let truth = [1.4, -0.9];
    let mut x = vec![0.0; 4];
    ExpEmission.eval_batch(&truth, &mut x).unwrap();
    let p = Params {
        mu0: vec![0.0, 0.0],
        v0: vec![25.0, 0.0, 0.0, 25.0],
        vz: vec![1e-9, 0.0, 0.0, 1e-9],
        vx: vec![1e-4; 4],
    };
    let mut tr = Tracker::new(LimitedEmission { last_beyond: 3.0 }, x.clone()).unwrap();
    let plain = tr.filter(&p, None).unwrap();
    assert_eq!((plain.used, plain.invisible), (0, 4));
    assert!(tr.means()[2..4].iter().all(|v| v.abs() < 1e-6));
    let hint_m = vec![0.0, 0.0, 1.2, -0.7];
    let hint_c = vec![0.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.1];
    assert!(tr
        .set_linearization_hint(Some((hint_m.clone(), vec![0.0; 3])))
        .is_err());
    tr.set_linearization_hint(Some((hint_m, hint_c))).unwrap();
    let hinted = tr.filter(&p, None).unwrap();
    assert_eq!(
        (hinted.used, hinted.invisible, hinted.relinearized_frames),
        (4, 0, 1)
    );
    assert!(tr.mask().iter().all(|&m| m == status::USED));
    let m = &tr.means()[2..4];
    let err = ((m[0] - truth[0]).powi(2) + (m[1] - truth[1]).powi(2)).sqrt();
    assert!(err < 0.01, "hinted posterior {m:?}");
}

#[test]
fn a_hint_that_fails_leaves_the_plain_update() {
    // Prior N(0, 9 I): its sigma points (±√2 · 3) predict only the last entry, so the prior
    // counts as too broad and the hint is tried; the hint (near z = 10) predicts nothing, so
    // its linearisation fails after evaluating its own sigma points. The frame must then get
    // the plain update of the prior, exactly as without a hint.
    let mut x = vec![0.0; 4];
    ExpEmission.eval_batch(&[0.4, -0.3], &mut x).unwrap();
    let p = Params {
        mu0: vec![0.0, 0.0],
        v0: vec![9.0, 0.0, 0.0, 9.0],
        vz: vec![1e-9, 0.0, 0.0, 1e-9],
        vx: vec![1e-2; 4],
    };
    let mut plain = Tracker::new(LimitedEmission { last_beyond: 6.0 }, x.clone()).unwrap();
    let s0 = plain.filter(&p, None).unwrap();
    assert_eq!((s0.used, s0.invisible), (1, 3));
    let mut tr = Tracker::new(LimitedEmission { last_beyond: 6.0 }, x).unwrap();
    let hint_m = vec![0.0, 0.0, 10.0, 10.0];
    let hint_c = vec![1.0, 0.0, 0.0, 1.0, 0.1, 0.0, 0.0, 0.1];
    tr.set_linearization_hint(Some((hint_m, hint_c))).unwrap();
    let s1 = tr.filter(&p, None).unwrap();
    assert_eq!((s1.used, s1.invisible, s1.relinearized_frames), (1, 3, 0));
    assert!(tr.means().iter().all(|v| v.is_finite()));
    assert_eq!(tr.means(), plain.means());
    assert_eq!(tr.covs(), plain.covs());
    assert_eq!(tr.mask(), plain.mask());
}

#[test]
fn online_tracker_equals_the_offline_filter_and_fixed_lag_smoother() {
    let (em, x, p, n, n_x, t_len) = linear_problem(13);
    // the filter, frame by frame, equals the offline forward pass
    let mut off = Tracker::new(em.clone(), x.clone()).unwrap();
    off.filter(&p, None).unwrap();
    let lag = 6;
    let mut on = OnlineTracker::new(em.clone(), p.clone(), 1, None, 10, lag).unwrap();
    assert!(on.lagged().is_err());
    for t in 0..t_len {
        on.update(&x[t * n_x..(t + 1) * n_x]).unwrap();
        let (m, _) = on.filtered();
        for (a, b) in m.iter().zip(&off.means()[(t + 1) * n..(t + 2) * n]) {
            assert!((a - b).abs() < 1e-12, "t={t}");
        }
        // fixed lag: the smoother of the recording up to t, at frame t − k
        if t % 9 == 3 {
            let (lm, lv, k) = on.lagged().unwrap();
            assert_eq!(k, lag.min(t));
            // the cached gains give the same moments again, and the mean alone
            assert_eq!(on.lagged().unwrap(), (lm.clone(), lv.clone(), k));
            assert_eq!(on.lagged_mean().unwrap(), (lm.clone(), k));
            // the whole window: its first frame is lagged(), the last the filtered frame
            let (win, kw) = on.lagged_window().unwrap();
            assert_eq!((kw, win.len()), (k, k + 1));
            assert_eq!((&win[0].0, &win[0].1), (&lm, &lv));
            assert_eq!(&win[k].0[..], on.filtered().0);
            let mut part = Tracker::new(em.clone(), x[..(t + 1) * n_x].to_vec()).unwrap();
            part.e_step(&p, None).unwrap();
            let f = t - k + 1;
            for i in 0..n {
                assert!(
                    (lm[i] - part.means()[f * n + i]).abs() < 1e-10,
                    "lagged t={t}"
                );
                assert!((lv[i * n + i] - part.covs()[f * n * n + i * n + i]).abs() < 1e-10);
                for (j, (wm, _)) in win.iter().enumerate() {
                    let g = f + j;
                    assert!(
                        (wm[i] - part.means()[g * n + i]).abs() < 1e-10,
                        "window t={t}"
                    );
                }
            }
        }
    }
    assert_eq!(on.frames(), t_len);
    assert_eq!(on.stats().used, off.stats().used);
    // prediction: the random walk keeps the mean and adds V_z per step
    let (pm, pv) = on.predict(3);
    let (m, v) = on.filtered();
    assert_eq!(&pm[..], m);
    assert!((pv[0] - v[0] - 3.0 * p.vz[0]).abs() < 1e-12);
    on.reset();
    assert_eq!(on.frames(), 0);
    assert!(on.update(&[1.0]).is_err());
    assert!(OnlineTracker::new(em, p, 3, None, 0, 0).is_err());
}

#[test]
fn smoothing_without_statistics_gives_the_same_moments_and_refuses_an_m_step() {
    let (em, x, p, ..) = linear_problem(5);
    let mut full = Tracker::new(em.clone(), x.clone()).unwrap();
    full.e_step(&p, None).unwrap();
    let mut fast = Tracker::new(em, x).unwrap();
    fast.smooth(&p, None).unwrap();
    assert_eq!(full.means(), fast.means());
    assert_eq!(full.covs(), fast.covs());
    assert!(full.m_step(&p).is_ok());
    let err = fast.m_step(&p).unwrap_err().to_string();
    assert!(err.contains("statistics"), "{err}");
}

/// EM over many windows frees each window's covariances between its M-step and its next
/// E-step: the means and statuses stay, what needs the covariances says so, and the next
/// E-step gives the same moments and M-step as a tracker that never released them.
#[test]
fn released_covariances_come_back_with_the_next_e_step() {
    for order in [1, 2] {
        let (em, x, p, _, n_x, _) = linear_problem(7);
        let p = of_order(p, order, n_x);
        let mut kept = Tracker::new(em.clone(), x.clone()).unwrap();
        let mut freed = Tracker::new(em, x).unwrap();
        for tr in [&mut kept, &mut freed] {
            tr.set_order(order).unwrap();
            tr.e_step(&p, None).unwrap();
        }
        let means = freed.means().to_vec();
        let q = freed.m_step(&p).unwrap();
        freed.release_covariances();
        assert!(freed.covs().is_empty() && freed.state_moments().1.is_empty());
        assert_eq!(freed.means(), &means[..]);
        for err in [
            freed.m_step(&p).unwrap_err(),
            freed.state_row(0).unwrap_err(),
            freed.require_covariances().unwrap_err(),
        ] {
            assert!(err.to_string().contains("released"), "{err}");
        }
        assert!(freed.filtered_packed().is_err());
        let a = kept.e_step(&q, None).unwrap();
        let b = freed.e_step(&q, None).unwrap();
        assert_eq!(a, b);
        assert_eq!(kept.state_moments(), freed.state_moments());
        assert_eq!(kept.covs(), freed.covs());
        assert_eq!(kept.m_step(&q).unwrap(), freed.m_step(&q).unwrap());
        // a filter pass restored from a spill after a release
        kept.filter(&q, None).unwrap();
        let (m, packed) = kept.filtered_packed().unwrap();
        let (m, mask) = (m.to_vec(), kept.mask().to_vec());
        freed.release_covariances();
        freed.load_filtered(&m, &packed, &mask).unwrap();
        assert_eq!(kept.state_moments(), freed.state_moments());
    }
}

/// The parameters of [`linear_problem`] for the motion model of `order` (2: velocity 0 with
/// the position's mean, the same `V_x`).
fn of_order(p: Params, order: usize, n_x: usize) -> Params {
    if order == 1 {
        return p;
    }
    let n = p.mu0.len();
    let mut q = Params::initial(vec![0.0; order * n], n_x, 0.01);
    q.mu0[..n].copy_from_slice(&p.mu0);
    q.vx = p.vx;
    q
}

/// The streaming smoother of long recordings: forward pass over segments keeping only the
/// filtered moments at their ends, then the segments backwards, each refiltered from its
/// checkpoint and smoothed from the next segment's first smoothed moments.
#[test]
fn segments_with_checkpoints_reproduce_the_whole_smoother() {
    for order in [1, 2] {
        let (em, x, p, n, n_x, t_len) = linear_problem(11);
        let ns = order * n;
        let p = of_order(p, order, n_x);
        let mut whole = Tracker::new(em.clone(), x.clone()).unwrap();
        whole.set_order(order).unwrap();
        whole.smooth(&p, None).unwrap();
        let bounds = [0, 7, 10, 23, t_len];
        let tracker = |a: usize, b: usize| {
            let mut tr = Tracker::new(em.clone(), x[a * n_x..b * n_x].to_vec()).unwrap();
            tr.set_order(order).unwrap();
            tr
        };
        // forward: checkpoints at every boundary
        let mut checkpoints = vec![(p.mu0.clone(), p.v0.clone())];
        for w in bounds.windows(2) {
            let mut tr = tracker(w[0], w[1]);
            let (m, v) = checkpoints.last().unwrap().clone();
            tr.filter(
                &Params {
                    mu0: m,
                    v0: v,
                    ..p.clone()
                },
                None,
            )
            .unwrap();
            let (m, v) = tr.state_row(w[1] - w[0]).unwrap();
            checkpoints.push((m.to_vec(), v.to_vec()));
        }
        // backward
        let (wm, wv) = whole.state_moments();
        let mut end: Option<(Vec<f64>, Vec<f64>)> = None;
        for k in (0..bounds.len() - 1).rev() {
            let (a, b) = (bounds[k], bounds[k + 1]);
            let mut tr = tracker(a, b);
            let (m, v) = checkpoints[k].clone();
            let q = Params {
                mu0: m,
                v0: v,
                ..p.clone()
            };
            let e = end.as_ref().map(|(m, v)| (m.as_slice(), v.as_slice()));
            tr.filter(&q, None).unwrap();
            tr.smooth_filtered(&q, e).unwrap();
            let (sm, sv) = tr.state_moments();
            for i in 0..(b - a + 1) * ns {
                assert!(
                    (sm[i] - wm[a * ns + i]).abs() < 1e-12,
                    "order {order} mean {i}"
                );
            }
            for i in 0..(b - a + 1) * ns * ns {
                assert!(
                    (sv[i] - wv[a * ns * ns + i]).abs() < 1e-12,
                    "order {order} cov {i}"
                );
            }
            let (m, v) = tr.state_row(0).unwrap();
            end = Some((m.to_vec(), v.to_vec()));
        }
        let mut tr = tracker(0, 7);
        assert!(tr.state_row(8).is_err());
        assert!(tr.smooth_filtered(&p, None).is_err()); // no filter pass yet
        tr.filter(&p, None).unwrap();
        let bad = vec![0.0; ns + 1];
        assert!(tr.smooth_filtered(&p, Some((&bad, &p.v0))).is_err());
        tr.smooth_filtered(&p, None).unwrap();
        assert!(tr.smooth_filtered(&p, None).is_err()); // already smoothed
    }
}

/// The spill of the streaming smoother: the filtered moments stored compactly and loaded
/// into a fresh tracker give the same smoother as the tracker that filtered, bit for bit;
/// wrong lengths, NaN and unknown statuses are refused.
#[test]
fn filtered_moments_survive_a_spill() {
    for order in [1, 2] {
        let (em, x, p, n, n_x, _) = linear_problem(5);
        let ns = order * n;
        let p = of_order(p, order, n_x);
        let fresh = || {
            let mut tr = Tracker::new(em.clone(), x.clone()).unwrap();
            tr.set_order(order).unwrap();
            tr
        };
        let mut a = fresh();
        assert!(a.filtered_packed().is_err()); // no filter pass yet
        a.filter(&p, Some(9.0)).unwrap();
        let (means, packed) = a.filtered_packed().unwrap();
        let (means, mask) = (means.to_vec(), a.mask().to_vec());
        assert_eq!(packed.len() * 2, (a.n_frames() + 1) * ns * (ns + 1));
        let mut b = fresh();
        b.load_filtered(&means, &packed, &mask).unwrap();
        assert_eq!(b.state_moments(), a.state_moments());
        a.smooth_filtered(&p, None).unwrap();
        b.smooth_filtered(&p, None).unwrap();
        assert_eq!(b.state_moments(), a.state_moments());
        assert_eq!(b.mask(), a.mask());
        let mut c = fresh();
        assert!(c.load_filtered(&means[1..], &packed, &mask).is_err());
        assert!(c.load_filtered(&means, &packed[1..], &mask).is_err());
        assert!(c.load_filtered(&means, &packed, &mask[1..]).is_err());
        let mut nan = packed.clone();
        nan[3] = f64::NAN;
        assert!(c.load_filtered(&means, &nan, &mask).is_err());
        let mut bad = mask.clone();
        bad[0] = 7;
        assert!(c.load_filtered(&means, &packed, &bad).is_err());
    }
}

/// Alg. 9 frame by frame (`rts_step`): the reference of the pipelined smoother.
fn sequential_smoother(
    means: &mut [f64],
    covs: &mut [f64],
    vz: &[f64],
    ns: usize,
    n: usize,
    statistics: bool,
) -> DMatrix<f64> {
    let (nn, steps) = (ns * ns, means.len() / ns);
    let vz = DMatrix::from_column_slice(ns, ns, vz);
    let mut acc = DMatrix::zeros(ns, ns);
    for t in (0..steps - 1).rev() {
        let mf = DVector::from_column_slice(&means[t * ns..(t + 1) * ns]);
        let ms_next = DVector::from_column_slice(&means[(t + 1) * ns..(t + 2) * ns]);
        let vf = DMatrix::from_column_slice(ns, ns, &covs[t * nn..(t + 1) * nn]);
        let vs_next = DMatrix::from_column_slice(ns, ns, &covs[(t + 1) * nn..(t + 2) * nn]);
        let (ms, vs, gt) =
            smoother::rts_step(&mf, &vf, &ms_next, &vs_next, &vz, Transition::plain(n), t).unwrap();
        if statistics {
            smoother::add_statistic(
                &mut acc,
                &ms,
                &vs,
                &ms_next,
                &vs_next,
                &gt,
                Transition::plain(n),
            );
        }
        means[t * ns..(t + 1) * ns].copy_from_slice(ms.as_slice());
        covs[t * nn..(t + 1) * nn].copy_from_slice(vs.as_slice());
    }
    dense::symmetrize(&mut acc);
    acc
}

/// The smoother computes the gains of a block ahead in parallel; it must give the sequential
/// smoother's numbers and eq. 79's statistic bit for bit (several blocks, both orders).
#[test]
fn pipelined_smoother_equals_the_sequential_one() {
    let mut rng = Lcg(7);
    for (ns, n) in [(4usize, 4usize), (6, 3)] {
        let steps = 101;
        let means: Vec<f64> = (0..steps * ns).map(|_| rng.next()).collect();
        let mut covs = Vec::with_capacity(steps * ns * ns);
        for _ in 0..steps {
            let a: Vec<f64> = (0..ns * ns).map(|_| 0.3 * rng.next()).collect();
            for c in 0..ns {
                for r in 0..ns {
                    let v: f64 = (0..ns).map(|k| a[r * ns + k] * a[c * ns + k]).sum();
                    covs.push(v + if r == c { 0.05 } else { 0.0 });
                }
            }
        }
        let mut vz = vec![0.0; ns * ns];
        for i in 0..ns {
            vz[i * ns + i] = 0.01 * (1.0 + i as f64);
        }
        for statistics in [true, false] {
            let (mut m1, mut c1) = (means.clone(), covs.clone());
            let (mut m2, mut c2) = (means.clone(), covs.clone());
            let a1 = sequential_smoother(&mut m1, &mut c1, &vz, ns, n, statistics);
            let a2 = smoother::smooth_in_place(
                &mut m2,
                &mut c2,
                &vz,
                ns,
                Transition::plain(n),
                statistics,
            )
            .unwrap();
            assert_eq!(m1, m2, "means, ns = {ns}");
            assert_eq!(c1, c2, "covariances, ns = {ns}");
            assert_eq!(a1, a2, "statistic, ns = {ns}");
            assert_eq!(statistics, a1.iter().any(|v| *v != 0.0));
        }
    }
}

#[test]
fn em_returns_the_best_parameters_it_evaluated() {
    // With 10 % outliers and a tight innovation gate, which entries count changes from one
    // iteration to the next and EM's log-likelihood falls (here from 260.05 at iteration 4 to
    // 243.48 at the end). The run must return the parameters of iteration 4: the final
    // E-step under them scores exactly what iteration 4's did, and the moments left are
    // their posterior.
    let (em, mut x, p, _, _, _) = linear_problem(13);
    let mut rng = Lcg(13 + 90);
    for v in x.iter_mut() {
        if v.is_finite() && rng.next() > 0.9 {
            *v += 0.3 * rng.next().signum();
        }
    }
    let opts = EmOptions {
        max_iter: 30,
        tol: 1e-12,
        gate: Some(4.0),
        ll_tol: None,
        dof: None,
        patience: None,
        overrelax: None,
    };
    let mut tr = Tracker::new(em.clone(), x.clone()).unwrap();
    let out = tr.run_em(p.clone(), &opts, |_| true).unwrap();
    let ll: Vec<f64> = out.history.iter().map(|h| h.stats.log_lik).collect();
    assert_eq!(ll.len(), 30);
    assert!(!out.stalled);
    let (k, best) =
        ll.iter().enumerate().fold(
            (0, f64::NEG_INFINITY),
            |a, (i, &v)| if v > a.1 { (i, v) } else { a },
        );
    assert!(ll[ll.len() - 1] < best - 1.0, "no fall to test: {ll:?}");
    assert_eq!(out.returned, Some(k + 1), "{ll:?}");
    assert_eq!(out.final_stats.log_lik, best);
    let mut check = Tracker::new(em.clone(), x.clone()).unwrap();
    let s = check.e_step(&out.params, opts.gate).unwrap();
    assert_eq!(s.log_lik, best);
    assert_eq!(check.means(), tr.means());

    // With patience 3 the same run stops after the three E-steps that follow the best one
    // (none of them beats it), returns the best parameters and leaves their posterior.
    let first_best = ll.iter().position(|&v| v == best).unwrap();
    assert!(first_best + 3 < ll.len(), "{ll:?}");
    let patient = EmOptions {
        patience: Some(3),
        overrelax: None,
        ..opts
    };
    let mut tr3 = Tracker::new(em, x).unwrap();
    let out3 = tr3.run_em(p, &patient, |_| true).unwrap();
    assert!(out3.stalled && !out3.converged);
    // the same path up to the stop (the same E-steps from the same start)
    let ll3: Vec<f64> = out3.history.iter().map(|h| h.stats.log_lik).collect();
    assert_eq!(ll3, ll[..first_best + 4].to_vec());
    assert_eq!(out3.returned, Some(first_best + 1));
    assert_eq!(out3.final_stats.log_lik, best);
    assert_eq!(out3.params, out.params);
    assert_eq!(tr3.means(), tr.means());
}

/// An EM history entry with this log-likelihood over 1,000 used entries.
fn iteration(ll: f64, step: f64, rejected: bool) -> Iteration {
    Iteration {
        iteration: 0,
        delta: 0.0,
        seconds: 0.0,
        stats: FilterStats {
            used: 1000,
            log_lik: ll,
            ..FilterStats::default()
        },
        step,
        rejected,
    }
}

#[test]
fn the_log_likelihood_stop_needs_two_small_changes() {
    let it = |ll: f64| iteration(ll, 1.0, false);
    let tol = 1e-3; // 1 nat for 1,000 entries
    let h: Vec<Iteration> = [0.0, 500.0, 500.5].map(it).to_vec();
    assert!(
        !super::ll_settled(&h, tol),
        "one small change after a big one"
    );
    let h: Vec<Iteration> = [0.0, 500.0, 500.5, 500.9].map(it).to_vec();
    assert!(super::ll_settled(&h, tol));
    let h: Vec<Iteration> = [500.0, 500.5, 400.0].map(it).to_vec();
    assert!(!super::ll_settled(&h, tol), "a fall is not convergence");
    let h: Vec<Iteration> = [500.0, 500.5].map(it).to_vec();
    assert!(!super::ll_settled(&h, tol), "too few iterations");
}

/// The memoryless rows of [`Transition`] (elastic segments' log-stretch): `predict`, `f_left`
/// and `f_right` equal the products with the explicit `F` whose rows are zero there, for the
/// random walk and the position–velocity state.
#[test]
fn memoryless_rows_match_the_explicit_transition() {
    let n = 4;
    let zero = [1usize, 3];
    for order in [1usize, 2] {
        let ns = order * n;
        let mut f = DMatrix::<f64>::identity(ns, ns);
        if order == 2 {
            for i in 0..n {
                f[(i, n + i)] = 1.0;
            }
        }
        for &i in &zero {
            f.row_mut(i).fill(0.0);
            if order == 2 {
                f.row_mut(n + i).fill(0.0);
            }
        }
        let a = DMatrix::from_fn(ns, ns, |r, c| ((r * 7 + c * 3) % 11) as f64 - 5.0);
        let v = &a * a.transpose() + DMatrix::identity(ns, ns);
        let vz = DMatrix::from_fn(ns, ns, |r, c| if r == c { 0.5 + r as f64 } else { 0.1 });
        let mu: Vec<f64> = (0..ns).map(|i| i as f64 - 2.5).collect();
        let tr = Transition {
            n,
            memoryless: &zero,
        };
        let (m, p) = filter::predict(&mu, v.as_slice(), vz.as_slice(), tr);
        let m_ref = &f * DVector::from_vec(mu.clone());
        let p_ref = &f * &v * f.transpose() + &vz;
        assert!((m - m_ref).amax() < 1e-12);
        assert!((p - p_ref).amax() < 1e-9);
        assert!((filter::f_left(&a, tr) - &f * &a).amax() < 1e-12);
        assert!((filter::f_right(&a, tr) - &a * f.transpose()).amax() < 1e-12);
    }
}

fn spd(n: usize, seed: u64) -> Vec<f64> {
    let mut rng = Lcg(seed);
    let g: Vec<f64> = (0..n * n).map(|_| rng.next()).collect();
    let mut a = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..n {
            a[i * n + j] = (0..n).map(|k| g[i * n + k] * g[j * n + k]).sum::<f64>();
        }
        a[i * n + i] += 0.1;
    }
    a
}

#[test]
fn over_relaxed_parameters_follow_the_geodesic() {
    let n = 4;
    let from = Params {
        mu0: vec![0.0, 1.0, 2.0, 3.0],
        v0: spd(n, 1),
        vz: spd(n, 2),
        vx: vec![1e-3, 2e-3],
    };
    let to = Params {
        mu0: vec![1.0, 1.0, 0.0, 3.5],
        v0: spd(n, 3),
        vz: spd(n, 4),
        vx: vec![2e-3, 1e-3],
    };
    let close = |a: &[f64], b: &[f64], tol: f64| {
        a.iter()
            .zip(b)
            .all(|(x, y)| (x - y).abs() <= tol * (1.0 + y.abs()))
    };
    // η = 0 and 1 are the ends
    let p0 = super::extrapolate(&from, &to, 0.0).unwrap();
    let p1 = super::extrapolate(&from, &to, 1.0).unwrap();
    assert!(close(&p0.vz, &from.vz, 1e-10) && close(&p1.vz, &to.vz, 1e-10));
    assert!(close(&p1.v0, &to.v0, 1e-10) && close(&p1.vx, &to.vx, 1e-12));
    // η = 2 in closed form: A #₂ B = B A⁻¹ B; V_x: b² / a; μ0: 2 b − a
    let p2 = super::extrapolate(&from, &to, 2.0).unwrap();
    let a = nalgebra::DMatrix::from_row_slice(n, n, &from.vz);
    let b = nalgebra::DMatrix::from_row_slice(n, n, &to.vz);
    let want = &b * a.clone().try_inverse().unwrap() * &b;
    assert!(close(&p2.vz, want.transpose().as_slice(), 1e-9));
    assert!(close(&p2.vx, &[4e-3, 0.5e-3], 1e-12));
    assert!(close(&p2.mu0, &[2.0, 1.0, -2.0, 4.0], 1e-12));
    // far out it stays positive definite
    let p8 = super::extrapolate(&from, &to, 8.0).unwrap();
    let m = nalgebra::DMatrix::from_row_slice(n, n, &p8.vz);
    assert!(m.clone().cholesky().is_some() && close(&p8.vz, m.transpose().as_slice(), 1e-12));
    // a covariance that is not positive definite: no step
    let mut bad = to.clone();
    bad.vz[0] = -1.0;
    assert!(super::extrapolate(&from, &bad, 2.0).is_none());
    let mut bad = to;
    bad.vx[1] = 0.0;
    assert!(super::extrapolate(&from, &bad, 2.0).is_none());
}

#[test]
fn over_relaxed_em_reaches_plain_ems_fit_in_fewer_e_steps() {
    let (em, x, p, _, _, _) = linear_problem(11);
    let run = |overrelax: Option<f64>, max_iter: usize| {
        let mut tr = Tracker::new(em.clone(), x.clone()).unwrap();
        let opts = EmOptions {
            max_iter,
            tol: 1e-12,
            gate: None,
            ll_tol: None,
            dof: None,
            patience: None,
            overrelax,
        };
        tr.run_em(p.clone(), &opts, |_| true).unwrap()
    };
    // plain EM's fixed point after many iterations
    let long = run(None, 400);
    let target = long.final_stats.log_lik - 0.05;
    let first_at = |h: &[Iteration]| h.iter().position(|it| it.stats.log_lik >= target);
    let plain = run(None, 150);
    let over = run(Some(1.5), 150);
    let (kp, ko) = (first_at(&plain.history), first_at(&over.history));
    assert!(
        matches!((kp, ko), (Some(kp), Some(ko)) if 2 * ko < kp),
        "E-steps to within 0.05 nats of plain EM's end: plain {kp:?}, over-relaxed {ko:?}"
    );
    assert!(over.history.iter().any(|it| it.step > 1.0 && !it.rejected));
    // a rejected step is followed by the plain one; an accepted one never scored below
    // the point it came from
    for w in over.history.windows(2) {
        if w[0].rejected {
            assert_eq!(w[1].step, 1.0);
        }
    }
    // the same fixed point
    let rel = |a: &[f64], b: &[f64]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs() / y.abs())
            .fold(0.0, f64::max)
    };
    assert!(rel(&over.params.vx, &long.params.vx) < 0.02);
    assert!(rel(&over.params.vz[..1], &long.params.vz[..1]) < 0.02);
}

#[test]
fn the_log_likelihood_stop_ends_on_a_plain_step() {
    let it = iteration;
    let tol = 1e-3; // 1 nat for 1,000 entries
                    // an over-relaxed step that gained little: not a stop, but the next step is plain
    let mut h = vec![
        it(0.0, 1.0, false),
        it(500.0, 1.5, false),
        it(500.5, 2.25, false),
    ];
    assert!(!super::ll_settled(&h, tol));
    assert!(super::overrelaxed_settled(&h, tol));
    // then a small plain change: two small changes in a row, the last a plain step's
    let mut settled = h.clone();
    settled.push(it(500.9, 1.0, false));
    assert!(super::ll_settled(&settled, tol) && !super::overrelaxed_settled(&settled, tol));
    // a rejected step in between does not count; a large change before the plain one does
    h.push(it(400.0, 3.375, true));
    h.push(it(500.9, 1.0, false));
    assert!(super::ll_settled(&h, tol));
    let h = vec![
        it(0.0, 1.0, false),
        it(500.0, 1.5, false),
        it(510.0, 2.25, false),
        it(510.5, 1.0, false),
    ];
    assert!(!super::ll_settled(&h, tol));
    // a large over-relaxed gain is not settling
    let h = vec![
        it(0.0, 1.0, false),
        it(500.0, 1.5, false),
        it(510.0, 2.25, false),
    ];
    assert!(!super::overrelaxed_settled(&h, tol));
}
