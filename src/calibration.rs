//! Multi-camera calibration objective (ACM supp. section 2.2, eq. 7) with its exact sparse
//! Jacobian.
//!
//! Eq. 7 sums, over board views `τ`, cameras `i` and detected board corners `j`, the squared
//! pixel distance between the detection `m_τij` and the projection (eq. 4) of the board corner
//! `R(r̂_τ) m̂_j + t̂_τ` into camera `i`. This module evaluates the residual vector of that sum
//! (one `(u, v)` pair per detection, in pixels) and its Jacobian as a CSR matrix whose sparsity
//! pattern is fixed at construction, so that a trust-region solver (scipy's
//! `least_squares(method="trf")`) receives `(data, indices, indptr)` without any reshuffling.
//!
//! # Parameter layout
//! The full parameter vector is
//! `[camera 0 | camera 1 | … | camera C−1 | board view 0 | … | board view F−1]` with
//! [`N_CAM_PARAMS`] = 13 entries per camera `[fx, fy, cx, cy, k1, k2, rx, ry, rz, tx, ty, tz, s]`
//! (the paper's camera model: radial `k1, k2` only, eq. 5; the skew `s` of MATLAB's model,
//! usually held fixed at 0 as OpenCV's calibration does) and [`N_VIEW_PARAMS`] = 6 per board
//! view `[rx, ry, rz, tx, ty, tz]` (board → world). A boolean mask marks fixed parameters; the
//! reference camera's `r, t` (the world frame), board views without any detection, and anything
//! the caller fixes (e.g. known intrinsics) are held at their initial values. The solver sees
//! only the free entries, in layout order.
//!
//! # Work split
//! Residuals and Jacobian values are computed in parallel over (camera, view) pairs with rayon;
//! each pair owns a contiguous slice of the residual vector and of the CSR data array.

use crate::camera::{param, Camera, N_PARAMS};
use crate::error::{ensure_finite, ensure_len, AcmError, Result};
use crate::rotation::rodrigues_jacobian;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

/// Parameters per camera in the calibration layout: `[fx, fy, cx, cy, k1, k2, r(3), t(3), s]`.
pub const N_CAM_PARAMS: usize = 13;
/// Position of the skew in a camera's calibration block.
pub const CAM_SKEW: usize = 12;
/// Parameters per board view: `[r(3), t(3)]` of the board → world transform.
pub const N_VIEW_PARAMS: usize = 6;
/// Residual (px, both coordinates) reported for a detection whose board corner lies at or
/// behind the camera plane. It makes such a trial step expensive, so the trust-region solver
/// rejects it; the Jacobian rows of such detections are zero.
pub const BEHIND_PENALTY: f64 = 1.0e5;

/// Position of calibration-layout camera entry `k` in [`Camera`]'s parameter vector.
const CAM_TO_CAMERA: [usize; N_CAM_PARAMS] = [
    param::FX,
    param::FY,
    param::CX,
    param::CY,
    param::DIST,
    param::DIST + 1,
    param::RVEC,
    param::RVEC + 1,
    param::RVEC + 2,
    param::TVEC,
    param::TVEC + 1,
    param::TVEC + 2,
    param::SKEW,
];

/// Board → world rotation, its derivatives `∂R/∂r_k` and the translation of one view.
type ViewPose = (Matrix3<f64>, [Matrix3<f64>; 3], Vector3<f64>);

/// Detections of one camera in one board view: observations `start..end` (in the order of
/// [`CalibrationProblem::observation_index`]).
#[derive(Debug, Clone)]
struct View {
    cam: usize,
    frame: usize,
    start: usize,
    end: usize,
    /// Free columns of this view's rows (camera block first, then board-view block).
    cols: Vec<i32>,
    /// Layout positions (full vector) of `cols`, as (is_camera, offset within block).
    blocks: Vec<(bool, usize)>,
    /// Offset of this view's first entry in the CSR data array.
    data_start: usize,
}

/// Eq. 7 for a fixed set of detections: residuals and exact sparse Jacobian.
#[derive(Debug, Clone)]
pub struct CalibrationProblem {
    n_cams: usize,
    n_frames: usize,
    board: Vec<Vector3<f64>>,
    /// Observed pixels `(u, v)` per observation.
    observed: Vec<[f64; 2]>,
    /// Board point index per observation.
    point: Vec<usize>,
    /// Flat index `(cam · F + frame) · P + point` per observation.
    flat_index: Vec<usize>,
    views: Vec<View>,
    /// Initial full parameter vector (fixed entries keep these values).
    base: Vec<f64>,
    /// Full-layout indices of the free parameters, ascending.
    free: Vec<usize>,
    indptr: Vec<i32>,
    indices: Vec<i32>,
}

