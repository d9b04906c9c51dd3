//! Posterior poses, joints and markers from the smoothed state moments.
//!
//! The reported pose of a frame is `f_{z*→z}(μ̂_t)` (Alg. 10) and its forward kinematics; the
//! uncertainty of every joint and marker coordinate is the unscented transform (Alg. 5,
//! eq. 43) of forward kinematics under `N(μ̂_t, V̂_t)`.

use super::dense::cholesky;
use super::filter::sigma_points;
use super::model::SkeletonEmission;
use crate::emission::state_forward_into;
use crate::error::{ensure_len, Result};
#[cfg(test)]
use nalgebra::DMatrix;
use rayon::prelude::*;

/// Posterior summaries of `T` frames.
#[derive(Debug, Clone, Default)]
pub struct PosteriorPoses {
    /// `(T, n_pose)` full poses `[t, r]` of the mean states.
    pub poses: Vec<f64>,
    /// `(T, J, 3)` joints of the mean states.
    pub joints: Vec<f64>,
    /// `(T, M, 3)` markers of the mean states.
    pub markers: Vec<f64>,
    /// `(T, J, 3)` posterior standard deviation of the joints.
    pub joints_std: Vec<f64>,
    /// `(T, M, 3)` posterior standard deviation of the markers.
    pub markers_std: Vec<f64>,
}

