//! Rodrigues rotations (ACM supp. section 1, eqs. 1-3) and their exact derivatives.
//!
//! A Rodrigues vector `r = θ ω` (eq. 1) encodes a rotation by the angle `θ = |r|` about the
//! unit axis `ω`. [`rodrigues`] is `f_{r→R}` of eq. 2, [`rodrigues_log`] its inverse, and
//! [`rodrigues_jacobian`] the derivative `∂R/∂r`. Every function is numerically stable at
//! `θ = 0` (Taylor series below [`SMALL_ANGLE`]) and [`rodrigues_log`] also near `θ = π`.

use crate::error::{ensure_finite, AcmError, Result};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

/// Below this angle (rad) the trigonometric coefficients are evaluated by Taylor series.
pub const SMALL_ANGLE: f64 = 0.05;

/// Tolerance on `max |RᵀR − I|` accepted by [`rodrigues_log`] for a rotation matrix.
pub const ORTHONORMAL_TOL: f64 = 1e-6;

/// The cross-product matrix `ω̂` of eq. 3: `skew(a) * b == a.cross(&b)`.
///
/// # Example
/// ```
/// use nalgebra::Vector3;
/// let a = Vector3::new(1.0, 2.0, 3.0);
/// let b = Vector3::new(-1.0, 0.5, 2.0);
/// assert!((acm_rs::rotation::skew(&a) * b - a.cross(&b)).norm() < 1e-15);
/// ```
pub fn skew(a: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -a.z, a.y, a.z, 0.0, -a.x, -a.y, a.x, 0.0)
}

/// The scalar coefficients of the Rodrigues formula and of its left Jacobian.
///
/// `a = sin θ / θ`, `b = (1 − cos θ) / θ²`, `e = (θ − sin θ) / θ³`, so that
/// `R = I + a K + b K²` and `J_l = I + b K + e K²` with `K = [r]×`.
#[derive(Debug, Clone, Copy)]
struct Coefficients {
    a: f64,
    b: f64,
    e: f64,
}

fn coefficients(theta2: f64) -> Coefficients {
    let theta = theta2.sqrt();
    if theta < SMALL_ANGLE {
        // Taylor series; the first omitted terms are below 1e-17 at θ = SMALL_ANGLE.
        let t2 = theta2;
        let t4 = t2 * t2;
        let t6 = t4 * t2;
        Coefficients {
            a: 1.0 - t2 / 6.0 + t4 / 120.0 - t6 / 5040.0,
            b: 0.5 - t2 / 24.0 + t4 / 720.0 - t6 / 40320.0,
            e: 1.0 / 6.0 - t2 / 120.0 + t4 / 5040.0 - t6 / 362880.0,
        }
    } else {
        let (s, c) = theta.sin_cos();
        Coefficients {
            a: s / theta,
            b: (1.0 - c) / theta2,
            e: (theta - s) / (theta2 * theta),
        }
    }
}

/// Rotation matrix of a Rodrigues vector (ACM supp. eq. 2, `f_{r→R}`).
///
/// # Arguments
/// * `r` - Rodrigues vector `θ ω` (rad).
///
/// # Example
/// The zero vector gives the identity; `π/2` about z maps x to y.
/// ```
/// use nalgebra::{Matrix3, Vector3};
/// use acm_rs::rotation::rodrigues;
/// assert_eq!(rodrigues(&Vector3::zeros()), Matrix3::identity());
/// let r = rodrigues(&Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2));
/// assert!((r * Vector3::x() - Vector3::y()).norm() < 1e-15);
/// ```
pub fn rodrigues(r: &Vector3<f64>) -> Matrix3<f64> {
    let t2 = r.norm_squared();
    if t2 == 0.0 {
        return Matrix3::identity();
    }
    let co = coefficients(t2);
    // I + a K + b K² with K² = r rᵀ − θ² I, written out: (1 − b θ²) I + a K + b r rᵀ.
    let c = 1.0 - co.b * t2;
    let (x, y, z) = (r.x, r.y, r.z);
    let (ax, ay, az) = (co.a * x, co.a * y, co.a * z);
    let (bxy, bxz, byz) = (co.b * x * y, co.b * x * z, co.b * y * z);
    Matrix3::new(
        c + co.b * x * x,
        bxy - az,
        bxz + ay,
        bxy + az,
        c + co.b * y * y,
        byz - ax,
        bxz - ay,
        byz + ax,
        c + co.b * z * z,
    )
}

