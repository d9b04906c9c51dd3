//! The emission function `g` of the state-space model (ACM supp. Alg. 4, eq. 50): state →
//! forward kinematics → projection into every camera → normalised pixels (eq. 11). Batches
//! of states (e.g. one set of sigma points) are evaluated in parallel.

use crate::camera::{camera_blocks, Camera};
use crate::error::{ensure_len, AcmError, Result};
use crate::limits::StateMap;
use crate::normalization::Normalization;
use crate::skeleton::Skeleton;
use nalgebra::Vector3;
use rayon::prelude::*;

/// Projects flat `(M, 3)` markers into one camera, writing `(M, 2)` into `out` (normalised by
/// eq. 11 when `norm` is given); NaN where a marker is behind the camera.
fn project_one_camera(
    markers: &[f64],
    cam: &Camera,
    out: &mut [f64],
    norm: Option<&Normalization>,
) {
    for (o, m) in out.chunks_exact_mut(2).zip(markers.chunks_exact(3)) {
        match cam.project(&Vector3::new(m[0], m[1], m[2])) {
            Some(uv) => {
                let (u, v) = match norm {
                    Some(n) => n.normalize_pixel(uv.x, uv.y),
                    None => (uv.x, uv.y),
                };
                o[0] = u;
                o[1] = v;
            }
            None => {
                o[0] = f64::NAN;
                o[1] = f64::NAN;
            }
        }
    }
}

/// One camera's projection (eq. 4 with the distortion of eqs. 5-6) fused with the pixel
/// normalisation of eq. 11, for the hot loop of the emission: `u_n = a_u x'' + s_u y'' + b_u`
/// with `a_u = f_x / c_u`, `s_u = s / c_u` (skew), `b_u = c_x / c_u − 1` (likewise `v`, no
/// skew term), one division per point.
/// The same model as [`Camera::project`] followed by [`Normalization::normalize_pixel`];
/// the results agree to rounding.
#[derive(Debug, Clone, Copy)]
struct NormalizedProjector {
    /// Rotation, row-major.
    r: [f64; 9],
    t: [f64; 3],
    /// `k1, k2, p1, p2, k3`.
    dist: [f64; 5],
    /// `a_u, b_u, a_v, b_v`.
    affine: [f64; 4],
    /// `s_u = s / c_u` (0 without skew: `a_u x'' + 0 y''` is `a_u x''` exactly).
    skew: f64,
}

impl NormalizedProjector {
    fn new(cam: &Camera, norm: &Normalization) -> Self {
        let p = cam.params();
        let rot = cam.rotation();
        let t = cam.translation();
        let mut r = [0.0; 9];
        for i in 0..3 {
            for j in 0..3 {
                r[3 * i + j] = rot[(i, j)];
            }
        }
        let [cu, cv] = norm.pixel;
        Self {
            r,
            t: [t.x, t.y, t.z],
            dist: [p[10], p[11], p[12], p[13], p[14]],
            affine: [p[6] / cu, p[8] / cu - 1.0, p[7] / cv, p[9] / cv - 1.0],
            skew: p[crate::camera::param::SKEW] / cu,
        }
    }

    /// Projects flat `(M, 3)` markers to flat `(M, 2)` normalised pixels (NaN behind the
    /// camera).
    #[inline(always)]
    fn project(&self, markers: &[f64], out: &mut [f64]) {
        // Four markers at a time without a branch (the loops over the lanes vectorise; a
        // marker behind the camera is set to NaN afterwards): the same operations per marker
        // as the one-at-a-time loop below, so the same pixels bit for bit.
        const LANES: usize = 4;
        let mut mq = markers.chunks_exact(3 * LANES);
        let mut oq = out.chunks_exact_mut(2 * LANES);
        for (m, o) in (&mut mq).zip(&mut oq) {
            self.project_lanes::<LANES>(m, o);
        }
        self.project_one_by_one(mq.remainder(), oq.into_remainder());
    }

