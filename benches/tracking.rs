//! Criterion benchmarks of the tracker (ACM supp. Alg. 5-13) on the rat model (n_z = 50) with
//! a 4-camera rig (n_x = 344): one E-step (UKF + RTS smoother), one M-step and the parts of a
//! filter step, on 200 frames (the authors' example size) with 15 % of entries missing.

use acm_rs::emission::emission_batch;
use acm_rs::limits::StateMap;
use acm_rs::normalization::Normalization;
use acm_rs::tracking::{dense, Emission, Params, SkeletonEmission, Tracker};
use common::{pseudo_random, rat, rig};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use std::hint::black_box;

mod common;

const FRAMES: usize = 200;

fn benches(c: &mut Criterion) {
    let (sk, lower, upper) = rat();
    let norm = Normalization::default();
    let map = StateMap::new(sk.n_bones(), &lower, &upper, &norm, true).unwrap();
    let em = SkeletonEmission::new(sk, rig(), map, norm).unwrap();
    let (n, n_x) = (em.n_state(), em.n_meas());
    // A smooth random walk of states, its emission, noise of ~2 px and 15 % missing.
    let steps = pseudo_random(FRAMES * n, 5);
    let mut z = vec![0.0; FRAMES * n];
    for t in 0..FRAMES {
        for i in 0..n {
            let prev = if t == 0 { 0.0 } else { z[(t - 1) * n + i] };
            z[t * n + i] = prev + 0.02 * steps[t * n + i];
        }
    }
    let mut x = vec![0.0; FRAMES * n_x];
    em.eval_batch(&z, &mut x).unwrap();
    let noise = pseudo_random(FRAMES * n_x, 6);
    for (v, e) in x.iter_mut().zip(&noise) {
        *v += 0.003 * e;
        if e.abs() > 0.85 {
            *v = f64::NAN;
        }
    }
    let mut params = Params::initial(z[..n].to_vec(), n_x, 1e-3);
    params.vx.iter_mut().for_each(|v| *v = 1e-5);
    let mut tracker = Tracker::new(em.clone(), x).unwrap();

    let mut group = c.benchmark_group("tracking");
    group.sample_size(10);
    group.throughput(Throughput::Elements(FRAMES as u64));
    group.bench_function("e_step_200_frames", |b| {
        b.iter(|| tracker.e_step(black_box(&params), None).unwrap())
    });
    group.bench_function("filter_200_frames", |b| {
        b.iter(|| tracker.filter(black_box(&params), None).unwrap())
    });
    tracker.e_step(&params, None).unwrap();
    group.bench_function("m_step_200_frames", |b| {
        b.iter(|| tracker.m_step(black_box(&params)).unwrap())
    });
    group.finish();

    // Parts of one filter step.
    let sigma: Vec<f64> = pseudo_random(2 * n * n, 7)
        .iter()
        .map(|v| 0.3 * v)
        .collect();
    c.bench_function("tracking/emission_100_sigma_points", |b| {
        b.iter(|| {
            emission_batch(
                &em.skeleton,
                &em.cameras,
                &em.map,
                &em.norm,
                black_box(&sigma),
            )
        })
    });
    let ytil = pseudo_random(2 * n * n_x, 8);
    let mut gram = vec![0.0; 4 * n * n];
    c.bench_function("tracking/gram_100x344", |b| {
        b.iter(|| dense::add_gram_rows(black_box(&ytil), 2 * n, n_x, &mut gram, true))
    });
}

criterion_group!(tracking, benches);
criterion_main!(tracking);
