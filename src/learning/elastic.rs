//! Elastic segments (issue 28 item 2, beyond the paper): bones whose length varies per frame
//! around a learned mean, with a variance learned by EM. For sparse keypoint sets (a spine, an
//! ear, a keypoint on fur over a joint) rigid bones are wrong; the ACM's dense marker model keeps
//! them rigid.
//!
//! Model of frame `τ` (the state carries the stretch):
//! * the length of an elastic bone `b` is `l_{b,τ} = l_b · exp(s_{b,τ})`, with the log-stretch
//!   `s_{b,τ} ~ N(0, σ_b²)` independent over frames and bones (dimensionless, so unit-free);
//!   rigid bones keep `l_b`;
//! * labels `x = π(FK(z_τ, l_τ)) + N(0, σ_x² I)` in pixels.
//!
//! E-step (Laplace approximation, as the paper's unscented E-step approximates its posterior):
//! each frame's MAP `(ẑ_τ, ŝ_τ)` of
//! `Σ ‖π − x‖² / σ_x² + Σ_b s_b² / σ_b²`
//! by box-constrained Levenberg-Marquardt, and the posterior covariance `H_τ⁻¹`, with the
//! Gauss-Newton matrix `H_τ = Jᵀ J / σ_x² + diag(0, σ_b⁻²)` at the MAP. This module returns the
//! statistics; the M-step lives in `acm_rs.elastic`:
//! `μ_b = mean_τ ŝ_{b,τ}` (absorbed into `l_b`),
//! `σ_b² = mean_τ ((ŝ_{b,τ} − μ_b)² + [H_τ⁻¹]_{bb})`,
//! `σ_x² = Σ_τ (‖π − x‖²_τ + σ_x² d_τ) / N` with `d_τ = tr(Jᵀ J H_τ⁻¹) / σ_x²` the frame's
//! effective number of parameters.

use super::{damped_lm, LearningProblem};
use crate::error::{ensure_finite, ensure_len, AcmError, Result};
use nalgebra::DMatrix;
use rayon::prelude::*;

/// Bound on the log-stretch of one frame (`exp(±1)`: a bone at 0.37-2.7 × its mean length).
pub const MAX_LOG_STRETCH: f64 = 1.0;

/// The E-step statistics of [`LearningProblem::fit_poses_elastic`].
#[derive(Debug, Clone)]
pub struct ElasticFit {
    /// The parameter vector with every frame's MAP state (skeleton part unchanged).
    pub x: Vec<f64>,
    /// MAP log-stretch `ŝ` (frames × elastic bones, row-major).
    pub stretch: Vec<f64>,
    /// Posterior variance `[H⁻¹]_{bb}` of each log-stretch (frames × elastic bones).
    pub stretch_var: Vec<f64>,
    /// Sum of squared pixel residuals at the MAP, per frame (px²).
    pub sq_px: Vec<f64>,
    /// Effective number of parameters `d_τ = tr(JᵀJ H⁻¹)/σ_x²` per frame.
    pub dof: Vec<f64>,
    /// Number of pixel residuals (2 per used label) per frame.
    pub n_px: Vec<usize>,
    /// Levenberg-Marquardt iterations per frame.
    pub iterations: Vec<usize>,
}

/// One frame's E-step outcome: `(stretch, variances, ‖r‖², d, n_px, iterations)`.
type FrameStats = (Vec<f64>, Vec<f64>, f64, f64, usize, usize);