    /// [`Self::project`] of `L` markers (`3L` coordinates into `2L` values), lane-wise.
    #[inline(always)]
    fn project_lanes<const L: usize>(&self, m: &[f64], o: &mut [f64]) {
        let (r, t) = (&self.r, &self.t);
        let [k1, k2, p1, p2, k3] = self.dist;
        let [au, bu, av, bv] = self.affine;
        let su = self.skew;
        let (mut u, mut v, mut z) = ([0.0; L], [0.0; L], [0.0; L]);
        for k in 0..L {
            let (mx, my, mz) = (m[3 * k], m[3 * k + 1], m[3 * k + 2]);
            let x = r[0] * mx + r[1] * my + r[2] * mz + t[0];
            let y = r[3] * mx + r[4] * my + r[5] * mz + t[1];
            z[k] = r[6] * mx + r[7] * my + r[8] * mz + t[2];
            let iz = 1.0 / z[k];
            let (xn, yn) = (x * iz, y * iz);
            let r2 = xn * xn + yn * yn;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn);
            let yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
            u[k] = au * xd + su * yd + bu;
            v[k] = av * yd + bv;
        }
        for k in 0..L {
            let behind = z[k] <= crate::camera::MIN_DEPTH;
            o[2 * k] = if behind { f64::NAN } else { u[k] };
            o[2 * k + 1] = if behind { f64::NAN } else { v[k] };
        }
    }

    /// [`Self::project`] one marker at a time.
    #[inline(always)]
    fn project_one_by_one(&self, markers: &[f64], out: &mut [f64]) {
        let (r, t) = (&self.r, &self.t);
        let [k1, k2, p1, p2, k3] = self.dist;
        let [au, bu, av, bv] = self.affine;
        let su = self.skew;
        for (o, m) in out.chunks_exact_mut(2).zip(markers.chunks_exact(3)) {
            let x = r[0] * m[0] + r[1] * m[1] + r[2] * m[2] + t[0];
            let y = r[3] * m[0] + r[4] * m[1] + r[5] * m[2] + t[1];
            let z = r[6] * m[0] + r[7] * m[1] + r[8] * m[2] + t[2];
            if z <= crate::camera::MIN_DEPTH {
                o[0] = f64::NAN;
                o[1] = f64::NAN;
                continue;
            }
            let iz = 1.0 / z;
            let (xn, yn) = (x * iz, y * iz);
            let r2 = xn * xn + yn * yn;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn);
            let yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
            o[0] = au * xd + su * yd + bu;
            o[1] = av * yd + bv;
        }
    }
}

impl NormalizedProjector {
    const ZERO: Self = Self {
        r: [0.0; 9],
        t: [0.0; 3],
        dist: [0.0; 5],
        affine: [0.0; 4],
        skew: 0.0,
    };
}

/// Rigs of up to this many cameras keep their projectors on the stack.
const STACK_CAMERAS: usize = 16;

