//! Levenberg-Marquardt on the whole learning problem (eq. 9/12 in [`Mode::Full`]): exact
//! Gauss-Newton steps for the shared skeleton parameters and every frame's pose, with the
//! per-frame pose blocks eliminated by the Schur complement (the structure of bundle
//! adjustment), box bounds by projection with an active set.
//!
//! L-BFGS-B (the authors' optimiser) stalls in the long, flat valleys of this problem (a joint
//! sliding along a chain while the marker offsets on both sides follow): on noise-free labels
//! it stops at ~0.4 px RMS with bones 1 cm off. Gauss-Newton steps cross such valleys.

use super::{LearningProblem, Mode};
use crate::error::{ensure_finite, ensure_len, AcmError, Result};
use nalgebra::{DMatrix, DVector, Vector3};
use rayon::prelude::*;

/// Outcome of [`LearningProblem::fit_full_lm`].
#[derive(Debug, Clone)]
pub struct LmReport {
    /// Accepted steps.
    pub iterations: usize,
    /// Objective (mean squared normalised residual) before and after.
    pub initial_value: f64,
    /// Objective at the returned point.
    pub final_value: f64,
    /// Why it stopped.
    pub message: String,
}

/// One frame after eliminating its pose: `U⁻¹W`, `U⁻¹gz` and the (held-masked) `W`.
struct Eliminated {
    uw: DMatrix<f64>,
    ug: DVector<f64>,
    w: DMatrix<f64>,
}

/// One frame's normal-equation blocks: `U = AᵀA`, `W = AᵀB`, `V = BᵀB`, `gz = Aᵀr`,
/// `gs = Bᵀr` (A: pose columns, B: reduced skeleton columns).
struct FrameBlocks {
    u: DMatrix<f64>,
    w: DMatrix<f64>,
    v: DMatrix<f64>,
    gz: DVector<f64>,
    gs: DVector<f64>,
}

impl LearningProblem {
    /// Residuals of one frame with their Jacobians w.r.t. the frame's state (`A`) and the
    /// reduced skeleton parameters in parameter units (`B`), as normal-equation blocks.
    fn frame_blocks(
        &self,
        lengths: &[f64],
        offsets: &[Vector3<f64>],
        z: &[f64],
        obs: &[f64],
    ) -> FrameBlocks {
        let sk = &self.skeleton;
        let (nm, np, ns, nb) = (sk.n_markers(), sk.n_pose(), z.len(), sk.n_bones());
        let nrb = self.sym.n_reduced_bones();
        let nsk = self.n_skeleton_params();
        let s = self.length_scale;
        let (t, r, dz) = self.decode(z);
        let jac = sk
            .forward_jacobian(&t, &r, Some(lengths), Some(offsets))
            .expect("validated inputs");
        let nj = sk.n_joints();
        let (c1, c2) = (self.norm.pixel[0], self.norm.pixel[1]);
        let mut res = Vec::new();
        let mut a_rows: Vec<f64> = Vec::new();
        let mut b_rows: Vec<f64> = Vec::new();
        let mut arow = vec![0.0; ns];
        let mut brow = vec![0.0; nsk];
        for (ci, cam) in self.cameras.iter().enumerate() {
            for k in 0..nm {
                let o = &obs[(ci * nm + k) * 2..(ci * nm + k) * 2 + 2];
                if !(o[0].is_finite() && o[1].is_finite()) {
                    continue;
                }
                let Some(pj) = cam.project_jacobian(&jac.fk.markers[k]) else {
                    continue; // behind the camera: no usable residual at this pose
                };
                let (src, mirrored) = self.sym.marker_source()[k];
                for (u, c) in [(0, c1), (1, c2)] {
                    res.push((pj.pixel[u] - o[u]) / c);
                    let dp = pj.d_point.row(u) / c;
                    let row = |a: usize| 3 * (nj + k) + a;
                    for (i, &idx) in self.map.free_indices().iter().enumerate() {
                        let v: f64 = (0..3).map(|a| dp[a] * jac.d_pose[row(a) * np + idx]).sum();
                        arow[i] = v * dz[i];
                    }
                    brow.iter_mut().for_each(|v| *v = 0.0);
                    for b in 0..nb {
                        let v: f64 = (0..3).map(|a| dp[a] * jac.d_lengths[row(a) * nb + b]).sum();
                        brow[self.sym.bone_source()[b]] += v * s;
                    }
                    for cc in 0..3 {
                        let v: f64 = (0..3)
                            .map(|a| dp[a] * jac.d_offsets[9 * k + 3 * a + cc])
                            .sum();
                        let sign = if mirrored && cc == 0 { -1.0 } else { 1.0 };
                        brow[nrb + 3 * src + cc] += v * s * sign;
                    }
                    a_rows.extend_from_slice(&arow);
                    b_rows.extend_from_slice(&brow);
                }
            }
        }
        let m = res.len();
        let a = DMatrix::from_row_slice(m, ns, &a_rows);
        let b = DMatrix::from_row_slice(m, nsk, &b_rows);
        let r = DVector::from_column_slice(&res);
        let at = a.transpose();
        let bt = b.transpose();
        FrameBlocks {
            u: &at * &a,
            w: &at * &b,
            v: &bt * &b,
            gz: &at * &r,
            gs: &bt * &r,
        }
    }

