//! The emission function `g` of the state-space model (ACM supp. Alg. 4, eq. 50): state →
//! forward kinematics → projection into every camera → normalised pixels (eq. 11). Batches
//! of states (e.g. one set of sigma points) are evaluated in parallel.

use crate::camera::Camera;
use crate::error::{ensure_len, AcmError, Result};
use crate::limits::StateMap;
use crate::normalization::Normalization;
use crate::skeleton::Skeleton;
use nalgebra::Vector3;
use rayon::prelude::*;

fn pose_to_fk_input(pose: &[f64]) -> (Vector3<f64>, Vec<Vector3<f64>>) {
    let t = Vector3::new(pose[0], pose[1], pose[2]);
    let r = pose[3..]
        .chunks(3)
        .map(|c| Vector3::new(c[0], c[1], c[2]))
        .collect();
    (t, r)
}

fn project_markers_into(
    markers: &[Vector3<f64>],
    cameras: &[Camera],
    out: &mut [f64],
    norm: Option<&Normalization>,
) {
    let n_m = markers.len();
    for (c, cam) in cameras.iter().enumerate() {
        for (k, m) in markers.iter().enumerate() {
            let o = &mut out[(c * n_m + k) * 2..(c * n_m + k) * 2 + 2];
            match cam.project(m) {
                Some(uv) => {
                    let (u, v) = match norm {
                        Some(n) => n.normalize_pixel(uv.x, uv.y),
                        None => (uv.x, uv.y),
                    };
                    o[0] = u;
                    o[1] = v;
                }
                None => {
                    o[0] = f64::NAN;
                    o[1] = f64::NAN;
                }
            }
        }
    }
}

/// Projects the markers of `N` full poses `[t, r]` into every camera (pixels).
///
/// # Arguments
/// * `poses` - `(N, 3 + 3 n_bones)` flat.
///
/// # Returns
/// `(N, n_cams, M, 2)` flat pixels; NaN where a marker is behind a camera.
///
/// # Errors
/// Shape error for a wrong pose length; non-finite error naming the first bad pose.
pub fn project_poses(skeleton: &Skeleton, cameras: &[Camera], poses: &[f64]) -> Result<Vec<f64>> {
    let np = skeleton.n_pose();
    if poses.len() % np != 0 {
        return Err(AcmError::Shape(format!(
            "poses: {} values is not a multiple of the pose length {np}",
            poses.len()
        )));
    }
    if let Some(i) = poses.iter().position(|v| !v.is_finite()) {
        return Err(AcmError::NonFinite(format!(
            "pose {} contains NaN or infinity",
            i / np
        )));
    }
    let block = cameras.len() * skeleton.n_markers() * 2;
    let mut out = vec![0.0; (poses.len() / np) * block];
    if block == 0 {
        return Ok(out);
    }
    out.par_chunks_mut(block)
        .zip(poses.par_chunks(np))
        .for_each(|(o, pose)| {
            let (t, r) = pose_to_fk_input(pose);
            let fk = skeleton.forward_unchecked(&t, &r, skeleton.lengths(), skeleton.offsets());
            project_markers_into(&fk.markers, cameras, o, None);
        });
    Ok(out)
}

/// Alg. 4 for a batch of states: `g(f_{z*→z}(z))` for each row of `states`.
///
/// # Arguments
/// * `states` - `(N, n_state)` flat, in the state space of `map`.
///
/// # Returns
/// `(N, n_cams · M · 2)` flat normalised pixels `(u / c_1 − 1, v / c_2 − 1)`, ordered camera,
/// marker, coordinate (Alg. 4 line 9); NaN where a marker is behind a camera.
///
/// # Errors
/// Shape error if the map does not fit the skeleton or `states` has a wrong length;
/// non-finite error naming the first bad state.
pub fn emission_batch(
    skeleton: &Skeleton,
    cameras: &[Camera],
    map: &StateMap,
    norm: &Normalization,
    states: &[f64],
) -> Result<Vec<f64>> {
    norm.validate()?;
    ensure_len(map.n_pose(), skeleton.n_pose(), "state map pose length")?;
    let ns = map.n_state();
    if ns == 0 || states.len() % ns != 0 {
        return Err(AcmError::Shape(format!(
            "states: {} values is not a multiple of the state length {ns}",
            states.len()
        )));
    }
    if let Some(i) = states.iter().position(|v| !v.is_finite()) {
        return Err(AcmError::NonFinite(format!(
            "state {} contains NaN or infinity",
            i / ns
        )));
    }
    let block = cameras.len() * skeleton.n_markers() * 2;
    let mut out = vec![0.0; (states.len() / ns) * block];
    if block == 0 {
        return Ok(out);
    }
    out.par_chunks_mut(block)
        .zip(states.par_chunks(ns))
        .for_each_init(
            || vec![0.0; skeleton.n_pose()],
            |pose, (o, z)| {
                map.to_pose_into(z, pose, None);
                let (t, r) = pose_to_fk_input(pose);
                let fk = skeleton.forward_unchecked(&t, &r, skeleton.lengths(), skeleton.offsets());
                project_markers_into(&fk.markers, cameras, o, Some(norm));
            },
        );
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::tests::branching;

    fn rig() -> Vec<Camera> {
        // Two cameras looking at the origin from +z and from +x.
        let c0 = Camera::from_params(&[
            0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 800.0, 800.0, 640.0, 512.0, -0.1, 0.01, 0.0, 0.0, 0.0,
        ])
        .unwrap();
        let c1 = Camera::from_params(&[
            0.0,
            -std::f64::consts::FRAC_PI_2,
            0.0,
            0.0,
            0.0,
            20.0,
            900.0,
            900.0,
            600.0,
            500.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
        ])
        .unwrap();
        vec![c0, c1]
    }

    #[test]
    fn emission_equals_fk_then_projection() {
        let sk = branching();
        let cams = rig();
        let n_b = sk.n_bones();
        let inf = f64::INFINITY;
        let mut lower = vec![-inf; 3 * n_b];
        let mut upper = vec![inf; 3 * n_b];
        lower[5] = 0.0; // bone 1 axis z fixed at 0
        upper[5] = 0.0;
        lower[6] = -0.4; // bone 2 axis x bounded
        upper[6] = 0.9;
        let norm = Normalization::default();
        let map = StateMap::new(n_b, &lower, &upper, &norm, true).unwrap();
        let ns = map.n_state();
        let states: Vec<f64> = (0..3 * ns)
            .map(|i| ((i * 37 % 17) as f64 / 17.0 - 0.5) * 0.3)
            .collect();
        let g = emission_batch(&sk, &cams, &map, &norm, &states).unwrap();
        for s in 0..3 {
            let pose = map.to_pose(&states[s * ns..(s + 1) * ns]).unwrap();
            let px = project_poses(&sk, &cams, &pose).unwrap();
            let block = cams.len() * sk.n_markers() * 2;
            for i in 0..block {
                let expect = px[i] / norm.pixel[i % 2] - 1.0;
                assert!((g[s * block + i] - expect).abs() < 1e-12);
            }
        }
        assert!(matches!(
            emission_batch(&sk, &cams, &map, &norm, &states[1..]),
            Err(AcmError::Shape(_))
        ));
    }
}
