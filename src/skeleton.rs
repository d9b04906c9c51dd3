//! Skeleton model and forward kinematics (ACM supp. section 3.1, Alg. 1, eq. 8) with exact
//! Jacobians with respect to the pose `(t, r)`, the bone lengths `l` and the marker offsets `v`.
//!
//! # Conventions
//! * Joints form a tree with one root; bone `b` ends at the `b`-th non-root joint (in joint
//!   order) and starts at that joint's parent.
//! * Each bone has a rest orientation `R̄_b` (columns = bone axes in world coordinates) whose
//!   z-axis points along the bone, a length `l_b`, and a Rodrigues vector `r_b`.
//! * Which bones a rotation moves (the authors' `skeleton_vertices_links`): by default the
//!   **tree rule**: the rotation of bone `i` moves bone `i` and its descendants, never its
//!   siblings, so `R_b = Q_{a1} Q_{a2} … Q_b R̄_b` over the bones on the path from the root
//!   to `b` (`Q = f_{r→R}(r)`, eq. 8). This is how the authors' published output moves (see
//!   `docs/models.md`); Alg. 1's line "if j₁ is child of i₀", read literally, would also turn
//!   the siblings that share `i`'s start joint. Any other link matrix (e.g. from an ACM
//!   `model.npy`) can be set with [`Skeleton::with_links`]: then
//!   `R_b = Π_{i: links[i, b]} Q_i R̄_b` in a given application order, as the authors'
//!   `adjust_joint_marker_pos2` composes them.
//! * A marker attached to joint `j` moves rigidly with the bone that ends at `j`:
//!   `m = p_j + R_b v` (Alg. 1, line 15). Markers attached to the root move with the global
//!   translation and the first bone that starts at the root.
//! * Derivatives: `∂R_b/∂r_ik = [w_ibk]× R_b` with the world axis `w_ibk = A_ib J_l(r_i) e_k`,
//!   where `A_ib` is the product of the rotations applied to `b` before `Q_i` and `J_l` the
//!   left Jacobian of SO(3); a point moves by `w × s` for every segment `s` of its chain
//!   (`l_b R_b e_z`) and its offset (`R_b v`).

use crate::error::{ensure_finite, ensure_len, AcmError, Result};
use crate::rotation::{left_jacobian, rodrigues};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

/// A kinematic tree with rest geometry, bone lengths and marker offsets.
#[derive(Debug, Clone)]
pub struct Skeleton {
    parents: Vec<Option<usize>>,
    root: usize,
    bones: Vec<(usize, usize)>,
    bone_of_end: Vec<Option<usize>>,
    rest_frames: Vec<Matrix3<f64>>,
    lengths: Vec<f64>,
    marker_joints: Vec<usize>,
    offsets: Vec<Vector3<f64>>,
    // Derived structure.
    order: Vec<usize>,
    marker_bone: Vec<usize>,
    /// Whether any marker is expressed in the frame of each bone.
    bone_has_marker: Vec<bool>,
    /// `anc[a * J + b]`: joint `a` is an ancestor of joint `b` or `a == b`.
    anc: Vec<bool>,
    /// A link matrix set by [`Skeleton::with_links`] (row-major `n_bones × n_bones`, `[i, b]`:
    /// the rotation of bone `i` moves bone `b`) and the order the rotations apply in;
    /// `None`: the tree rule.
    custom_links: Option<(Vec<bool>, Vec<usize>)>,
    /// The bones whose rotation acts on each bone, in application order.
    acting: Vec<Vec<usize>>,
    /// How the bone orientations are formed: `(b, base, from)` sets
    /// `G_b = G_base · Π acting[b][from..]` (base: a bone whose acting list is a prefix of
    /// `b`'s, evaluated earlier in the plan).
    plan: Vec<(usize, Option<usize>, usize)>,
}

/// Joint and marker positions of one frame plus the bone orientations they came from.
#[derive(Debug, Clone)]
pub struct FkResult {
    /// Joint positions `p` (J).
    pub joints: Vec<Vector3<f64>>,
    /// Marker positions `m` (M).
    pub markers: Vec<Vector3<f64>>,
    /// Global bone orientations `R_b = G_b R̄_b` (n_bones).
    pub bone_rotations: Vec<Matrix3<f64>>,
}

/// Per-thread scratch space of forward kinematics (see [`Skeleton::workspace`]).
#[derive(Debug, Clone)]
pub struct FkWorkspace {
    /// `Q_i = f_{r→R}(r_i)` of each bone.
    q: Vec<Matrix3<f64>>,
    /// `G_b`: the product of the rotations acting on bone `b`.
    g: Vec<Matrix3<f64>>,
    bone_rot: Vec<Matrix3<f64>>,
    joints: Vec<Vector3<f64>>,
}

impl FkWorkspace {
    /// The joint positions of the last forward kinematics evaluated in this workspace.
    pub fn joints(&self) -> &[Vector3<f64>] {
        &self.joints
    }
    /// Copies `other`'s values (same sizes) without allocating.
    pub fn copy_from(&mut self, other: &FkWorkspace) {
        self.q.copy_from_slice(&other.q);
        self.g.copy_from_slice(&other.g);
        self.bone_rot.copy_from_slice(&other.bone_rot);
        self.joints.copy_from_slice(&other.joints);
    }
    /// Whether this workspace has the sizes of `skeleton`'s ([`Skeleton::workspace`]).
    pub fn fits(&self, skeleton: &Skeleton) -> bool {
        self.q.len() == skeleton.n_bones()
            && self.g.len() == skeleton.n_bones()
            && self.joints.len() == skeleton.n_joints()
            && self.bone_rot.len() == skeleton.n_bones()
    }
}

/// The parts of the forward kinematics that change when some pose entries (the root
/// translation, some bones' rotation vectors) and some bone lengths change, the rest keeping
/// their values from another pose ([`Skeleton::fk_dirty`], [`Skeleton::forward_dirty_into`]).
/// Each list is in the order [`Skeleton::forward_flat_into`] computes it.
#[derive(Debug, Clone, Default)]
pub struct FkDirty {
    translation: bool,
    /// Bones whose rotation `Q_b` changes.
    q: Vec<usize>,
    /// Steps of the plan whose product `G_b` changes.
    plan: Vec<usize>,
    /// Joints whose position changes, in FK order.
    joints: Vec<usize>,
    /// Bones with markers whose orientation `R_b` changes.
    bone_rot: Vec<usize>,
    /// Markers that move.
    markers: Vec<usize>,
}

impl FkDirty {
    /// The markers that move, ascending.
    pub fn markers(&self) -> &[usize] {
        &self.markers
    }
    /// The joints other than the root that move, in forward-kinematics order.
    pub fn joints(&self) -> &[usize] {
        &self.joints
    }
    /// Whether the root translation (so the root joint) moves.
    pub fn translation(&self) -> bool {
        self.translation
    }
}

/// Exact derivatives of joint and marker positions (rows `[joints (3J), markers (3M)]`).
#[derive(Debug, Clone)]
pub struct FkJacobian {
    /// Forward kinematics at the evaluation point.
    pub fk: FkResult,
    /// `(3J + 3M) × (3 + 3 n_bones)` row-major: derivatives w.r.t. `[t, r_0, r_1, …]`.
    pub d_pose: Vec<f64>,
    /// `(3J + 3M) × n_bones` row-major: derivatives w.r.t. the bone lengths.
    pub d_lengths: Vec<f64>,
    /// `(M, 3, 3)` row-major: `∂m_k/∂v_k = R_{b(k)}` (markers depend only on their own offset).
    pub d_offsets: Vec<f64>,
}

/// Orthonormal bone frame with its z-axis along `dir` and its y-axis as close as possible to
/// `up` (x = y × z). Falls back to `fallback_up` when `dir` is parallel to `up`.
///
/// With `up` in the sagittal plane this construction is mirror-consistent: mirroring a bone at
/// the sagittal plane mirrors the x-component of every offset in its frame (Alg. 3).
pub fn frame_from_direction(
    dir: &Vector3<f64>,
    up: &Vector3<f64>,
    fallback_up: Option<&Vector3<f64>>,
) -> Result<Matrix3<f64>> {
    let n = dir.norm();
    if n <= 1e-12 || !n.is_finite() {
        return Err(AcmError::Invalid(
            "bone of zero length has no direction".into(),
        ));
    }
    let z = dir / n;
    let mut y = up - z * up.dot(&z);
    if y.norm() < 1e-6 {
        if let Some(f) = fallback_up {
            y = f - z * f.dot(&z);
        }
    }
    if y.norm() < 1e-6 {
        return Err(AcmError::Invalid(
            "bone is parallel to the up vector and no fallback frame is available".into(),
        ));
    }
    let y = y.normalize();
    let x = y.cross(&z);
    Ok(Matrix3::from_columns(&[x, y, z]))
}

