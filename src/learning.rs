//! Learning bone lengths and marker offsets from labelled frames (ACM supp. sections 3.2-3.4):
//! the objective of eq. 9 with the symmetric parameterisation of eq. 12 (Alg. 2-3), normalised
//! as in sec. 3.3, and its exact gradient, evaluated in parallel over frames.
//!
//! Parameter vector (what L-BFGS-B sees):
//! * [`Mode::Full`]: `[l* / s, v* / s, z_0, z_1, …]` with the reduced lengths `l*` (Alg. 2),
//!   the reduced offsets `v*` (Alg. 3, flat), the length scale `s`, and one state `z_τ` per
//!   frame (the free pose entries of a linear [`StateMap`]: `t = c_t z`, `r = c_r z`).
//! * [`Mode::PosesOnly`]: `[z_0, z_1, …]` with fixed lengths and offsets (sec. 4.7, the
//!   first-pose fit, and the per-frame initialisation).
//!
//! Objective: the mean over labelled (frame, camera, marker) of the squared normalised pixel
//! residual `((û − u)/c_1)² + ((v̂ − v)/c_2)²` (eq. 9 with eq. 11 divided by the number of
//! labels, so its value does not grow with the data set).

use crate::camera::Camera;
use crate::error::{ensure_finite, ensure_len, AcmError, Result};
use crate::limits::StateMap;
use crate::normalization::Normalization;
use crate::skeleton::Skeleton;
use crate::symmetry::SymmetryMap;
use nalgebra::{DMatrix, DVector, Vector3};
use rayon::prelude::*;

pub mod elastic;
mod lm;
pub use elastic::ElasticFit;
pub use lm::LmReport;

/// What is optimised.
#[derive(Debug, Clone)]
pub enum Mode {
    /// Reduced lengths and offsets shared by all frames plus every frame's pose.
    Full,
    /// Only the poses; lengths and offsets fixed at the given values.
    PosesOnly {
        /// Bone lengths (n_bones).
        lengths: Vec<f64>,
        /// Marker offsets (M).
        offsets: Vec<Vector3<f64>>,
    },
}

/// The learning objective for one skeleton, rig and label set.
#[derive(Debug, Clone)]
pub struct LearningProblem {
    skeleton: Skeleton,
    cameras: Vec<Camera>,
    norm: Normalization,
    map: StateMap,
    sym: SymmetryMap,
    /// `(F, C, M, 2)` pixels, NaN where unlabelled.
    labels: Vec<f64>,
    n_frames: usize,
    n_labels: usize,
    length_scale: f64,
    mode: Mode,
}

/// Per-label residuals of a parameter vector.
#[derive(Debug, Clone)]
pub struct Residuals {
    /// `(F, C, M, 2)` reprojected pixels (NaN where behind a camera).
    pub projected: Vec<f64>,
    /// Lengths used (n_bones).
    pub lengths: Vec<f64>,
    /// Offsets used (M, flat 3).
    pub offsets: Vec<f64>,
    /// Full poses `(F, 3 + 3 n_bones)`.
    pub poses: Vec<f64>,
}

