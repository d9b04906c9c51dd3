//! Pinhole camera with lens distortion (ACM supp. section 2.1, eqs. 4-6) and exact Jacobians.
//!
//! The paper's model (eq. 5) has radial coefficients `k1, k2`; the authors' tool and every
//! calibration file of the field use OpenCV's five coefficients `(k1, k2, p1, p2, k3)`. This
//! module implements the OpenCV model; the paper's model is the special case
//! `p1 = p2 = k3 = 0`.
//!
//! A camera is described by the flat parameter vector of [`N_PARAMS`] values
//! `[rx, ry, rz, tx, ty, tz, fx, fy, cx, cy, k1, k2, p1, p2, k3, s]` (see [`param`]), where
//! `x_cam = R(r) x_world + t` (eq. 4).
//!
//! The skew `s` (px) is beyond OpenCV's model, which has none: MATLAB's `cameraParameters`
//! (and Bouguet's toolbox, `alpha_c · fx`) apply it after distortion,
//! `u = fx x'' + s y'' + cx`, `v = fy y'' + cy`. Calibrations from MATLAB (Label3D, DANNCE)
//! carry it; `s = 0` is OpenCV's model, bit for bit. The first 15 entries are the model
//! without skew, and [`Camera::from_params`] also takes those 15 (skew 0).

use crate::error::{ensure_finite, ensure_len, AcmError, Result};
use crate::rotation::rodrigues_jacobian;
use nalgebra::{Matrix2x3, Matrix3, SMatrix, Vector2, Vector3};
use rayon::prelude::*;

/// Number of parameters of one camera.
pub const N_PARAMS: usize = 16;

/// Parameters of a camera without skew (OpenCV's model, the layout before skew existed);
/// accepted wherever [`N_PARAMS`] are, with skew 0.
pub const N_PARAMS_NO_SKEW: usize = 15;

/// Indices into the camera parameter vector.
pub mod param {
    /// Rodrigues vector of the world→camera rotation (3 entries from here).
    pub const RVEC: usize = 0;
    /// World→camera translation (3 entries from here), in world units.
    pub const TVEC: usize = 3;
    /// Focal length in x (px).
    pub const FX: usize = 6;
    /// Focal length in y (px).
    pub const FY: usize = 7;
    /// Principal point x (px).
    pub const CX: usize = 8;
    /// Principal point y (px).
    pub const CY: usize = 9;
    /// OpenCV distortion `(k1, k2, p1, p2, k3)` (5 entries from here).
    pub const DIST: usize = 10;
    /// Skew (px): `u = fx x'' + s y'' + cx` (MATLAB's `K(2, 1)`); 0 in OpenCV's model.
    pub const SKEW: usize = 15;
}

/// Points with a camera-frame depth at or below this value (world units) are "behind" the
/// camera: they are reported (`None` / NaN), never projected.
pub const MIN_DEPTH: f64 = 1e-9;

/// Jacobian of a pixel with respect to the camera parameters.
pub type ParamJacobian = SMatrix<f64, 2, N_PARAMS>;

/// One calibrated camera.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    params: [f64; N_PARAMS],
    rot: Matrix3<f64>,
    drot: [Matrix3<f64>; 3],
}

/// A projected point with its exact derivatives.
#[derive(Debug, Clone)]
pub struct ProjectionJacobian {
    /// Pixel coordinates `(u, v)`.
    pub pixel: Vector2<f64>,
    /// `∂(u, v)/∂x_world` (2×3).
    pub d_point: Matrix2x3<f64>,
    /// `∂(u, v)/∂params` (2×16) in the order of [`param`].
    pub d_params: ParamJacobian,
}

impl Camera {
    /// Builds a camera from its flat parameter vector (layout in [`param`]); the 15 values
    /// without skew ([`N_PARAMS_NO_SKEW`]) are a camera with skew 0.
    ///
    /// # Errors
    /// Shape error for a length other than [`N_PARAMS`] or [`N_PARAMS_NO_SKEW`], non-finite
    /// error for NaN/inf, invalid error for non-positive focal lengths.
    pub fn from_params(params: &[f64]) -> Result<Self> {
        if params.len() != N_PARAMS_NO_SKEW {
            ensure_len(params.len(), N_PARAMS, "camera parameter vector")?;
        }
        ensure_finite(params, "camera parameters")?;
        if params[param::FX] <= 0.0 || params[param::FY] <= 0.0 {
            return Err(AcmError::Invalid(format!(
                "focal lengths must be positive, got fx={}, fy={}",
                params[param::FX],
                params[param::FY]
            )));
        }
        let mut p = [0.0; N_PARAMS];
        p[..params.len()].copy_from_slice(params);
        let (rot, drot) = rodrigues_jacobian(&Vector3::new(p[0], p[1], p[2]));
        Ok(Self {
            params: p,
            rot,
            drot,
        })
    }

