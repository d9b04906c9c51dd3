//! Criterion benchmarks of the geometry core on the ACM rat model (29 joints, 28 bones,
//! 43 markers, 50 free pose entries) and a 4-camera rig.
//!
//! The headline figure is `emission/101_sigma_points`: Alg. 4 (state → FK → projection into
//! 4 cameras → normalised pixels) for the 2·50 + 1 sigma points of one UKF step.

use acm_rs::camera::{self, Camera};
use acm_rs::emission::emission_batch;
use acm_rs::limits::StateMap;
use acm_rs::normalization::Normalization;
use acm_rs::rotation::rodrigues_jacobian;
use acm_rs::skeleton::Skeleton;
use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::{Matrix3, Vector3};
use std::hint::black_box;

/// Loads the bundled rat model from the Python package's data file.
fn rat() -> (Skeleton, Vec<f64>, Vec<f64>) {
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
fn rig() -> Vec<Camera> {
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

fn pseudo_random(n: usize, seed: u64) -> Vec<f64> {
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

fn benches(c: &mut Criterion) {
    let (sk, lower, upper) = rat();
    let cams = rig();
    let norm = Normalization::default();
    let map = StateMap::new(sk.n_bones(), &lower, &upper, &norm, true).unwrap();
    assert_eq!(map.n_state(), 50);

    let r = Vector3::new(0.3, -0.2, 0.9);
    c.bench_function("rotation/rodrigues_jacobian", |b| {
        b.iter(|| rodrigues_jacobian(black_box(&r)))
    });
    let x = Vector3::new(1.0, -2.0, 3.0);
    c.bench_function("camera/project_jacobian", |b| {
        b.iter(|| cams[0].project_jacobian(black_box(&x)))
    });

    let z = pseudo_random(map.n_state(), 1);
    let pose = map.to_pose(&z).unwrap();
    let t = Vector3::new(pose[0], pose[1], pose[2]);
    let rs: Vec<Vector3<f64>> = pose[3..]
        .chunks(3)
        .map(|c| Vector3::new(c[0], c[1], c[2]))
        .collect();
    c.bench_function("skeleton/forward_rat", |b| {
        b.iter(|| sk.forward_unchecked(black_box(&t), &rs, sk.lengths(), sk.offsets()))
    });
    c.bench_function("skeleton/forward_jacobian_rat", |b| {
        b.iter(|| sk.forward_jacobian(black_box(&t), &rs, None, None).unwrap())
    });

    let sigma: Vec<f64> = pseudo_random(101 * map.n_state(), 2)
        .iter()
        .map(|v| 0.3 * v)
        .collect();
    c.bench_function("emission/101_sigma_points", |b| {
        b.iter(|| emission_batch(&sk, &cams, &map, &norm, black_box(&sigma)).unwrap())
    });

    let frames = 10_000;
    let zs: Vec<f64> = pseudo_random(frames * map.n_state(), 3);
    let mut ts = Vec::with_capacity(frames * 3);
    let mut rvs = Vec::with_capacity(frames * 3 * sk.n_bones());
    for zf in zs.chunks(map.n_state()) {
        let p = map.to_pose(zf).unwrap();
        ts.extend_from_slice(&p[..3]);
        rvs.extend_from_slice(&p[3..]);
    }
    let mut group = c.benchmark_group("batch");
    group.sample_size(20);
    group.bench_function("forward_10k_frames", |b| {
        b.iter(|| sk.forward_batch(black_box(&ts), &rvs, None, None).unwrap())
    });
    let (_, markers) = sk.forward_batch(&ts, &rvs, None, None).unwrap();
    group.bench_function("project_10k_frames_4_cameras", |b| {
        b.iter(|| camera::project_points(&cams, black_box(&markers)).unwrap())
    });
    group.finish();
}

criterion_group!(geometry, benches);
criterion_main!(geometry);
