//! Criterion benchmarks of the tracker (ACM supp. Alg. 5-13) on the rat model (n_z = 50) with
//! a 4-camera rig (n_x = 344), and on the state size of a user's skeleton without joint limits
//! (issue 29: the rat's 29 joints without limits, n_z = 87, and 62 markers, n_x = 496): one
//! E-step (UKF + RTS smoother) under both motion models, one M-step and the parts of a filter
//! step, on 200 frames (the authors' example size) with 15 % of entries missing.
//!
//! `cargo bench --bench tracking -- rat50` or `-- big87` for one case.

use acm_rs::emission::emission_batch;
use acm_rs::kernels::cholesky_in_place;
use acm_rs::limits::StateMap;
use acm_rs::normalization::Normalization;
use acm_rs::skeleton::Skeleton;
use acm_rs::tracking::{dense, Emission, Params, SkeletonEmission, Tracker};
use common::{pseudo_random, rat, rig};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use nalgebra::Vector3;
use std::hint::black_box;

mod common;

const FRAMES: usize = 200;

/// The rat with its joint limits: 50 free state entries, 43 markers.
fn rat50() -> SkeletonEmission {
    let (sk, lower, upper) = rat();
    let norm = Normalization::default();
    let map = StateMap::new(sk.n_bones(), &lower, &upper, &norm, true).unwrap();
    SkeletonEmission::new(sk, rig(), map, norm).unwrap()
}

/// The rat's 29 joints without joint limits (3 + 28 · 3 = 87 state entries) wearing 62
/// markers: its 43 and one more on each of the 19 joints with the fewest.
fn big87() -> SkeletonEmission {
    let (sk, _, _) = rat();
    let parents: Vec<i64> = sk
        .parents()
        .iter()
        .map(|p| p.map_or(-1, |p| p as i64))
        .collect();
    let mut count = vec![0usize; sk.n_joints()];
    for &j in sk.marker_joints() {
        count[j] += 1;
    }
    let mut joints: Vec<usize> = (0..sk.n_joints()).collect();
    joints.sort_by_key(|&j| count[j]);
    let mut mj = sk.marker_joints().to_vec();
    let mut offsets = sk.offsets().to_vec();
    let jitter = pseudo_random(3 * 19, 11);
    for (k, &j) in joints.iter().take(19).enumerate() {
        mj.push(j);
        offsets.push(0.4 * Vector3::new(jitter[3 * k], jitter[3 * k + 1], jitter[3 * k + 2]));
    }
    let sk = Skeleton::new(
        &parents,
        sk.rest_frames().to_vec(),
        sk.lengths().to_vec(),
        mj,
        offsets,
    )
    .unwrap();
    let free = vec![f64::INFINITY; 3 * sk.n_bones()];
    let neg: Vec<f64> = free.iter().map(|v| -v).collect();
    let norm = Normalization::default();
    let map = StateMap::new(sk.n_bones(), &neg, &free, &norm, false).unwrap();
    SkeletonEmission::new(sk, rig(), map, norm).unwrap()
}

fn benches(c: &mut Criterion) {
    for (name, em) in [("rat50", rat50()), ("big87", big87())] {
        case(c, name, &em);
    }
}

