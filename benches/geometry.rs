//! Criterion benchmarks of the geometry core on the ACM rat model (29 joints, 28 bones,
//! 43 markers, 50 free pose entries) and a 4-camera rig.
//!
//! The headline figure is `emission/101_sigma_points`: Alg. 4 (state → FK → projection into
//! 4 cameras → normalised pixels) for the 2·50 + 1 sigma points of one UKF step.

use acm_rs::camera;
use acm_rs::emission::emission_batch;
use acm_rs::limits::StateMap;
use acm_rs::normalization::Normalization;
use acm_rs::rotation::rodrigues_jacobian;
use common::{pseudo_random, rat, rig};
use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::Vector3;
use std::hint::black_box;

mod common;

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