fn check_rotation(m: &Matrix3<f64>, what: &str) -> Result<()> {
    ensure_finite(m.as_slice(), what)?;
    let err = (m.transpose() * m - Matrix3::identity()).abs().max();
    if err > 1e-6 || m.determinant() < 0.0 {
        return Err(AcmError::Invalid(format!(
            "{what} is not a proper rotation (max |R^T R - I| = {err:.2e})"
        )));
    }
    Ok(())
}

impl Skeleton {
    /// Builds a skeleton from its tree, rest frames, lengths and marker offsets.
    ///
    /// # Arguments
    /// * `parents` - parent joint index per joint, `-1` for the single root.
    /// * `rest_frames` - one rest orientation `R̄_b` per bone (z-axis along the bone).
    /// * `lengths` - bone lengths `l` (> 0), one per bone.
    /// * `marker_joints` - joint each marker is attached to.
    /// * `offsets` - marker offsets `v` in the frame of the bone ending at that joint.
    ///
    /// # Errors
    /// Invalid error for a parent list that is not a tree with one root, an out-of-range
    /// joint index, non-rotation frames or non-positive lengths; shape errors for
    /// inconsistent lengths; non-finite errors for NaN/inf.
    pub fn new(
        parents: &[i64],
        rest_frames: Vec<Matrix3<f64>>,
        lengths: Vec<f64>,
        marker_joints: Vec<usize>,
        offsets: Vec<Vector3<f64>>,
    ) -> Result<Self> {
        let (parents, root, order) = validate_tree(parents)?;
        let n_j = parents.len();
        let n_b = n_j - 1;
        let mut bones = Vec::with_capacity(n_b);
        let mut bone_of_end = vec![None; n_j];
        for (j, p) in parents.iter().enumerate() {
            if let Some(p) = p {
                bone_of_end[j] = Some(bones.len());
                bones.push((*p, j));
            }
        }
        ensure_len(rest_frames.len(), n_b, "rest frames (one per bone)")?;
        ensure_len(lengths.len(), n_b, "bone lengths")?;
        ensure_len(offsets.len(), marker_joints.len(), "marker offsets")?;
        for (b, f) in rest_frames.iter().enumerate() {
            check_rotation(f, &format!("rest frame of bone {b}"))?;
        }
        validate_lengths(&lengths)?;
        let first_root_bone = bones
            .iter()
            .position(|&(s, _)| s == root)
            .expect("the root of a validated tree has a bone");
        let mut marker_bone = Vec::with_capacity(marker_joints.len());
        for (k, &j) in marker_joints.iter().enumerate() {
            if j >= n_j {
                return Err(AcmError::Invalid(format!(
                    "marker {k} is attached to joint {j}, but there are only {n_j} joints"
                )));
            }
            marker_bone.push(bone_of_end[j].unwrap_or(first_root_bone));
        }
        for v in &offsets {
            ensure_finite(v.as_slice(), "marker offsets")?;
        }
        let mut anc = vec![false; n_j * n_j];
        for b in 0..n_j {
            let mut a = Some(b);
            while let Some(x) = a {
                anc[x * n_j + b] = true;
                a = parents[x];
            }
        }
        let mut bone_has_marker = vec![false; n_b];
        for &b in &marker_bone {
            bone_has_marker[b] = true;
        }
        let mut sk = Self {
            parents,
            root,
            bones,
            bone_of_end,
            rest_frames,
            lengths,
            marker_joints,
            offsets,
            order,
            marker_bone,
            bone_has_marker,
            anc,
            custom_links: None,
            acting: Vec::new(),
            plan: Vec::new(),
        };
        sk.set_tree_links();
        Ok(sk)
    }

    /// The tree rule: bone `b` is turned by the bones on the path from the root to `b`,
    /// root first; `G_b = G_{parent bone} Q_b`.
    fn set_tree_links(&mut self) {
        let n_b = self.bones.len();
        self.custom_links = None;
        self.acting = vec![Vec::new(); n_b];
        self.plan = Vec::with_capacity(n_b);
        for &a in &self.order {
            let Some(b) = self.bone_of_end[a] else {
                continue;
            };
            let base = self.bone_of_end[self.bones[b].0];
            let mut chain = base.map(|c| self.acting[c].clone()).unwrap_or_default();
            let from = chain.len();
            chain.push(b);
            self.acting[b] = chain;
            self.plan.push((b, base, from));
        }
    }

    /// Uses an explicit link matrix instead of the tree rule, as the authors' forward model
    /// (`adjust_joint_marker_pos2`) does with a `model.npy`'s `skeleton_vertices_links`:
    /// `R_b = Π_{i: links[i, b]} Q_i R̄_b`, the product taken in `order`.
    ///
    /// # Arguments
    /// * `links` - row-major `n_bones × n_bones`; `[i, b]`: the rotation of bone `i` moves
    ///   bone `b`. Any matrix is accepted (a bone that no rotation moves keeps its rest
    ///   orientation).
    /// * `order` - the order in which the rotations apply (a permutation of the bones; the
    ///   authors' file order); `None`: bone index order.
    ///
    /// # Errors
    /// Shape errors for a wrong size; invalid errors for an order that is not a permutation.
    pub fn with_links(mut self, links: &[bool], order: Option<&[usize]>) -> Result<Self> {
        let n = self.bones.len();
        ensure_len(links.len(), n * n, "link matrix (n_bones x n_bones)")?;
        let order: Vec<usize> = match order {
            Some(o) => {
                ensure_len(o.len(), n, "link order (one entry per bone)")?;
                let mut seen = vec![false; n];
                for &i in o {
                    if i >= n || seen[i] {
                        return Err(AcmError::Invalid(format!(
                            "link order must be a permutation of the {n} bones; got {o:?}"
                        )));
                    }
                    seen[i] = true;
                }
                o.to_vec()
            }
            None => (0..n).collect(),
        };
        self.acting = (0..n)
            .map(|b| {
                order
                    .iter()
                    .copied()
                    .filter(|&i| links[i * n + b])
                    .collect()
            })
            .collect();
        // Share prefixes: bones by the length of their acting list, each based on the
        // longest earlier list that is a prefix of its own.
        let mut by_len: Vec<usize> = (0..n).collect();
        by_len.sort_by_key(|&b| self.acting[b].len());
        self.plan = Vec::with_capacity(n);
        for (k, &b) in by_len.iter().enumerate() {
            let base = by_len[..k]
                .iter()
                .copied()
                .filter(|&c| self.acting[b].starts_with(&self.acting[c]))
                .max_by_key(|&c| self.acting[c].len());
            let from = base.map_or(0, |c| self.acting[c].len());
            self.plan.push((b, base, from));
        }
        self.custom_links = Some((links.to_vec(), order));
        Ok(self)
    }

    /// Goes back to the tree rule (drops a link matrix set by [`Skeleton::with_links`]).
    pub fn with_tree_links(mut self) -> Self {
        self.set_tree_links();
        self
    }

    /// The link matrix and application order set by [`Skeleton::with_links`]; `None` for
    /// the tree rule.
    pub fn custom_links(&self) -> Option<(&[bool], &[usize])> {
        self.custom_links
            .as_ref()
            .map(|(l, o)| (l.as_slice(), o.as_slice()))
    }