fn cam_offset(c: usize) -> usize {
    c * N_CAM_PARAMS
}

impl CalibrationProblem {
    /// Builds the problem.
    ///
    /// # Arguments
    /// * `n_cams`, `n_frames` - numbers of cameras `C` and board views `F`.
    /// * `board` - flat `(P, 3)` board corners in board units (typically `z = 0`).
    /// * `corners` - flat `(C, F, P, 2)` detected pixels; NaN (in either coordinate) marks a
    ///   corner that was not detected.
    /// * `reference` - the camera whose `r, t` define the world frame (held fixed).
    /// * `params0` - full initial parameter vector (`13 C + 6 F`, layout in the module docs).
    /// * `fixed` - full-length mask of parameters to hold at their initial values.
    ///
    /// # Errors
    /// Shape errors for inconsistent lengths; non-finite errors for infinite corners or
    /// non-finite board points/parameters; invalid errors for a reference index out of range,
    /// non-positive focal lengths, a camera without any detection, or a problem with no free
    /// parameter.
    pub fn new(
        n_cams: usize,
        n_frames: usize,
        board: &[f64],
        corners: &[f64],
        reference: usize,
        params0: &[f64],
        fixed: &[bool],
    ) -> Result<Self> {
        if n_cams == 0 || n_frames == 0 {
            return Err(AcmError::Shape(format!(
                "need at least one camera and one board view, got {n_cams} and {n_frames}"
            )));
        }
        if board.is_empty() || !board.len().is_multiple_of(3) {
            return Err(AcmError::Shape(format!(
                "board points: {} values is not a positive multiple of 3",
                board.len()
            )));
        }
        ensure_finite(board, "board points")?;
        let n_points = board.len() / 3;
        ensure_len(
            corners.len(),
            n_cams * n_frames * n_points * 2,
            "corners (n_cams, n_frames, n_points, 2)",
        )?;
        if let Some(i) = corners.iter().position(|v| v.is_infinite()) {
            return Err(AcmError::NonFinite(format!(
                "corners: infinite value at camera {}, view {}, point {} (use NaN for \
                 undetected corners)",
                i / 2 / n_points / n_frames,
                (i / 2 / n_points) % n_frames,
                (i / 2) % n_points
            )));
        }
        let n_full = N_CAM_PARAMS * n_cams + N_VIEW_PARAMS * n_frames;
        ensure_len(params0.len(), n_full, "initial parameter vector")?;
        ensure_len(fixed.len(), n_full, "fixed-parameter mask")?;
        ensure_finite(params0, "initial parameters")?;
        if reference >= n_cams {
            return Err(AcmError::Invalid(format!(
                "reference camera {reference} is out of range for {n_cams} cameras"
            )));
        }
        for c in 0..n_cams {
            let (fx, fy) = (params0[cam_offset(c)], params0[cam_offset(c) + 1]);
            if fx <= 0.0 || fy <= 0.0 {
                return Err(AcmError::Invalid(format!(
                    "camera {c}: focal lengths must be positive, got fx={fx}, fy={fy}"
                )));
            }
        }
        let board: Vec<Vector3<f64>> = board
            .chunks_exact(3)
            .map(|p| Vector3::new(p[0], p[1], p[2]))
            .collect();

        // Observations in (camera, frame, point) order.
        let mut observed = Vec::new();
        let mut point = Vec::new();
        let mut flat_index = Vec::new();
        let mut raw_views = Vec::new();
        let mut frame_seen = vec![false; n_frames];
        let mut cam_seen = vec![false; n_cams];
        for c in 0..n_cams {
            for f in 0..n_frames {
                let start = observed.len();
                for (j, _) in board.iter().enumerate() {
                    let flat = (c * n_frames + f) * n_points + j;
                    let (u, v) = (corners[2 * flat], corners[2 * flat + 1]);
                    if u.is_nan() || v.is_nan() {
                        continue;
                    }
                    observed.push([u, v]);
                    point.push(j);
                    flat_index.push(flat);
                }
                if observed.len() > start {
                    raw_views.push((c, f, start, observed.len()));
                }
            }
        }
        for &(c, f, _, _) in &raw_views {
            cam_seen[c] = true;
            frame_seen[f] = true;
        }
        if let Some(c) = cam_seen.iter().position(|s| !s) {
            return Err(AcmError::Invalid(format!(
                "camera {c} has no detected board corner in any view"
            )));
        }

        // Free mask: caller's mask, plus the reference pose and views nobody saw.
        let mut is_fixed = fixed.to_vec();
        for k in 6..CAM_SKEW {
            is_fixed[cam_offset(reference) + k] = true;
        }
        for (f, seen) in frame_seen.iter().enumerate() {
            if !seen {
                let o = N_CAM_PARAMS * n_cams + N_VIEW_PARAMS * f;
                is_fixed[o..o + N_VIEW_PARAMS].fill(true);
            }
        }
        let free: Vec<usize> = (0..n_full).filter(|&i| !is_fixed[i]).collect();
        if free.is_empty() {
            return Err(AcmError::Invalid("every parameter is fixed".into()));
        }
        if free.len() > i32::MAX as usize {
            return Err(AcmError::Invalid("too many parameters".into()));
        }
        let mut column = vec![-1i32; n_full];
        for (k, &i) in free.iter().enumerate() {
            column[i] = k as i32;
        }

        // Fixed CSR pattern: every row of a view has the view's free columns.
        let n_rows = 2 * observed.len();
        let mut indptr = Vec::with_capacity(n_rows + 1);
        let mut indices = Vec::new();
        indptr.push(0i32);
        let mut views = Vec::with_capacity(raw_views.len());
        for (cam, frame, start, end) in raw_views {
            let mut cols = Vec::new();
            let mut blocks = Vec::new();
            for k in 0..N_CAM_PARAMS {
                let col = column[cam_offset(cam) + k];
                if col >= 0 {
                    cols.push(col);
                    blocks.push((true, k));
                }
            }
            let vo = N_CAM_PARAMS * n_cams + N_VIEW_PARAMS * frame;
            for k in 0..N_VIEW_PARAMS {
                let col = column[vo + k];
                if col >= 0 {
                    cols.push(col);
                    blocks.push((false, k));
                }
            }
            let data_start = indices.len();
            for _ in 0..2 * (end - start) {
                indices.extend_from_slice(&cols);
                let nnz = i32::try_from(indices.len()).map_err(|_| {
                    AcmError::Invalid("Jacobian has more than 2^31 non-zeros".into())
                })?;
                indptr.push(nnz);
            }
            views.push(View {
                cam,
                frame,
                start,
                end,
                cols,
                blocks,
                data_start,
            });
        }
        Ok(Self {
            n_cams,
            n_frames,
            board,
            observed,
            point,
            flat_index,
            views,
            base: params0.to_vec(),
            free,
            indptr,
            indices,
        })
    }

