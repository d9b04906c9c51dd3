//! Helpers shared by the integration tests.

use acm_rs::camera::Camera;
use acm_rs::limits::StateMap;
use acm_rs::normalization::Normalization;
use acm_rs::skeleton::Skeleton;
use acm_rs::tracking::SkeletonEmission;
use nalgebra::Vector3;

/// `n` cameras 60 cm from the origin (units: cm), turned about y in steps of 0.3 rad around
/// the z axis, 1280 × 1024 px, f = 1000 px, mild radial distortion.
pub fn ring_rig(n: usize) -> Vec<Camera> {
    let rows: Vec<f64> = (0..n)
        .flat_map(|i| {
            let a = 0.3 * (i as f64 - (n - 1) as f64 / 2.0);
            [
                0.0, a, 0.0, 0.0, -5.0, 60.0, 1000.0, 1000.0, 640.0, 512.0, -0.1, 0.02, 0.0, 0.0,
                0.0,
            ]
        })
        .collect();
    Camera::many_from_rows(&rows, 15).unwrap()
}

/// The emission of the skeleton with joints `rest` (tree `parents`, root −1) and `markers` on
/// `marker_joints`, seen by [`ring_rig`]`(n_cams)`, with the joint-angle limits
/// `limit(entry)` for each of the `3 · bones` rotation entries.
pub fn chain_emission(
    parents: &[i64],
    rest: &[Vector3<f64>],
    marker_joints: Vec<usize>,
    markers: &[Vector3<f64>],
    limit: impl Fn(usize) -> (f64, f64),
    n_cams: usize,
) -> SkeletonEmission {
    let sk = Skeleton::from_rest_pose(parents, rest, marker_joints, markers, &Vector3::y(), None)
        .unwrap();
    let nb = sk.n_bones();
    let norm = Normalization::default();
    let (lo, hi): (Vec<f64>, Vec<f64>) = (0..3 * nb).map(limit).unzip();
    let map = StateMap::new(nb, &lo, &hi, &norm, true).unwrap();
    SkeletonEmission::new(sk, ring_rig(n_cams), map, norm).unwrap()
}
