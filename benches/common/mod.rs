//! Shared fixtures of the criterion benches: the bundled rat model (from the Python package's
//! TOML data file), a 4-camera ring rig and a seeded pseudo-random generator.

#![allow(dead_code)]

use acm_rs::camera::Camera;
use acm_rs::skeleton::Skeleton;
use nalgebra::{Matrix3, Vector3};

/// Loads the bundled rat model from the Python package's data file.
pub fn rat() -> (Skeleton, Vec<f64>, Vec<f64>) {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/python/acm_rs/models/rat.toml");
    let doc: toml::Table = std::fs::read_to_string(path)
        .expect("rat.toml")
        .parse()
        .expect("valid TOML");
    let vec3 = |v: &toml::Value| {
        let a = v.as_array().expect("array");
        Vector3::new(
            a[0].as_float().unwrap(),
            a[1].as_float().unwrap(),
            a[2].as_float().unwrap(),
        )
    };
    let joints = doc["joints"].as_array().unwrap();
    let names: Vec<&str> = joints.iter().map(|j| j["name"].as_str().unwrap()).collect();
    let index = |n: &str| names.iter().position(|x| *x == n).unwrap();
    let parents: Vec<i64> = joints
        .iter()
        .map(|j| match j["parent"].as_str().unwrap() {
            "" => -1,
            p => index(p) as i64,
        })
        .collect();
    let rest: Vec<Vector3<f64>> = joints.iter().map(|j| vec3(&j["position"])).collect();
    let markers = doc["markers"].as_array().unwrap();
    let mj: Vec<usize> = markers
        .iter()
        .map(|m| index(m["joint"].as_str().unwrap()))
        .collect();
    let mr: Vec<Vector3<f64>> = markers.iter().map(|m| vec3(&m["position"])).collect();
    let sk = Skeleton::from_rest_pose(&parents, &rest, mj, &mr, &Vector3::y(), None).unwrap();
    let n_b = sk.n_bones();
    let mut lower = vec![f64::NEG_INFINITY; 3 * n_b];
    let mut upper = vec![f64::INFINITY; 3 * n_b];
    for lim in doc["joint_limits"].as_array().unwrap() {
        let b = sk.bone_of_end()[index(lim["bone"].as_str().unwrap())].unwrap();
        for (k, ax) in ["x", "y", "z"].iter().enumerate() {
            let iv = lim[*ax].as_array().unwrap();
            lower[3 * b + k] = iv[0].as_float().unwrap().to_radians();
            upper[3 * b + k] = iv[1].as_float().unwrap().to_radians();
        }
    }
    (sk, lower, upper)
}

/// Four cameras on a ring, 60 cm away, looking at the origin.
pub fn rig() -> Vec<Camera> {
    (0..4)
        .map(|i| {
            let a = std::f64::consts::FRAC_PI_4 + i as f64 * std::f64::consts::FRAC_PI_2;
            let c = Vector3::new(60.0 * a.cos(), 60.0 * a.sin(), 45.0);
            let z = (-c).normalize();
            let x = z.cross(&Vector3::z()).normalize();
            let y = z.cross(&x);
            let rot = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
            let r = acm_rs::rotation::rodrigues_log(&rot).unwrap();
            let t = -(rot * c);
            Camera::from_params(&[
                r.x, r.y, r.z, t.x, t.y, t.z, 1400.0, 1400.0, 640.0, 512.0, -0.15, 0.08, 0.0, 0.0,
                0.0,
            ])
            .unwrap()
        })
        .collect()
}

pub fn pseudo_random(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        })
        .collect()
}