impl LearningProblem {
    /// E-step of the elastic-segment EM (module docs): per frame (in parallel) the MAP state
    /// and log-stretch under the current `σ_b` (`stretch_sd`) and `σ_x` (`noise_px`), and
    /// their Laplace posterior statistics.
    ///
    /// # Arguments
    /// * `x` - parameter vector (its frames' states are the starting poses).
    /// * `lower`, `upper` - box bounds of one frame's state (as [`Self::fit_poses_lm`]).
    /// * `stretch_bones` - the elastic bones (distinct bone indices).
    /// * `stretch_sd` - `σ_b` of each elastic bone (> 0).
    /// * `stretch0` - starting log-stretch (frames × elastic bones).
    /// * `noise_px` - `σ_x` (px, > 0).
    ///
    /// # Errors
    /// Shape errors for wrong lengths; invalid errors for an unknown or repeated bone, a
    /// non-positive SD or noise; non-finite errors for NaN inputs.
    #[allow(clippy::too_many_arguments)]
    pub fn fit_poses_elastic(
        &self,
        x: &[f64],
        lower: &[f64],
        upper: &[f64],
        stretch_bones: &[usize],
        stretch_sd: &[f64],
        stretch0: &[f64],
        noise_px: f64,
        max_iter: usize,
    ) -> Result<ElasticFit> {
        ensure_len(x.len(), self.n_params(), "parameter vector")?;
        ensure_finite(x, "parameter vector")?;
        let nz = self.map.n_state();
        ensure_len(lower.len(), nz, "lower state bounds")?;
        ensure_len(upper.len(), nz, "upper state bounds")?;
        let ne = stretch_bones.len();
        crate::limits::check_elastic_bones(stretch_bones, self.skeleton.n_bones())?;
        ensure_len(stretch_sd.len(), ne, "stretch SDs (one per elastic bone)")?;
        if let Some(e) = stretch_sd.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(AcmError::Invalid(format!(
                "the stretch SD of elastic bone {} must be finite and > 0, got {}",
                stretch_bones[e], stretch_sd[e]
            )));
        }
        ensure_len(
            stretch0.len(),
            self.n_frames * ne,
            "starting log-stretch (F, elastic bones)",
        )?;
        ensure_finite(stretch0, "starting log-stretch")?;
        if !(noise_px.is_finite() && noise_px > 0.0) {
            return Err(AcmError::Invalid(format!(
                "the label noise must be finite and > 0 px, got {noise_px}"
            )));
        }
        let (lengths, offsets) = self.skeleton_from_params(x)?;
        let nsk = self.n_skeleton_params();
        let per_frame = self.cameras.len() * self.skeleton.n_markers() * 2;
        let (c1, c2) = (self.norm.pixel[0], self.norm.pixel[1]);
        let mut lo = lower.to_vec();
        let mut hi = upper.to_vec();
        lo.extend(std::iter::repeat_n(-MAX_LOG_STRETCH, ne));
        hi.extend(std::iter::repeat_n(MAX_LOG_STRETCH, ne));
        // Whitened residuals of the MAP objective and their Jacobian: pixel rows (u, v pairs)
        // scaled by c/σ_x, then one prior row s_b/σ_b per elastic bone. Also returns the
        // number of pixel rows.
        let whitened = |w: &[f64], obs: &[f64]| -> (Vec<f64>, DMatrix<f64>, usize) {
            let (z, s) = w.split_at(nz);
            let mut len_t = lengths.clone();
            for (&b, v) in stretch_bones.iter().zip(s) {
                len_t[b] *= v.exp();
            }
            let (mut r, j) = self.frame_residual_jacobian(&len_t, &offsets, z, obs, stretch_bones);
            let n_px = r.len();
            let mut jw = DMatrix::zeros(n_px + ne, nz + ne);
            for q in 0..n_px {
                let sc = if q % 2 == 0 { c1 } else { c2 } / noise_px;
                r[q] *= sc;
                for c in 0..nz + ne {
                    jw[(q, c)] = j[(q, c)] * sc;
                }
            }
            for (e, (v, sd)) in s.iter().zip(stretch_sd).enumerate() {
                r.push(v / sd);
                jw[(n_px + e, nz + e)] = 1.0 / sd;
            }
            (r, jw, n_px)
        };
        let s_rows: Vec<&[f64]> = (0..self.n_frames)
            .map(|f| &stretch0[f * ne..(f + 1) * ne])
            .collect();
        let mut out = x.to_vec();
        let stats: Vec<FrameStats> = out[nsk..]
            .par_chunks_mut(nz)
            .zip(self.labels.par_chunks(per_frame))
            .zip(s_rows.par_iter())
            .map(|((z, obs), s0)| {
                let mut w: Vec<f64> = z.iter().chain(s0.iter()).copied().collect();
                let it = damped_lm(&mut w, &lo, &hi, max_iter, |w| {
                    let (r, j, _) = whitened(w, obs);
                    (r, j)
                });
                z.copy_from_slice(&w[..nz]);
                let (r, j, n_px) = whitened(&w, obs);
                let sq_px = r[..n_px].iter().map(|v| v * v).sum::<f64>() * noise_px * noise_px;
                // Laplace covariance H⁻¹ (H = JᵀJ of the whitened problem; a tiny ridge where a
                // direction is not observed in this frame, e.g. a bone with no label below it).
                let jp = j.rows(0, n_px);
                let g = jp.transpose() * jp;
                let mut h = j.transpose() * &j;
                let ridge = 1e-10 * (0..nz + ne).map(|d| h[(d, d)]).fold(1e-300, f64::max);
                for d in 0..nz + ne {
                    h[(d, d)] += ridge;
                }
                let (var, dof) = match h.cholesky() {
                    Some(ch) => {
                        let hg = ch.solve(&g);
                        let dof = hg.trace();
                        let mut units = DMatrix::zeros(nz + ne, ne);
                        for e in 0..ne {
                            units[(nz + e, e)] = 1.0;
                        }
                        let cols = ch.solve(&units);
                        ((0..ne).map(|e| cols[(nz + e, e)]).collect(), dof)
                    }
                    // not reached with the ridge; keep the prior if it ever is
                    None => (stretch_sd.iter().map(|s| s * s).collect(), 0.0),
                };
                (w[nz..].to_vec(), var, sq_px, dof, n_px, it)
            })
            .collect();
        let mut fit = ElasticFit {
            x: out,
            stretch: Vec::with_capacity(self.n_frames * ne),
            stretch_var: Vec::with_capacity(self.n_frames * ne),
            sq_px: Vec::with_capacity(self.n_frames),
            dof: Vec::with_capacity(self.n_frames),
            n_px: Vec::with_capacity(self.n_frames),
            iterations: Vec::with_capacity(self.n_frames),
        };
        for (s, v, sq, d, n, it) in stats {
            fit.stretch.extend(s);
            fit.stretch_var.extend(v);
            fit.sq_px.push(sq);
            fit.dof.push(d);
            fit.n_px.push(n);
            fit.iterations.push(it);
        }
        Ok(fit)
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::problem;
    use super::super::Mode;
    use super::*;
    use nalgebra::Vector3;