impl LearningProblem {
    /// Builds the objective.
    ///
    /// # Arguments
    /// * `labels` - `(F, C, M, 2)` flat pixels, NaN where a marker is not labelled in a camera.
    /// * `map` - the pose parameterisation (a linear [`StateMap`]; joint limits become box
    ///   bounds of L-BFGS-B).
    /// * `sym` - symmetry map (use one without pairs for an asymmetric fit).
    /// * `length_scale` - divides lengths and offsets in the parameter vector (> 0).
    ///
    /// # Errors
    /// Shape errors for inconsistent sizes; invalid errors for no labels at all, a frame with
    /// fewer than 3 labelled 2D points, infinite labels or a non-positive length scale.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        skeleton: Skeleton,
        cameras: Vec<Camera>,
        norm: Normalization,
        map: StateMap,
        sym: SymmetryMap,
        labels: Vec<f64>,
        length_scale: f64,
        mode: Mode,
    ) -> Result<Self> {
        norm.validate()?;
        ensure_len(map.n_pose(), skeleton.n_pose(), "state map pose length")?;
        if !(length_scale.is_finite() && length_scale > 0.0) {
            return Err(AcmError::Invalid(format!(
                "length scale must be finite and > 0, got {length_scale}"
            )));
        }
        let per_frame = cameras.len() * skeleton.n_markers() * 2;
        if per_frame == 0 || !labels.len().is_multiple_of(per_frame) {
            return Err(AcmError::Shape(format!(
                "labels: {} values do not form (frames, {} cameras, {} markers, 2)",
                labels.len(),
                cameras.len(),
                skeleton.n_markers()
            )));
        }
        if labels.iter().any(|v| v.is_infinite()) {
            return Err(AcmError::NonFinite(
                "labels contain infinity (use NaN for unlabelled)".into(),
            ));
        }
        let n_frames = labels.len() / per_frame;
        let mut n_labels = 0;
        for (f, frame) in labels.chunks(per_frame).enumerate() {
            let n = frame
                .chunks(2)
                .filter(|p| p[0].is_finite() && p[1].is_finite())
                .count();
            if n < 3 {
                return Err(AcmError::Invalid(format!(
                    "frame {f} has {n} labelled 2D points in total; at least 3 are needed"
                )));
            }
            n_labels += n;
        }
        if let Mode::PosesOnly { lengths, offsets } = &mode {
            ensure_len(lengths.len(), skeleton.n_bones(), "fixed bone lengths")?;
            ensure_len(offsets.len(), skeleton.n_markers(), "fixed marker offsets")?;
        }
        ensure_len(
            sym.bone_source().len(),
            skeleton.n_bones(),
            "symmetry map bones",
        )?;
        ensure_len(
            sym.marker_source().len(),
            skeleton.n_markers(),
            "symmetry map markers",
        )?;
        Ok(Self {
            skeleton,
            cameras,
            norm,
            map,
            sym,
            labels,
            n_frames,
            n_labels,
            length_scale,
            mode,
        })
    }

    /// Number of frames.
    pub fn n_frames(&self) -> usize {
        self.n_frames
    }
    /// Number of labelled 2D points.
    pub fn n_labels(&self) -> usize {
        self.n_labels
    }
    /// Length of the skeleton part of the parameter vector (0 in [`Mode::PosesOnly`]).
    pub fn n_skeleton_params(&self) -> usize {
        match self.mode {
            Mode::Full => self.sym.n_reduced_bones() + 3 * self.sym.n_reduced_markers(),
            Mode::PosesOnly { .. } => 0,
        }
    }
    /// Length of the parameter vector.
    pub fn n_params(&self) -> usize {
        self.n_skeleton_params() + self.n_frames * self.map.n_state()
    }

    fn skeleton_from_params(&self, x: &[f64]) -> Result<(Vec<f64>, Vec<Vector3<f64>>)> {
        match &self.mode {
            Mode::Full => {
                let nb = self.sym.n_reduced_bones();
                let s = self.length_scale;
                let l_red: Vec<f64> = x[..nb].iter().map(|v| v * s).collect();
                let v_red: Vec<f64> = x[nb..self.n_skeleton_params()]
                    .iter()
                    .map(|v| v * s)
                    .collect();
                let lengths = self.sym.expand_lengths(&l_red)?;
                if let Some(b) = lengths.iter().position(|&l| l <= 0.0) {
                    return Err(AcmError::Invalid(format!(
                        "bone {b} has a non-positive length {} (give the optimiser a positive \
                         lower bound)",
                        lengths[b]
                    )));
                }
                let offsets = self
                    .sym
                    .expand_offsets(&v_red)?
                    .chunks(3)
                    .map(|c| Vector3::new(c[0], c[1], c[2]))
                    .collect();
                Ok((lengths, offsets))
            }
            Mode::PosesOnly { lengths, offsets } => Ok((lengths.clone(), offsets.clone())),
        }
    }

    /// One frame's state → `(t, r, ∂pose[free]/∂z)` (Alg. 4 lines 1-3, linear map).
    fn decode(&self, z: &[f64]) -> (Vector3<f64>, Vec<Vector3<f64>>, Vec<f64>) {
        let mut pose = vec![0.0; self.skeleton.n_pose()];
        let mut dz = vec![0.0; z.len()];
        self.map.to_pose_into(z, &mut pose, Some(&mut dz));
        let t = Vector3::new(pose[0], pose[1], pose[2]);
        let r = pose[3..]
            .chunks(3)
            .map(|c| Vector3::new(c[0], c[1], c[2]))
            .collect();
        (t, r, dz)
    }

    /// Objective value and exact gradient (eq. 9/12), in parallel over frames.
    ///
    /// # Errors
    /// Shape error for a wrong parameter length; non-finite error for NaN/inf parameters;
    /// invalid error for non-positive bone lengths.
    pub fn value_grad(&self, x: &[f64]) -> Result<(f64, Vec<f64>)> {
        ensure_len(x.len(), self.n_params(), "parameter vector")?;
        ensure_finite(x, "parameter vector")?;
        let (lengths, offsets) = self.skeleton_from_params(x)?;
        let ns = self.map.n_state();
        let nsk = self.n_skeleton_params();
        let per_frame = self.cameras.len() * self.skeleton.n_markers() * 2;
        let (nb, nm) = (self.skeleton.n_bones(), self.skeleton.n_markers());
        let mut grad = vec![0.0; x.len()];
        let scale = 1.0 / self.n_labels as f64;
        // Per-frame gradients go straight into their slice; the skeleton gradients of the
        // frames are collected in frame order and summed sequentially, so the result does not
        // depend on how rayon split the work (reproducible optimiser paths).
        let per_frame_parts: Vec<(f64, Vec<f64>, Vec<Vector3<f64>>)> = grad[nsk..]
            .par_chunks_mut(ns)
            .zip(x[nsk..].par_chunks(ns))
            .zip(self.labels.par_chunks(per_frame))
            .map(|((gz, z), obs)| {
                let mut gl = vec![0.0; nb];
                let mut gv = vec![Vector3::zeros(); nm];
                let f = self.frame_value_grad(&lengths, &offsets, z, obs, gz, &mut gl, &mut gv);
                (f, gl, gv)
            })
            .collect();
        let mut value = 0.0;
        let mut gl = vec![0.0; nb];
        let mut gv = vec![Vector3::zeros(); nm];
        for (f, l, v) in &per_frame_parts {
            value += f;
            gl.iter_mut().zip(l).for_each(|(a, b)| *a += b);
            gv.iter_mut().zip(v).for_each(|(a, b)| *a += b);
        }
        for g in grad[nsk..].iter_mut() {
            *g *= scale;
        }
        if let Mode::Full = self.mode {
            // Chain through Alg. 2-3 (transposed maps) and the length scale.
            let s = self.length_scale * scale;
            let gl_red = self.sym.reduce_length_grad(&gl)?;
            let gv_flat: Vec<f64> = gv.iter().flat_map(|v| [v.x, v.y, v.z]).collect();
            let gv_red = self.sym.reduce_offset_grad(&gv_flat)?;
            let nrb = self.sym.n_reduced_bones();
            for (dst, g) in grad[..nrb].iter_mut().zip(&gl_red) {
                *dst = g * s;
            }
            for (dst, g) in grad[nrb..nsk].iter_mut().zip(&gv_red) {
                *dst = g * s;
            }
        }
        Ok((value * scale, grad))
    }

    /// Squared-residual sum of one frame; adds `∂/∂z` into `gz` (unscaled) and the skeleton
    /// gradients into `gl`, `gv`.
    #[allow(clippy::too_many_arguments)]
    fn frame_value_grad(
        &self,
        lengths: &[f64],
        offsets: &[Vector3<f64>],
        z: &[f64],
        obs: &[f64],
        gz: &mut [f64],
        gl: &mut [f64],
        gv: &mut [Vector3<f64>],
    ) -> f64 {
        let sk = &self.skeleton;
        let nm = sk.n_markers();
        let (t, r, dz) = self.decode(z);
        let fk = sk.forward_unchecked(&t, &r, lengths, offsets);
        let mut value = 0.0;
        let mut g = vec![Vector3::zeros(); nm];
        let (c1, c2) = (self.norm.pixel[0], self.norm.pixel[1]);
        for (ci, cam) in self.cameras.iter().enumerate() {
            for (k, m) in fk.markers.iter().enumerate() {
                let o = &obs[(ci * nm + k) * 2..(ci * nm + k) * 2 + 2];
                if !(o[0].is_finite() && o[1].is_finite()) {
                    continue;
                }
                match cam.project_jacobian(m) {
                    Some(j) => {
                        let (ru, rv) = ((j.pixel.x - o[0]) / c1, (j.pixel.y - o[1]) / c2);
                        value += ru * ru + rv * rv;
                        let dpx = nalgebra::Vector2::new(2.0 * ru / c1, 2.0 * rv / c2);
                        g[k] += j.d_point.transpose() * dpx;
                    }
                    None => {
                        // A labelled marker behind a camera: a constant penalty of one
                        // normalised image (no gradient; the other views pull it back).
                        value += 4.0;
                    }
                }
            }
        }
        let (dp, dl, dv) = sk.markers_vjp(&fk, &r, &g);
        for (i, &idx) in self.map.free_indices().iter().enumerate() {
            gz[i] = dp[idx] * dz[i];
        }
        for (a, b) in gl.iter_mut().zip(&dl) {
            *a += b;
        }
        for (a, b) in gv.iter_mut().zip(&dv) {
            *a += b;
        }
        value
    }

    /// Diagonal of the Gauss-Newton matrix `JᵀJ` of the (unscaled, summed) residuals at `x`:
    /// one value per parameter, used to precondition L-BFGS-B (variables rescaled so that every
    /// diagonal entry is 1). For mirrored reduced parameters the copies' squares are summed.
    ///
    /// # Errors
    /// As [`LearningProblem::value_grad`].
    pub fn gauss_newton_diagonal(&self, x: &[f64]) -> Result<Vec<f64>> {
        ensure_len(x.len(), self.n_params(), "parameter vector")?;
        ensure_finite(x, "parameter vector")?;
        let (lengths, offsets) = self.skeleton_from_params(x)?;
        let sk = &self.skeleton;
        let (nb, nm, np) = (sk.n_bones(), sk.n_markers(), sk.n_pose());
        let ns = self.map.n_state();
        let nsk = self.n_skeleton_params();
        let per_frame = self.cameras.len() * nm * 2;
        let (c1, c2) = (self.norm.pixel[0], self.norm.pixel[1]);
        let mut diag = vec![0.0; x.len()];
        let (dl, dv) = diag[nsk..]
            .par_chunks_mut(ns)
            .zip(x[nsk..].par_chunks(ns))
            .zip(self.labels.par_chunks(per_frame))
            .map(|((dz_out, z), obs)| {
                let (t, r, dz) = self.decode(z);
                let jac = sk
                    .forward_jacobian(&t, &r, Some(&lengths), Some(&offsets))
                    .expect("validated inputs");
                let nj = sk.n_joints();
                let mut dpose = vec![0.0; np];
                let mut dl = vec![0.0; nb];
                let mut dv = vec![0.0; 3 * nm];
                for (ci, cam) in self.cameras.iter().enumerate() {
                    for k in 0..nm {
                        let o = &obs[(ci * nm + k) * 2..(ci * nm + k) * 2 + 2];
                        if !(o[0].is_finite() && o[1].is_finite()) {
                            continue;
                        }
                        let Some(pj) = cam.project_jacobian(&jac.fk.markers[k]) else {
                            continue;
                        };
                        let row = |a: usize| 3 * (nj + k) + a;
                        for (u, c) in [(0, c1), (1, c2)] {
                            let dp = pj.d_point.row(u) / c;
                            for (col, acc) in dpose.iter_mut().enumerate() {
                                let v: f64 =
                                    (0..3).map(|a| dp[a] * jac.d_pose[row(a) * np + col]).sum();
                                *acc += v * v;
                            }
                            for (b, acc) in dl.iter_mut().enumerate() {
                                let v: f64 =
                                    (0..3).map(|a| dp[a] * jac.d_lengths[row(a) * nb + b]).sum();
                                *acc += v * v;
                            }
                            for cc in 0..3 {
                                let v: f64 = (0..3)
                                    .map(|a| dp[a] * jac.d_offsets[9 * k + 3 * a + cc])
                                    .sum();
                                dv[3 * k + cc] += v * v;
                            }
                        }
                    }
                }
                for (i, &idx) in self.map.free_indices().iter().enumerate() {
                    dz_out[i] = dpose[idx] * dz[i] * dz[i];
                }
                (dl, dv)
            })
            .collect::<Vec<_>>()
            .into_iter()
            .fold((vec![0.0; nb], vec![0.0; 3 * nm]), |mut a, b| {
                a.0.iter_mut().zip(&b.0).for_each(|(x, y)| *x += y);
                a.1.iter_mut().zip(&b.1).for_each(|(x, y)| *x += y);
                a
            });
        if let Mode::Full = self.mode {
            let s2 = self.length_scale * self.length_scale;
            let nrb = self.sym.n_reduced_bones();
            for (b, &src) in self.sym.bone_source().iter().enumerate() {
                diag[src] += dl[b] * s2;
            }
            for (k, &(src, _)) in self.sym.marker_source().iter().enumerate() {
                for c in 0..3 {
                    diag[nrb + 3 * src + c] += dv[3 * k + c] * s2;
                }
            }
        }
        Ok(diag)
    }

    /// Normalised residuals of one frame's labelled points and their Jacobian with respect to
    /// the frame's state `z` (rows: u and v of each label; columns: state entries), followed by
    /// one column per bone of `stretch_bones`: the derivative with respect to that bone's
    /// log-length, `l_b ∂x/∂l_b` (the elastic segments of [`elastic`]).
    pub(crate) fn frame_residual_jacobian(
        &self,
        lengths: &[f64],
        offsets: &[Vector3<f64>],
        z: &[f64],
        obs: &[f64],
        stretch_bones: &[usize],
    ) -> (Vec<f64>, DMatrix<f64>) {
        let sk = &self.skeleton;
        let (nm, np, nz) = (sk.n_markers(), sk.n_pose(), z.len());
        let (nb, ns) = (sk.n_bones(), nz + stretch_bones.len());
        let (t, r, dz) = self.decode(z);
        let jac = sk
            .forward_jacobian(&t, &r, Some(lengths), Some(offsets))
            .expect("validated inputs");
        let nj = sk.n_joints();
        let (c1, c2) = (self.norm.pixel[0], self.norm.pixel[1]);
        let mut res = Vec::new();
        let mut rows: Vec<f64> = Vec::new();
        for (ci, cam) in self.cameras.iter().enumerate() {
            for k in 0..nm {
                let o = &obs[(ci * nm + k) * 2..(ci * nm + k) * 2 + 2];
                if !(o[0].is_finite() && o[1].is_finite()) {
                    continue;
                }
                let Some(pj) = cam.project_jacobian(&jac.fk.markers[k]) else {
                    continue; // behind the camera: no usable residual at this pose
                };
                for (u, c) in [(0, c1), (1, c2)] {
                    res.push((pj.pixel[u] - o[u]) / c);
                    let dp = pj.d_point.row(u) / c;
                    for (i, &idx) in self.map.free_indices().iter().enumerate() {
                        let v: f64 = (0..3)
                            .map(|a| dp[a] * jac.d_pose[(3 * (nj + k) + a) * np + idx])
                            .sum();
                        rows.push(v * dz[i]);
                    }
                    for &b in stretch_bones {
                        let v: f64 = (0..3)
                            .map(|a| dp[a] * jac.d_lengths[(3 * (nj + k) + a) * nb + b])
                            .sum();
                        rows.push(v * lengths[b]);
                    }
                }
            }
        }
        let n = res.len();
        (res, DMatrix::from_row_slice(n, ns, &rows))
    }

    /// Box-constrained Levenberg-Marquardt on every frame's pose (in parallel), with the
    /// skeleton part of `x` held fixed: a fast per-frame solver of eq. 9 for initialisation
    /// (steps are projected onto `[lower, upper]`, per state entry). Returns the new `x` and
    /// the number of iterations per frame.
    ///
    /// # Errors
    /// As [`LearningProblem::value_grad`], plus shape errors for the bounds.
    pub fn fit_poses_lm(
        &self,
        x: &[f64],
        lower: &[f64],
        upper: &[f64],
        max_iter: usize,
    ) -> Result<(Vec<f64>, Vec<usize>)> {
        ensure_len(x.len(), self.n_params(), "parameter vector")?;
        ensure_finite(x, "parameter vector")?;
        let ns = self.map.n_state();
        ensure_len(lower.len(), ns, "lower state bounds")?;
        ensure_len(upper.len(), ns, "upper state bounds")?;
        let (lengths, offsets) = self.skeleton_from_params(x)?;
        let nsk = self.n_skeleton_params();
        let per_frame = self.cameras.len() * self.skeleton.n_markers() * 2;
        let mut out = x.to_vec();
        let iters: Vec<usize> = out[nsk..]
            .par_chunks_mut(ns)
            .zip(self.labels.par_chunks(per_frame))
            .map(|(z, obs)| {
                damped_lm(z, lower, upper, max_iter, |z| {
                    self.frame_residual_jacobian(&lengths, &offsets, z, obs, &[])
                })
            })
            .collect();
        Ok((out, iters))
    }

    /// Reprojections and the decoded skeleton/poses of a parameter vector.
    ///
    /// # Errors
    /// As [`LearningProblem::value_grad`].
    pub fn residuals(&self, x: &[f64]) -> Result<Residuals> {
        ensure_len(x.len(), self.n_params(), "parameter vector")?;
        ensure_finite(x, "parameter vector")?;
        let (lengths, offsets) = self.skeleton_from_params(x)?;
        let ns = self.map.n_state();
        let nsk = self.n_skeleton_params();
        let per_frame = self.cameras.len() * self.skeleton.n_markers() * 2;
        let np = self.skeleton.n_pose();
        let mut projected = vec![0.0; self.n_frames * per_frame];
        let mut poses = vec![0.0; self.n_frames * np];
        projected
            .par_chunks_mut(per_frame)
            .zip(poses.par_chunks_mut(np))
            .zip(x[nsk..].par_chunks(ns))
            .for_each(|((px, pose), z)| {
                self.map.to_pose_into(z, pose, None);
                let t = Vector3::new(pose[0], pose[1], pose[2]);
                let r: Vec<Vector3<f64>> = pose[3..]
                    .chunks(3)
                    .map(|c| Vector3::new(c[0], c[1], c[2]))
                    .collect();
                let fk = self.skeleton.forward_unchecked(&t, &r, &lengths, &offsets);
                let nm = fk.markers.len();
                for (ci, cam) in self.cameras.iter().enumerate() {
                    for (k, m) in fk.markers.iter().enumerate() {
                        let o = &mut px[(ci * nm + k) * 2..(ci * nm + k) * 2 + 2];
                        let uv = cam.project(m);
                        o[0] = uv.map_or(f64::NAN, |p| p.x);
                        o[1] = uv.map_or(f64::NAN, |p| p.y);
                    }
                }
            });
        Ok(Residuals {
            projected,
            lengths,
            offsets: offsets.iter().flat_map(|v| [v.x, v.y, v.z]).collect(),
            poses,
        })
    }
}