/// Per-thread scratch of [`emission_batch_into`]: forward kinematics, one pose and its
/// markers, kept between calls (resized for another skeleton) so that evaluating the sigma
/// points of a UKF step allocates nothing once each thread has seen one.
#[derive(Default)]
struct Scratch {
    ws: Option<crate::skeleton::FkWorkspace>,
    pose: Vec<f64>,
    markers: Vec<f64>,
    /// Bone lengths of a state with elastic bones ([`StateMap::with_stretch`]).
    lengths: Vec<f64>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

crate::kernels::dispatch!(
    /// Projects one pose's markers into every camera (normalised pixels, camera-major).
    fn project_all(projs: &[NormalizedProjector], markers: &[f64], out: &mut [f64]) -> () {
        let per_cam = out.len() / projs.len().max(1);
        for (pr, oc) in projs.iter().zip(out.chunks_exact_mut(per_cam)) {
            pr.project(markers, oc);
        }
    }
);

/// Projects the markers of `N` poses into every camera (fused FK + projection, pixels).
///
/// # Arguments
/// * `t` - `(N, 3)` flat translations; `r` - `(N, n_bones, 3)` flat Rodrigues vectors.
///
/// # Returns
/// `(n_cams, N, M, 2)` flat pixels (the layout of [`crate::camera::project_points`]); NaN
/// where a marker is behind a camera.
///
/// # Errors
/// Shape errors for inconsistent lengths; non-finite error naming the first bad pose.
pub fn project_poses(
    skeleton: &Skeleton,
    cameras: &[Camera],
    t: &[f64],
    r: &[f64],
) -> Result<Vec<f64>> {
    let mut out = vec![0.0; (t.len() / 3) * cameras.len() * skeleton.n_markers() * 2];
    project_poses_into(skeleton, cameras, t, r, &mut out)?;
    Ok(out)
}

/// Like [`project_poses`], writing into a caller-provided `(n_cams, N, M, 2)` buffer.
///
/// # Errors
/// As [`project_poses`], plus a shape error for a wrong buffer size.
pub fn project_poses_into(
    skeleton: &Skeleton,
    cameras: &[Camera],
    t: &[f64],
    r: &[f64],
    out: &mut [f64],
) -> Result<()> {
    if t.len() % 3 != 0 {
        return Err(AcmError::Shape(format!(
            "translations: {} values is not a multiple of 3",
            t.len()
        )));
    }
    let n = t.len() / 3;
    let (n_b, n_m, c) = (skeleton.n_bones(), skeleton.n_markers(), cameras.len());
    ensure_len(r.len(), n * 3 * n_b, "rotations (N, n_bones, 3)")?;
    if let Some(i) = t.iter().chain(r).position(|v| !v.is_finite()) {
        let pose = if i < t.len() {
            i / 3
        } else {
            (i - t.len()) / (3 * n_b)
        };
        return Err(AcmError::NonFinite(format!(
            "pose {pose} contains NaN or infinity"
        )));
    }
    ensure_len(out.len(), c * n * n_m * 2, "pixel output buffer")?;
    if n == 0 || c == 0 || n_m == 0 {
        return Ok(());
    }
    const BLOCK: usize = 32;
    let blocks = camera_blocks(out, c, n * n_m * 2, BLOCK * n_m * 2);
    blocks.into_par_iter().enumerate().for_each_init(
        || (skeleton.workspace(), vec![0.0; 3 * n_m]),
        |(ws, markers), (blk, mut dst)| {
            let nf = dst[0].len() / (n_m * 2);
            for f in 0..nf {
                let i = blk * BLOCK + f;
                skeleton.forward_flat_into(
                    &t[3 * i..3 * i + 3],
                    &r[3 * n_b * i..3 * n_b * (i + 1)],
                    skeleton.lengths(),
                    skeleton.offsets(),
                    ws,
                    None,
                    markers,
                );
                for (ci, cam) in cameras.iter().enumerate() {
                    let o = &mut dst[ci][f * n_m * 2..(f + 1) * n_m * 2];
                    project_one_camera(markers, cam, o, None);
                }
            }
        },
    );
    Ok(())
}

/// Alg. 4 for a batch of states: `g(f_{z*→z}(z))` for each row of `states`.
///
/// # Arguments
/// * `states` - `(N, n_state)` flat, in the state space of `map`.
///
/// # Returns
/// `(N, n_cams · M · 2)` flat normalised pixels `(u / c_1 − 1, v / c_2 − 1)`, ordered camera,
/// marker, coordinate (Alg. 4 line 9); NaN where a marker is behind a camera.
///
/// # Errors
/// Shape error if the map does not fit the skeleton or `states` has a wrong length;
/// non-finite error naming the first bad state.
pub fn emission_batch(
    skeleton: &Skeleton,
    cameras: &[Camera],
    map: &StateMap,
    norm: &Normalization,
    states: &[f64],
) -> Result<Vec<f64>> {
    let ns = map.n_state().max(1);
    let block = cameras.len() * skeleton.n_markers() * 2;
    let mut out = vec![0.0; (states.len() / ns) * block];
    emission_batch_into(skeleton, cameras, map, norm, states, &mut out, true)?;
    Ok(out)
}

/// Forward kinematics of one state (Alg. 4 lines 1-3 ∘ Alg. 1) with the state's own bone
/// lengths (elastic bones stretched, [`StateMap::with_stretch`]): joints (optional) and
/// markers into flat `(J, 3)` / `(M, 3)` buffers; `pose` (`n_pose`) and `lengths`
/// (`n_bones`) are scratch.
#[allow(clippy::too_many_arguments)]
pub fn state_forward_into(
    skeleton: &Skeleton,
    map: &StateMap,
    z: &[f64],
    ws: &mut crate::skeleton::FkWorkspace,
    pose: &mut [f64],
    lengths: &mut [f64],
    joints: Option<&mut [f64]>,
    markers: &mut [f64],
) {
    map.to_pose_into(z, pose, None);
    map.lengths_into(z, skeleton.lengths(), lengths);
    skeleton.forward_flat_into(
        &pose[..3],
        &pose[3..],
        lengths,
        skeleton.offsets(),
        ws,
        joints,
        markers,
    );
}

/// Like [`emission_batch`], writing into a caller-provided `(N, n_cams · M · 2)` buffer;
/// the states shared among rayon's threads if `parallel`, else all on the calling thread
/// (no hand-off to the pool: nothing is allocated once the thread's scratch is sized, and
/// no other thread is woken). The same values either way.
///
/// # Errors
/// As [`emission_batch`], plus a shape error for a wrong buffer size.
pub fn emission_batch_into(
    skeleton: &Skeleton,
    cameras: &[Camera],
    map: &StateMap,
    norm: &Normalization,
    states: &[f64],
    out: &mut [f64],
    parallel: bool,
) -> Result<()> {
    norm.validate()?;
    ensure_len(map.n_pose(), skeleton.n_pose(), "state map pose length")?;
    let ns = map.n_state();
    if ns == 0 || states.len() % ns != 0 {
        return Err(AcmError::Shape(format!(
            "states: {} values is not a multiple of the state length {ns}",
            states.len()
        )));
    }
    if let Some(i) = states.iter().position(|v| !v.is_finite()) {
        return Err(AcmError::NonFinite(format!(
            "state {} contains NaN or infinity",
            i / ns
        )));
    }
    let block = cameras.len() * skeleton.n_markers() * 2;
    ensure_len(
        out.len(),
        (states.len() / ns) * block,
        "emission output buffer",
    )?;
    if block == 0 {
        return Ok(());
    }
    // the cameras' projectors on the stack (a UKF step allocates nothing; see `Scratch`)
    let mut on_stack = [NormalizedProjector::ZERO; STACK_CAMERAS];
    let on_heap: Vec<NormalizedProjector>;
    let projs: &[NormalizedProjector] = if cameras.len() <= STACK_CAMERAS {
        for (p, c) in on_stack.iter_mut().zip(cameras) {
            *p = NormalizedProjector::new(c, norm);
        }
        &on_stack[..cameras.len()]
    } else {
        on_heap = cameras
            .iter()
            .map(|c| NormalizedProjector::new(c, norm))
            .collect();
        &on_heap
    };
    let one = |o: &mut [f64], z: &[f64]| {
        SCRATCH.with(|cell| {
            let mut guard = cell.borrow_mut();
            let Scratch {
                ws,
                pose,
                markers,
                lengths,
            } = &mut *guard;
            if !ws.as_ref().is_some_and(|w| w.fits(skeleton)) {
                *ws = Some(skeleton.workspace());
            }
            let ws = ws.as_mut().expect("set above");
            pose.resize(skeleton.n_pose(), 0.0);
            markers.resize(3 * skeleton.n_markers(), 0.0);
            map.to_pose_into(z, pose, None);
            let l = if map.stretch_bones().is_empty() {
                skeleton.lengths()
            } else {
                lengths.resize(skeleton.n_bones(), 0.0);
                map.lengths_into(z, skeleton.lengths(), lengths);
                lengths.as_slice()
            };
            skeleton.forward_flat_into(
                &pose[..3],
                &pose[3..],
                l,
                skeleton.offsets(),
                ws,
                None,
                markers,
            );
            project_all(projs, markers, o);
        })
    };
    if parallel {
        // Tasks of >= 16 states: small enough for work stealing to balance a UKF step's 2n
        // sigma points over the cores (one task per thread measured 30 % slower on this VM).
        out.par_chunks_mut(block)
            .zip(states.par_chunks(ns))
            .with_min_len(16)
            .for_each(|(o, z)| one(o, z));
    } else {
        for (o, z) in out.chunks_exact_mut(block).zip(states.chunks_exact(ns)) {
            one(o, z);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::tests::branching;

    fn rig() -> Vec<Camera> {
        // Two cameras looking at the origin from +z and from +x.
        let c0 = Camera::from_params(&[
            0.0, 0.0, 0.0, 0.0, 0.0, 20.0, 800.0, 800.0, 640.0, 512.0, -0.1, 0.01, 0.0, 0.0, 0.0,
        ])
        .unwrap();
        let c1 = Camera::from_params(&[
            0.0,
            -std::f64::consts::FRAC_PI_2,
            0.0,
            0.0,
            0.0,
            20.0,
            900.0,
            900.0,
            600.0,
            500.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            4.5, // skew: the fused projector must apply it as Camera::project does
        ])
        .unwrap();
        vec![c0, c1]
    }

    #[test]
    fn emission_equals_fk_then_projection() {
        let sk = branching();
        let cams = rig();
        let n_b = sk.n_bones();
        let inf = f64::INFINITY;
        let mut lower = vec![-inf; 3 * n_b];
        let mut upper = vec![inf; 3 * n_b];
        lower[5] = 0.0; // bone 1 axis z fixed at 0
        upper[5] = 0.0;
        lower[6] = -0.4; // bone 2 axis x bounded
        upper[6] = 0.9;
        let norm = Normalization::default();
        let map = StateMap::new(n_b, &lower, &upper, &norm, true).unwrap();
        let ns = map.n_state();
        let states: Vec<f64> = (0..3 * ns)
            .map(|i| ((i * 37 % 17) as f64 / 17.0 - 0.5) * 0.3)
            .collect();
        let g = emission_batch(&sk, &cams, &map, &norm, &states).unwrap();
        let mut t = Vec::new();
        let mut r = Vec::new();
        for s in 0..3 {
            let pose = map.to_pose(&states[s * ns..(s + 1) * ns]).unwrap();
            t.extend_from_slice(&pose[..3]);
            r.extend_from_slice(&pose[3..]);
        }
        // project_poses: (C, N, M, 2); emission: (N, C, M, 2), normalised.
        let px = project_poses(&sk, &cams, &t, &r).unwrap();
        let n_m = sk.n_markers();
        for s in 0..3 {
            for c in 0..cams.len() {
                for k in 0..2 * n_m {
                    let expect = px[(c * 3 + s) * 2 * n_m + k] / norm.pixel[k % 2] - 1.0;
                    let got = g[(s * cams.len() + c) * 2 * n_m + k];
                    assert!((got - expect).abs() < 1e-12);
                }
            }
        }
        // ... and the fused path equals FK followed by the batch projection.
        let (_, markers) = sk.forward_batch(&t, &r, None, None).unwrap();
        let sep = crate::camera::project_points(&cams, &markers).unwrap();
        assert_eq!(sep.pixels, px);
        assert!(matches!(
            emission_batch(&sk, &cams, &map, &norm, &states[1..]),
            Err(AcmError::Shape(_))
        ));
    }
}