/// Left Jacobian of SO(3) at `r`: `R(r + δ) ≈ R(J_l(r) δ) R(r)` to first order.
///
/// This is the map from a change of the Rodrigues vector to the world-frame angular
/// increment; it gives the exact derivative `∂R/∂r_k = [J_l e_k]× R` used everywhere below.
pub fn left_jacobian(r: &Vector3<f64>) -> Matrix3<f64> {
    let k = skew(r);
    let co = coefficients(r.norm_squared());
    Matrix3::identity() + k * co.b + k * k * co.e
}

/// Rotation matrix and its exact derivatives `[∂R/∂r_0, ∂R/∂r_1, ∂R/∂r_2]`.
///
/// Exact for all `r`, including `r = 0` where `∂R/∂r_k = [e_k]×`.
pub fn rodrigues_jacobian(r: &Vector3<f64>) -> (Matrix3<f64>, [Matrix3<f64>; 3]) {
    let rot = rodrigues(r);
    let jl = left_jacobian(r);
    let d = [0, 1, 2].map(|k| skew(&jl.column(k).into_owned()) * rot);
    (rot, d)
}

/// Rodrigues vector of a rotation matrix (inverse of eq. 2), stable at `θ = 0` and `θ = π`.
///
/// The returned angle lies in `[0, π]`. At exactly `θ = π` the axis sign is ambiguous; the
/// sign whose first non-negligible component is positive is returned.
///
/// # Errors
/// [`AcmError::NonFinite`] for NaN/inf entries, [`AcmError::Invalid`] when `rot` is not a
/// proper rotation (`max |RᵀR − I| > 1e-6` or `det R < 0`).
pub fn rodrigues_log(rot: &Matrix3<f64>) -> Result<Vector3<f64>> {
    ensure_finite(rot.as_slice(), "rotation matrix")?;
    let err = (rot.transpose() * rot - Matrix3::identity()).abs().max();
    if err > ORTHONORMAL_TOL || rot.determinant() < 0.0 {
        return Err(AcmError::Invalid(format!(
            "matrix is not a rotation (max |R^T R - I| = {err:.3e}, det = {:.6})",
            rot.determinant()
        )));
    }
    // sin θ · ω from the antisymmetric part, cos θ from the trace.
    let v = Vector3::new(
        rot[(2, 1)] - rot[(1, 2)],
        rot[(0, 2)] - rot[(2, 0)],
        rot[(1, 0)] - rot[(0, 1)],
    ) * 0.5;
    let sin_t = v.norm();
    let cos_t = ((rot.trace() - 1.0) * 0.5).clamp(-1.0, 1.0);
    let theta = sin_t.atan2(cos_t);
    if cos_t >= 0.0 {
        // θ ≤ π/2: v / sinc(θ), with the series of θ / sin θ near zero.
        let scale = if theta < SMALL_ANGLE {
            let t2 = theta * theta;
            1.0 + t2 / 6.0 + 7.0 * t2 * t2 / 360.0
        } else {
            theta / sin_t
        };
        return Ok(v * scale);
    }
    // θ > π/2: the axis from the symmetric part (R + Rᵀ)/2 − cos θ I = (1 − cos θ) ω ωᵀ,
    // which is well conditioned here (1 − cos θ ≥ 1), with its sign taken from v.
    let sym = (rot + rot.transpose()) * 0.5 - Matrix3::identity() * cos_t;
    let diag = sym.diagonal();
    let k = diag.imax();
    let mut axis = sym.column(k).into_owned() / (diag[k] * (1.0 - cos_t)).sqrt();
    axis /= axis.norm();
    let sign_ref = if sin_t > 1e-12 {
        axis.dot(&v)
    } else {
        // θ = π: choose the representative with a positive leading component.
        axis.iter()
            .copied()
            .find(|c| c.abs() > 1e-12)
            .unwrap_or(1.0)
    };
    if sign_ref < 0.0 {
        axis = -axis;
    }
    Ok(axis * theta)
}

/// Batch version of [`rodrigues`]: `n` vectors (flat, `3n`) → `n` row-major 3×3 matrices
/// (flat, `9n`), in parallel.
///
/// # Errors
/// Shape error if `r.len()` is not a multiple of 3; non-finite error for NaN/inf.
pub fn rodrigues_batch(r: &[f64]) -> Result<Vec<f64>> {
    if !r.len().is_multiple_of(3) {
        return Err(AcmError::Shape(format!(
            "Rodrigues vectors: {} values is not a multiple of 3",
            r.len()
        )));
    }
    ensure_finite(r, "Rodrigues vectors")?;
    let mut out = vec![0.0; r.len() * 3];
    out.par_chunks_mut(9)
        .zip(r.par_chunks(3))
        .for_each(|(o, v)| write_row_major(&rodrigues(&Vector3::new(v[0], v[1], v[2])), o));
    Ok(out)
}