    /// Number of cameras `C`.
    pub fn n_cams(&self) -> usize {
        self.n_cams
    }

    /// Number of board views `F`.
    pub fn n_frames(&self) -> usize {
        self.n_frames
    }

    /// Length of the full parameter vector, `13 C + 6 F`.
    pub fn n_full(&self) -> usize {
        self.base.len()
    }

    /// Number of free parameters (the solver's unknowns).
    pub fn n_free(&self) -> usize {
        self.free.len()
    }

    /// Number of detections (observations); the residual vector has twice as many entries.
    pub fn n_observations(&self) -> usize {
        self.observed.len()
    }

    /// Full-layout indices of the free parameters, ascending.
    pub fn free_indices(&self) -> &[usize] {
        &self.free
    }

    /// Flat index `(cam · F + frame) · P + point` of each observation, ascending: residual
    /// rows `2k, 2k+1` belong to observation `k`.
    pub fn observation_index(&self) -> &[usize] {
        &self.flat_index
    }

    /// CSR row pointer of the Jacobian (`2 n_obs + 1` entries).
    pub fn indptr(&self) -> &[i32] {
        &self.indptr
    }

    /// CSR column indices of the Jacobian (sorted within each row).
    pub fn indices(&self) -> &[i32] {
        &self.indices
    }