    /// Builds cameras from `n` concatenated parameter vectors (flat, `16 n`).
    ///
    /// # Errors
    /// As [`Camera::from_params`], naming the camera index.
    pub fn many_from_params(params: &[f64]) -> Result<Vec<Self>> {
        Self::many_from_rows(params, N_PARAMS)
    }

    /// Builds cameras from `n` concatenated rows of `width` parameters: [`N_PARAMS`], or
    /// [`N_PARAMS_NO_SKEW`] for rows without skew (files written before skew existed).
    ///
    /// # Errors
    /// Shape error for another width or a length that is not a positive multiple of it; else
    /// as [`Camera::from_params`], naming the camera index.
    pub fn many_from_rows(params: &[f64], width: usize) -> Result<Vec<Self>> {
        if width != N_PARAMS && width != N_PARAMS_NO_SKEW {
            return Err(AcmError::Shape(format!(
                "camera parameters: rows of {width} values; expected {N_PARAMS} (with skew) or \
                 {N_PARAMS_NO_SKEW} (without)"
            )));
        }
        if params.is_empty() || !params.len().is_multiple_of(width) {
            return Err(AcmError::Shape(format!(
                "camera parameters: {} values is not a positive multiple of {width}",
                params.len()
            )));
        }
        params
            .chunks(width)
            .enumerate()
            .map(|(i, p)| {
                Self::from_params(p).map_err(|e| match e {
                    AcmError::Invalid(s) => AcmError::Invalid(format!("camera {i}: {s}")),
                    AcmError::NonFinite(s) => AcmError::NonFinite(format!("camera {i}: {s}")),
                    other => other,
                })
            })
            .collect()
    }

    /// The flat parameter vector.
    pub fn params(&self) -> &[f64; N_PARAMS] {
        &self.params
    }

    /// World→camera rotation matrix `R(r̃)`.
    pub fn rotation(&self) -> &Matrix3<f64> {
        &self.rot
    }

    /// World→camera translation `t̃`.
    pub fn translation(&self) -> Vector3<f64> {
        Vector3::new(self.params[3], self.params[4], self.params[5])
    }

    /// Camera centre in world coordinates, `−Rᵀ t`.
    pub fn center(&self) -> Vector3<f64> {
        -(self.rot.transpose() * self.translation())
    }

    /// Maps a world point into the camera frame (the inner part of eq. 4).
    pub fn to_camera(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.rot * x + self.translation()
    }

    /// The skew `s` (px).
    pub fn skew(&self) -> f64 {
        self.params[param::SKEW]
    }