/// Batch version of [`rodrigues_log`]: row-major matrices (flat, `9n`) → vectors (flat, `3n`).
///
/// # Errors
/// As [`rodrigues_log`], naming the index of the first offending matrix.
pub fn rodrigues_log_batch(mats: &[f64]) -> Result<Vec<f64>> {
    if !mats.len().is_multiple_of(9) {
        return Err(AcmError::Shape(format!(
            "rotation matrices: {} values is not a multiple of 9",
            mats.len()
        )));
    }
    let vecs: Result<Vec<Vector3<f64>>> = mats
        .par_chunks(9)
        .enumerate()
        .map(|(i, m)| {
            rodrigues_log(&Matrix3::from_row_slice(m)).map_err(|e| match e {
                AcmError::Invalid(s) => AcmError::Invalid(format!("matrix {i}: {s}")),
                AcmError::NonFinite(s) => AcmError::NonFinite(format!("matrix {i}: {s}")),
                other => other,
            })
        })
        .collect();
    Ok(vecs?.iter().flat_map(|v| [v.x, v.y, v.z]).collect())
}

/// Batch version of [`rodrigues_jacobian`]: `n` vectors → `n` blocks of 27 values laid out as
/// `(n, 3, 3, 3)` row-major with index `[i, a, b, k] = ∂R_ab / ∂r_k`.
///
/// # Errors
/// Shape error if `r.len()` is not a multiple of 3; non-finite error for NaN/inf.
pub fn rodrigues_jacobian_batch(r: &[f64]) -> Result<Vec<f64>> {
    if !r.len().is_multiple_of(3) {
        return Err(AcmError::Shape(format!(
            "Rodrigues vectors: {} values is not a multiple of 3",
            r.len()
        )));
    }
    ensure_finite(r, "Rodrigues vectors")?;
    let mut out = vec![0.0; r.len() * 9];
    out.par_chunks_mut(27)
        .zip(r.par_chunks(3))
        .for_each(|(o, v)| {
            let (_, d) = rodrigues_jacobian(&Vector3::new(v[0], v[1], v[2]));
            for a in 0..3 {
                for b in 0..3 {
                    for (k, dk) in d.iter().enumerate() {
                        o[(a * 3 + b) * 3 + k] = dk[(a, b)];
                    }
                }
            }
        });
    Ok(out)
}