fn case(c: &mut Criterion, name: &str, em: &SkeletonEmission) {
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
    let mut tracker = Tracker::new(em.clone(), x.clone()).unwrap();
    // the position-velocity model (state 2n), velocity starting at 0
    let mut mu2 = z[..n].to_vec();
    mu2.resize(2 * n, 0.0);
    let mut params2 = Params::initial(mu2, n_x, 1e-3);
    params2.vx.iter_mut().for_each(|v| *v = 1e-5);
    let mut velocity = Tracker::new(em.clone(), x).unwrap();
    velocity.set_order(2).unwrap();

    let mut group = c.benchmark_group(format!("tracking/{name}"));
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
    group.bench_function("velocity_e_step_200_frames", |b| {
        b.iter(|| velocity.e_step(black_box(&params2), None).unwrap())
    });
    group.bench_function("velocity_smooth_200_frames", |b| {
        b.iter(|| velocity.smooth(black_box(&params2), None).unwrap())
    });
    group.finish();

    // Parts of one filter step: the 2n sigma points through g, the Gram matrix ỸỸᵀ
    // (2n × n_x) and the Cholesky factor of M = I + ỸỸᵀ.
    let mut group = c.benchmark_group(format!("tracking/{name}/step"));
    let sigma: Vec<f64> = pseudo_random(2 * n * n, 7)
        .iter()
        .map(|v| 0.3 * v)
        .collect();
    group.bench_function(format!("emission_{}_sigma_points", 2 * n), |b| {
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
    // the sigma points of a lower-triangular factor (a UKF step's): each point moves only the
    // markers of its state entries onward (Emission::eval_sigma), one thread and two
    let centre: Vec<f64> = sigma[..n].to_vec();
    let lower: Vec<f64> = pseudo_random(n * n, 9)
        .iter()
        .enumerate()
        .map(|(e, v)| if e % n < e / n { 0.0 } else { 0.02 * v })
        .collect();
    let mut points = vec![0.0; 2 * n * n];
    let s = (n as f64).sqrt();
    for i in 0..n {
        for r in 0..n {
            points[i * n + r] = centre[r] + s * lower[i * n + r];
            points[(n + i) * n + r] = centre[r] - s * lower[i * n + r];
        }
    }
    let mut gx = vec![0.0; 2 * n * n_x];
    for serial in [true, false] {
        let threads = if serial { "one_thread" } else { "two_threads" };
        group.bench_function(format!("emission_{}_full_{threads}", 2 * n), |b| {
            b.iter(|| {
                if serial {
                    em.eval_batch_serial(black_box(&points), &mut gx).unwrap()
                } else {
                    em.eval_batch(black_box(&points), &mut gx).unwrap()
                }
            })
        });
        group.bench_function(format!("emission_{}_sigma_{threads}", 2 * n), |b| {
            b.iter(|| {
                em.eval_sigma(&centre, black_box(&points), serial, &mut gx)
                    .unwrap()
            })
        });
    }
    let ytil = pseudo_random(2 * n * n_x, 8);
    let mut gram = vec![0.0; 4 * n * n];
    group.bench_function(format!("gram_{}x{n_x}", 2 * n), |b| {
        b.iter(|| dense::add_gram_rows(black_box(&ytil), 2 * n, n_x, &mut gram, true))
    });
    group.bench_function(format!("gram_{}x{n_x}_one_thread", 2 * n), |b| {
        b.iter(|| dense::add_gram_rows(black_box(&ytil), 2 * n, n_x, &mut gram, false))
    });
    for (i, g) in gram.iter_mut().enumerate() {
        if i % (2 * n + 1) == 0 {
            *g += 1.0;
        }
    }
    let mut l = gram.clone();
    group.bench_function(format!("cholesky_{}", 2 * n), |b| {
        b.iter(|| {
            l.copy_from_slice(&gram);
            assert!(cholesky_in_place(black_box(&mut l), 2 * n));
        })
    });
    // the 87-entry skeleton's `M = I + ỸᵀỸ` (174 × 174) and its prediction (87 × 87)
    for size in [87usize, 174] {
        let y = pseudo_random(size * 300, 9);
        let mut spd = vec![0.0; size * size];
        dense::add_gram_rows(&y, size, 300, &mut spd, false);
        for i in 0..size {
            spd[i * (size + 1)] += 1.0;
        }
        let mut l = spd.clone();
        group.bench_function(format!("cholesky_{size}"), |b| {
            b.iter(|| {
                l.copy_from_slice(&spd);
                assert!(cholesky_in_place(black_box(&mut l), size));
            })
        });
    }
    group.finish();
}

criterion_group!(tracking, benches);
criterion_main!(tracking);