    /// Distortion and intrinsics applied to normalised image coordinates `(x', y')`
    /// (eqs. 5-6 with OpenCV's tangential and k3 terms, then MATLAB's skew).
    fn distort(&self, xn: f64, yn: f64) -> Vector2<f64> {
        let p = &self.params;
        let (k1, k2, p1, p2, k3) = (p[10], p[11], p[12], p[13], p[14]);
        let r2 = xn * xn + yn * yn;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn);
        let yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
        // `fx x'' + 0 y''` is `fx x''` exactly: skew 0 is OpenCV's projection bit for bit
        Vector2::new(p[6] * xd + p[15] * yd + p[8], p[7] * yd + p[9])
    }

    /// Projects a world point to pixels (eq. 4); `None` if the point is not in front of the
    /// camera (depth ≤ [`MIN_DEPTH`]).
    pub fn project(&self, x: &Vector3<f64>) -> Option<Vector2<f64>> {
        let y = self.to_camera(x);
        if y.z <= MIN_DEPTH {
            return None;
        }
        Some(self.distort(y.x / y.z, y.y / y.z))
    }

    /// Projects a world point and returns the exact Jacobians with respect to the point and
    /// to all 16 camera parameters; `None` if the point is behind the camera.
    pub fn project_jacobian(&self, x: &Vector3<f64>) -> Option<ProjectionJacobian> {
        let y = self.to_camera(x);
        if y.z <= MIN_DEPTH {
            return None;
        }
        let p = &self.params;
        let (fx, fy, s) = (p[6], p[7], p[15]);
        let (k1, k2, p1, p2, k3) = (p[10], p[11], p[12], p[13], p[14]);
        let iz = 1.0 / y.z;
        let (xn, yn) = (y.x * iz, y.y * iz);
        let r2 = xn * xn + yn * yn;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
        let xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn);
        let yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
        let pixel = Vector2::new(fx * xd + s * yd + p[8], fy * yd + p[9]);

        // ∂(x'', y'')/∂(x', y')
        let cross = 2.0 * xn * yn * dradial + 2.0 * p1 * xn + 2.0 * p2 * yn;
        let dxd_dxn = radial + 2.0 * xn * xn * dradial + 2.0 * p1 * yn + 6.0 * p2 * xn;
        let dyd_dyn = radial + 2.0 * yn * yn * dradial + 6.0 * p1 * yn + 2.0 * p2 * xn;
        // ∂(u, v)/∂(x', y'), with u = fx x'' + s y'' + cx
        let d_norm = nalgebra::Matrix2::new(
            fx * dxd_dxn + s * cross,
            fx * cross + s * dyd_dyn,
            fy * cross,
            fy * dyd_dyn,
        );
        // ∂(x', y')/∂y_cam
        let d_proj = Matrix2x3::new(iz, 0.0, -xn * iz, 0.0, iz, -yn * iz);
        let d_cam = d_norm * d_proj; // ∂(u, v)/∂y_cam

        let d_point = d_cam * self.rot;
        let mut d_params = ParamJacobian::zeros();
        for k in 0..3 {
            let col = d_cam * (self.drot[k] * x);
            d_params.set_column(param::RVEC + k, &col);
            d_params.set_column(param::TVEC + k, &d_cam.column(k).into_owned());
        }
        d_params[(0, param::FX)] = xd;
        d_params[(1, param::FY)] = yd;
        d_params[(0, param::CX)] = 1.0;
        d_params[(1, param::CY)] = 1.0;
        d_params[(0, param::SKEW)] = yd;
        let r4 = r2 * r2;
        let dist_cols = [
            (xn * r2, yn * r2),                  // k1
            (xn * r4, yn * r4),                  // k2
            (2.0 * xn * yn, r2 + 2.0 * yn * yn), // p1
            (r2 + 2.0 * xn * xn, 2.0 * xn * yn), // p2
            (xn * r4 * r2, yn * r4 * r2),        // k3
        ];
        for (k, (a, b)) in dist_cols.iter().enumerate() {
            d_params[(0, param::DIST + k)] = fx * a + s * b;
            d_params[(1, param::DIST + k)] = fy * b;
        }
        Some(ProjectionJacobian {
            pixel,
            d_point,
            d_params,
        })
    }
}

/// Pixels and visibility of `n` points in `c` cameras.
#[derive(Debug, Clone)]
pub struct Projected {
    /// `(c, n, 2)` row-major pixels; NaN where the point is behind the camera.
    pub pixels: Vec<f64>,
    /// `(c, n)`: `true` where the point is in front of the camera.
    pub in_front: Vec<bool>,
}

/// Checks a flat `(n, 3)` point array: NaN marks a missing point (projected to NaN), while
/// infinity is an error.
fn points_from_flat(points: &[f64]) -> Result<usize> {
    if !points.len().is_multiple_of(3) {
        return Err(AcmError::Shape(format!(
            "points: {} values is not a multiple of 3",
            points.len()
        )));
    }
    if let Some(i) = points.iter().position(|v| v.is_infinite()) {
        return Err(AcmError::NonFinite(format!(
            "3D points: point {} has an infinite coordinate",
            i / 3
        )));
    }
    Ok(points.len() / 3)
}

fn is_missing(x: &[f64]) -> bool {
    x[0].is_nan() || x[1].is_nan() || x[2].is_nan()
}

/// Points per parallel task in the batch projections.
const POINT_BLOCK: usize = 2048;

/// Projects `n` world points (flat `(n, 3)`) into every camera, in parallel over points.
/// A point with a NaN coordinate is missing: its pixels are NaN and `in_front` is false.
///
/// # Errors
/// Shape error if `points.len()` is not a multiple of 3; non-finite error for infinite
/// coordinates.
pub fn project_points(cameras: &[Camera], points: &[f64]) -> Result<Projected> {
    let n = points_from_flat(points)?;
    let mut pixels = vec![0.0; cameras.len() * n * 2];
    let mut in_front = vec![false; cameras.len() * n];
    project_points_into(cameras, points, &mut pixels, Some(&mut in_front))?;
    Ok(Projected { pixels, in_front })
}