    /// Builds a skeleton from joint and marker positions of a rest pose (all rotations zero).
    ///
    /// Bone lengths are the joint distances; rest frames come from
    /// [`frame_from_direction`] with `up` (falling back to the parent bone's y-axis) unless
    /// `rest_frames` is given, in which case each frame's z-axis must point along its bone;
    /// offsets are the marker positions relative to their joint, in the frame of the bone
    /// that ends there.
    ///
    /// # Errors
    /// As [`Skeleton::new`], plus invalid errors for zero-length bones and given frames whose
    /// z-axis is not along the bone.
    pub fn from_rest_pose(
        parents: &[i64],
        rest_joints: &[Vector3<f64>],
        marker_joints: Vec<usize>,
        marker_rest: &[Vector3<f64>],
        up: &Vector3<f64>,
        rest_frames: Option<Vec<Matrix3<f64>>>,
    ) -> Result<Self> {
        let (tree, _, order) = validate_tree(parents)?;
        ensure_len(rest_joints.len(), tree.len(), "rest joint positions")?;
        ensure_len(
            marker_rest.len(),
            marker_joints.len(),
            "rest marker positions",
        )?;
        for p in rest_joints.iter().chain(marker_rest.iter()) {
            ensure_finite(p.as_slice(), "rest pose positions")?;
        }
        ensure_finite(up.as_slice(), "up vector")?;
        let n_j = tree.len();
        let mut bone_of_end = vec![None; n_j];
        let mut ends = Vec::new();
        for (j, p) in tree.iter().enumerate() {
            if p.is_some() {
                bone_of_end[j] = Some(ends.len());
                ends.push(j);
            }
        }
        let mut lengths = vec![0.0; ends.len()];
        let mut frames = vec![Matrix3::identity(); ends.len()];
        // Root-first so that the parent bone's frame is known for the fallback.
        for &j in &order {
            let Some(p) = tree[j] else { continue };
            let b = bone_of_end[j].expect("non-root joint has a bone");
            let d = rest_joints[j] - rest_joints[p];
            lengths[b] = d.norm();
            if lengths[b] <= 1e-12 {
                return Err(AcmError::Invalid(format!(
                    "bone {b} (joints {p}->{j}) has zero length in the rest pose"
                )));
            }
            frames[b] = match &rest_frames {
                Some(given) => {
                    ensure_len(given.len(), ends.len(), "rest frames (one per bone)")?;
                    let f = given[b];
                    check_rotation(&f, &format!("rest frame of bone {b}"))?;
                    if (f.column(2) - d / lengths[b]).norm() > 1e-6 {
                        return Err(AcmError::Invalid(format!(
                            "rest frame of bone {b} (joints {p}->{j}): its z-axis does not point \
                             along the bone"
                        )));
                    }
                    f
                }
                None => {
                    let fallback = bone_of_end[p].map(|pb| frames[pb].column(1).into_owned());
                    frame_from_direction(&d, up, fallback.as_ref()).map_err(|e| {
                        AcmError::Invalid(format!("bone {b} (joints {p}->{j}): {e}"))
                    })?
                }
            };
        }
        let root = tree.iter().position(|p| p.is_none()).expect("validated");
        let first_root_bone = tree
            .iter()
            .enumerate()
            .filter(|(_, p)| **p == Some(root))
            .map(|(j, _)| bone_of_end[j].expect("child has bone"))
            .min()
            .ok_or_else(|| AcmError::Invalid("the skeleton needs at least one bone".into()))?;
        let mut offsets = Vec::with_capacity(marker_joints.len());
        for (k, &j) in marker_joints.iter().enumerate() {
            if j >= n_j {
                return Err(AcmError::Invalid(format!(
                    "marker {k} is attached to joint {j}, but there are only {n_j} joints"
                )));
            }
            let b = bone_of_end[j].unwrap_or(first_root_bone);
            offsets.push(frames[b].transpose() * (marker_rest[k] - rest_joints[j]));
        }
        Self::new(parents, frames, lengths, marker_joints, offsets)
    }

    /// Number of joints `J`.
    pub fn n_joints(&self) -> usize {
        self.parents.len()
    }
    /// Number of bones (`J − 1`).
    pub fn n_bones(&self) -> usize {
        self.bones.len()
    }
    /// Number of markers `M`.
    pub fn n_markers(&self) -> usize {
        self.marker_joints.len()
    }
    /// Length of the full pose vector `[t (3), r (3 n_bones)]`.
    pub fn n_pose(&self) -> usize {
        3 + 3 * self.bones.len()
    }
    /// Index of the root joint.
    pub fn root(&self) -> usize {
        self.root
    }
    /// Parent of each joint (`None` for the root).
    pub fn parents(&self) -> &[Option<usize>] {
        &self.parents
    }
    /// `(start, end)` joint of each bone.
    pub fn bones(&self) -> &[(usize, usize)] {
        &self.bones
    }
    /// Bone ending at each joint (`None` for the root).
    pub fn bone_of_end(&self) -> &[Option<usize>] {
        &self.bone_of_end
    }
    /// Rest orientations `R̄`.
    pub fn rest_frames(&self) -> &[Matrix3<f64>] {
        &self.rest_frames
    }
    /// Bone lengths `l`.
    pub fn lengths(&self) -> &[f64] {
        &self.lengths
    }
    /// Joint each marker is attached to.
    pub fn marker_joints(&self) -> &[usize] {
        &self.marker_joints
    }
    /// Bone whose frame each marker's offset is expressed in.
    pub fn marker_bones(&self) -> &[usize] {
        &self.marker_bone
    }
    /// Marker offsets `v` (bone frame).
    pub fn offsets(&self) -> &[Vector3<f64>] {
        &self.offsets
    }
    /// Whether joint `a` is an ancestor of joint `b` (or `a == b`).
    pub fn is_ancestor_or_self(&self, a: usize, b: usize) -> bool {
        self.anc[a * self.parents.len() + b]
    }
    /// `[i, j]`: the rotation of bone `i` moves bone `j` (the authors' `skeleton_vertices_links`),
    /// row-major `n_bones × n_bones`.
    pub fn bone_links(&self) -> Vec<bool> {
        let n = self.bones.len();
        let mut out = vec![false; n * n];
        for (j, acting) in self.acting.iter().enumerate() {
            for &i in acting {
                out[i * n + j] = true;
            }
        }
        out
    }

    /// The order in which the rotations apply: the one given to [`Skeleton::with_links`], or
    /// for the tree rule the bones root first (breadth-first by end joint).
    pub fn link_order(&self) -> Vec<usize> {
        match &self.custom_links {
            Some((_, order)) => order.clone(),
            None => self.plan.iter().map(|&(b, _, _)| b).collect(),
        }
    }

    /// The bones whose rotation acts on bone `b`, in the order they apply.
    pub fn acting_bones(&self, b: usize) -> &[usize] {
        &self.acting[b]
    }

    fn check_overrides(
        &self,
        lengths: Option<&[f64]>,
        offsets: Option<&[Vector3<f64>]>,
    ) -> Result<()> {
        if let Some(l) = lengths {
            ensure_len(l.len(), self.n_bones(), "bone lengths")?;
            validate_lengths(l)?;
        }
        if let Some(v) = offsets {
            ensure_len(v.len(), self.n_markers(), "marker offsets")?;
            for x in v {
                ensure_finite(x.as_slice(), "marker offsets")?;
            }
        }
        Ok(())
    }

    /// Forward kinematics of one pose (Alg. 1), using the skeleton's own lengths/offsets
    /// unless overrides are given.
    ///
    /// # Arguments
    /// * `t` - global translation = root joint position (world units).
    /// * `r` - one Rodrigues vector per bone (rad).
    ///
    /// # Errors
    /// Shape errors for wrong counts, non-finite errors for NaN/inf, invalid errors for
    /// non-positive lengths.
    pub fn forward(
        &self,
        t: &Vector3<f64>,
        r: &[Vector3<f64>],
        lengths: Option<&[f64]>,
        offsets: Option<&[Vector3<f64>]>,
    ) -> Result<FkResult> {
        ensure_len(r.len(), self.n_bones(), "bone rotations")?;
        ensure_finite(t.as_slice(), "translation")?;
        for x in r {
            ensure_finite(x.as_slice(), "bone rotations")?;
        }
        self.check_overrides(lengths, offsets)?;
        Ok(self.forward_unchecked(
            t,
            r,
            lengths.unwrap_or(&self.lengths),
            offsets.unwrap_or(&self.offsets),
        ))
    }

    /// Scratch space for allocation-free forward kinematics ([`Skeleton::forward_flat_into`]).
    pub fn workspace(&self) -> FkWorkspace {
        FkWorkspace {
            q: vec![Matrix3::identity(); self.n_bones()],
            g: vec![Matrix3::identity(); self.n_bones()],
            bone_rot: vec![Matrix3::identity(); self.n_bones()],
            joints: vec![Vector3::zeros(); self.n_joints()],
        }
    }