/// Computes [`PosteriorPoses`] for the frames of `means` (`T × n`) and `covs` (`T × n × n`),
/// in parallel over frames.
///
/// # Errors
/// Shape errors; numerical error if a covariance is not positive semi-definite.
pub fn posterior_poses(
    model: &SkeletonEmission,
    means: &[f64],
    covs: &[f64],
) -> Result<PosteriorPoses> {
    let sk = &model.skeleton;
    let n = model.map.n_state();
    let t_len = means.len() / n;
    ensure_len(means.len(), t_len * n, "state means (T, n)")?;
    ensure_len(covs.len(), t_len * n * n, "state covariances (T, n, n)")?;
    let (np, nj, nm) = (sk.n_pose(), sk.n_joints(), sk.n_markers());
    let plan = model.sigma_plan();
    let mut out = PosteriorPoses {
        poses: vec![0.0; t_len * np],
        joints: vec![0.0; t_len * nj * 3],
        markers: vec![0.0; t_len * nm * 3],
        joints_std: vec![0.0; t_len * nj * 3],
        markers_std: vec![0.0; t_len * nm * 3],
    };
    out.poses
        .par_chunks_mut(np)
        .zip(out.joints.par_chunks_mut(nj * 3))
        .zip(out.markers.par_chunks_mut(nm * 3))
        .zip(out.joints_std.par_chunks_mut(nj * 3))
        .zip(out.markers_std.par_chunks_mut(nm * 3))
        .enumerate()
        .try_for_each_init(
            || {
                (
                    sk.workspace(),
                    vec![0.0; 2 * n * n],
                    vec![0.0; np],
                    vec![0.0; nj * 3],
                    vec![0.0; nm * 3],
                    vec![0.0; sk.n_bones()],
                )
            },
            |(ws, sigma, pose, jb, mb, len), (t, ((((po, jo), mo), js), ms))| -> Result<()> {
                let mu = &means[t * n..(t + 1) * n];
                state_forward_into(sk, &model.map, mu, ws, po, len, Some(jo), mo);
                let l = cholesky(&covs[t * n * n..(t + 1) * n * n], n, &|| {
                    format!("the posterior covariance of frame {t}")
                })?;
                sigma_points(mu, &l, sigma);
                let mut jsum = vec![0.0; nj * 3];
                let mut jsq = vec![0.0; nj * 3];
                let mut msum = vec![0.0; nm * 3];
                let mut msq = vec![0.0; nm * 3];
                let add = |sum: &mut [f64], sq: &mut [f64], k: usize, d: f64| {
                    sum[k] += d;
                    sq[k] += d * d;
                };
                let Some(plan) = plan else {
                    for z in sigma.chunks_exact(n) {
                        state_forward_into(sk, &model.map, z, ws, pose, len, Some(jb), mb);
                        for (k, v) in jb.iter().enumerate() {
                            add(&mut jsum, &mut jsq, k, v - jo[k]);
                        }
                        for (k, v) in mb.iter().enumerate() {
                            add(&mut msum, &mut msq, k, v - mo[k]);
                        }
                    }
                    return finish(2 * n, &jsum, &jsq, &msum, &msq, js, ms);
                };
                // Sigma points of a lower-triangular factor: point i (rows i and n + i)
                // differs from the centre in the entries i..n only, so only the joints and
                // markers those move are recomputed (`SigmaPlan`, as in the filter's
                // emission); the others deviate from the centre by exactly 0 and add
                // nothing. Descending i: each point recomputes a superset of what the point
                // before changed, so the workspace holds the centre everywhere else.
                let mut centre_held = false;
                for i in (0..n).rev() {
                    let d = plan.dirty(i);
                    for row in [i, n + i] {
                        let z = &sigma[row * n..(row + 1) * n];
                        if z[..i] != mu[..i] {
                            // (not of a lower-triangular factor: in full)
                            state_forward_into(sk, &model.map, z, ws, pose, len, Some(jb), mb);
                            for (k, v) in jb.iter().enumerate() {
                                add(&mut jsum, &mut jsq, k, v - jo[k]);
                            }
                            for (k, v) in mb.iter().enumerate() {
                                add(&mut msum, &mut msq, k, v - mo[k]);
                            }
                            centre_held = false;
                            continue;
                        }
                        if !centre_held {
                            state_forward_into(sk, &model.map, mu, ws, pose, len, None, mb);
                            centre_held = true;
                        }
                        model.map.to_pose_tail_into(z, pose, i);
                        model.map.lengths_into(z, sk.lengths(), len);
                        let (t, r) = pose.split_at(3);
                        sk.forward_dirty_into(t, r, len, sk.offsets(), ws, d, mb);
                        let root = d.translation().then_some(sk.root());
                        for &j in root.iter().chain(d.joints()) {
                            let p = ws.joints()[j];
                            for a in 0..3 {
                                add(&mut jsum, &mut jsq, 3 * j + a, p[a] - jo[3 * j + a]);
                            }
                        }
                        for &m in d.markers() {
                            for k in 3 * m..3 * m + 3 {
                                add(&mut msum, &mut msq, k, mb[k] - mo[k]);
                            }
                        }
                    }
                }
                finish(2 * n, &jsum, &jsq, &msum, &msq, js, ms)
            },
        )?;
    Ok(out)
}