    /// Sum of squared normalised residuals (behind-camera labels cost one image each, as in
    /// [`LearningProblem::value_grad`]) plus the prior residuals `w (x − c)` of the skeleton
    /// parameters.
    fn total_cost(&self, x: &[f64], prior: Option<(&[f64], &[f64])>) -> Result<f64> {
        let (value, _) = self.value_grad(x)?;
        let mut cost = value * self.n_labels as f64;
        if let Some((c, w)) = prior {
            for ((xi, ci), wi) in x.iter().zip(c).zip(w) {
                cost += (wi * (xi - ci)).powi(2);
            }
        }
        Ok(cost)
    }

    /// Levenberg-Marquardt on `[skeleton, poses]` within `[lower, upper]` (Mode::Full only).
    ///
    /// Each step solves the damped Gauss-Newton system with the per-frame pose blocks
    /// eliminated (Schur complement on the skeleton parameters); variables on a bound whose
    /// gradient points outwards are held there for the step; trial points are projected onto
    /// the box. Stops when a step lowers the objective by less than `tol` (relative), when no
    /// damping gives a decrease, or after `max_iter` steps.
    ///
    /// `prior = (c, w)` adds a Gaussian prior on the skeleton parameters as residuals
    /// `w_i (x_i − c_i)` (normalised-pixel units; `w_i = 0` for none).
    ///
    /// # Errors
    /// As [`LearningProblem::value_grad`], plus an invalid error in [`Mode::PosesOnly`] and
    /// shape errors for the bounds and the prior.
    pub fn fit_full_lm(
        &self,
        x: &[f64],
        lower: &[f64],
        upper: &[f64],
        max_iter: usize,
        tol: f64,
        prior: Option<(&[f64], &[f64])>,
    ) -> Result<(Vec<f64>, LmReport)> {
        if !matches!(self.mode, Mode::Full) {
            return Err(AcmError::Invalid(
                "fit_full_lm needs the full problem (lengths, offsets and poses)".into(),
            ));
        }
        ensure_len(x.len(), self.n_params(), "parameter vector")?;
        ensure_finite(x, "parameter vector")?;
        ensure_len(lower.len(), x.len(), "lower bounds")?;
        ensure_len(upper.len(), x.len(), "upper bounds")?;
        let ns = self.map.n_state();
        let nsk = self.n_skeleton_params();
        if let Some((c, w)) = prior {
            ensure_len(c.len(), nsk, "prior centre")?;
            ensure_len(w.len(), nsk, "prior weights")?;
            ensure_finite(c, "prior centre")?;
            ensure_finite(w, "prior weights")?;
        }
        let per_frame = self.cameras.len() * self.skeleton.n_markers() * 2;
        let clip = |v: &mut [f64]| {
            for (i, e) in v.iter_mut().enumerate() {
                *e = e.clamp(lower[i], upper[i]);
            }
        };
        let mut x = x.to_vec();
        clip(&mut x);
        let mut cost = self.total_cost(&x, prior)?;
        let initial = cost;
        let mut lambda = 1e-4;
        let mut iterations = 0;
        let mut message = format!("maximum number of iterations ({max_iter}) reached");
        'outer: while iterations < max_iter {
            let (lengths, offsets) = self.skeleton_from_params(&x)?;
            let blocks: Vec<FrameBlocks> = x[nsk..]
                .par_chunks(ns)
                .zip(self.labels.par_chunks(per_frame))
                .map(|(z, obs)| self.frame_blocks(&lengths, &offsets, z, obs))
                .collect();
            // active set: on a bound with the gradient pointing out of the box
            let mut grad = vec![0.0; x.len()];
            let mut v_sum = DMatrix::<f64>::zeros(nsk, nsk);
            for (f, b) in blocks.iter().enumerate() {
                grad[nsk + f * ns..nsk + (f + 1) * ns].copy_from_slice(b.gz.as_slice());
                for (g, v) in grad[..nsk].iter_mut().zip(b.gs.iter()) {
                    *g += v;
                }
                v_sum += &b.v;
            }
            if let Some((c, w)) = prior {
                for i in 0..nsk {
                    let w2 = w[i] * w[i];
                    v_sum[(i, i)] += w2;
                    grad[i] += w2 * (x[i] - c[i]);
                }
            }
            let held: Vec<bool> = (0..x.len())
                .map(|i| (x[i] <= lower[i] && grad[i] > 0.0) || (x[i] >= upper[i] && grad[i] < 0.0))
                .collect();
            let mut accepted = false;
            for _ in 0..20 {
                let Some(step) = self.damped_step(&blocks, &v_sum, &grad, &held, lambda) else {
                    lambda *= 10.0;
                    continue;
                };
                let mut trial: Vec<f64> = x.iter().zip(&step).map(|(a, b)| a + b).collect();
                clip(&mut trial);
                let c1 = match self.total_cost(&trial, prior) {
                    Ok(c) => c,
                    Err(AcmError::Invalid(_)) => f64::INFINITY, // e.g. a length through zero
                    Err(e) => return Err(e),
                };
                if c1 < cost {
                    let rel = (cost - c1) / cost.max(1e-300);
                    x = trial;
                    cost = c1;
                    iterations += 1;
                    lambda = (lambda / 3.0).max(1e-12);
                    accepted = true;
                    if rel < tol {
                        message = format!("relative reduction {rel:.2e} < {tol:.2e}");
                        break 'outer;
                    }
                    break;
                }
                lambda *= 10.0;
            }
            if !accepted {
                message = "no damping gave a decrease (converged)".into();
                break;
            }
        }
        let scale = 1.0 / self.n_labels as f64;
        Ok((
            x,
            LmReport {
                iterations,
                initial_value: initial * scale,
                final_value: cost * scale,
                message,
            },
        ))
    }

    /// The damped Gauss-Newton step for all parameters (None if a block is not positive
    /// definite at this damping).
    fn damped_step(
        &self,
        blocks: &[FrameBlocks],
        v_sum: &DMatrix<f64>,
        grad: &[f64],
        held: &[bool],
        lambda: f64,
    ) -> Option<Vec<f64>> {
        let ns = self.map.n_state();
        let nsk = self.n_skeleton_params();
        let damp = |m: &mut DMatrix<f64>, held: &[bool]| {
            let n = m.nrows();
            for i in 0..n {
                if held[i] {
                    for j in 0..n {
                        m[(i, j)] = 0.0;
                        m[(j, i)] = 0.0;
                    }
                    m[(i, i)] = 1.0;
                } else {
                    let d = m[(i, i)];
                    m[(i, i)] = d + lambda * d.max(1e-12);
                }
            }
        };
        // per frame: U⁻¹W and U⁻¹gz (held pose entries zeroed)
        let parts: Vec<Option<Eliminated>> = blocks
            .par_iter()
            .enumerate()
            .map(|(f, b)| {
                let h = &held[nsk + f * ns..nsk + (f + 1) * ns];
                let mut u = b.u.clone();
                damp(&mut u, h);
                let mut w = b.w.clone();
                let mut gz = b.gz.clone();
                for (i, &hi) in h.iter().enumerate() {
                    if hi {
                        w.row_mut(i).fill(0.0);
                        gz[i] = 0.0;
                    }
                }
                for (j, &hj) in held[..nsk].iter().enumerate() {
                    if hj {
                        w.column_mut(j).fill(0.0);
                    }
                }
                let ch = u.cholesky()?;
                let uw = ch.solve(&w);
                let ug = ch.solve(&gz);
                Some(Eliminated { uw, ug, w })
            })
            .collect();
        let mut s = v_sum.clone();
        damp(&mut s, &held[..nsk]);
        let mut rhs = DVector::from_column_slice(&grad[..nsk]);
        for (j, &hj) in held[..nsk].iter().enumerate() {
            if hj {
                rhs[j] = 0.0;
            }
        }
        let mut rhs = -rhs;
        for p in &parts {
            let Eliminated { uw, ug, w } = p.as_ref()?;
            s -= w.transpose() * uw;
            rhs += w.transpose() * ug;
        }
        // held rows of the Schur complement stay identity (their couplings were zeroed)
        let ds = s.cholesky()?.solve(&rhs);
        let mut step = vec![0.0; nsk + blocks.len() * ns];
        step[..nsk].copy_from_slice(ds.as_slice());
        for (f, p) in parts.iter().enumerate() {
            let Eliminated { uw, ug, .. } = p.as_ref()?;
            let dz = -(ug + uw * &ds);
            step[nsk + f * ns..nsk + (f + 1) * ns].copy_from_slice(dz.as_slice());
        }
        Some(step)
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::problem;
    use super::*;

    /// Normalised residuals of the labelled points (in label order) of a parameter vector.
    fn residual_vector(p: &LearningProblem, x: &[f64]) -> Vec<f64> {
        let r = p.residuals(x).unwrap();
        r.projected
            .iter()
            .zip(&p.labels)
            .enumerate()
            .filter(|(_, (_, o))| o.is_finite())
            .map(|(i, (a, o))| (a - o) / p.norm.pixel[i % 2])
            .collect()
    }

    #[test]
    fn schur_step_equals_the_dense_gauss_newton_step() {
        let (p, x) = problem(Mode::Full);
        let r0 = residual_vector(&p, &x);
        assert!(
            r0.iter().all(|v| v.is_finite()),
            "test labels must be in front"
        );
        // dense Jacobian by central differences
        let (m, n) = (r0.len(), x.len());
        let h = 1e-6;
        let mut jac = DMatrix::<f64>::zeros(m, n);
        for i in 0..n {
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[i] += h;
            xm[i] -= h;
            let (rp, rm) = (residual_vector(&p, &xp), residual_vector(&p, &xm));
            for k in 0..m {
                jac[(k, i)] = (rp[k] - rm[k]) / (2.0 * h);
            }
        }
        let lambda = 0.3;
        let jtj = jac.transpose() * &jac;
        let mut a = jtj.clone();
        for i in 0..n {
            a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
        }
        let g = jac.transpose() * DVector::from_column_slice(&r0);
        let dense = a.cholesky().unwrap().solve(&(-&g));
        // Schur
        let (lengths, offsets) = p.skeleton_from_params(&x).unwrap();
        let (ns, nsk) = (p.map.n_state(), p.n_skeleton_params());
        let per_frame = p.cameras.len() * p.skeleton.n_markers() * 2;
        let blocks: Vec<FrameBlocks> = x[nsk..]
            .chunks(ns)
            .zip(p.labels.chunks(per_frame))
            .map(|(z, obs)| p.frame_blocks(&lengths, &offsets, z, obs))
            .collect();
        let mut grad = vec![0.0; n];
        let mut v_sum = DMatrix::<f64>::zeros(nsk, nsk);
        for (f, b) in blocks.iter().enumerate() {
            grad[nsk + f * ns..nsk + (f + 1) * ns].copy_from_slice(b.gz.as_slice());
            for (gi, v) in grad[..nsk].iter_mut().zip(b.gs.iter()) {
                *gi += v;
            }
            v_sum += &b.v;
        }
        for (i, (a, b)) in grad.iter().zip(g.iter()).enumerate() {
            assert!(
                (a - b).abs() < 1e-6 * (1.0 + b.abs()),
                "gradient {i}: {a} vs {b}"
            );
        }
        let step = p
            .damped_step(&blocks, &v_sum, &grad, &vec![false; n], lambda)
            .unwrap();
        for i in 0..n {
            assert!(
                (step[i] - dense[i]).abs() < 1e-5 * (1.0 + dense[i].abs()),
                "step {i}: {} vs {}",
                step[i],
                dense[i]
            );
        }
    }

    #[test]
    fn recovers_an_exact_fit_within_bounds() {
        // labels made from a known parameter vector: LM from a perturbed start fits them
        let (p0, x_true) = problem(Mode::Full);
        let res = p0.residuals(&x_true).unwrap();
        let mut p = p0.clone();
        p.labels = res
            .projected
            .iter()
            .zip(&p0.labels)
            .map(|(a, o)| if o.is_finite() { *a } else { f64::NAN })
            .collect();
        let mut x0 = x_true.clone();
        for (i, v) in x0.iter_mut().enumerate() {
            *v += 0.02 * (((i * 31) % 7) as f64 / 7.0 - 0.5);
        }
        let n = x0.len();
        let nsk = p.n_skeleton_params();
        let mut lower = vec![f64::NEG_INFINITY; n];
        lower[..nsk].iter_mut().for_each(|v| *v = 0.5);
        let upper = vec![f64::INFINITY; n];
        let (x, rep) = p
            .fit_full_lm(&x0, &lower, &upper, 200, 1e-14, None)
            .unwrap();
        assert!(rep.initial_value > 1e-6, "{rep:?}");
        assert!(rep.final_value < 1e-16, "{rep:?}");
        assert!(x[..nsk].iter().all(|&v| v >= 0.5));
        // a prior pulls the skeleton towards its centre and costs residual
        let centre = vec![1.0; nsk];
        let weight = vec![0.5; nsk];
        let (_, rep2) = p
            .fit_full_lm(&x0, &lower, &upper, 200, 1e-14, Some((&centre, &weight)))
            .unwrap();
        assert!(rep2.final_value > rep.final_value);
        assert!(p
            .fit_full_lm(&x0, &lower[1..], &upper, 5, 1e-9, None)
            .is_err());
    }
}