    /// Alg. 1 core: bone orientations and joint positions into `ws`. `r` is flat
    /// `(n_bones, 3)`. With `full == false` only the orientations of bones that carry markers
    /// are formed.
    fn fk_core(
        &self,
        t: &Vector3<f64>,
        r: &[f64],
        lengths: &[f64],
        ws: &mut FkWorkspace,
        full: bool,
    ) {
        for (b, q) in ws.q.iter_mut().enumerate() {
            let rv = Vector3::new(r[3 * b], r[3 * b + 1], r[3 * b + 2]);
            *q = if rv == Vector3::zeros() {
                Matrix3::identity()
            } else {
                rodrigues(&rv)
            };
        }
        // Eq. 8: G_b = Q_{a1} Q_{a2} … over the rotations acting on b (tree rule: the bones
        // from the root to b), sharing the product of a prefix.
        for &(b, base, from) in &self.plan {
            let mut g = base.map_or_else(Matrix3::identity, |c| ws.g[c]);
            for &i in &self.acting[b][from..] {
                g *= ws.q[i];
            }
            ws.g[b] = g;
        }
        ws.joints[self.root] = *t;
        for &a in &self.order[1..] {
            let b = self.bone_of_end[a].expect("non-root joint has a bone");
            // Alg. 1 lines 8 and 11: R_b = G_b R̄_b, p_end = p_start + R_b e_z l_b.
            let start = self.bones[b].0;
            let gb = &ws.g[b];
            ws.joints[a] = ws.joints[start] + gb * self.rest_frames[b].column(2) * lengths[b];
            if full || self.bone_has_marker[b] {
                ws.bone_rot[b] = gb * self.rest_frames[b];
            }
        }
    }

    /// Which parts of the forward kinematics change with the root translation (if
    /// `translation`), the rotations of the bones `rot[b]` and the lengths of the bones
    /// `len[b]` (both `n_bones`), everything else fixed: the closure of Alg. 1's dependencies
    /// through this skeleton's plan of `G_b` products, joint chain and markers.
    pub fn fk_dirty(&self, translation: bool, rot: &[bool], len: &[bool]) -> FkDirty {
        let n_b = self.n_bones();
        let mut g = vec![false; n_b];
        let mut plan = Vec::new();
        for (p, &(b, base, from)) in self.plan.iter().enumerate() {
            g[b] = base.is_some_and(|c| g[c]) || self.acting[b][from..].iter().any(|&i| rot[i]);
            if g[b] {
                plan.push(p);
            }
        }
        let mut jd = vec![false; self.n_joints()];
        jd[self.root] = translation;
        let mut joints = Vec::new();
        for &a in &self.order[1..] {
            let b = self.bone_of_end[a].expect("non-root joint has a bone");
            jd[a] = jd[self.bones[b].0] || g[b] || len[b];
            if jd[a] {
                joints.push(a);
            }
        }
        let bone_rot = (0..n_b)
            .filter(|&b| self.bone_has_marker[b] && g[b])
            .collect();
        let markers = (0..self.n_markers())
            .filter(|&k| jd[self.marker_joints[k]] || g[self.marker_bone[k]])
            .collect();
        FkDirty {
            translation,
            q: (0..n_b).filter(|&b| rot[b]).collect(),
            plan,
            joints,
            bone_rot,
            markers,
        }
    }

    /// [`Self::fk_core`] (with `full == false`) of the parts in `d` only; `ws` holds the
    /// others from a pose that differs from this one only where `d` says. Each recomputed
    /// value is the same expression of the same inputs as in `fk_core`, so the result equals
    /// `fk_core`'s bit for bit.
    fn fk_core_dirty(
        &self,
        t: &Vector3<f64>,
        r: &[f64],
        lengths: &[f64],
        ws: &mut FkWorkspace,
        d: &FkDirty,
    ) {
        for &b in &d.q {
            let rv = Vector3::new(r[3 * b], r[3 * b + 1], r[3 * b + 2]);
            ws.q[b] = if rv == Vector3::zeros() {
                Matrix3::identity()
            } else {
                rodrigues(&rv)
            };
        }
        for &p in &d.plan {
            let (b, base, from) = self.plan[p];
            let mut g = base.map_or_else(Matrix3::identity, |c| ws.g[c]);
            for &i in &self.acting[b][from..] {
                g *= ws.q[i];
            }
            ws.g[b] = g;
        }
        if d.translation {
            ws.joints[self.root] = *t;
        }
        for &a in &d.joints {
            let b = self.bone_of_end[a].expect("non-root joint has a bone");
            let start = self.bones[b].0;
            let gb = &ws.g[b];
            ws.joints[a] = ws.joints[start] + gb * self.rest_frames[b].column(2) * lengths[b];
        }
        for &b in &d.bone_rot {
            ws.bone_rot[b] = ws.g[b] * self.rest_frames[b];
        }
    }

    /// [`Self::forward_flat_into`] of a pose that differs from the one whose forward
    /// kinematics `ws` and `markers_out` hold only in the parts named by `d`
    /// ([`Self::fk_dirty`]): recomputes those parts and the markers that move (the others
    /// are left as they are). The same values as a full evaluation, bit for bit.
    #[allow(clippy::too_many_arguments)] // hot path: flat slices, no per-call packing
    pub fn forward_dirty_into(
        &self,
        t: &[f64],
        r: &[f64],
        lengths: &[f64],
        offsets: &[Vector3<f64>],
        ws: &mut FkWorkspace,
        d: &FkDirty,
        markers_out: &mut [f64],
    ) {
        self.fk_core_dirty(&Vector3::new(t[0], t[1], t[2]), r, lengths, ws, d);
        for &k in &d.markers {
            let (j, b) = (self.marker_joints[k], self.marker_bone[k]);
            let m = ws.joints[j] + ws.bone_rot[b] * offsets[k];
            markers_out[3 * k..3 * k + 3].copy_from_slice(m.as_slice());
        }
    }

    /// Allocation-free forward kinematics of one pose without validation (hot path of batch
    /// code that validated its inputs once).
    ///
    /// # Arguments
    /// * `t` - root translation (3 values); `r` - flat `(n_bones, 3)` Rodrigues vectors.
    /// * `joints_out` - optional flat `(J, 3)` output; `markers_out` - flat `(M, 3)` output.
    #[allow(clippy::too_many_arguments)] // hot path: flat slices, no per-call packing
    pub fn forward_flat_into(
        &self,
        t: &[f64],
        r: &[f64],
        lengths: &[f64],
        offsets: &[Vector3<f64>],
        ws: &mut FkWorkspace,
        joints_out: Option<&mut [f64]>,
        markers_out: &mut [f64],
    ) {
        self.fk_core(&Vector3::new(t[0], t[1], t[2]), r, lengths, ws, false);
        if let Some(jo) = joints_out {
            for (dst, p) in jo.chunks_exact_mut(3).zip(&ws.joints) {
                dst.copy_from_slice(p.as_slice());
            }
        }
        // Alg. 1 line 15: m_k = p_j + R_b v_k.
        for (((dst, &j), &b), v) in markers_out
            .chunks_exact_mut(3)
            .zip(&self.marker_joints)
            .zip(&self.marker_bone)
            .zip(offsets)
        {
            let m = ws.joints[j] + ws.bone_rot[b] * v;
            dst.copy_from_slice(m.as_slice());
        }
    }

    /// Forward kinematics without input validation, returning every intermediate.
    pub fn forward_unchecked(
        &self,
        t: &Vector3<f64>,
        r: &[Vector3<f64>],
        lengths: &[f64],
        offsets: &[Vector3<f64>],
    ) -> FkResult {
        let flat: Vec<f64> = r.iter().flat_map(|v| [v.x, v.y, v.z]).collect();
        let mut ws = self.workspace();
        self.fk_core(t, &flat, lengths, &mut ws, true);
        let markers = self
            .marker_joints
            .iter()
            .zip(&self.marker_bone)
            .zip(offsets)
            .map(|((&j, &b), v)| ws.joints[j] + ws.bone_rot[b] * v)
            .collect();
        FkResult {
            joints: ws.joints,
            markers,
            bone_rotations: ws.bone_rot,
        }
    }

