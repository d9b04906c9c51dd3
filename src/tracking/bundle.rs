//! NPZ bundles for batch smoothing without Python (the `acm-smooth` binary).
//!
//! A bundle holds the learned skeleton, the calibrated cameras, the 2D detections, the initial
//! state `μ0` (the single-frame fit of sec. 4.7) and options; the result NPZ holds the
//! smoothed poses, joints, markers, their posterior standard deviations and the learned
//! parameters. `acm_rs.tracking.write_bundle` / `read_smoothed` write and read them from
//! Python; the layout is documented in `docs/tracking.md`.

use super::{
    moments, status, EmOptions, EmOutcome, Emission, Iteration, Params, SkeletonEmission, Tracker,
};
use crate::camera::Camera;
use crate::error::{AcmError, Result};
use crate::limits::StateMap;
use crate::normalization::Normalization;
use crate::npz::{self, Array};
use crate::skeleton::Skeleton;
use nalgebra::{Matrix3, Vector3};
use std::collections::BTreeMap;
use std::path::Path;

/// Everything needed to run EM + smoothing on one recording.
#[derive(Debug, Clone)]
pub struct Bundle {
    /// Emission model (skeleton, cameras, state map, normalisation).
    pub model: SkeletonEmission,
    /// Detections in pixels, `(n_cams, T, M, 2)`, NaN = missing (after the `pcutoff`).
    pub detections: Vec<f64>,
    /// Number of frames.
    pub n_frames: usize,
    /// Initial parameters (sec. 4.7).
    pub init: Params,
    /// EM options.
    pub options: EmOptions,
}

/// Outcome of [`smooth_bundle`].
#[derive(Debug, Clone)]
pub struct Summary {
    /// Number of frames.
    pub n_frames: usize,
    /// EM outcome (parameters, history, convergence).
    pub outcome: EmOutcome,
    /// Mean reprojection error of the posterior mean poses over the used detections (px).
    pub mean_reprojection_px: f64,
}

fn get<'a>(m: &'a BTreeMap<String, Array>, key: &str, what: &str) -> Result<&'a Array> {
    m.get(key).ok_or_else(|| {
        AcmError::Invalid(format!(
            "{what}: the bundle has no array '{key}' (see docs/tracking.md for the layout)"
        ))
    })
}

fn shaped<'a>(
    m: &'a BTreeMap<String, Array>,
    key: &str,
    shape: &[Option<usize>],
    what: &str,
) -> Result<&'a Array> {
    let a = get(m, key, what)?;
    let ok = a.shape.len() == shape.len()
        && a.shape
            .iter()
            .zip(shape)
            .all(|(s, e)| e.is_none_or(|e| e == *s));
    if !ok {
        let expected: Vec<String> = shape
            .iter()
            .map(|e| e.map_or_else(|| "any".to_string(), |e| e.to_string()))
            .collect();
        return Err(AcmError::Shape(format!(
            "{what}: '{key}' has shape {:?}, expected [{}]",
            a.shape,
            expected.join(", ")
        )));
    }
    Ok(a)
}

fn scalar(m: &BTreeMap<String, Array>, key: &str, default: f64) -> f64 {
    m.get(key)
        .and_then(|a| a.data.first().copied())
        .unwrap_or(default)
}

/// A scalar option of the bundle checked against `ok` (the message says what is allowed).
fn checked(
    m: &BTreeMap<String, Array>,
    key: &str,
    default: f64,
    ok: impl Fn(f64) -> bool,
    allowed: &str,
    what: &str,
) -> Result<f64> {
    if let Some(a) = m.get(key) {
        if a.data.len() != 1 {
            return Err(AcmError::Shape(format!(
                "{what}: '{key}' must be one number, got shape {:?}",
                a.shape
            )));
        }
    }
    let v = scalar(m, key, default);
    if ok(v) {
        Ok(v)
    } else {
        Err(AcmError::Invalid(format!(
            "{what}: '{key}' = {v} is not allowed; it must be {allowed}"
        )))
    }
}