    /// Number of stored Jacobian entries.
    pub fn nnz(&self) -> usize {
        self.indices.len()
    }

    /// The full parameter vector with the free entries replaced by `x`.
    ///
    /// # Errors
    /// Shape error if `x.len() != n_free`; non-finite error for NaN/inf.
    pub fn full_params(&self, x: &[f64]) -> Result<Vec<f64>> {
        ensure_len(x.len(), self.free.len(), "free parameter vector")?;
        ensure_finite(x, "free parameters")?;
        let mut full = self.base.clone();
        for (&i, &v) in self.free.iter().zip(x) {
            full[i] = v;
        }
        Ok(full)
    }

    /// Cameras (the model with `p1 = p2 = k3 = 0`) from a full parameter vector.
    fn cameras(&self, full: &[f64]) -> Result<Vec<Camera>> {
        (0..self.n_cams)
            .map(|c| {
                let block = &full[cam_offset(c)..cam_offset(c) + N_CAM_PARAMS];
                let mut p = [0.0; N_PARAMS];
                for (k, &dst) in CAM_TO_CAMERA.iter().enumerate() {
                    p[dst] = block[k];
                }
                Camera::from_params(&p).map_err(|e| match e {
                    AcmError::Invalid(s) => AcmError::Numerical(format!("camera {c}: {s}")),
                    other => other,
                })
            })
            .collect()
    }

    /// Board → world rotation, its derivatives and translation of every view.
    fn poses(&self, full: &[f64]) -> Vec<ViewPose> {
        let o = N_CAM_PARAMS * self.n_cams;
        full[o..]
            .chunks_exact(N_VIEW_PARAMS)
            .map(|v| {
                let (rot, d) = rodrigues_jacobian(&Vector3::new(v[0], v[1], v[2]));
                (rot, d, Vector3::new(v[3], v[4], v[5]))
            })
            .collect()
    }

    /// Residuals of eq. 7, `projection − detection` in pixels, for the free parameters `x`,
    /// written into `out` (`2 n_obs` entries, rows ordered as [`Self::observation_index`]).
    ///
    /// Returns the number of detections whose board corner lies at or behind its camera; their
    /// residuals are [`BEHIND_PENALTY`].
    ///
    /// # Errors
    /// Shape/non-finite errors for `x` or `out`; numerical error if a focal length became
    /// non-positive.
    pub fn residuals_into(&self, x: &[f64], out: &mut [f64]) -> Result<usize> {
        ensure_len(out.len(), 2 * self.observed.len(), "residual buffer")?;
        let full = self.full_params(x)?;
        let cams = self.cameras(&full)?;
        let poses = self.poses(&full);
        let chunks = split_by(out, self.views.iter().map(|v| 2 * (v.end - v.start)));
        let behind: usize = chunks
            .into_par_iter()
            .zip(self.views.par_iter())
            .map(|(res, view)| {
                let cam = &cams[view.cam];
                let (rot, _, t) = &poses[view.frame];
                let mut behind = 0;
                for (k, o) in (view.start..view.end).enumerate() {
                    let xw = rot * self.board[self.point[o]] + t;
                    match cam.project(&xw) {
                        Some(px) => {
                            res[2 * k] = px.x - self.observed[o][0];
                            res[2 * k + 1] = px.y - self.observed[o][1];
                        }
                        None => {
                            res[2 * k] = BEHIND_PENALTY;
                            res[2 * k + 1] = BEHIND_PENALTY;
                            behind += 1;
                        }
                    }
                }
                behind
            })
            .sum();
        Ok(behind)
    }

    /// Residuals as a new vector (see [`Self::residuals_into`]).
    ///
    /// # Errors
    /// As [`Self::residuals_into`].
    pub fn residuals(&self, x: &[f64]) -> Result<(Vec<f64>, usize)> {
        let mut out = vec![0.0; 2 * self.observed.len()];
        let behind = self.residuals_into(x, &mut out)?;
        Ok((out, behind))
    }

