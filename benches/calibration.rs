//! Criterion benchmarks of the calibration objective (ACM supp. eq. 7): residuals and the
//! exact CSR Jacobian for a real-rig-sized problem (4 cameras, 220 board views, 9×6 board,
//! 11,880 detections).

use acm_rs::calibration::{CalibrationProblem, CAM_SKEW, N_CAM_PARAMS};
use acm_rs::camera::Camera;
use acm_rs::rotation::rodrigues;
use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::Vector3;
use std::hint::black_box;

/// Deterministic synthetic problem: cameras on a ring, boards in the middle, each (camera,
/// view) detection kept for about a quarter of the pairs.
fn problem() -> (CalibrationProblem, Vec<f64>) {
    let (nc, nf, nx, ny) = (4usize, 220usize, 9usize, 6usize);
    let mut board = Vec::new();
    for y in 0..ny {
        for x in 0..nx {
            board.extend_from_slice(&[x as f64 * 40.0 - 160.0, y as f64 * 40.0 - 100.0, 0.0]);
        }
    }
    let np = nx * ny;
    let mut params = Vec::new();
    let mut cams = Vec::new();
    for c in 0..nc {
        let a = c as f64 * std::f64::consts::FRAC_PI_2;
        // World = camera 0's frame; other cameras rotated about the board centre at z = 1000.
        let r = Vector3::new(0.0, -a * 0.35, 0.0);
        let rot = rodrigues(&r);
        let t = -(rot * Vector3::new(0.0, 0.0, 1000.0)) + Vector3::new(0.0, 0.0, 1000.0);
        let intr = [1200.0 + 10.0 * c as f64, 1195.0, 640.0, 512.0, -0.12, 0.03];
        params.extend_from_slice(&intr);
        params.extend_from_slice(&[r.x, r.y, r.z, t.x, t.y, t.z]);
        params.push(0.0); // skew, held fixed below (the solver's default)
        let mut p15 = [0.0; 15];
        p15[..3].copy_from_slice(&[r.x, r.y, r.z]);
        p15[3..6].copy_from_slice(&[t.x, t.y, t.z]);
        p15[6..12].copy_from_slice(&intr);
        cams.push(Camera::from_params(&p15).expect("valid camera"));
    }
    let mut corners = vec![f64::NAN; nc * nf * np * 2];
    for f in 0..nf {
        let s = f as f64;
        let pose = [
            0.3 * (0.37 * s).sin(),
            0.3 * (0.23 * s).cos(),
            0.5 * (0.11 * s).sin(),
            150.0 * (0.13 * s).sin(),
            100.0 * (0.17 * s).cos(),
            1000.0 + 80.0 * (0.07 * s).sin(),
        ];
        params.extend_from_slice(&pose);
        let rot = rodrigues(&Vector3::new(pose[0], pose[1], pose[2]));
        for (c, cam) in cams.iter().enumerate() {
            if (f * 7 + c * 3) % 4 != 0 {
                continue;
            }
            for j in 0..np {
                let m = Vector3::new(board[3 * j], board[3 * j + 1], board[3 * j + 2]);
                let x = rot * m + Vector3::new(pose[3], pose[4], pose[5]);
                if let Some(px) = cam.project(&x) {
                    let k = ((c * nf + f) * np + j) * 2;
                    corners[k] = px.x + 0.3 * ((k % 7) as f64 - 3.0) / 3.0;
                    corners[k + 1] = px.y - 0.3 * ((k % 5) as f64 - 2.0) / 2.0;
                }
            }
        }
    }
    let mut fixed = vec![false; params.len()];
    for c in 0..nc {
        fixed[c * N_CAM_PARAMS + CAM_SKEW] = true;
    }
    let p = CalibrationProblem::new(nc, nf, &board, &corners, 0, &params, &fixed)
        .expect("valid problem");
    let x = p.free_indices().iter().map(|&i| params[i]).collect();
    (p, x)
}

fn bench(c: &mut Criterion) {
    let (p, x) = problem();
    let mut res = vec![0.0; 2 * p.n_observations()];
    let mut data = vec![0.0; p.nnz()];
    let mut g = c.benchmark_group(format!(
        "calibration/{}_detections_{}_free",
        p.n_observations(),
        p.n_free()
    ));
    g.bench_function("residuals", |b| {
        b.iter(|| p.residuals_into(black_box(&x), &mut res).unwrap())
    });
    g.bench_function("jacobian_csr", |b| {
        b.iter(|| p.jacobian_into(black_box(&x), &mut data).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
