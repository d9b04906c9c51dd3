//! The emission function `g` of the state-space model (ACM supp. Alg. 4, eq. 50): state →
//! forward kinematics → projection into every camera → normalised pixels (eq. 11). Batches
//! of states (e.g. one set of sigma points) are evaluated in parallel.

use crate::camera::{camera_blocks, Camera};
use crate::error::{ensure_len, AcmError, Result};
use crate::limits::StateMap;
use crate::normalization::Normalization;
use crate::skeleton::{FkDirty, FkWorkspace, Skeleton};
use crate::team::Team;
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
    ws: Option<FkWorkspace>,
    pose: Vec<f64>,
    markers: Vec<f64>,
    /// Bone lengths of a state with elastic bones ([`StateMap::with_stretch`]).
    lengths: Vec<f64>,
    /// [`emission_sigma_into`]: the centre's pixels, and the moving markers of one sigma
    /// point with their pixels.
    centre_pixels: Vec<f64>,
    sub_markers: Vec<f64>,
    sub_pixels: Vec<f64>,
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
    if !t.len().is_multiple_of(3) {
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
    let Some(block) = check_batch(skeleton, cameras, map, norm, states, out)? else {
        return Ok(());
    };
    let ns = map.n_state();
    with_projectors(cameras, norm, |projs| {
        batch_with(skeleton, map, projs, states, out, block, ns, parallel)
    });
    Ok(())
}

/// The checks of [`emission_batch_into`]; `None` if there is nothing to compute, else the
/// length of one output row.
fn check_batch(
    skeleton: &Skeleton,
    cameras: &[Camera],
    map: &StateMap,
    norm: &Normalization,
    states: &[f64],
    out: &[f64],
) -> Result<Option<usize>> {
    norm.validate()?;
    ensure_len(map.n_pose(), skeleton.n_pose(), "state map pose length")?;
    let ns = map.n_state();
    if ns == 0 || !states.len().is_multiple_of(ns) {
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
    Ok((block > 0).then_some(block))
}

/// Calls `f` with the cameras' projectors, on the stack for rigs of up to
/// [`STACK_CAMERAS`] cameras (a UKF step allocates nothing; see `Scratch`).
fn with_projectors<R>(
    cameras: &[Camera],
    norm: &Normalization,
    f: impl FnOnce(&[NormalizedProjector]) -> R,
) -> R {
    if cameras.len() <= STACK_CAMERAS {
        let mut on_stack = [NormalizedProjector::ZERO; STACK_CAMERAS];
        for (p, c) in on_stack.iter_mut().zip(cameras) {
            *p = NormalizedProjector::new(c, norm);
        }
        f(&on_stack[..cameras.len()])
    } else {
        let on_heap: Vec<NormalizedProjector> = cameras
            .iter()
            .map(|c| NormalizedProjector::new(c, norm))
            .collect();
        f(&on_heap)
    }
}

/// Bone lengths of state `z` (`scratch` when the map stretches bones, else the skeleton's).
fn state_lengths<'a>(
    skeleton: &'a Skeleton,
    map: &StateMap,
    z: &[f64],
    scratch: &'a mut Vec<f64>,
) -> &'a [f64] {
    if map.stretch_bones().is_empty() {
        skeleton.lengths()
    } else {
        scratch.resize(skeleton.n_bones(), 0.0);
        map.lengths_into(z, skeleton.lengths(), scratch);
        scratch.as_slice()
    }
}