/// Like [`project_points`], writing `(c, n, 2)` pixels (and optionally the `(c, n)` mask)
/// into caller-provided buffers; every entry is written.
///
/// # Errors
/// As [`project_points`], plus shape errors for wrong buffer sizes.
pub fn project_points_into(
    cameras: &[Camera],
    points: &[f64],
    pixels: &mut [f64],
    in_front: Option<&mut [bool]>,
) -> Result<()> {
    let n = points_from_flat(points)?;
    let c = cameras.len();
    ensure_len(pixels.len(), c * n * 2, "pixel output buffer")?;
    if let Some(m) = in_front.as_deref() {
        ensure_len(m.len(), c * n, "visibility output buffer")?;
    }
    if n == 0 || c == 0 {
        return Ok(());
    }
    // Parallel over blocks of points; each point is read once and projected into every
    // camera (the batch is memory-bound, so the points are streamed once, not once per camera).
    let px_blocks = camera_blocks(pixels, c, 2 * n, 2 * POINT_BLOCK);
    let mut mask_blocks: Vec<Option<Vec<&mut [bool]>>> = match in_front {
        Some(m) => camera_blocks(m, c, n, POINT_BLOCK)
            .into_iter()
            .map(Some)
            .collect(),
        None => (0..px_blocks.len()).map(|_| None).collect(),
    };
    px_blocks
        .into_par_iter()
        .zip(mask_blocks.par_iter_mut())
        .zip(points.par_chunks(3 * POINT_BLOCK))
        .for_each(|((mut px, mask), pts)| {
            for (i, x) in pts.chunks_exact(3).enumerate() {
                let missing = is_missing(x);
                let xv = Vector3::new(x[0], x[1], x[2]);
                for (ci, cam) in cameras.iter().enumerate() {
                    let uv = if missing { None } else { cam.project(&xv) };
                    let (u, v, vis) = match uv {
                        Some(uv) => (uv.x, uv.y, true),
                        None => (f64::NAN, f64::NAN, false),
                    };
                    px[ci][2 * i] = u;
                    px[ci][2 * i + 1] = v;
                    if let Some(m) = mask.as_deref_mut() {
                        m[ci][i] = vis;
                    }
                }
            }
        });
    Ok(())
}

/// Splits a `(c, slab)` buffer into blocks: `result[k][ci]` is block `k` (of `block` values)
/// of camera `ci`'s slab, so that parallel tasks over blocks write disjoint slices.
pub(crate) fn camera_blocks<T>(
    buf: &mut [T],
    c: usize,
    slab: usize,
    block: usize,
) -> Vec<Vec<&mut [T]>> {
    let n_blocks = slab.div_ceil(block);
    let mut iters: Vec<_> = buf.chunks_mut(slab).map(|s| s.chunks_mut(block)).collect();
    debug_assert_eq!(iters.len(), c);
    (0..n_blocks)
        .map(|_| {
            iters
                .iter_mut()
                .map(|it| it.next().expect("every slab has n_blocks blocks"))
                .collect()
        })
        .collect()
}

/// Projections with Jacobians of `n` points in `c` cameras.
#[derive(Debug, Clone)]
pub struct ProjectedJacobians {
    /// `(c, n, 2)` pixels; NaN where the point is behind the camera.
    pub pixels: Vec<f64>,
    /// `(c, n, 2, 3)` derivatives with respect to the world point; NaN where behind.
    pub d_point: Vec<f64>,
    /// `(c, n, 2, 16)` derivatives with respect to the camera parameters; NaN where behind.
    pub d_params: Vec<f64>,
}