    /// Exact Jacobian of [`Self::residuals_into`] with respect to the free parameters: the CSR
    /// values for the fixed pattern [`Self::indptr`] / [`Self::indices`], written into `data`
    /// (`nnz` entries). Rows of detections behind their camera are zero.
    ///
    /// Chain rule per detection of corner `m̂_j` in view `τ`, camera `i` (eqs. 4-7):
    /// `∂u/∂θ_cam` from the camera model, `∂u/∂r̂_τk = ∂u/∂X · (∂R/∂r̂_k) m̂_j`,
    /// `∂u/∂t̂_τ = ∂u/∂X`, with `X = R(r̂_τ) m̂_j + t̂_τ`.
    ///
    /// # Errors
    /// As [`Self::residuals_into`], for a buffer of `nnz` entries.
    pub fn jacobian_into(&self, x: &[f64], data: &mut [f64]) -> Result<()> {
        ensure_len(data.len(), self.indices.len(), "Jacobian data buffer")?;
        let full = self.full_params(x)?;
        let cams = self.cameras(&full)?;
        let poses = self.poses(&full);
        let chunks = split_by(
            data,
            self.views
                .iter()
                .map(|v| 2 * (v.end - v.start) * v.cols.len()),
        );
        chunks
            .into_par_iter()
            .zip(self.views.par_iter())
            .for_each(|(dat, view)| {
                debug_assert_eq!(
                    dat.len(),
                    2 * (view.end - view.start) * view.cols.len(),
                    "view at {}",
                    view.data_start
                );
                let cam = &cams[view.cam];
                let (rot, drot, t) = &poses[view.frame];
                let nc = view.cols.len();
                for (k, o) in (view.start..view.end).enumerate() {
                    let m = self.board[self.point[o]];
                    let xw = rot * m + t;
                    let rows = &mut dat[2 * k * nc..2 * (k + 1) * nc];
                    let Some(j) = cam.project_jacobian(&xw) else {
                        rows.fill(0.0);
                        continue;
                    };
                    let dr = [drot[0] * m, drot[1] * m, drot[2] * m];
                    for (a, row) in rows.chunks_exact_mut(nc).enumerate() {
                        for (slot, &(is_cam, b)) in row.iter_mut().zip(&view.blocks) {
                            *slot = if is_cam {
                                j.d_params[(a, CAM_TO_CAMERA[b])]
                            } else if b < 3 {
                                (j.d_point.row(a) * dr[b])[0]
                            } else {
                                j.d_point[(a, b - 3)]
                            };
                        }
                    }
                }
            });
        Ok(())
    }

    /// Jacobian values as a new vector (see [`Self::jacobian_into`]).
    ///
    /// # Errors
    /// As [`Self::jacobian_into`].
    pub fn jacobian(&self, x: &[f64]) -> Result<Vec<f64>> {
        let mut data = vec![0.0; self.indices.len()];
        self.jacobian_into(x, &mut data)?;
        Ok(data)
    }
}