    /// Forward kinematics with exact Jacobians with respect to `t`, `r`, `l` and `v`.
    ///
    /// A point moved by bone `i` through bone `b` has `∂x/∂r_ik = Σ w_ibk × s` over the
    /// segments `s` of its chain that `i` turns (`l_b R_b e_z`, and `R_b v` for a marker's
    /// offset), with the world axis `w_ibk = A_ib J_l(r_i) e_k` (module docs; exact, no finite
    /// differences). Under the tree rule this is `w_ik × (x − p_start(i))`.
    ///
    /// # Errors
    /// As [`Skeleton::forward`].
    pub fn forward_jacobian(
        &self,
        t: &Vector3<f64>,
        r: &[Vector3<f64>],
        lengths: Option<&[f64]>,
        offsets: Option<&[Vector3<f64>]>,
    ) -> Result<FkJacobian> {
        let fk = self.forward(t, r, lengths, offsets)?;
        let n_j = self.n_joints();
        let n_m = self.n_markers();
        let n_b = self.n_bones();
        let rows = 3 * (n_j + n_m);
        let cols = self.n_pose();
        let mut d_pose = vec![0.0; rows * cols];
        let mut d_lengths = vec![0.0; rows * n_b];
        let mut d_offsets = vec![0.0; n_m * 9];
        let axes = self.rotation_axes(r);
        // Adds the derivative of a segment `s` of bone `b` to the rows of point `p`.
        let add_segment = |d_pose: &mut [f64], p: usize, b: usize, s: &Vector3<f64>| {
            for (&i, w) in self.acting[b].iter().zip(&axes[b]) {
                for k in 0..3 {
                    let d = w.column(k).cross(s);
                    for a in 0..3 {
                        d_pose[(3 * p + a) * cols + 3 + 3 * i + k] += d[a];
                    }
                }
            }
        };
        // Joints root first: a joint's rows are its start joint's plus its own segment.
        for a in 0..3 {
            d_pose[(3 * self.root + a) * cols + a] = 1.0;
        }
        for &j in &self.order[1..] {
            let b = self.bone_of_end[j].expect("non-root joint has a bone");
            let s = self.bones[b].0;
            d_pose.copy_within(3 * s * cols..3 * (s + 1) * cols, 3 * j * cols);
            add_segment(&mut d_pose, j, b, &(fk.joints[j] - fk.joints[s]));
        }
        // Markers: their joint's rows plus the offset's segment.
        for (k, (&j, &b)) in self.marker_joints.iter().zip(&self.marker_bone).enumerate() {
            let p = n_j + k;
            d_pose.copy_within(3 * j * cols..3 * (j + 1) * cols, 3 * p * cols);
            add_segment(&mut d_pose, p, b, &(fk.markers[k] - fk.joints[j]));
        }
        // Bone lengths: points at or below the bone's end joint move along its axis.
        for (b, &(_, eb)) in self.bones.iter().enumerate() {
            let axis = fk.bone_rotations[b].column(2);
            let target = |j: usize| self.is_ancestor_or_self(eb, j);
            for j in (0..n_j).filter(|&j| target(j)) {
                for a in 0..3 {
                    d_lengths[(3 * j + a) * n_b + b] = axis[a];
                }
            }
            for (k, &j) in self.marker_joints.iter().enumerate() {
                if target(j) {
                    for a in 0..3 {
                        d_lengths[(3 * (n_j + k) + a) * n_b + b] = axis[a];
                    }
                }
            }
        }
        // Offsets.
        for (k, &b) in self.marker_bone.iter().enumerate() {
            crate::rotation::write_row_major(
                &fk.bone_rotations[b],
                &mut d_offsets[9 * k..9 * k + 9],
            );
        }
        Ok(FkJacobian {
            fk,
            d_pose,
            d_lengths,
            d_offsets,
        })
    }

    /// World-frame rotation axes: entry `b` lists, for each bone `i` acting on `b` (in
    /// [`Skeleton::acting_bones`] order), `W_ib = A_ib J_l(r_i)`, whose column `k` is the axis
    /// `w_ibk` of `∂R_b/∂r_ik = [w_ibk]× R_b`.
    pub fn rotation_axes(&self, r: &[Vector3<f64>]) -> Vec<Vec<Matrix3<f64>>> {
        let q: Vec<Matrix3<f64>> = r.iter().map(rodrigues).collect();
        let jl: Vec<Matrix3<f64>> = r.iter().map(left_jacobian).collect();
        self.acting
            .iter()
            .map(|acting| {
                let mut before = Matrix3::<f64>::identity();
                acting
                    .iter()
                    .map(|&i| {
                        let w = before * jl[i];
                        before *= q[i];
                        w
                    })
                    .collect()
            })
            .collect()
    }

    /// Vector-Jacobian product of the marker positions: given `g_k = ∂f/∂m_k` for a scalar
    /// `f`, returns `(∂f/∂[t, r] (n_pose), ∂f/∂l (n_bones), ∂f/∂v (M))` exactly, in
    /// O(Σ_b |acting(b)| + M) without forming the Jacobian. `fk` must come from `(t, r)` with
    /// [`Skeleton::forward_unchecked`] (or `forward`).
    pub fn markers_vjp(
        &self,
        fk: &FkResult,
        r: &[Vector3<f64>],
        g: &[Vector3<f64>],
    ) -> (Vec<f64>, Vec<f64>, Vec<Vector3<f64>>) {
        let mut d_pose = vec![0.0; self.n_pose()];
        let gt: Vector3<f64> = g.iter().sum();
        d_pose[..3].copy_from_slice(gt.as_slice());
        // below[j]: the sum of g over the markers at or below joint j.
        let mut below = vec![Vector3::zeros(); self.n_joints()];
        for (&j, gk) in self.marker_joints.iter().zip(g) {
            below[j] += gk;
        }
        for &j in self.order[1..].iter().rev() {
            let p = self.parents[j].expect("non-root joint has a parent");
            let add = below[j];
            below[p] += add;
        }
        // u_b: Σ over the points bone b's orientation moves of (segment × gradient).
        let mut u: Vec<Vector3<f64>> = self
            .bones
            .iter()
            .map(|&(s, e)| (fk.joints[e] - fk.joints[s]).cross(&below[e]))
            .collect();
        for (k, (&j, &b)) in self.marker_joints.iter().zip(&self.marker_bone).enumerate() {
            u[b] += (fk.markers[k] - fk.joints[j]).cross(&g[k]);
        }
        // ∂f/∂r_i = Σ_b W_ib^T u_b over the bones b that i turns.
        let axes = self.rotation_axes(r);
        for (b, (acting, ws)) in self.acting.iter().zip(&axes).enumerate() {
            for (&i, w) in acting.iter().zip(ws) {
                let d = w.transpose() * u[b];
                for k in 0..3 {
                    d_pose[3 + 3 * i + k] += d[k];
                }
            }
        }
        let d_lengths = self
            .bones
            .iter()
            .enumerate()
            .map(|(b, &(_, eb))| fk.bone_rotations[b].column(2).dot(&below[eb]))
            .collect();
        let d_offsets = self
            .marker_bone
            .iter()
            .zip(g)
            .map(|(&b, gk)| fk.bone_rotations[b].transpose() * gk)
            .collect();
        (d_pose, d_lengths, d_offsets)
    }

    /// Forward kinematics of `T` poses in parallel.
    ///
    /// # Arguments
    /// * `t` - `(T, 3)` flat translations.
    /// * `r` - `(T, n_bones, 3)` flat Rodrigues vectors.
    /// * `lengths`, `offsets` - optional overrides, shared by all frames (`(n_bones,)`,
    ///   `(M, 3)` flat).
    ///
    /// # Returns
    /// `(joints (T, J, 3), markers (T, M, 3))`, flat row-major.
    ///
    /// # Errors
    /// Shape errors for inconsistent sizes, non-finite errors naming the first bad frame.
    pub fn forward_batch(
        &self,
        t: &[f64],
        r: &[f64],
        lengths: Option<&[f64]>,
        offsets: Option<&[f64]>,
    ) -> Result<(Vec<f64>, Vec<f64>)> {
        let n_t = t.len() / 3;
        let mut joints = vec![0.0; n_t * self.n_joints() * 3];
        let mut markers = vec![0.0; n_t * self.n_markers() * 3];
        self.forward_batch_into(t, r, lengths, offsets, &mut joints, &mut markers)?;
        Ok((joints, markers))
    }