/// The SDs of the unscented transform (eq. 43, weights `1/(2n)`) from the sums of the sigma
/// points' deviations from the centre and of their squares.
fn finish(
    n_points: usize,
    jsum: &[f64],
    jsq: &[f64],
    msum: &[f64],
    msq: &[f64],
    js: &mut [f64],
    ms: &mut [f64],
) -> Result<()> {
    let w = 1.0 / n_points as f64;
    for (k, s) in js.iter_mut().enumerate() {
        let m = jsum[k] * w;
        *s = (jsq[k] * w - m * m).max(0.0).sqrt();
    }
    for (k, s) in ms.iter_mut().enumerate() {
        let m = msum[k] * w;
        *s = (msq[k] * w - m * m).max(0.0).sqrt();
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::emission::tests::sigma_cases;
    use crate::normalization::Normalization;

    /// The posterior SDs with the sigma plan equal those of every sigma point's full forward
    /// kinematics (summed in row order here), for a tree, a link matrix and elastic bones.
    #[test]
    fn posterior_sds_equal_the_full_unscented_transform() {
        let cam = Camera::from_params(&[
            0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 800.0, 800.0, 640.0, 512.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        ])
        .unwrap();
        let norm = Normalization::default();
        for (case, sk, map) in sigma_cases(&norm) {
            let model = SkeletonEmission::new(sk, vec![cam.clone()], map, norm).unwrap();
            assert!(model.sigma_plan().is_some());
            let n = model.map.n_state();
            let frames = 3;
            let means: Vec<f64> = (0..frames * n)
                .map(|i| ((i * 37 % 17) as f64 - 8.0) * 0.03)
                .collect();
            let mut covs = Vec::new();
            for t in 0..frames {
                let a = DMatrix::from_fn(n, n, |r, c| {
                    (((r * 7 + c * 13 + t) % 11) as f64 - 5.0) * 0.01
                });
                let v = &a * a.transpose() + DMatrix::identity(n, n) * 1e-3;
                covs.extend_from_slice(v.as_slice());
            }
            let got = posterior_poses(&model, &means, &covs).unwrap();
            let sk = &model.skeleton;
            let (nj, nm) = (sk.n_joints(), sk.n_markers());
            let mut ws = sk.workspace();
            let (mut pose, mut len) = (vec![0.0; sk.n_pose()], vec![0.0; sk.n_bones()]);
            let (mut j0, mut m0) = (vec![0.0; 3 * nj], vec![0.0; 3 * nm]);
            let (mut jz, mut mz) = (vec![0.0; 3 * nj], vec![0.0; 3 * nm]);
            for t in 0..frames {
                let mu = &means[t * n..(t + 1) * n];
                let map = &model.map;
                state_forward_into(
                    sk,
                    map,
                    mu,
                    &mut ws,
                    &mut pose,
                    &mut len,
                    Some(&mut j0),
                    &mut m0,
                );
                let l = cholesky(&covs[t * n * n..(t + 1) * n * n], n, &String::new).unwrap();
                let mut sigma = vec![0.0; 2 * n * n];
                sigma_points(mu, &l, &mut sigma);
                let (mut js, mut jq) = (vec![0.0; 3 * nj], vec![0.0; 3 * nj]);
                let (mut ms, mut mq) = (vec![0.0; 3 * nm], vec![0.0; 3 * nm]);
                for z in sigma.chunks_exact(n) {
                    state_forward_into(
                        sk,
                        map,
                        z,
                        &mut ws,
                        &mut pose,
                        &mut len,
                        Some(&mut jz),
                        &mut mz,
                    );
                    for k in 0..3 * nj {
                        js[k] += jz[k] - j0[k];
                        jq[k] += (jz[k] - j0[k]).powi(2);
                    }
                    for k in 0..3 * nm {
                        ms[k] += mz[k] - m0[k];
                        mq[k] += (mz[k] - m0[k]).powi(2);
                    }
                }
                let w = 1.0 / (2 * n) as f64;
                let sd = |s: f64, q: f64| (q * w - (s * w).powi(2)).max(0.0).sqrt();
                let mut moved = 0;
                for k in 0..3 * nj {
                    let want = sd(js[k], jq[k]);
                    let have = got.joints_std[t * 3 * nj + k];
                    assert!(
                        (have - want).abs() <= 1e-12 * (1.0 + want),
                        "{case} joint {k}: {have} vs {want}"
                    );
                    moved += usize::from(want > 0.0);
                }
                for k in 0..3 * nm {
                    let want = sd(ms[k], mq[k]);
                    let have = got.markers_std[t * 3 * nm + k];
                    assert!(
                        (have - want).abs() <= 1e-12 * (1.0 + want),
                        "{case} marker {k}: {have} vs {want}"
                    );
                }
                assert!(moved > 3 * nj / 2, "{case}: the joints have spread");
                assert_eq!(&got.joints[t * 3 * nj..(t + 1) * 3 * nj], &j0[..]);
                assert_eq!(&got.markers[t * 3 * nm..(t + 1) * 3 * nm], &m0[..]);
            }
        }
    }
}