/// Splits `buf` into consecutive mutable slices of the given lengths (which must sum to
/// `buf.len()`).
fn split_by<T>(mut buf: &mut [T], lens: impl Iterator<Item = usize>) -> Vec<&mut [T]> {
    let mut out = Vec::new();
    for n in lens {
        let (head, tail) = std::mem::take(&mut buf).split_at_mut(n);
        out.push(head);
        buf = tail;
    }
    debug_assert!(buf.is_empty());
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rotation::rodrigues;

    /// A 3-camera rig looking at a 4×3 board from ~1 m, five board views, some dropouts.
    fn synthetic() -> (usize, usize, Vec<f64>, Vec<f64>, Vec<f64>) {
        let (nc, nf) = (3, 5);
        let mut board = Vec::new();
        for y in 0..3 {
            for x in 0..4 {
                board.extend_from_slice(&[x as f64 * 0.05, y as f64 * 0.05, 0.0]);
            }
        }
        let np = board.len() / 3;
        let mut params = Vec::new();
        for c in 0..nc {
            let cf = c as f64;
            params.extend_from_slice(&[
                900.0 + 30.0 * cf,
                905.0 + 20.0 * cf,
                640.0 - 5.0 * cf,
                512.0 + 3.0 * cf,
                -0.1 + 0.02 * cf,
                0.03,
            ]);
            if c == 0 {
                params.extend_from_slice(&[0.0; 6]);
            } else {
                params.extend_from_slice(&[0.02 * cf, -0.3 * cf, 0.01, 0.3 * cf, 0.01, 0.05]);
            }
            params.push(3.0 - 2.5 * cf); // skew (px), nonzero on two cameras
        }
        for f in 0..nf {
            let ff = f as f64;
            params.extend_from_slice(&[
                0.1 * ff - 0.2,
                0.2 - 0.05 * ff,
                0.03 * ff,
                -0.1 + 0.02 * ff,
                -0.05,
                1.0 + 0.05 * ff,
            ]);
        }
        // Project to make the "detections", and drop some.
        let mut corners = vec![f64::NAN; nc * nf * np * 2];
        for c in 0..nc {
            let b = &params[c * N_CAM_PARAMS..(c + 1) * N_CAM_PARAMS];
            let mut p = [0.0; N_PARAMS];
            for (k, &dst) in CAM_TO_CAMERA.iter().enumerate() {
                p[dst] = b[k];
            }
            let cam = Camera::from_params(&p).unwrap();
            for f in 0..nf {
                let v = &params[nc * N_CAM_PARAMS + 6 * f..nc * N_CAM_PARAMS + 6 * f + 6];
                let rot = rodrigues(&Vector3::new(v[0], v[1], v[2]));
                for j in 0..np {
                    if (c + 2 * f + 3 * j) % 7 == 0 {
                        continue;
                    }
                    let m = Vector3::new(board[3 * j], board[3 * j + 1], board[3 * j + 2]);
                    let px = cam
                        .project(&(rot * m + Vector3::new(v[3], v[4], v[5])))
                        .unwrap();
                    let flat = (c * nf + f) * np + j;
                    corners[2 * flat] = px.x + 0.1 * ((flat % 5) as f64 - 2.0);
                    corners[2 * flat + 1] = px.y - 0.1 * ((flat % 3) as f64 - 1.0);
                }
            }
        }
        (nc, nf, board, corners, params)
    }

    fn perturbed(x: &[f64]) -> Vec<f64> {
        x.iter()
            .enumerate()
            .map(|(i, v)| v * (1.0 + 1e-3 * ((i % 7) as f64 - 3.0)) + 1e-3)
            .collect()
    }

    #[test]
    fn residuals_vanish_at_truth_up_to_the_added_noise() {
        let (nc, nf, board, corners, params) = synthetic();
        let fixed = vec![false; params.len()];
        let p = CalibrationProblem::new(nc, nf, &board, &corners, 0, &params, &fixed).unwrap();
        let x: Vec<f64> = p.free_indices().iter().map(|&i| params[i]).collect();
        let (r, behind) = p.residuals(&x).unwrap();
        assert_eq!(behind, 0);
        assert_eq!(r.len(), 2 * p.n_observations());
        assert!(r.iter().all(|v| v.abs() <= 0.2 + 1e-9), "{r:?}");
        // The reference camera's r, t are not free.
        assert!(p.free_indices().iter().all(|&i| !(6..12).contains(&i)));
        assert!(p.free_indices().contains(&CAM_SKEW)); // ... but its skew is
        assert_eq!(p.n_free(), params.len() - 6);
        // Observation order is ascending flat index.
        assert!(p.observation_index().windows(2).all(|w| w[0] < w[1]));
    }

    #[test]
    fn jacobian_matches_central_finite_differences() {
        let (nc, nf, board, corners, params) = synthetic();
        let mut fixed = vec![false; params.len()];
        fixed[N_CAM_PARAMS + 4] = true; // camera 1's k1 held fixed: its column must disappear
        let p = CalibrationProblem::new(nc, nf, &board, &corners, 1, &params, &fixed).unwrap();
        let x0: Vec<f64> = p.free_indices().iter().map(|&i| params[i]).collect();
        let x = perturbed(&x0);
        let data = p.jacobian(&x).unwrap();
        let (indptr, indices) = (p.indptr(), p.indices());
        let n_rows = indptr.len() - 1;
        // Dense copy of the sparse Jacobian.
        let n = p.n_free();
        let mut dense = vec![0.0; n_rows * n];
        for r in 0..n_rows {
            for k in indptr[r] as usize..indptr[r + 1] as usize {
                dense[r * n + indices[k] as usize] = data[k];
            }
            let cols = &indices[indptr[r] as usize..indptr[r + 1] as usize];
            assert!(cols.windows(2).all(|w| w[0] < w[1]), "row {r} unsorted");
        }
        for col in 0..n {
            let full_i = p.free_indices()[col];
            // Relative step: focal lengths ~1e3, angles ~0.1.
            let h = 1e-6 * (1.0 + x[col].abs());
            let mut xp = x.clone();
            let mut xm = x.clone();
            xp[col] += h;
            xm[col] -= h;
            let (rp, _) = p.residuals(&xp).unwrap();
            let (rm, _) = p.residuals(&xm).unwrap();
            for r in 0..n_rows {
                let fd = (rp[r] - rm[r]) / (2.0 * h);
                let ex = dense[r * n + col];
                assert!(
                    (fd - ex).abs() <= 1e-5 * (1.0 + ex.abs()),
                    "row {r}, full param {full_i}: fd {fd} vs exact {ex}"
                );
            }
        }
        // Fixed parameters (camera 1 = reference r, t; camera 1 k1) have no column.
        assert!(!p.free_indices().contains(&(N_CAM_PARAMS + 4)));
        assert!(!p.free_indices().contains(&(N_CAM_PARAMS + 6)));
        // every camera's skew is free here (the FD check above covered its column)
        assert!((0..nc).all(|c| p.free_indices().contains(&(c * N_CAM_PARAMS + CAM_SKEW))));
    }

    #[test]
    fn unseen_views_are_fixed_and_unseen_cameras_rejected() {
        let (nc, nf, board, mut corners, params) = synthetic();
        let np = board.len() / 3;
        // View 2 unseen by every camera.
        for c in 0..nc {
            let s = (c * nf + 2) * np * 2;
            corners[s..s + 2 * np].fill(f64::NAN);
        }
        let fixed = vec![false; params.len()];
        let p = CalibrationProblem::new(nc, nf, &board, &corners, 0, &params, &fixed).unwrap();
        let vo = N_CAM_PARAMS * nc + 6 * 2;
        assert!(p.free_indices().iter().all(|&i| !(vo..vo + 6).contains(&i)));
        // Camera 2 sees nothing.
        let s = 2 * nf * np * 2;
        corners[s..].fill(f64::NAN);
        let err = CalibrationProblem::new(nc, nf, &board, &corners, 0, &params, &fixed);
        assert!(matches!(err, Err(AcmError::Invalid(s)) if s.contains("camera 2")));
    }

    #[test]
    fn bad_inputs_are_errors() {
        let (nc, nf, board, corners, params) = synthetic();
        let fixed = vec![false; params.len()];
        let mut inf = corners.clone();
        inf[10] = f64::INFINITY;
        assert!(matches!(
            CalibrationProblem::new(nc, nf, &board, &inf, 0, &params, &fixed),
            Err(AcmError::NonFinite(_))
        ));
        assert!(matches!(
            CalibrationProblem::new(nc, nf, &board, &corners[1..], 0, &params, &fixed),
            Err(AcmError::Shape(_))
        ));
        assert!(matches!(
            CalibrationProblem::new(nc, nf, &board, &corners, 3, &params, &fixed),
            Err(AcmError::Invalid(_))
        ));
        let mut neg = params.clone();
        neg[N_CAM_PARAMS] = -1.0;
        assert!(matches!(
            CalibrationProblem::new(nc, nf, &board, &corners, 0, &neg, &fixed),
            Err(AcmError::Invalid(_))
        ));
        let all = vec![true; params.len()];
        assert!(matches!(
            CalibrationProblem::new(nc, nf, &board, &corners, 0, &params, &all),
            Err(AcmError::Invalid(_))
        ));
        let p = CalibrationProblem::new(nc, nf, &board, &corners, 0, &params, &fixed).unwrap();
        assert!(matches!(p.residuals(&[0.0; 3]), Err(AcmError::Shape(_))));
    }

    #[test]
    fn board_behind_a_camera_is_penalised_not_projected() {
        let (nc, nf, board, corners, mut params) = synthetic();
        // Move view 0 behind every camera.
        params[N_CAM_PARAMS * nc + 5] = -1.0;
        let fixed = vec![false; params.len()];
        let p = CalibrationProblem::new(nc, nf, &board, &corners, 0, &params, &fixed).unwrap();
        let x: Vec<f64> = p.free_indices().iter().map(|&i| params[i]).collect();
        let (r, behind) = p.residuals(&x).unwrap();
        assert!(behind > 0);
        assert_eq!(
            r.iter().filter(|&&v| v == BEHIND_PENALTY).count(),
            2 * behind
        );
        assert!(p.jacobian(&x).unwrap().iter().all(|v| v.is_finite()));
    }
}