/// Builds a [`Bundle`] from the arrays of a bundle NPZ.
///
/// # Errors
/// Invalid/shape errors naming the missing or malformed array; model errors (not a tree,
/// bad limits, bad cameras).
pub fn bundle_from_arrays(m: &BTreeMap<String, Array>, what: &str) -> Result<Bundle> {
    let parents = get(m, "parents", what)?;
    let nj = parents.data.len();
    if nj < 2 {
        return Err(AcmError::Invalid(format!(
            "{what}: the skeleton needs at least 2 joints"
        )));
    }
    let nb = nj - 1;
    let parents: Vec<i64> = parents.data.iter().map(|&v| v as i64).collect();
    let frames = shaped(m, "rest_frames", &[Some(nb), Some(3), Some(3)], what)?;
    let lengths = shaped(m, "bone_lengths", &[Some(nb)], what)?;
    let mj = get(m, "marker_joints", what)?;
    let nm = mj.data.len();
    let offsets = shaped(m, "marker_offsets", &[Some(nm), Some(3)], what)?;
    let limits = shaped(m, "joint_limits", &[Some(nb), Some(3), Some(2)], what)?;
    // (C, 16) cameras, or (C, 15) without skew (bundles written before skew existed)
    let width = match get(m, "cameras", what)?.shape.as_slice() {
        [_, w] if *w == crate::camera::N_PARAMS_NO_SKEW => crate::camera::N_PARAMS_NO_SKEW,
        _ => crate::camera::N_PARAMS,
    };
    let cams = shaped(m, "cameras", &[None, Some(width)], what)?;
    let normv = shaped(m, "normalization", &[Some(4)], what)?;
    let nc = cams.shape[0];
    let det = shaped(m, "detections", &[Some(nc), None, Some(nm), Some(2)], what)?;
    let t_len = det.shape[1];
    let skeleton = Skeleton::new(
        &parents,
        frames
            .data
            .chunks_exact(9)
            .map(Matrix3::from_row_slice)
            .collect(),
        lengths.data.clone(),
        mj.data.iter().map(|&v| v as usize).collect(),
        offsets
            .data
            .chunks_exact(3)
            .map(|c| Vector3::new(c[0], c[1], c[2]))
            .collect(),
    )?;
    // An explicit link matrix (e.g. from an ACM model.npy); absent: the tree rule.
    let skeleton = match m.get("bone_links") {
        None => skeleton,
        Some(_) => {
            let links = shaped(m, "bone_links", &[Some(nb), Some(nb)], what)?;
            let order = shaped(m, "link_order", &[Some(nb)], what)?;
            let flat: Vec<bool> = links.data.iter().map(|&v| v != 0.0).collect();
            let mut ord = Vec::with_capacity(nb);
            for &v in &order.data {
                if !(v >= 0.0 && v.fract() == 0.0) {
                    return Err(AcmError::Invalid(format!(
                        "{what}: 'link_order' must hold bone indices, got {v}"
                    )));
                }
                ord.push(v as usize);
            }
            skeleton.with_links(&flat, Some(&ord))?
        }
    };
    let cameras = Camera::many_from_rows(&cams.data, width)?;
    let norm = Normalization {
        translation: normv.data[0],
        rotation: normv.data[1],
        pixel: [normv.data[2], normv.data[3]],
    };
    let lower: Vec<f64> = limits.data.chunks_exact(2).map(|c| c[0]).collect();
    let upper: Vec<f64> = limits.data.chunks_exact(2).map(|c| c[1]).collect();
    let enforce = scalar(m, "joint_limits_on", 1.0) != 0.0;
    let map = StateMap::new(nb, &lower, &upper, &norm, enforce)?;
    let model = SkeletonEmission::new(skeleton, cameras, map, norm)?;
    let n = model.n_state();
    let mu0 = shaped(m, "mu0", &[Some(n)], what)?.data.clone();
    let mut detections = det.data.clone();
    if let Some(lik) = m.get("likelihood") {
        if lik.shape != [nc, t_len, nm] {
            return Err(AcmError::Shape(format!(
                "{what}: 'likelihood' has shape {:?}, expected [{nc}, {t_len}, {nm}]",
                lik.shape
            )));
        }
        let pcutoff = checked(
            m,
            "pcutoff",
            0.9,
            |v| (0.0..=1.0).contains(&v),
            "in [0, 1]",
            what,
        )?;
        for (k, &l) in lik.data.iter().enumerate() {
            if l.is_nan() || l < pcutoff {
                detections[2 * k] = f64::NAN;
                detections[2 * k + 1] = f64::NAN;
            }
        }
    }
    let noise = checked(
        m,
        "noise",
        2e-4,
        |v| v.is_finite() && v > 0.0,
        "a finite number > 0",
        what,
    )?;
    let nan_or_positive = |v: f64| v.is_nan() || (v.is_finite() && v > 0.0);
    let gate = checked(
        m,
        "gate",
        f64::NAN,
        nan_or_positive,
        "NaN (off) or > 0",
        what,
    )?;
    let ll_tol = checked(
        m,
        "ll_tol",
        f64::NAN,
        nan_or_positive,
        "NaN (off) or > 0",
        what,
    )?;
    let dof = checked(
        m,
        "dof",
        f64::NAN,
        nan_or_positive,
        "NaN (Gaussian) or > 0",
        what,
    )?;
    let max_iter = checked(
        m,
        "max_iter",
        100.0,
        |v| v.is_finite() && v >= 1.0 && v.fract() == 0.0,
        "a whole number >= 1",
        what,
    )?;
    let tol = checked(
        m,
        "tol",
        0.05,
        |v| v.is_finite() && v > 0.0,
        "a finite number > 0",
        what,
    )?;
    let options = EmOptions {
        max_iter: max_iter as usize,
        tol,
        gate: (gate.is_finite() && gate > 0.0).then_some(gate),
        ll_tol: Some(ll_tol).filter(|v| v.is_finite() && *v > 0.0),
        dof: Some(dof).filter(|v| v.is_finite() && *v > 0.0),
        patience: Some(super::DEFAULT_PATIENCE),
        overrelax: Some(super::DEFAULT_OVERRELAX),
    };
    let mut init = Params::initial(mu0, model.n_meas(), noise);
    // Optional start of diag(V_x) (`acm_rs.tracking.track.initial_vx`: the detections' own
    // noise); absent: `noise` as for V0 and V_z (sec. 4.7).
    if m.contains_key("vx_init") {
        let vx = shaped(m, "vx_init", &[Some(model.n_meas())], what)?;
        if let Some(v) = vx.data.iter().find(|v| !(v.is_finite() && **v > 0.0)) {
            return Err(AcmError::Invalid(format!(
                "{what}: 'vx_init' must be finite and > 0, got {v}"
            )));
        }
        init.vx = vx.data.clone();
    }
    Ok(Bundle {
        model,
        detections,
        n_frames: t_len,
        init,
        options,
    })
}

