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
                for z in sigma.chunks_exact(n) {
                    state_forward_into(sk, &model.map, z, ws, pose, len, Some(jb), mb);
                    for (k, v) in jb.iter().enumerate() {
                        let d = v - jo[k];
                        jsum[k] += d;
                        jsq[k] += d * d;
                    }
                    for (k, v) in mb.iter().enumerate() {
                        let d = v - mo[k];
                        msum[k] += d;
                        msq[k] += d * d;
                    }
                }
                let w = 1.0 / (2 * n) as f64;
                for (k, s) in js.iter_mut().enumerate() {
                    let m = jsum[k] * w;
                    *s = (jsq[k] * w - m * m).max(0.0).sqrt();
                }
                for (k, s) in ms.iter_mut().enumerate() {
                    let m = msum[k] * w;
                    *s = (msq[k] * w - m * m).max(0.0).sqrt();
                }
                Ok(())
            },
        )?;
    Ok(out)
}
