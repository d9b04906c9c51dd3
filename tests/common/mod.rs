//! Helpers shared by the integration tests.

use acm_rs::camera::Camera;

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