    fn poses_only() -> (LearningProblem, Vec<f64>) {
        let (full, _) = problem(Mode::Full);
        let sk = full.skeleton.clone();
        let lengths: Vec<f64> = (0..sk.n_bones()).map(|b| 1.0 + 0.1 * b as f64).collect();
        let offsets = sk.offsets().to_vec();
        let mode = Mode::PosesOnly { lengths, offsets };
        problem(mode)
    }

    #[test]
    fn stretch_columns_match_central_differences() {
        let (p, x) = poses_only();
        let nz = p.map.n_state();
        let (lengths, offsets) = p.skeleton_from_params(&x).unwrap();
        let per_frame = p.cameras.len() * p.skeleton.n_markers() * 2;
        let obs = &p.labels[..per_frame];
        let z = &x[..nz];
        let bones = [0usize, 2];
        let s = [0.1, -0.05];
        let stretched = |s: &[f64]| {
            let mut l = lengths.clone();
            for (&b, v) in bones.iter().zip(s) {
                l[b] *= v.exp();
            }
            l
        };
        let (_, j) = p.frame_residual_jacobian(&stretched(&s), &offsets, z, obs, &bones);
        assert_eq!(j.ncols(), nz + bones.len());
        let h = 1e-6;
        for e in 0..bones.len() {
            let (mut sp, mut sm) = (s, s);
            sp[e] += h;
            sm[e] -= h;
            let (rp, _) = p.frame_residual_jacobian(&stretched(&sp), &offsets, z, obs, &[]);
            let (rm, _) = p.frame_residual_jacobian(&stretched(&sm), &offsets, z, obs, &[]);
            let mut max_abs: f64 = 0.0;
            for q in 0..rp.len() {
                let fd = (rp[q] - rm[q]) / (2.0 * h);
                let err = (fd - j[(q, nz + e)]).abs();
                assert!(
                    err < 1e-6 * (1.0 + fd.abs()),
                    "row {q} bone {}: {fd} vs {}",
                    bones[e],
                    j[(q, nz + e)]
                );
                max_abs = max_abs.max(fd.abs());
            }
            assert!(
                max_abs > 1e-3,
                "the stretch of bone {} moves no label",
                bones[e]
            );
        }
    }