/// The body of [`emission_batch_into`] once checked, with the projectors.
#[allow(clippy::too_many_arguments)]
fn batch_with(
    skeleton: &Skeleton,
    map: &StateMap,
    projs: &[NormalizedProjector],
    states: &[f64],
    out: &mut [f64],
    block: usize,
    ns: usize,
    parallel: bool,
) {
    let one = |o: &mut [f64], z: &[f64]| {
        SCRATCH.with(|cell| {
            let mut guard = cell.borrow_mut();
            let Scratch {
                ws,
                pose,
                markers,
                lengths,
                ..
            } = &mut *guard;
            if !ws.as_ref().is_some_and(|w| w.fits(skeleton)) {
                *ws = Some(skeleton.workspace());
            }
            let ws = ws.as_mut().expect("set above");
            pose.resize(skeleton.n_pose(), 0.0);
            markers.resize(3 * skeleton.n_markers(), 0.0);
            map.to_pose_into(z, pose, None);
            let l = state_lengths(skeleton, map, z, lengths);
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
}

/// For each sigma point of a UKF step whose factor is lower-triangular (Alg. 5: the points
/// `m ± √n L_i`, `L = chol(P)`, differ from the centre `m` only in the state entries
/// `i..n`), the parts of the forward kinematics that move ([`Skeleton::fk_dirty`]): the
/// points of the later entries (bones far from the root, in the state's order) leave most
/// markers where the centre has them.
#[derive(Debug, Clone)]
pub struct SigmaPlan {
    dirty: Vec<FkDirty>,
    n_markers: usize,
    /// What the plan was made from ([`Self::fits`]).
    map: StateMap,
    structure: Vec<usize>,
}

/// The parts of a skeleton a [`SigmaPlan`] depends on, in a fixed order: bones, the rotations
/// acting on each, and the markers' joints and bones (not lengths, offsets or rest geometry).
fn plan_structure(skeleton: &Skeleton) -> impl Iterator<Item = usize> + '_ {
    let head = [skeleton.n_bones(), skeleton.n_markers()];
    let bones = skeleton
        .bones()
        .iter()
        .enumerate()
        .flat_map(move |(b, &(a, e))| {
            let acting = skeleton.acting_bones(b);
            [a, e, acting.len()]
                .into_iter()
                .chain(acting.iter().copied())
        });
    head.into_iter()
        .chain(bones)
        .chain(skeleton.marker_joints().iter().copied())
        .chain(skeleton.marker_bones().iter().copied())
}

impl SigmaPlan {
    /// The plan of `skeleton` under `map` (entry `i`: what the state entries `i..n` move).
    pub fn new(skeleton: &Skeleton, map: &StateMap) -> Self {
        let (n, nf, nb) = (map.n_state(), map.n_pose_state(), skeleton.n_bones());
        let (free, stretch) = (map.free_indices(), map.stretch_bones());
        let dirty = (0..n)
            .map(|i| {
                let (mut tr, mut rot, mut len) = (false, vec![false; nb], vec![false; nb]);
                for e in i..n {
                    if e >= nf {
                        len[stretch[e - nf]] = true;
                    } else if free[e] < 3 {
                        tr = true;
                    } else {
                        rot[(free[e] - 3) / 3] = true;
                    }
                }
                skeleton.fk_dirty(tr, &rot, &len)
            })
            .collect();
        Self {
            dirty,
            n_markers: skeleton.n_markers(),
            map: map.clone(),
            structure: plan_structure(skeleton).collect(),
        }
    }

    /// Whether the plan was made for this skeleton's structure and this map (e.g. not after
    /// a caller replaced the model's skeleton).
    pub fn fits(&self, skeleton: &Skeleton, map: &StateMap) -> bool {
        *map == self.map && plan_structure(skeleton).eq(self.structure.iter().copied())
    }

    /// What the sigma points of state entry `i` move (the points differ from the centre in
    /// the entries `i..n` only).
    pub fn dirty(&self, i: usize) -> &FkDirty {
        &self.dirty[i]
    }

    /// Mean fraction of the markers that a sigma point moves (1: no saving).
    pub fn moving_fraction(&self) -> f64 {
        let moved: usize = self.dirty.iter().map(|d| d.markers().len()).sum();
        moved as f64 / (self.dirty.len() * self.n_markers).max(1) as f64
    }
}

/// The output rows of [`emission_sigma_into`], shared by its tasks, each of which writes
/// rows no other task writes.
#[derive(Clone, Copy)]
struct RowsPtr(*mut f64);
// SAFETY: the tasks write disjoint rows (see `row`) and the buffer outlives them.
unsafe impl Send for RowsPtr {}
unsafe impl Sync for RowsPtr {}

impl RowsPtr {
    /// Row `row` (`len` values).
    ///
    /// # Safety
    /// The row must lie inside the buffer and no other live reference may touch it.
    #[allow(clippy::mut_from_ref)]
    unsafe fn row(&self, row: usize, len: usize) -> &mut [f64] {
        std::slice::from_raw_parts_mut(self.0.add(row * len), len)
    }
}

/// [`emission_batch_into`] of the `2n` sigma points `m ± √n L_i` of a lower-triangular `L`
/// (rows `i` and `n + i` of `sigma`, `2n × n`): the centre `m` (`mean`) is evaluated once
/// (per task of 16 points when `parallel`), then each point recomputes only the pose entries,
/// forward kinematics and pixels that its entries `i..n` move ([`SigmaPlan`]) and copies
/// the other pixels from the centre. A point that differs from the centre in an entry before `i`
/// (a factor that is not lower-triangular) is evaluated in full. The same values as
/// `emission_batch_into(sigma)` bit for bit.
///
/// # Errors
/// As [`emission_batch_into`], plus shape errors for `mean` and for a `sigma` of other than
/// `2n` rows, a non-finite error for the centre, and an invalid error for a plan made for
/// another skeleton or map.
#[allow(clippy::too_many_arguments)]
pub fn emission_sigma_into(
    skeleton: &Skeleton,
    cameras: &[Camera],
    map: &StateMap,
    norm: &Normalization,
    plan: &SigmaPlan,
    mean: &[f64],
    sigma: &[f64],
    out: &mut [f64],
    parallel: bool,
) -> Result<()> {
    let Some(block) = check_batch(skeleton, cameras, map, norm, sigma, out)? else {
        return Ok(());
    };
    let ns = map.n_state();
    ensure_len(mean.len(), ns, "sigma point centre")?;
    ensure_len(sigma.len(), 2 * ns * ns, "sigma points (2n × n)")?;
    if !plan.fits(skeleton, map) {
        return Err(AcmError::Invalid(
            "the sigma plan was made for another skeleton or state map".into(),
        ));
    }
    if mean.iter().any(|v| !v.is_finite()) {
        return Err(AcmError::NonFinite(
            "sigma point centre contains NaN or infinity".into(),
        ));
    }
    let n_m = skeleton.n_markers();
    with_projectors(cameras, norm, |projs| {
        // One task: the points of the entries i ≡ c (mod tasks) (rows i and n + i), i
        // descending. Points i and n + i differ from the centre only in what
        // `plan.dirty[i]` names, which grows as i falls, so the forward kinematics and pose
        // left by the point before hold the centre's values wherever this one does not
        // recompute them. (Interleaved entries: the early ones, which move most markers,
        // are shared out evenly.)
        let rows = RowsPtr(out.as_mut_ptr());
        let task = |c: usize, tasks: usize| {
            SCRATCH.with(|cell| {
                let mut guard = cell.borrow_mut();
                let sc = &mut *guard;
                if !sc.ws.as_ref().is_some_and(|w| w.fits(skeleton)) {
                    sc.ws = Some(skeleton.workspace());
                }
                let ws = sc.ws.as_mut().expect("set above");
                sc.pose.resize(skeleton.n_pose(), 0.0);
                sc.markers.resize(3 * n_m, 0.0);
                sc.centre_pixels.resize(block, 0.0);
                // room for every marker at once: which points a thread gets varies from step
                // to step, and a later, larger set must not allocate (the online promise)
                sc.sub_markers.clear();
                sc.sub_markers.reserve(3 * n_m);
                sc.sub_pixels.clear();
                sc.sub_pixels.reserve(block);
                let offsets = skeleton.offsets();
                let mut centre_held = false;
                for i in (0..ns).rev().filter(|i| i % tasks == c) {
                    let d = &plan.dirty[i];
                    for row in [i, ns + i] {
                        let z = &sigma[row * ns..(row + 1) * ns];
                        // SAFETY: row `row` of `out` (`block` values, in bounds: `out` has
                        // 2n rows, checked above) is written by this task alone (each entry
                        // i belongs to one task), and `out` outlives the tasks.
                        let o = unsafe { rows.row(row, block) };
                        if z[..i] != mean[..i] || d.markers().len() == n_m {
                            // in full: every marker moves, or the point is not of a
                            // lower-triangular factor (then the centre is needed again)
                            map.to_pose_into(z, &mut sc.pose, None);
                            let l = state_lengths(skeleton, map, z, &mut sc.lengths);
                            let (t, r) = sc.pose.split_at(3);
                            skeleton.forward_flat_into(t, r, l, offsets, ws, None, &mut sc.markers);
                            project_all(projs, &sc.markers, o);
                            centre_held = false;
                            continue;
                        }
                        if !centre_held {
                            map.to_pose_into(mean, &mut sc.pose, None);
                            let l = state_lengths(skeleton, map, mean, &mut sc.lengths);
                            let (t, r) = sc.pose.split_at(3);
                            skeleton.forward_flat_into(t, r, l, offsets, ws, None, &mut sc.markers);
                            project_all(projs, &sc.markers, &mut sc.centre_pixels);
                            centre_held = true;
                        }
                        map.to_pose_tail_into(z, &mut sc.pose, i);
                        let l = state_lengths(skeleton, map, z, &mut sc.lengths);
                        let (t, r) = sc.pose.split_at(3);
                        skeleton.forward_dirty_into(t, r, l, offsets, ws, d, &mut sc.markers);
                        o.copy_from_slice(&sc.centre_pixels);
                        let moving = d.markers();
                        if moving.is_empty() {
                            continue;
                        }
                        sc.sub_markers.clear();
                        for &m in moving {
                            sc.sub_markers
                                .extend_from_slice(&sc.markers[3 * m..3 * m + 3]);
                        }
                        let per_cam = 2 * moving.len();
                        sc.sub_pixels.resize(projs.len() * per_cam, 0.0);
                        project_all(projs, &sc.sub_markers, &mut sc.sub_pixels);
                        for (oc, pc) in o
                            .chunks_exact_mut(2 * n_m)
                            .zip(sc.sub_pixels.chunks_exact(per_cam))
                        {
                            for (q, &m) in moving.iter().enumerate() {
                                oc[2 * m..2 * m + 2].copy_from_slice(&pc[2 * q..2 * q + 2]);
                            }
                        }
                    }
                }
            })
        };
        if parallel {
            // two tasks per thread (each evaluates the centre once), on the spinning team
            // (a region of ~50 µs: rayon's wake-ups would cost more than it gains)
            let threads = rayon::current_num_threads();
            let tasks = (2 * threads).clamp(1, ns);
            Team::global().run(tasks, threads, &|c| task(c, tasks));
        } else {
            task(0, 1);
        }
    });
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
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

    /// The skeletons and maps on which the sigma-point shortcuts are tested: the branching
    /// tree, the same with a link matrix (every bone also turned by bone 0, and bone 2
    /// turning bone 4), and with elastic bones; one state entry fixed, one bounded.
    pub(crate) fn sigma_cases(norm: &Normalization) -> Vec<(&'static str, Skeleton, StateMap)> {
        ["tree", "link matrix", "stretch"]
            .into_iter()
            .map(|case| {
                let mut sk = branching();
                let n_b = sk.n_bones();
                if case == "link matrix" {
                    let mut lm = sk.bone_links();
                    lm[..n_b].iter_mut().for_each(|v| *v = true);
                    lm[2 * n_b + 4] = true;
                    sk = sk.with_links(&lm, None).unwrap();
                }
                let inf = f64::INFINITY;
                let (mut lower, mut upper) = (vec![-inf; 3 * n_b], vec![inf; 3 * n_b]);
                lower[5] = 0.0; // a fixed entry
                upper[5] = 0.0;
                lower[6] = -0.4; // a bounded one
                upper[6] = 0.9;
                let mut map = StateMap::new(n_b, &lower, &upper, norm, true).unwrap();
                if case == "stretch" {
                    map = map.with_stretch(&[3, 1]).unwrap();
                }
                (case, sk, map)
            })
            .collect()
    }

    /// The `2n` sigma points `m ± √n L_i` of a factor `l` (column-major `n × n`).
    fn sigma_of(m: &[f64], l: &[f64]) -> Vec<f64> {
        let n = m.len();
        let s = (n as f64).sqrt();
        let mut out = vec![0.0; 2 * n * n];
        for i in 0..n {
            for r in 0..n {
                out[i * n + r] = m[r] + s * l[i * n + r];
                out[(n + i) * n + r] = m[r] - s * l[i * n + r];
            }
        }
        out
    }

    #[test]
    fn sigma_points_share_the_centres_markers_bit_for_bit() {
        let cams = rig();
        let norm = Normalization::default();
        for (case, sk, map) in sigma_cases(&norm) {
            let plan = SigmaPlan::new(&sk, &map);
            assert!(
                plan.moving_fraction() < 0.8,
                "{case}: {}",
                plan.moving_fraction()
            );
            let n = map.n_state();
            let m: Vec<f64> = (0..n)
                .map(|i| ((i * 29 % 13) as f64 / 13.0 - 0.5) * 0.4)
                .collect();
            // lower-triangular factor (the UKF's), then a full one (not the contract: the
            // points must fall back to full evaluation)
            for lower_only in [true, false] {
                let l: Vec<f64> = (0..n * n)
                    .map(|e| {
                        let (r, c) = (e % n, e / n);
                        if lower_only && r < c {
                            0.0
                        } else {
                            ((e * 17 % 11) as f64 / 11.0 - 0.5) * 0.05
                                + if r == c { 0.1 } else { 0.0 }
                        }
                    })
                    .collect();
                let sigma = sigma_of(&m, &l);
                let block = cams.len() * sk.n_markers() * 2;
                let mut want = vec![0.0; 2 * n * block];
                emission_batch_into(&sk, &cams, &map, &norm, &sigma, &mut want, false).unwrap();
                for parallel in [false, true] {
                    let mut got = vec![0.0; 2 * n * block];
                    emission_sigma_into(
                        &sk, &cams, &map, &norm, &plan, &m, &sigma, &mut got, parallel,
                    )
                    .unwrap();
                    let same = got
                        .iter()
                        .zip(&want)
                        .all(|(a, b)| a.to_bits() == b.to_bits());
                    assert!(same, "{case}, lower {lower_only}, parallel {parallel}");
                }
            }
            // wrong shapes and a NaN centre are errors
            let sigma = sigma_of(&m, &vec![0.0; n * n]);
            let mut out = vec![0.0; 2 * n * cams.len() * sk.n_markers() * 2];
            let bad = emission_sigma_into(
                &sk,
                &cams,
                &map,
                &norm,
                &plan,
                &m[1..],
                &sigma,
                &mut out,
                false,
            );
            assert!(matches!(bad, Err(AcmError::Shape(_))));
            let mut nan = m.clone();
            nan[0] = f64::NAN;
            let bad = emission_sigma_into(
                &sk, &cams, &map, &norm, &plan, &nan, &sigma, &mut out, false,
            );
            assert!(matches!(bad, Err(AcmError::NonFinite(_))));
        }
        // a plan made for another skeleton is refused; a model whose public skeleton was
        // replaced after construction falls back to the full evaluation (the same values)
        use crate::tracking::{Emission, SkeletonEmission};
        let (tree, n_b) = (branching(), branching().n_bones());
        let mut lm = tree.bone_links();
        lm[2 * n_b + 4] = true;
        let linked = tree.clone().with_links(&lm, None).unwrap();
        let inf = vec![f64::INFINITY; 3 * n_b];
        let neg: Vec<f64> = inf.iter().map(|v| -v).collect();
        let map = StateMap::new(n_b, &neg, &inf, &norm, false).unwrap();
        let n = map.n_state();
        let m: Vec<f64> = (0..n).map(|i| 0.01 * i as f64).collect();
        let l: Vec<f64> = (0..n * n)
            .map(|e| {
                if e % n >= e / n {
                    0.02 + 0.001 * (e % 7) as f64
                } else {
                    0.0
                }
            })
            .collect();
        let sigma = sigma_of(&m, &l);
        let block = cams.len() * tree.n_markers() * 2;
        let mut out = vec![0.0; 2 * n * block];
        let plan = SigmaPlan::new(&tree, &map);
        assert!(plan.fits(&tree, &map) && !plan.fits(&linked, &map));
        let bad = emission_sigma_into(
            &linked, &cams, &map, &norm, &plan, &m, &sigma, &mut out, false,
        );
        assert!(matches!(bad, Err(AcmError::Invalid(_))));
        let mut em = SkeletonEmission::new(tree, cams.clone(), map.clone(), norm).unwrap();
        em.skeleton = linked.clone();
        em.eval_sigma(&m, &sigma, true, &mut out).unwrap();
        let mut want = vec![0.0; 2 * n * block];
        emission_batch_into(&linked, &cams, &map, &norm, &sigma, &mut want, false).unwrap();
        assert!(out
            .iter()
            .zip(&want)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
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