    /// Like [`Skeleton::forward_batch`], writing into caller-provided buffers of
    /// `T·J·3` and `T·M·3` values (e.g. numpy arrays).
    ///
    /// # Errors
    /// As [`Skeleton::forward_batch`], plus shape errors for wrong buffer sizes.
    pub fn forward_batch_into(
        &self,
        t: &[f64],
        r: &[f64],
        lengths: Option<&[f64]>,
        offsets: Option<&[f64]>,
        joints_out: &mut [f64],
        markers_out: &mut [f64],
    ) -> Result<()> {
        if !t.len().is_multiple_of(3) {
            return Err(AcmError::Shape(format!(
                "translations: {} values is not a multiple of 3",
                t.len()
            )));
        }
        let n_t = t.len() / 3;
        let (n_j, n_m, n_b) = (self.n_joints(), self.n_markers(), self.n_bones());
        ensure_len(r.len(), n_t * 3 * n_b, "rotations (T, n_bones, 3)")?;
        ensure_len(joints_out.len(), n_t * n_j * 3, "joint output buffer")?;
        ensure_len(markers_out.len(), n_t * n_m * 3, "marker output buffer")?;
        if let Some(i) = t.iter().chain(r.iter()).position(|v| !v.is_finite()) {
            let frame = if i < t.len() {
                i / 3
            } else {
                (i - t.len()) / (3 * n_b)
            };
            return Err(AcmError::NonFinite(format!(
                "pose of frame {frame} contains NaN or infinity"
            )));
        }
        let offsets_v: Option<Vec<Vector3<f64>>> = match offsets {
            Some(o) => {
                ensure_len(o.len(), 3 * n_m, "marker offsets (M, 3)")?;
                Some(
                    o.chunks(3)
                        .map(|c| Vector3::new(c[0], c[1], c[2]))
                        .collect(),
                )
            }
            None => None,
        };
        self.check_overrides(lengths, offsets_v.as_deref())?;
        let l = lengths.unwrap_or(&self.lengths);
        let v = offsets_v.as_deref().unwrap_or(&self.offsets);
        // Blocks of frames keep rayon's per-task overhead negligible.
        const BLOCK: usize = 64;
        let run = |ws: &mut FkWorkspace, blk: usize, jo: &mut [f64], mo: &mut [f64]| {
            let nf = jo.len() / (n_j * 3);
            for f in 0..nf {
                let fr = blk * BLOCK + f;
                let mo_f: &mut [f64] = if n_m == 0 {
                    &mut []
                } else {
                    &mut mo[f * n_m * 3..(f + 1) * n_m * 3]
                };
                self.forward_flat_into(
                    &t[3 * fr..3 * fr + 3],
                    &r[fr * 3 * n_b..(fr + 1) * 3 * n_b],
                    l,
                    v,
                    ws,
                    Some(&mut jo[f * n_j * 3..(f + 1) * n_j * 3]),
                    mo_f,
                );
            }
        };
        if n_m == 0 {
            joints_out
                .par_chunks_mut(BLOCK * n_j * 3)
                .enumerate()
                .for_each_init(
                    || self.workspace(),
                    |ws, (blk, jo)| run(ws, blk, jo, &mut []),
                );
        } else {
            joints_out
                .par_chunks_mut(BLOCK * n_j * 3)
                .zip(markers_out.par_chunks_mut(BLOCK * n_m * 3))
                .enumerate()
                .for_each_init(
                    || self.workspace(),
                    |ws, (blk, (jo, mo))| run(ws, blk, jo, mo),
                );
        }
        Ok(())
    }
}

fn validate_lengths(lengths: &[f64]) -> Result<()> {
    ensure_finite(lengths, "bone lengths")?;
    if let Some(b) = lengths.iter().position(|&l| l <= 0.0) {
        return Err(AcmError::Invalid(format!(
            "bone lengths must be positive, bone {b} has {}",
            lengths[b]
        )));
    }
    Ok(())
}

