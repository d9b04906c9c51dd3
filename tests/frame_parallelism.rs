//! `FrameParallelism` (issue 29): a filter step shared between two threads, a step on one
//! thread, and the automatic choice between them (timed on alternating frames, then the
//! faster) give the same moments bit for bit — so choosing by timing cannot change a result.

mod common;

use acm_rs::tracking::{Emission, FrameParallelism, Params, SkeletonEmission, Tracker};
use nalgebra::Vector3;

/// A 16-joint chain with a side branch, three markers per joint (n_z = 48, 2n = 96 sigma
/// points), six cameras (n_x = 576): large enough that the parallel step splits the sigma
/// points and the Gram matrix between the threads.
fn model() -> SkeletonEmission {
    let parents: Vec<i64> = (0..16)
        .map(|j| match j {
            0 => -1,
            10 => 5,
            _ => j - 1,
        })
        .collect();
    let rest: Vec<Vector3<f64>> = (0..16)
        .map(|j| match j {
            0..=9 => Vector3::new(0.0, 0.0, 1.5 * j as f64),
            _ => Vector3::new(1.2 * (j - 9) as f64, 0.0, 7.5),
        })
        .collect();
    let mut marker_joints = Vec::new();
    let mut markers = Vec::new();
    for (j, p) in rest.iter().enumerate() {
        for k in 0..3 {
            let a = 2.1 * k as f64 + 0.3 * j as f64;
            marker_joints.push(j);
            markers.push(p + Vector3::new(0.3 * a.cos(), 0.3 * a.sin(), 0.1 * k as f64));
        }
    }
    common::chain_emission(&parents, &rest, marker_joints, &markers, |_| (-1.2, 1.2), 6)
}

#[test]
fn serial_parallel_and_automatic_steps_give_the_same_moments() {
    let em = model();
    let (n, n_x) = (em.n_state(), em.n_meas());
    assert!(2 * n >= 96 && n_x >= 576, "n = {n}, n_x = {n_x}");
    // Past the automatic mode's trial (48 + 32 frames), so all three paths run.
    let frames = 130;
    let states: Vec<f64> = (0..frames)
        .flat_map(|t| (0..n).map(move |i| 0.4 * ((0.04 * t as f64) + 0.7 * i as f64).sin()))
        .collect();
    let mut x = vec![0.0; frames * n_x];
    em.eval_batch(&states, &mut x).unwrap();
    for t in 0..frames {
        for j in 0..n_x {
            let noise = 2e-4 * ((t * 31 + j * 17) % 13) as f64 - 1.2e-3;
            x[t * n_x + j] += noise;
            if (t * 7 + j * 3) % 11 == 0 {
                x[t * n_x + j] = f64::NAN;
            }
        }
    }
    let mut p = Params::initial(states[..n].to_vec(), n_x, 1e-3);
    p.vx.iter_mut().for_each(|v| *v = 1e-5);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let run = |mode: FrameParallelism| {
        let mut tr = Tracker::new(em.clone(), x.clone()).unwrap();
        tr.set_frame_parallelism(mode);
        let stats = pool.install(|| tr.e_step(&p, Some(13.8))).unwrap();
        (tr.means().to_vec(), tr.covs().to_vec(), stats)
    };
    let (m_ser, c_ser, s_ser) = run(FrameParallelism::Serial);
    assert!(m_ser.iter().all(|v| v.is_finite()));
    for mode in [FrameParallelism::Parallel, FrameParallelism::Auto] {
        let (m, c, s) = run(mode);
        assert!(m == m_ser, "{mode:?}: means differ");
        assert!(c == c_ser, "{mode:?}: covariances differ");
        assert_eq!(s.log_lik.to_bits(), s_ser.log_lik.to_bits(), "{mode:?}");
    }
}