    #[test]
    fn map_recovers_the_stretch_of_consistent_labels() {
        // keypoints at the joints (a lab's landmarks): each bone's length is observable
        let parents = [-1, 0, 1, 2, 1];
        let rest = [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(0.0, 0.2, 2.0),
            Vector3::new(-1.0, -0.5, 2.5),
            Vector3::new(-1.2, 0.4, 3.4),
            Vector3::new(1.0, -0.4, 2.6),
        ];
        let sk = crate::skeleton::Skeleton::from_rest_pose(
            &parents,
            &rest,
            (0..5).collect(),
            &rest,
            &Vector3::y(),
            None,
        )
        .unwrap();
        let (p0, _) = problem(Mode::Full);
        let (nb, nm) = (sk.n_bones(), sk.n_markers());
        let norm = crate::normalization::Normalization::default();
        let inf = f64::INFINITY;
        let map =
            crate::limits::StateMap::new(nb, &vec![-inf; 3 * nb], &vec![inf; 3 * nb], &norm, false)
                .unwrap();
        let nz = map.n_state();
        let lengths = sk.lengths().to_vec();
        let offsets = sk.offsets().to_vec();
        let bones = [0usize, 2];
        let s_true: [f64; 2] = [0.12, -0.08];
        let mut l_true = lengths.clone();
        for (&b, v) in bones.iter().zip(&s_true) {
            l_true[b] *= v.exp();
        }
        let z_true: Vec<f64> = (0..nz).map(|i| 0.05 * ((i * 7) % 5) as f64 - 0.1).collect();
        let mut pose = vec![0.0; sk.n_pose()];
        map.to_pose_into(&z_true, &mut pose, None);
        let t = Vector3::new(pose[0], pose[1], pose[2]);
        let r: Vec<Vector3<f64>> = pose[3..]
            .chunks(3)
            .map(|c| Vector3::new(c[0], c[1], c[2]))
            .collect();
        let fk = sk.forward_unchecked(&t, &r, &l_true, &offsets);
        let mut frame = Vec::new();
        for cam in &p0.cameras {
            for m in &fk.markers {
                let px = cam.project_jacobian(m).unwrap().pixel;
                frame.extend([px.x, px.y]);
            }
        }
        let n_frames = 2;
        let labels: Vec<f64> = (0..n_frames).flat_map(|_| frame.clone()).collect();
        let sym = crate::symmetry::SymmetryMap::new(nb, &[], nm, &[]).unwrap();
        let mode = Mode::PosesOnly { lengths, offsets };
        let p = LearningProblem::new(sk, p0.cameras.clone(), norm, map, sym, labels, 1.0, mode)
            .unwrap();
        let x: Vec<f64> = z_true.iter().map(|v| v + 0.02).collect();
        let x0: Vec<f64> = (0..n_frames).flat_map(|_| x.clone()).collect();
        let (lo, hi) = (vec![-inf; nz], vec![inf; nz]);
        let sd = [0.2, 0.2];
        let fit = p
            .fit_poses_elastic(
                &x0,
                &lo,
                &hi,
                &bones,
                &sd,
                &vec![0.0; 2 * n_frames],
                0.01,
                100,
            )
            .unwrap();
        for f in 0..n_frames {
            for e in 0..2 {
                let s = fit.stretch[f * 2 + e];
                assert!(
                    (s - s_true[e]).abs() < 1e-4,
                    "frame {f} bone {}: {s}",
                    bones[e]
                );
                // data-dominated: the posterior variance is far below the prior's
                assert!(fit.stretch_var[f * 2 + e] < 1e-3 * sd[e] * sd[e]);
            }
            assert!(fit.sq_px[f] < 1e-6, "residual {}", fit.sq_px[f]);
            // every entry but the bones' twists (unseen for points on the axis) is informed
            assert!(
                fit.dof[f] > 2.0 && fit.dof[f] < (nz + 2) as f64 + 1e-6,
                "dof {}",
                fit.dof[f]
            );
            assert_eq!(fit.n_px[f], p.cameras.len() * p.skeleton.n_markers() * 2);
        }
        // bad inputs: a repeated bone, an SD of 0, a bone that does not exist
        let s0 = vec![0.0; 2 * n_frames];
        assert!(p
            .fit_poses_elastic(&x0, &lo, &hi, &[1, 1], &sd, &s0, 0.01, 5)
            .is_err());
        assert!(p
            .fit_poses_elastic(&x0, &lo, &hi, &bones, &[0.2, 0.0], &s0, 0.01, 5)
            .is_err());
        assert!(p
            .fit_poses_elastic(&x0, &lo, &hi, &[1, 99], &sd, &s0, 0.01, 5)
            .is_err());
        assert!(p
            .fit_poses_elastic(&x0, &lo, &hi, &bones, &sd, &s0, 0.0, 5)
            .is_err());
    }
}