/// Like [`project_points`], also returning the exact Jacobians (row-major blocks).
///
/// # Errors
/// As [`project_points`].
pub fn project_points_jacobian(cameras: &[Camera], points: &[f64]) -> Result<ProjectedJacobians> {
    let n = points_from_flat(points)?;
    let c = cameras.len();
    let mut pixels = vec![f64::NAN; c * n * 2];
    let mut d_point = vec![f64::NAN; c * n * 6];
    let mut d_params = vec![f64::NAN; c * n * 2 * N_PARAMS];
    for (ci, cam) in cameras.iter().enumerate() {
        pixels[ci * n * 2..(ci + 1) * n * 2]
            .par_chunks_mut(2)
            .zip(d_point[ci * n * 6..(ci + 1) * n * 6].par_chunks_mut(6))
            .zip(
                d_params[ci * n * 2 * N_PARAMS..(ci + 1) * n * 2 * N_PARAMS]
                    .par_chunks_mut(2 * N_PARAMS),
            )
            .zip(points.par_chunks(3))
            .for_each(|(((px, dp), dc), x)| {
                if is_missing(x) {
                    return;
                }
                if let Some(j) = cam.project_jacobian(&Vector3::new(x[0], x[1], x[2])) {
                    px[0] = j.pixel.x;
                    px[1] = j.pixel.y;
                    for a in 0..2 {
                        for b in 0..3 {
                            dp[a * 3 + b] = j.d_point[(a, b)];
                        }
                        for b in 0..N_PARAMS {
                            dc[a * N_PARAMS + b] = j.d_params[(a, b)];
                        }
                    }
                }
            });
    }
    Ok(ProjectedJacobians {
        pixels,
        d_point,
        d_params,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn test_camera() -> Camera {
        Camera::from_params(&[
            0.1, -0.2, 0.05, 0.3, -0.1, 2.5, 1200.0, 1180.0, 640.0, 512.0, -0.21, 0.08, 0.001,
            -0.0015, 0.01,
        ])
        .unwrap()
    }

    #[test]
    fn pinhole_without_distortion() {
        let cam = Camera::from_params(&[
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1000.0, 900.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        ])
        .unwrap();
        let uv = cam.project(&Vector3::new(0.2, -0.1, 2.0)).unwrap();
        assert!((uv - Vector2::new(320.0 + 100.0, 240.0 - 45.0)).norm() < 1e-12);
    }

    #[test]
    fn radial_distortion_matches_eq5() {
        // Paper's model: (x/z)(1 + k1 c + k2 c²), c = (x/z)² + (y/z)².
        let (k1, k2) = (-0.3, 0.12);
        let cam = Camera::from_params(&[
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1000.0, 1000.0, 0.0, 0.0, k1, k2, 0.0, 0.0, 0.0,
        ])
        .unwrap();
        let (x, y, z) = (0.4, 0.3, 1.0);
        let c = (x / z) * (x / z) + (y / z) * (y / z);
        let f = 1.0 + k1 * c + k2 * c * c;
        let uv = cam.project(&Vector3::new(x, y, z)).unwrap();
        assert!((uv - Vector2::new(1000.0 * x / z * f, 1000.0 * y / z * f)).norm() < 1e-10);
    }

    #[test]
    fn behind_camera_is_reported() {
        let cam = test_camera();
        let behind =
            cam.rotation().transpose() * (Vector3::new(0.0, 0.0, -1.0) - cam.translation());
        assert!(cam.project(&behind).is_none());
        assert!(cam.project_jacobian(&behind).is_none());
        let proj = project_points(&[cam], &[behind.x, behind.y, behind.z]).unwrap();
        assert!(proj.pixels[0].is_nan() && !proj.in_front[0]);
    }

    /// [`test_camera`] with a MATLAB-sized skew (the Label3D rig's camera 1 has −5.8 px).
    fn skewed_camera() -> Camera {
        let mut p = *test_camera().params();
        p[param::SKEW] = -5.8;
        Camera::from_params(&p).unwrap()
    }

    #[test]
    fn skew_is_applied_after_distortion() {
        // MATLAB's cameraParameters: [u v] = [x'' y'' 1] K, K = [fx 0 0; s fy 0; cx cy 1].
        let (plain, skewed) = (test_camera(), skewed_camera());
        let x = Vector3::new(0.15, 0.2, 0.4);
        let (a, b) = (plain.project(&x).unwrap(), skewed.project(&x).unwrap());
        let p = plain.params();
        let yd = (a.y - p[param::CY]) / p[param::FY]; // y'' from the skew-free v
        assert!((b.x - (a.x - 5.8 * yd)).abs() < 1e-9, "{a} {b}");
        assert_eq!(a.y, b.y);
        assert_eq!(skewed.skew(), -5.8);
    }

    #[test]
    fn zero_skew_and_fifteen_parameters_are_the_skew_free_model() {
        let cam = test_camera();
        let mut p16 = [0.0; N_PARAMS];
        p16[..N_PARAMS_NO_SKEW].copy_from_slice(&cam.params()[..N_PARAMS_NO_SKEW]);
        assert_eq!(Camera::from_params(&p16).unwrap(), cam);
        let rows: Vec<f64> = [cam.params()[..15].to_vec(), cam.params()[..15].to_vec()].concat();
        let two = Camera::many_from_rows(&rows, N_PARAMS_NO_SKEW).unwrap();
        assert_eq!(two, vec![cam.clone(), cam.clone()]);
        assert!(matches!(
            Camera::many_from_rows(&rows, 14),
            Err(AcmError::Shape(_))
        ));
        // the skew-free formula of eq. 6, evaluated independently, bit for bit
        let x = Vector3::new(0.15, 0.2, 0.4);
        let y = cam.to_camera(&x);
        let (xn, yn) = (y.x / y.z, y.y / y.z);
        let q = cam.params();
        let r2 = xn * xn + yn * yn;
        let radial = 1.0 + r2 * (q[10] + r2 * (q[11] + r2 * q[14]));
        let xd = xn * radial + 2.0 * q[12] * xn * yn + q[13] * (r2 + 2.0 * xn * xn);
        let yd = yn * radial + q[12] * (r2 + 2.0 * yn * yn) + 2.0 * q[13] * xn * yn;
        let uv = cam.project(&x).unwrap();
        assert_eq!(uv.x, q[6] * xd + q[8]);
        assert_eq!(uv.y, q[7] * yd + q[9]);
        assert_eq!(cam.project_jacobian(&x).unwrap().pixel, uv);
    }

    #[test]
    fn jacobians_match_central_differences() {
        jacobians_match_central_differences_for(&test_camera());
        jacobians_match_central_differences_for(&skewed_camera());
    }

    fn jacobians_match_central_differences_for(cam: &Camera) {
        let cam = cam.clone();
        let x = Vector3::new(0.15, 0.2, 0.4);
        let j = cam.project_jacobian(&x).unwrap();
        let h = 1e-6;
        for k in 0..3 {
            let mut xp = x;
            let mut xm = x;
            xp[k] += h;
            xm[k] -= h;
            let fd = (cam.project(&xp).unwrap() - cam.project(&xm).unwrap()) / (2.0 * h);
            assert!(
                (fd - j.d_point.column(k)).norm() < 1e-5 * (1.0 + fd.norm()),
                "point {k}"
            );
        }
        for k in 0..N_PARAMS {
            let mut pp = *cam.params();
            let mut pm = *cam.params();
            let step = h * (1.0 + pp[k].abs());
            pp[k] += step;
            pm[k] -= step;
            let fd = (Camera::from_params(&pp).unwrap().project(&x).unwrap()
                - Camera::from_params(&pm).unwrap().project(&x).unwrap())
                / (2.0 * step);
            let an = j.d_params.column(k);
            assert!(
                (fd - an).norm() < 1e-5 * (1.0 + fd.norm()),
                "param {k}: {fd} vs {an}"
            );
        }
    }

    #[test]
    fn batch_layout_and_errors() {
        let cams = vec![test_camera(), test_camera()];
        let pts = [0.1, 0.0, 0.3, -0.2, 0.1, 0.0];
        let proj = project_points_jacobian(&cams, &pts).unwrap();
        let single = cams[1]
            .project_jacobian(&Vector3::new(-0.2, 0.1, 0.0))
            .unwrap();
        // camera 1, point 1
        assert_eq!(proj.pixels[(2 + 1) * 2 + 1], single.pixel.y);
        assert_eq!(proj.d_point[(2 + 1) * 6 + 5], single.d_point[(1, 2)]);
        assert_eq!(
            proj.d_params[((2 + 1) * 2 + 1) * N_PARAMS + 14],
            single.d_params[(1, 14)]
        );
        assert!(matches!(
            project_points(&cams, &pts[..4]),
            Err(AcmError::Shape(_))
        ));
        assert!(matches!(
            project_points(&cams, &[f64::INFINITY, 0.0, 1.0]),
            Err(AcmError::NonFinite(_))
        ));
        let missing = project_points_jacobian(&cams, &[f64::NAN, 0.0, 1.0]).unwrap();
        assert!(missing
            .pixels
            .iter()
            .chain(&missing.d_params)
            .all(|v| v.is_nan()));
        let mut bad = *cams[0].params();
        bad[param::FX] = -1.0;
        assert!(matches!(
            Camera::from_params(&bad),
            Err(AcmError::Invalid(_))
        ));
        assert!(matches!(
            Camera::many_from_params(&bad[..14]),
            Err(AcmError::Shape(_))
        ));
    }

    #[test]
    fn center_is_mapped_to_origin() {
        let cam = test_camera();
        assert!(cam.to_camera(&cam.center()).norm() < 1e-12);
    }
}