/// Levenberg-Marquardt on one small least-squares problem `min ‖r(w)‖²`, steps projected onto
/// the box `[lower, upper]` (per entry): `f(w)` returns the residuals and their Jacobian
/// (rows × entries). Marquardt's diagonal damping, λ ÷ 3 after a successful step and × 4 after
/// a failed one; stops after `max_iter` iterations or when a step no longer lowers the cost.
/// Returns the number of iterations.
pub(crate) fn damped_lm<F>(
    w: &mut [f64],
    lower: &[f64],
    upper: &[f64],
    max_iter: usize,
    f: F,
) -> usize
where
    F: Fn(&[f64]) -> (Vec<f64>, DMatrix<f64>),
{
    let n = w.len();
    let clip = |v: &mut [f64]| {
        for (i, e) in v.iter_mut().enumerate() {
            *e = e.clamp(lower[i], upper[i]);
        }
    };
    clip(w);
    let sum_sq = |r: &[f64]| -> f64 { r.iter().map(|v| v * v).sum() };
    let mut lambda = 1e-3;
    let mut it = 0;
    // the residuals and Jacobian at `w`: an accepted trial's are kept for the next iteration
    // (one evaluation per accepted step instead of two; the same iterates bit for bit)
    let mut here = f(w);
    while it < max_iter {
        it += 1;
        let (r, j) = &here;
        let c0 = sum_sq(r);
        let jtj = j.transpose() * j;
        let jtr = j.transpose() * DVector::from_column_slice(r);
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj.clone();
            for d in 0..n {
                a[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
            }
            let Some(ch) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = ch.solve(&(-&jtr));
            let mut trial: Vec<f64> = w.iter().zip(step.iter()).map(|(a, b)| a + b).collect();
            clip(&mut trial);
            let at_trial = f(&trial);
            let c1 = sum_sq(&at_trial.0);
            if c1 < c0 {
                let rel = (c0 - c1) / c0.max(1e-300);
                w.copy_from_slice(&trial);
                here = at_trial;
                lambda = (lambda / 3.0).max(1e-9);
                improved = rel > 1e-12;
                break;
            }
            lambda *= 4.0;
        }
        if !improved {
            break;
        }
    }
    it
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::tests::branching;

    fn rig() -> Vec<Camera> {
        let mk = |r: [f64; 3], t: [f64; 3]| {
            Camera::from_params(&[
                r[0], r[1], r[2], t[0], t[1], t[2], 900.0, 900.0, 640.0, 512.0, -0.05, 0.01, 0.0,
                0.0, 0.0,
            ])
            .unwrap()
        };
        vec![
            mk([0.0, 0.0, 0.0], [0.0, 0.0, 15.0]),
            mk([0.0, 1.2, 0.0], [0.3, 0.0, 16.0]),
            mk([0.9, 0.0, 0.0], [0.0, 0.2, 14.0]),
        ]
    }

    pub(super) fn problem(mode: Mode) -> (LearningProblem, Vec<f64>) {
        let sk = branching();
        let cams = rig();
        let nb = sk.n_bones();
        let inf = f64::INFINITY;
        let norm = Normalization::default();
        let map = StateMap::new(nb, &vec![-inf; 3 * nb], &vec![inf; 3 * nb], &norm, false).unwrap();
        // bones 1 (1→2) and 3 (1→4) mirror; markers 2 and 3 mirror.
        let sym = SymmetryMap::new(nb, &[(1, 3)], sk.n_markers(), &[(2, 3)]).unwrap();
        let n_frames = 3;
        let nm = sk.n_markers();
        let mut labels = vec![f64::NAN; n_frames * cams.len() * nm * 2];
        for (i, v) in labels.iter_mut().enumerate() {
            if (i / 2) % 5 != 3 {
                *v = 500.0 + ((i * 37) % 101) as f64;
            }
        }
        let p = LearningProblem::new(sk.clone(), cams, norm, map, sym, labels, 1.0, mode).unwrap();
        let mut x: Vec<f64> = (0..p.n_params())
            .map(|i| 0.2 * (((i * 7919) % 13) as f64 / 13.0 - 0.5))
            .collect();
        let nsk = p.n_skeleton_params();
        for v in x[..nsk].iter_mut() {
            *v += 1.0; // positive lengths
        }
        (p, x)
    }

    #[test]
    fn gradient_matches_central_differences() {
        let sk = branching();
        for mode in [
            Mode::Full,
            Mode::PosesOnly {
                lengths: sk.lengths().to_vec(),
                offsets: sk.offsets().to_vec(),
            },
        ] {
            let (p, x) = problem(mode);
            let (_, g) = p.value_grad(&x).unwrap();
            let h = 1e-6;
            for i in 0..x.len() {
                let mut xp = x.clone();
                let mut xm = x.clone();
                xp[i] += h;
                xm[i] -= h;
                let fd = (p.value_grad(&xp).unwrap().0 - p.value_grad(&xm).unwrap().0) / (2.0 * h);
                assert!(
                    (fd - g[i]).abs() < 1e-6 * (1.0 + fd.abs()),
                    "param {i}: fd {fd} vs {}",
                    g[i]
                );
            }
        }
    }

    #[test]
    fn gauss_newton_diagonal_matches_jacobian_columns() {
        // diag_i = Σ_rows (∂res/∂x_i)², with residual vectors from `residuals` (normalised).
        let (p, x) = problem(Mode::Full);
        let diag = p.gauss_newton_diagonal(&x).unwrap();
        let norm = Normalization::default();
        let res = |x: &[f64]| -> Vec<f64> {
            let r = p.residuals(x).unwrap();
            r.projected
                .iter()
                .zip(&p.labels)
                .enumerate()
                .filter(|(_, (_, o))| o.is_finite())
                .map(|(i, (a, _))| a / norm.pixel[i % 2])
                .collect()
        };
        let h = 1e-6;
        for i in 0..x.len() {
            let mut xp = x.clone();
            let mut xm = x.clone();
            xp[i] += h;
            xm[i] -= h;
            let col: f64 = res(&xp)
                .iter()
                .zip(res(&xm))
                .map(|(a, b)| ((a - b) / (2.0 * h)).powi(2))
                .sum();
            assert!(
                (col - diag[i]).abs() < 1e-5 * (1.0 + col),
                "param {i}: {col} vs {}",
                diag[i]
            );
        }
    }

    #[test]
    fn levenberg_marquardt_recovers_poses() {
        // Labels made from known poses (no noise): LM from a perturbed start finds them.
        let sk = branching();
        let cams = rig();
        let nb = sk.n_bones();
        let inf = f64::INFINITY;
        let norm = Normalization::default();
        let map = StateMap::new(nb, &vec![-inf; 3 * nb], &vec![inf; 3 * nb], &norm, false).unwrap();
        let ns = map.n_state();
        let truth: Vec<f64> = (0..2 * ns)
            .map(|i| 0.3 * (((i * 31) % 17) as f64 / 17.0 - 0.5))
            .collect();
        let mut labels = Vec::new();
        for z in truth.chunks(ns) {
            let pose = map.to_pose(z).unwrap();
            let px = crate::emission::project_poses(&sk, &cams, &pose[..3], &pose[3..]).unwrap();
            labels.extend(px);
        }
        let sym = SymmetryMap::new(nb, &[], sk.n_markers(), &[]).unwrap();
        let mode = Mode::PosesOnly {
            lengths: sk.lengths().to_vec(),
            offsets: sk.offsets().to_vec(),
        };
        let p = LearningProblem::new(sk, cams, norm, map, sym, labels, 1.0, mode).unwrap();
        let start: Vec<f64> = truth
            .iter()
            .enumerate()
            .map(|(i, v)| v + 0.05 * ((i % 3) as f64 - 1.0))
            .collect();
        let (fit, iters) = p
            .fit_poses_lm(&start, &vec![-inf; ns], &vec![inf; ns], 100)
            .unwrap();
        assert!(iters.iter().all(|&n| n < 100));
        // Some rotations of this toy skeleton are unobservable (twists of bones whose markers
        // lie on their axis), so the labels, not the states, are what must be reproduced.
        assert!(p.value_grad(&start).unwrap().0 > 1e-6);
        assert!(p.value_grad(&fit).unwrap().0 < 1e-18);
    }

    #[test]
    fn value_is_mean_squared_normalised_residual() {
        let (p, x) = problem(Mode::Full);
        let res = p.residuals(&x).unwrap();
        let norm = Normalization::default();
        let mut sum = 0.0;
        let mut n = 0;
        for (i, (a, b)) in res.projected.iter().zip(&p.labels).enumerate() {
            if b.is_finite() {
                let d = (a - b) / norm.pixel[i % 2];
                sum += d * d;
                n += 1;
            }
        }
        assert_eq!(n, 2 * p.n_labels());
        assert!((p.value_grad(&x).unwrap().0 - sum / p.n_labels() as f64).abs() < 1e-12);
        // Symmetric bones share a length.
        assert_eq!(res.lengths[1], res.lengths[3]);
    }

    #[test]
    fn bad_labels_are_rejected() {
        let sk = branching();
        let cams = rig();
        let nb = sk.n_bones();
        let norm = Normalization::default();
        let inf = f64::INFINITY;
        let map = StateMap::new(nb, &vec![-inf; 3 * nb], &vec![inf; 3 * nb], &norm, false).unwrap();
        let sym = SymmetryMap::new(nb, &[], sk.n_markers(), &[]).unwrap();
        let n = cams.len() * sk.n_markers() * 2;
        let mut labels = vec![f64::NAN; n];
        labels[0] = 1.0;
        labels[1] = 2.0;
        let err = LearningProblem::new(
            sk.clone(),
            cams.clone(),
            norm,
            map.clone(),
            sym.clone(),
            labels,
            1.0,
            Mode::Full,
        )
        .unwrap_err();
        assert!(matches!(err, AcmError::Invalid(ref s) if s.contains("frame 0 has 1")));
        let err = LearningProblem::new(sk, cams, norm, map, sym, vec![0.0; n + 1], 1.0, Mode::Full)
            .unwrap_err();
        assert!(matches!(err, AcmError::Shape(_)));
    }

    /// `damped_lm` on Rosenbrock's function as least squares (`r = (10 (y − x²), 1 − x)`):
    /// it reaches the minimum (1, 1), keeps the box, and evaluates `f` once per trial step
    /// and once at the start (an accepted trial's residuals and Jacobian are reused).
    #[test]
    fn damped_lm_reuses_the_accepted_trials_evaluation() {
        let calls = std::cell::Cell::new(0usize);
        let f = |w: &[f64]| {
            calls.set(calls.get() + 1);
            let r = vec![10.0 * (w[1] - w[0] * w[0]), 1.0 - w[0]];
            let j = DMatrix::from_row_slice(2, 2, &[-20.0 * w[0], 10.0, -1.0, 0.0]);
            (r, j)
        };
        let mut w = [-1.2, 1.0];
        let inf = f64::INFINITY;
        let it = damped_lm(&mut w, &[-inf, -inf], &[inf, inf], 200, f);
        assert!(
            (w[0] - 1.0).abs() < 1e-6 && (w[1] - 1.0).abs() < 1e-6,
            "{w:?} after {it}"
        );
        // every iteration tries at least one step; only failed trials add evaluations
        assert!(calls.get() > it && calls.get() <= 1 + 10 * it);
        let mut boxed = [-1.2, 1.0];
        let it_box = damped_lm(&mut boxed, &[-inf, -inf], &[0.5, inf], 200, f);
        assert!(boxed[0] <= 0.5 && it_box > 0, "{boxed:?}");
        // the old loop evaluated f twice per iteration (its Jacobian at the trial unused):
        // the same problem from the same start needs fewer evaluations than 2 × iterations
        calls.set(0);
        let mut again = [-1.2, 1.0];
        let it2 = damped_lm(&mut again, &[-inf, -inf], &[inf, inf], 200, f);
        assert_eq!((it2, again), (it, w));
        assert!(
            calls.get() < 2 * it2,
            "{} evaluations for {it2} iterations",
            calls.get()
        );
    }
}