/// Writes a 3×3 matrix row-major into `out[0..9]` (numpy layout).
pub fn write_row_major(m: &Matrix3<f64>, out: &mut [f64]) {
    for a in 0..3 {
        for b in 0..3 {
            out[a * 3 + b] = m[(a, b)];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::f64::consts::PI;

    fn fd_jacobian(r: &Vector3<f64>, h: f64) -> [Matrix3<f64>; 3] {
        [0, 1, 2].map(|k| {
            let mut rp = *r;
            let mut rm = *r;
            rp[k] += h;
            rm[k] -= h;
            (rodrigues(&rp) - rodrigues(&rm)) / (2.0 * h)
        })
    }

    #[test]
    fn known_rotations() {
        let rz = rodrigues(&Vector3::new(0.0, 0.0, PI / 2.0));
        assert!((rz * Vector3::x() - Vector3::y()).norm() < 1e-15);
        let rx = rodrigues(&Vector3::new(PI, 0.0, 0.0));
        assert!((rx - Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))).norm() < 1e-15);
        // Rodrigues formula against nalgebra's own axis-angle construction.
        let r = Vector3::new(0.3, -1.1, 0.7);
        let reference = nalgebra::Rotation3::new(r);
        assert!((rodrigues(&r) - reference.matrix()).norm() < 1e-14);
    }

    #[test]
    fn small_angle_series_is_continuous() {
        // Both sides of the series threshold agree to rounding.
        let axis = Vector3::new(0.2, -0.5, 0.84).normalize();
        let below = axis * (SMALL_ANGLE * (1.0 - 1e-9));
        let above = axis * (SMALL_ANGLE * (1.0 + 1e-9));
        assert!((rodrigues(&below) - rodrigues(&above)).norm() < 1e-9);
        assert!((left_jacobian(&below) - left_jacobian(&above)).norm() < 1e-9);
    }

    #[test]
    fn jacobian_at_zero_is_generator() {
        let (_, d) = rodrigues_jacobian(&Vector3::zeros());
        for (k, dk) in d.iter().enumerate() {
            let mut e = Vector3::zeros();
            e[k] = 1.0;
            assert!((dk - skew(&e)).norm() < 1e-15);
        }
    }

    #[test]
    fn jacobian_matches_finite_differences_at_many_angles() {
        for &theta in &[0.0, 1e-9, 1e-4, 0.049, 0.051, 0.5, 1.5, 3.0, PI - 1e-4, 4.0] {
            let r = Vector3::new(0.36, -0.48, 0.8) * theta;
            let (_, d) = rodrigues_jacobian(&r);
            let fd = fd_jacobian(&r, 1e-6);
            for k in 0..3 {
                assert!((d[k] - fd[k]).norm() < 1e-8, "theta={theta} k={k}");
            }
        }
    }

    #[test]
    fn log_near_zero_and_pi() {
        for &theta in &[0.0, 1e-12, 1e-7, 0.03, 1.0, 2.0, PI - 1e-3, PI - 1e-8, PI] {
            let axis = Vector3::new(-0.36, 0.48, 0.8);
            let r = axis * theta;
            let back = rodrigues_log(&rodrigues(&r)).unwrap();
            // Compare rotations (the vector is unique except at exactly π).
            assert!(
                (rodrigues(&back) - rodrigues(&r)).norm() < 1e-12,
                "theta={theta}: {back:?}"
            );
            if theta < PI - 1e-6 {
                assert!((back - r).norm() < 1e-9 * (1.0 + theta), "theta={theta}");
            }
        }
    }

    #[test]
    fn log_rejects_non_rotations() {
        let reflection = Matrix3::from_diagonal(&Vector3::new(-1.0, 1.0, 1.0));
        assert!(matches!(
            rodrigues_log(&reflection),
            Err(AcmError::Invalid(_))
        ));
        let scaled = Matrix3::identity() * 1.01;
        assert!(matches!(rodrigues_log(&scaled), Err(AcmError::Invalid(_))));
        let mut nan = Matrix3::identity();
        nan[(1, 2)] = f64::NAN;
        assert!(matches!(rodrigues_log(&nan), Err(AcmError::NonFinite(_))));
    }

    #[test]
    fn batch_matches_single_and_checks_shape() {
        let r = [0.1, 0.2, 0.3, 0.0, 0.0, 0.0, -2.0, 1.0, 0.5];
        let mats = rodrigues_batch(&r).unwrap();
        for i in 0..3 {
            let single = rodrigues(&Vector3::new(r[3 * i], r[3 * i + 1], r[3 * i + 2]));
            assert_eq!(Matrix3::from_row_slice(&mats[9 * i..9 * i + 9]), single);
        }
        let back = rodrigues_log_batch(&mats).unwrap();
        for (a, b) in back.iter().zip(r.iter()) {
            assert!((a - b).abs() < 1e-12);
        }
        assert!(matches!(rodrigues_batch(&r[..4]), Err(AcmError::Shape(_))));
        assert!(matches!(
            rodrigues_batch(&[f64::NAN, 0.0, 0.0]),
            Err(AcmError::NonFinite(_))
        ));
        let jac = rodrigues_jacobian_batch(&r[..3]).unwrap();
        let (_, d) = rodrigues_jacobian(&Vector3::new(0.1, 0.2, 0.3));
        assert_eq!(jac[5 * 3 + 2], d[2][(1, 2)]);
    }

    proptest! {
        #[test]
        fn orthonormal_and_proper(x in -7.0f64..7.0, y in -7.0f64..7.0, z in -7.0f64..7.0) {
            let m = rodrigues(&Vector3::new(x, y, z));
            prop_assert!((m.transpose() * m - Matrix3::identity()).norm() < 1e-13);
            prop_assert!((m.determinant() - 1.0).abs() < 1e-13);
        }

        #[test]
        fn exp_of_log_is_identity(x in -7.0f64..7.0, y in -7.0f64..7.0, z in -7.0f64..7.0) {
            let m = rodrigues(&Vector3::new(x, y, z));
            let back = rodrigues_log(&m).unwrap();
            prop_assert!(back.norm() <= PI + 1e-12);
            prop_assert!((rodrigues(&back) - m).norm() < 1e-11);
        }

        #[test]
        fn log_of_exp_inside_the_ball(x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0,
                                      s in 0.0f64..3.1) {
            let v = Vector3::new(x, y, z);
            prop_assume!(v.norm() > 1e-6);
            let r = v.normalize() * s;
            prop_assert!((rodrigues_log(&rodrigues(&r)).unwrap() - r).norm() < 1e-9);
        }
    }
}