/// Runs EM + smoothing on a bundle; returns the result arrays and a summary.
///
/// # Errors
/// As [`Tracker::run_em`]; an error if no detection is usable.
pub fn smooth_bundle(
    b: Bundle,
    keep_cov: bool,
    on_iteration: impl FnMut(&Iteration) -> bool,
) -> Result<(BTreeMap<String, Array>, Summary)> {
    let model = b.model;
    let (nc, nm, t_len) = (model.cameras.len(), model.skeleton.n_markers(), b.n_frames);
    let n = model.n_state();
    let n_x = model.n_meas();
    if b.detections.iter().all(|v| v.is_nan()) {
        return Err(AcmError::Invalid(
            "no detection is usable (all NaN or below pcutoff)".into(),
        ));
    }
    // (C, T, M, 2) px → (T, C, M, 2) normalised (eq. 11).
    let mut x = vec![f64::NAN; t_len * n_x];
    for c in 0..nc {
        for t in 0..t_len {
            for k in 0..nm {
                for a in 0..2 {
                    let v = b.detections[((c * t_len + t) * nm + k) * 2 + a];
                    x[((t * nc + c) * nm + k) * 2 + a] = v / model.norm.pixel[a] - 1.0;
                }
            }
        }
    }
    let mut tracker = Tracker::new(model, x)?;
    let outcome = tracker.run_em(b.init, &b.options, on_iteration)?;
    let model = tracker.emission();
    let means = &tracker.means()[n..];
    let covs = &tracker.covs()[n * n..];
    let post = moments::posterior_poses(model, means, covs)?;
    // Reprojection error of the mean poses over the used detections.
    let mut g = vec![0.0; t_len * n_x];
    model.eval_batch(means, &mut g)?;
    let (mut sum, mut cnt) = (0.0, 0usize);
    let mut status_out = vec![0.0; nc * t_len * nm];
    for t in 0..t_len {
        for c in 0..nc {
            for k in 0..nm {
                let j = ((t * nc + c) * nm + k) * 2;
                let s = tracker.mask()[j];
                status_out[(c * t_len + t) * nm + k] = s as f64;
                if s == status::USED && g[j].is_finite() {
                    let px = |i: usize, a: usize| (g[i] + 1.0) * model.norm.pixel[a];
                    let det = |a: usize| b.detections[((c * t_len + t) * nm + k) * 2 + a];
                    let du = px(j, 0) - det(0);
                    let dv = px(j + 1, 1) - det(1);
                    sum += (du * du + dv * dv).sqrt();
                    cnt += 1;
                }
            }
        }
    }
    let (nb, nj) = (model.skeleton.n_bones(), model.skeleton.n_joints());
    let np = model.skeleton.n_pose();
    let mut out = BTreeMap::new();
    let mut put = |k: &str, shape: Vec<usize>, data: Vec<f64>| -> Result<()> {
        out.insert(k.to_string(), Array::new(shape, data)?);
        Ok(())
    };
    let poses = post.poses;
    let t_arr: Vec<f64> = poses
        .chunks_exact(np)
        .flat_map(|p| p[..3].to_vec())
        .collect();
    let r_arr: Vec<f64> = poses
        .chunks_exact(np)
        .flat_map(|p| p[3..].to_vec())
        .collect();
    put("t", vec![t_len, 3], t_arr)?;
    put("r", vec![t_len, nb, 3], r_arr)?;
    put("joints", vec![t_len, nj, 3], post.joints)?;
    put("joints_std", vec![t_len, nj, 3], post.joints_std)?;
    put("markers", vec![t_len, nm, 3], post.markers)?;
    put("markers_std", vec![t_len, nm, 3], post.markers_std)?;
    put("state_mean", vec![t_len, n], means.to_vec())?;
    if keep_cov {
        put("state_cov", vec![t_len, n, n], covs.to_vec())?;
    }
    put("status", vec![nc, t_len, nm], status_out)?;
    let hist = &outcome.history;
    put(
        "em_delta",
        vec![hist.len()],
        hist.iter().map(|h| h.delta).collect(),
    )?;
    put(
        "em_seconds",
        vec![hist.len()],
        hist.iter().map(|h| h.seconds).collect(),
    )?;
    put("converged", vec![], vec![outcome.converged as u8 as f64])?;
    let p = &outcome.params;
    put("mu0", vec![n], p.mu0.clone())?;
    put("V0", vec![n, n], p.v0.clone())?;
    put("Vz", vec![n, n], p.vz.clone())?;
    put("Vx_diag", vec![n_x], p.vx.clone())?;
    let mean_px = if cnt > 0 { sum / cnt as f64 } else { f64::NAN };
    put("mean_reprojection_px", vec![], vec![mean_px])?;
    Ok((
        out,
        Summary {
            n_frames: t_len,
            outcome,
            mean_reprojection_px: mean_px,
        },
    ))
}