/// Checks that `parents` describes one tree; returns the parent options, the root and a
/// root-first (breadth-first) joint order.
fn validate_tree(parents: &[i64]) -> Result<(Vec<Option<usize>>, usize, Vec<usize>)> {
    let n = parents.len();
    if n < 2 {
        return Err(AcmError::Invalid(format!(
            "a skeleton needs at least 2 joints (one bone), got {n}"
        )));
    }
    let mut out = Vec::with_capacity(n);
    for (j, &p) in parents.iter().enumerate() {
        if p == -1 {
            out.push(None);
        } else if p < 0 || p as usize >= n {
            return Err(AcmError::Invalid(format!(
                "joint {j} has parent {p}, which is not a joint index (0..{n}) or -1 for the root"
            )));
        } else if p as usize == j {
            return Err(AcmError::Invalid(format!("joint {j} is its own parent")));
        } else {
            out.push(Some(p as usize));
        }
    }
    let roots: Vec<usize> = (0..n).filter(|&j| out[j].is_none()).collect();
    if roots.len() != 1 {
        return Err(AcmError::Invalid(format!(
            "a skeleton needs exactly one root (parent -1), found {} ({roots:?})",
            roots.len()
        )));
    }
    let root = roots[0];
    let mut children = vec![Vec::new(); n];
    for (j, p) in out.iter().enumerate() {
        if let Some(p) = p {
            children[*p].push(j);
        }
    }
    let mut order = Vec::with_capacity(n);
    order.push(root);
    let mut head = 0;
    while head < order.len() {
        let a = order[head];
        head += 1;
        order.extend_from_slice(&children[a]);
    }
    if order.len() != n {
        let mut seen = vec![false; n];
        for &j in &order {
            seen[j] = true;
        }
        let cyc: Vec<usize> = (0..n).filter(|&j| !seen[j]).collect();
        return Err(AcmError::Invalid(format!(
            "parents do not form a tree: joints {cyc:?} are not connected to the root (cycle)"
        )));
    }
    Ok((out, root, order))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A small branching skeleton: root 0 → 1 → {2 → 3, 4 → 5}, plus 0 → 6.
    pub(crate) fn branching() -> Skeleton {
        let parents = [-1, 0, 1, 2, 1, 4, 0];
        let rest = [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(0.0, 0.0, 2.0),
            Vector3::new(-1.0, -0.5, 2.0),
            Vector3::new(-1.0, -0.5, 3.0),
            Vector3::new(1.0, -0.5, 2.0),
            Vector3::new(1.0, -0.5, 3.2),
            Vector3::new(0.0, 0.3, -1.0),
        ];
        let marker_joints = vec![0, 1, 3, 5, 2, 6];
        let marker_rest = [
            Vector3::new(0.1, 0.2, -0.1),
            Vector3::new(0.0, 0.4, 1.9),
            Vector3::new(-1.2, -0.4, 3.1),
            Vector3::new(1.1, -0.6, 3.3),
            Vector3::new(-0.9, -0.2, 2.2),
            Vector3::new(0.1, 0.5, -1.2),
        ];
        Skeleton::from_rest_pose(
            &parents,
            &rest,
            marker_joints,
            &marker_rest,
            &Vector3::y(),
            None,
        )
        .unwrap()
    }

    fn rest_positions() -> Vec<Vector3<f64>> {
        vec![
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(0.0, 0.0, 2.0),
            Vector3::new(-1.0, -0.5, 2.0),
            Vector3::new(-1.0, -0.5, 3.0),
            Vector3::new(1.0, -0.5, 2.0),
            Vector3::new(1.0, -0.5, 3.2),
            Vector3::new(0.0, 0.3, -1.0),
        ]
    }

    fn pose(seed: u64, scale: f64, n: usize) -> (Vector3<f64>, Vec<Vector3<f64>>) {
        // Small deterministic pseudo-random generator (LCG) for reproducible poses.
        let mut s = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        let t = Vector3::new(next(), next(), next());
        let r = (0..n)
            .map(|_| Vector3::new(next(), next(), next()) * scale)
            .collect();
        (t, r)
    }

    #[test]
    fn zero_rotation_gives_rest_pose() {
        let sk = branching();
        let r = vec![Vector3::zeros(); sk.n_bones()];
        let fk = sk.forward(&Vector3::zeros(), &r, None, None).unwrap();
        for (a, b) in fk.joints.iter().zip(rest_positions()) {
            assert!((a - b).norm() < 1e-12);
        }
        let expect_markers = [
            Vector3::new(0.1, 0.2, -0.1),
            Vector3::new(0.0, 0.4, 1.9),
            Vector3::new(-1.2, -0.4, 3.1),
            Vector3::new(1.1, -0.6, 3.3),
            Vector3::new(-0.9, -0.2, 2.2),
            Vector3::new(0.1, 0.5, -1.2),
        ];
        for (a, b) in fk.markers.iter().zip(expect_markers) {
            assert!((a - b).norm() < 1e-12);
        }
    }

    /// The literal reading of Alg. 1 line 5: bone `i` moves bone `j` when `j`'s end joint
    /// descends from `i`'s start joint (siblings included); row-major.
    fn literal_alg1_links(sk: &Skeleton) -> Vec<bool> {
        let n = sk.n_bones();
        let mut out = vec![false; n * n];
        for (i, &(si, _)) in sk.bones().iter().enumerate() {
            for (j, &(sj, _)) in sk.bones().iter().enumerate() {
                out[i * n + j] = sk.is_ancestor_or_self(si, sj);
            }
        }
        out
    }

    /// The branching skeleton with a pseudo-random link matrix and a shuffled order.
    fn scrambled() -> Skeleton {
        let sk = branching();
        let n = sk.n_bones();
        let links: Vec<bool> = (0..n * n).map(|k| (k * 7 + 3) % 5 < 3).collect();
        sk.with_links(&links, Some(&[3, 0, 5, 1, 4, 2])).unwrap()
    }

    #[test]
    fn a_rotation_moves_its_bone_and_descendants_rigidly_and_nothing_else() {
        let sk = branching();
        // Bone indices: 0: 0→1, 1: 1→2, 2: 2→3, 3: 1→4, 4: 4→5, 5: 0→6.
        let rest = sk
            .forward(
                &Vector3::zeros(),
                &vec![Vector3::zeros(); sk.n_bones()],
                None,
                None,
            )
            .unwrap();
        for b in 0..sk.n_bones() {
            let mut r = vec![Vector3::zeros(); sk.n_bones()];
            let rv = Vector3::new(0.3, -0.7, 0.2);
            r[b] = rv;
            let fk = sk.forward(&Vector3::zeros(), &r, None, None).unwrap();
            let (s, e) = sk.bones()[b];
            let pivot = rest.joints[s];
            let q = rodrigues(&rv);
            let moved = |j: usize| sk.is_ancestor_or_self(e, j);
            for j in 0..sk.n_joints() {
                let expect = if moved(j) {
                    pivot + q * (rest.joints[j] - pivot)
                } else {
                    rest.joints[j]
                };
                assert!((fk.joints[j] - expect).norm() < 1e-12, "bone {b} joint {j}");
            }
            for (k, &mb) in sk.marker_bones().iter().enumerate() {
                let expect = if mb == b || moved(sk.bones()[mb].1) {
                    pivot + q * (rest.markers[k] - pivot)
                } else {
                    rest.markers[k]
                };
                assert!(
                    (fk.markers[k] - expect).norm() < 1e-12,
                    "bone {b} marker {k}"
                );
            }
        }
    }

    #[test]
    fn tree_rule_composes_the_path_from_the_root_and_links_say_so() {
        let sk = branching();
        let (_, r) = pose(5, 0.8, sk.n_bones());
        let fk = sk.forward(&Vector3::zeros(), &r, None, None).unwrap();
        let q: Vec<Matrix3<f64>> = r.iter().map(rodrigues).collect();
        // Bone 2 (2→3): the path 0→1→2→3, i.e. bones 0, 1, 2 (not the sibling 3: 1→4).
        let expect = q[0] * q[1] * q[2] * sk.rest_frames()[2];
        assert!((fk.bone_rotations[2] - expect).norm() < 1e-12);
        let expect4 = q[0] * q[3] * q[4] * sk.rest_frames()[4];
        assert!((fk.bone_rotations[4] - expect4).norm() < 1e-12);
        assert!((fk.bone_rotations[5] - q[5] * sk.rest_frames()[5]).norm() < 1e-12);
        let links = sk.bone_links();
        let n = sk.n_bones();
        assert!(!links[3 * n + 1] && !links[n + 3]); // siblings at joint 1
        assert!(links[n + 2] && links[2 * n + 2] && !links[2 * n + 1]);
        assert!(!links[5] && !links[5 * n]); // the two root bones
        assert!(sk.custom_links().is_none());
    }

    #[test]
    fn literal_alg1_links_reproduce_the_sibling_coupling() {
        let sk = branching();
        let lit = sk
            .clone()
            .with_links(&literal_alg1_links(&sk), None)
            .unwrap();
        let (_, r) = pose(9, 0.8, sk.n_bones());
        let fk = lit.forward(&Vector3::zeros(), &r, None, None).unwrap();
        let q: Vec<Matrix3<f64>> = r.iter().map(rodrigues).collect();
        // Bone 2 (2→3) is acted on by the bones starting at 0, 1 and 2, in bone order.
        let expect = q[0] * q[1] * q[2] * q[3] * q[5] * sk.rest_frames()[2];
        assert!((fk.bone_rotations[2] - expect).norm() < 1e-12);
        assert_eq!(lit.bone_links(), literal_alg1_links(&sk));
        // Back to the tree rule.
        let back = lit.with_tree_links();
        assert_eq!(back.bone_links(), sk.bone_links());
    }

    #[test]
    fn custom_links_match_a_naive_product_in_the_given_order() {
        // A transcription of the authors' loop: start from the identity, for each bone i
        // in `order` left-multiply the transposes of the frames it links; then transpose.
        let sk = scrambled();
        let (links, order) = sk.custom_links().unwrap();
        let (links, order) = (links.to_vec(), order.to_vec());
        let n = sk.n_bones();
        let (t, r) = pose(7, 0.8, n);
        let fk = sk.forward(&t, &r, None, None).unwrap();
        let mut rt = vec![Matrix3::identity(); n];
        for &i in &order {
            for j in 0..n {
                if links[i * n + j] {
                    rt[j] = rodrigues(&r[i]).transpose() * rt[j];
                }
            }
        }
        let mut p = vec![Vector3::zeros(); sk.n_joints()];
        p[sk.root()] = t;
        let mut done = vec![false; n];
        while done.iter().any(|d| !d) {
            for j in 0..n {
                let (s, e) = sk.bones()[j];
                let placed = s == sk.root() || sk.bone_of_end()[s].map(|b| done[b]).unwrap();
                if !done[j] && placed {
                    let rj = rt[j].transpose() * sk.rest_frames()[j];
                    assert!((fk.bone_rotations[j] - rj).norm() < 1e-12);
                    p[e] = p[s] + rj.column(2) * sk.lengths()[j];
                    done[j] = true;
                }
            }
        }
        for (a, b) in fk.joints.iter().zip(&p) {
            assert!((a - b).norm() < 1e-12);
        }
        assert!(matches!(
            branching().with_links(&links, Some(&[0, 0, 1, 2, 3, 4])),
            Err(AcmError::Invalid(_))
        ));
        assert!(matches!(
            branching().with_links(&links[1..], None),
            Err(AcmError::Shape(_))
        ));
    }

    #[test]
    fn jacobian_matches_central_differences() {
        let base = branching();
        let lit = base
            .clone()
            .with_links(&literal_alg1_links(&base), None)
            .unwrap();
        for sk in [base, lit, scrambled()] {
            jacobian_matches_central_differences_for(&sk);
        }
    }

    fn jacobian_matches_central_differences_for(sk: &Skeleton) {
        let (t, r) = pose(3, 0.9, sk.n_bones());
        let lengths: Vec<f64> = sk.lengths().iter().map(|l| l * 1.1).collect();
        let offsets: Vec<Vector3<f64>> = sk.offsets().iter().map(|v| v * 0.9).collect();
        let jac = sk
            .forward_jacobian(&t, &r, Some(&lengths), Some(&offsets))
            .unwrap();
        let flat = |fk: &FkResult| -> Vec<f64> {
            fk.joints
                .iter()
                .chain(fk.markers.iter())
                .flat_map(|p| [p.x, p.y, p.z])
                .collect()
        };
        let rows = 3 * (sk.n_joints() + sk.n_markers());
        let h = 1e-6;
        let cols = sk.n_pose();
        for c in 0..cols {
            let mut tp = t;
            let mut tm = t;
            let mut rp = r.clone();
            let mut rm = r.clone();
            if c < 3 {
                tp[c] += h;
                tm[c] -= h;
            } else {
                rp[(c - 3) / 3][(c - 3) % 3] += h;
                rm[(c - 3) / 3][(c - 3) % 3] -= h;
            }
            let fp = flat(
                &sk.forward(&tp, &rp, Some(&lengths), Some(&offsets))
                    .unwrap(),
            );
            let fm = flat(
                &sk.forward(&tm, &rm, Some(&lengths), Some(&offsets))
                    .unwrap(),
            );
            for row in 0..rows {
                let fd = (fp[row] - fm[row]) / (2.0 * h);
                let an = jac.d_pose[row * cols + c];
                assert!(
                    (fd - an).abs() < 1e-7,
                    "pose col {c} row {row}: fd {fd} an {an}"
                );
            }
        }
        for b in 0..sk.n_bones() {
            let mut lp = lengths.clone();
            let mut lm = lengths.clone();
            lp[b] += h;
            lm[b] -= h;
            let fp = flat(&sk.forward(&t, &r, Some(&lp), Some(&offsets)).unwrap());
            let fm = flat(&sk.forward(&t, &r, Some(&lm), Some(&offsets)).unwrap());
            for row in 0..rows {
                let fd = (fp[row] - fm[row]) / (2.0 * h);
                let an = jac.d_lengths[row * sk.n_bones() + b];
                assert!((fd - an).abs() < 1e-7, "length {b} row {row}");
            }
        }
        for k in 0..sk.n_markers() {
            for c in 0..3 {
                let mut vp = offsets.clone();
                let mut vm = offsets.clone();
                vp[k][c] += h;
                vm[k][c] -= h;
                let mp = sk
                    .forward(&t, &r, Some(&lengths), Some(&vp))
                    .unwrap()
                    .markers[k];
                let mm = sk
                    .forward(&t, &r, Some(&lengths), Some(&vm))
                    .unwrap()
                    .markers[k];
                let fd = (mp - mm) / (2.0 * h);
                for a in 0..3 {
                    assert!((fd[a] - jac.d_offsets[9 * k + 3 * a + c]).abs() < 1e-7);
                }
            }
        }
    }

    #[test]
    #[allow(clippy::needless_range_loop)] // index arithmetic mirrors the Jacobian layout
    fn markers_vjp_is_jacobian_transpose() {
        for sk in [branching(), scrambled()] {
            markers_vjp_is_jacobian_transpose_for(&sk);
        }
    }

    #[allow(clippy::needless_range_loop)] // index arithmetic mirrors the Jacobian layout
    fn markers_vjp_is_jacobian_transpose_for(sk: &Skeleton) {
        let (t, r) = pose(11, 0.7, sk.n_bones());
        let jac = sk.forward_jacobian(&t, &r, None, None).unwrap();
        let g: Vec<Vector3<f64>> = (0..sk.n_markers())
            .map(|k| Vector3::new(1.0 + k as f64, -0.5 * k as f64, 0.25))
            .collect();
        let (dp, dl, dv) = sk.markers_vjp(&jac.fk, &r, &g);
        let (nj, cols, nb) = (sk.n_joints(), sk.n_pose(), sk.n_bones());
        for c in 0..cols {
            let expect: f64 = (0..sk.n_markers())
                .map(|k| {
                    (0..3)
                        .map(|a| jac.d_pose[(3 * (nj + k) + a) * cols + c] * g[k][a])
                        .sum::<f64>()
                })
                .sum();
            assert!((dp[c] - expect).abs() < 1e-12, "pose {c}");
        }
        for b in 0..nb {
            let expect: f64 = (0..sk.n_markers())
                .map(|k| {
                    (0..3)
                        .map(|a| jac.d_lengths[(3 * (nj + k) + a) * nb + b] * g[k][a])
                        .sum::<f64>()
                })
                .sum();
            assert!((dl[b] - expect).abs() < 1e-12, "length {b}");
        }
        for k in 0..sk.n_markers() {
            for c in 0..3 {
                let expect: f64 = (0..3)
                    .map(|a| jac.d_offsets[9 * k + 3 * a + c] * g[k][a])
                    .sum();
                assert!((dv[k][c] - expect).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn invalid_trees_are_rejected() {
        let f = |parents: &[i64]| {
            let n = parents.len().saturating_sub(1);
            Skeleton::new(
                parents,
                vec![Matrix3::identity(); n],
                vec![1.0; n],
                vec![],
                vec![],
            )
        };
        assert!(f(&[-1, 0, 1]).is_ok());
        assert!(matches!(f(&[-1, -1, 1]), Err(AcmError::Invalid(_))));
        assert!(matches!(f(&[-1, 2, 1]), Err(AcmError::Invalid(_)))); // cycle 1↔2
        assert!(matches!(f(&[-1, 5]), Err(AcmError::Invalid(_))));
        assert!(matches!(f(&[0, 0]), Err(AcmError::Invalid(_)))); // self parent, no root
        assert!(matches!(f(&[-1]), Err(AcmError::Invalid(_))));
        let bad_len = Skeleton::new(
            &[-1, 0],
            vec![Matrix3::identity()],
            vec![0.0],
            vec![],
            vec![],
        );
        assert!(matches!(bad_len, Err(AcmError::Invalid(_))));
        let bad_marker = Skeleton::new(
            &[-1, 0],
            vec![Matrix3::identity()],
            vec![1.0],
            vec![3],
            vec![Vector3::zeros()],
        );
        assert!(matches!(bad_marker, Err(AcmError::Invalid(_))));
    }

    #[test]
    fn batch_matches_single_and_reports_bad_frame() {
        let sk = branching();
        let n_b = sk.n_bones();
        let mut t = Vec::new();
        let mut r = Vec::new();
        for f in 0..5 {
            let (tf, rf) = pose(f, 1.0, n_b);
            t.extend_from_slice(tf.as_slice());
            r.extend(rf.iter().flat_map(|v| [v.x, v.y, v.z]));
        }
        let (joints, markers) = sk.forward_batch(&t, &r, None, None).unwrap();
        let (tf, rf) = pose(3, 1.0, n_b);
        let single = sk.forward(&tf, &rf, None, None).unwrap();
        let j0 = 3 * sk.n_joints() * 3;
        assert!((joints[j0 + 5] - single.joints[1].z).abs() < 1e-15);
        let m0 = 3 * sk.n_markers() * 3;
        assert!((markers[m0 + 3] - single.markers[1].x).abs() < 1e-15);
        r[2 * 3 * n_b + 4] = f64::NAN;
        match sk.forward_batch(&t, &r, None, None) {
            Err(AcmError::NonFinite(s)) => assert!(s.contains("frame 2"), "{s}"),
            other => panic!("expected NonFinite, got {other:?}"),
        }
        assert!(matches!(
            sk.forward_batch(&t, &r[1..], None, None),
            Err(AcmError::Shape(_))
        ));
    }

    proptest! {
        #[test]
        fn fk_preserves_bone_lengths_and_marker_distances(seed in 0u64..10_000, scale in 0.0f64..3.0) {
            let sk = if seed % 2 == 0 { branching() } else { scrambled() };
            let (t, r) = pose(seed, scale, sk.n_bones());
            let fk = sk.forward(&t, &r, None, None).unwrap();
            for (b, &(s, e)) in sk.bones().iter().enumerate() {
                prop_assert!(((fk.joints[e] - fk.joints[s]).norm() - sk.lengths()[b]).abs() < 1e-12);
            }
            for (k, &j) in sk.marker_joints().iter().enumerate() {
                prop_assert!(((fk.markers[k] - fk.joints[j]).norm() - sk.offsets()[k].norm()).abs() < 1e-12);
            }
            prop_assert!((fk.joints[sk.root()] - t).norm() < 1e-15);
        }
    }
}