/// Reads a bundle file, smooths it and writes the result NPZ atomically (temporary file in
/// the target folder, then rename).
///
/// # Errors
/// I/O errors (as invalid errors naming the path), bundle and tracker errors.
pub fn smooth_file(
    input: &Path,
    output: &Path,
    keep_cov: bool,
    on_iteration: impl FnMut(&Iteration) -> bool,
) -> Result<Summary> {
    let what = input.display().to_string();
    let f = std::fs::File::open(input).map_err(|e| AcmError::Invalid(format!("{what}: {e}")))?;
    let arrays = npz::read_npz(std::io::BufReader::new(f), &what)?;
    let bundle = bundle_from_arrays(&arrays, &what)?;
    let (out, summary) = smooth_bundle(bundle, keep_cov, on_iteration)?;
    let name = output
        .file_name()
        .ok_or_else(|| AcmError::Invalid(format!("{}: not a file path", output.display())))?;
    let tmp = output.with_file_name(format!(".{}.tmp", name.to_string_lossy()));
    let io_err = |e: std::io::Error| AcmError::Invalid(format!("{}: {e}", output.display()));
    {
        let f = std::fs::File::create(&tmp).map_err(io_err)?;
        let mut w = std::io::BufWriter::new(f);
        npz::write_npz(&mut w, &out, &["status", "converged"])?;
        let f = w.into_inner().map_err(|e| io_err(e.into_error()))?;
        f.sync_all().map_err(io_err)?;
    }
    std::fs::rename(&tmp, output).map_err(io_err)?;
    Ok(summary)
}
