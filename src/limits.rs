//! Joint-angle limits (ACM supp. section 4.4.3, Alg. 10) and the map between the tracker's
//! state and the full pose.
//!
//! The full pose is `[t (3), r_0 (3), …, r_{n-1} (3)]` (world units, rad). Rotation entries
//! whose limits are `[b, b]` are fixed at `b` and are not part of the state; the remaining
//! ("free") entries form the state vector `z`, normalised as in sec. 3.3:
//! * translation: `t = c_t z`;
//! * unbounded rotation entries (e.g. the global rotation): `r = c_r z`;
//! * bounded rotation entries, when limits are enforced: Alg. 10,
//!   `r = b0 + ½ (b1 − b0) (1 + erf(√π/2 · z))`, which maps ℝ onto `(b0, b1)` with slope
//!   `½ (b1 − b0)` at `z = 0`.

use crate::error::{ensure_finite, ensure_len, AcmError, Result};
use crate::normalization::Normalization;

const SQRT_PI_2: f64 = 0.886_226_925_452_758; // √π / 2

/// Alg. 10 lines 6-7: value and derivative of `b0 + ½ (b1 − b0)(1 + erf(√π/2 · z))`.
///
/// # Example
/// ```
/// let (r, dr) = acm_rs::limits::erf_map(0.0, -1.0, 3.0);
/// assert!((r - 1.0).abs() < 1e-15 && (dr - 2.0).abs() < 1e-15);
/// ```
pub fn erf_map(z: f64, b0: f64, b1: f64) -> (f64, f64) {
    let half = 0.5 * (b1 - b0);
    let n = libm::erf(SQRT_PI_2 * z);
    // d/dz erf(√π/2 z) = (2/√π) exp(−π z²/4) √π/2 = exp(−π z²/4)
    let dn = (-std::f64::consts::PI * 0.25 * z * z).exp();
    (b0 + half * (1.0 + n), half * dn)
}

/// Inverse error function on `(-1, 1)` (Newton iterations on `libm::erf`).
pub fn erfinv(y: f64) -> f64 {
    if y <= -1.0 {
        return f64::NEG_INFINITY;
    }
    if y >= 1.0 {
        return f64::INFINITY;
    }
    // Initial guess (Winitzki's approximation), then Newton steps to full precision.
    let a = 0.147;
    let ln = (1.0 - y * y).ln();
    let b = 2.0 / (std::f64::consts::PI * a) + 0.5 * ln;
    let mut x = (((b * b - ln / a).sqrt() - b).sqrt()).copysign(y);
    for _ in 0..4 {
        let err = libm::erf(x) - y;
        let deriv = std::f64::consts::FRAC_2_SQRT_PI * (-x * x).exp();
        if deriv == 0.0 {
            break;
        }
        x -= err / deriv;
    }
    x
}

/// Inverse of [`erf_map`]. Values at or beyond a bound are first moved inside by a relative
/// margin of `1e-9` of the range (the map never reaches its bounds).
pub fn erf_map_inverse(r: f64, b0: f64, b1: f64) -> f64 {
    let n = (2.0 * (r - b0) / (b1 - b0) - 1.0).clamp(-1.0 + 1e-9, 1.0 - 1e-9);
    erfinv(n) / SQRT_PI_2
}

/// How one free state entry maps to its pose entry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum EntryMap {
    /// `pose = scale · z`.
    Linear {
        /// Normalisation scale (`c_t` or `c_r`).
        scale: f64,
    },
    /// `pose = erf_map(z, lo, hi)` (Alg. 10).
    Bounded {
        /// Lower bound `b0` (rad).
        lo: f64,
        /// Upper bound `b1` (rad).
        hi: f64,
    },
}

/// Checks a list of elastic bones: each an index below `n_bones`, none twice.
///
/// # Errors
/// Invalid error naming the first bad entry.
pub fn check_elastic_bones(bones: &[usize], n_bones: usize) -> Result<()> {
    let mut seen = vec![false; n_bones];
    for &b in bones {
        if b >= n_bones {
            return Err(AcmError::Invalid(format!(
                "elastic bone {b} does not exist (the skeleton has {n_bones} bones)"
            )));
        }
        if std::mem::replace(&mut seen[b], true) {
            return Err(AcmError::Invalid(format!(
                "elastic bone {b} is listed twice"
            )));
        }
    }
    Ok(())
}

/// Map between the state `z` (free entries, normalised, optionally erf-constrained) and the
/// full pose `[t, r]`, optionally followed by the log-stretch of elastic bones (issue 28:
/// `l_b exp(z)`, see [`StateMap::with_stretch`]).
#[derive(Debug, Clone, PartialEq)]
pub struct StateMap {
    n_pose: usize,
    free: Vec<usize>,
    maps: Vec<EntryMap>,
    template: Vec<f64>,
    /// Elastic bones whose log-stretch follows the pose entries in the state.
    stretch: Vec<usize>,
}

impl StateMap {
    /// Builds the map from per-entry rotation limits.
    ///
    /// # Arguments
    /// * `n_bones` - number of bones.
    /// * `lower`, `upper` - `(n_bones, 3)` flat limits (rad); `±inf` for unbounded. Entries
    ///   with `lower == upper` are fixed at that value.
    /// * `norm` - normalisation constants (sec. 3.3).
    /// * `enforce_limits` - use Alg. 10 for bounded entries; otherwise every non-fixed
    ///   rotation entry is linear (`r = c_r z`).
    ///
    /// # Errors
    /// Shape errors for wrong lengths; invalid errors for NaN bounds, `lower > upper`, or a
    /// one-sided bound when limits are enforced (Alg. 10 needs both bounds).
    pub fn new(
        n_bones: usize,
        lower: &[f64],
        upper: &[f64],
        norm: &Normalization,
        enforce_limits: bool,
    ) -> Result<Self> {
        norm.validate()?;
        ensure_len(lower.len(), 3 * n_bones, "lower joint limits (n_bones, 3)")?;
        ensure_len(upper.len(), 3 * n_bones, "upper joint limits (n_bones, 3)")?;
        let n_pose = 3 + 3 * n_bones;
        let mut free = vec![0, 1, 2];
        let mut maps = vec![
            EntryMap::Linear {
                scale: norm.translation
            };
            3
        ];
        let mut template = vec![0.0; n_pose];
        for (e, (&lo, &hi)) in lower.iter().zip(upper).enumerate() {
            let (bone, axis) = (e / 3, ["x", "y", "z"][e % 3]);
            if lo.is_nan() || hi.is_nan() || lo > hi {
                return Err(AcmError::Invalid(format!(
                    "joint limit of bone {bone} axis {axis} is not an interval: [{lo}, {hi}]"
                )));
            }
            if lo == hi {
                if !lo.is_finite() {
                    return Err(AcmError::Invalid(format!(
                        "joint limit of bone {bone} axis {axis} is [{lo}, {hi}]"
                    )));
                }
                template[3 + e] = lo;
                continue;
            }
            free.push(3 + e);
            let bounded = lo.is_finite() && hi.is_finite();
            if enforce_limits && !bounded && (lo.is_finite() || hi.is_finite()) {
                return Err(AcmError::Invalid(format!(
                    "joint limit of bone {bone} axis {axis} is one-sided ([{lo}, {hi}]); the \
                     erf map of Alg. 10 needs two finite bounds or none"
                )));
            }
            maps.push(if enforce_limits && bounded {
                EntryMap::Bounded { lo, hi }
            } else {
                EntryMap::Linear {
                    scale: norm.rotation,
                }
            });
        }
        Ok(Self {
            n_pose,
            free,
            maps,
            template,
            stretch: Vec::new(),
        })
    }

    /// The same map with one more state entry per elastic bone: its log-stretch `s_b`, the
    /// bone's length in that state being `l_b exp(s_b)` (elastic segments, issue 28; beyond
    /// the paper). The entries follow the pose entries, in the order given.
    ///
    /// # Errors
    /// Invalid error for a bone index out of range or listed twice.
    pub fn with_stretch(mut self, bones: &[usize]) -> Result<Self> {
        check_elastic_bones(bones, (self.n_pose - 3) / 3)?;
        self.stretch = bones.to_vec();
        Ok(self)
    }

    /// Dimension of the state: the free pose entries, then one log-stretch per elastic bone.
    pub fn n_state(&self) -> usize {
        self.free.len() + self.stretch.len()
    }
    /// Number of pose entries of the state (the first ones).
    pub fn n_pose_state(&self) -> usize {
        self.free.len()
    }
    /// The elastic bones, in the order of their state entries (after the pose entries).
    pub fn stretch_bones(&self) -> &[usize] {
        &self.stretch
    }
    /// Bone lengths of a state: `base` with each elastic bone times `exp(s_b)`.
    pub fn lengths_into(&self, z: &[f64], base: &[f64], out: &mut [f64]) {
        out.copy_from_slice(base);
        let nf = self.free.len();
        for (e, &b) in self.stretch.iter().enumerate() {
            out[b] *= z[nf + e].exp();
        }
    }
    /// Length of the full pose vector.
    pub fn n_pose(&self) -> usize {
        self.n_pose
    }
    /// Indices of the free entries in the full pose.
    pub fn free_indices(&self) -> &[usize] {
        &self.free
    }
    /// Per free entry, how it maps.
    pub fn entry_maps(&self) -> &[EntryMap] {
        &self.maps
    }

    /// State → full pose (Alg. 4 lines 1-3 with Alg. 10), written into `pose`, returning
    /// nothing; `dpose` (if given) receives `∂pose[free[i]]/∂z[i]` (the map is diagonal).
    pub fn to_pose_into(&self, z: &[f64], pose: &mut [f64], mut dpose: Option<&mut [f64]>) {
        pose.copy_from_slice(&self.template);
        for (i, (&idx, m)) in self.free.iter().zip(&self.maps).enumerate() {
            let (v, d) = match *m {
                EntryMap::Linear { scale } => (scale * z[i], scale),
                EntryMap::Bounded { lo, hi } => erf_map(z[i], lo, hi),
            };
            pose[idx] = v;
            if let Some(dp) = dpose.as_deref_mut() {
                dp[i] = d;
            }
        }
    }

    /// [`Self::to_pose_into`] of the state entries `from..` only: the pose entries of the
    /// earlier ones keep their values (e.g. those of a state that agrees there).
    pub fn to_pose_tail_into(&self, z: &[f64], pose: &mut [f64], from: usize) {
        for (i, (&idx, m)) in self.free.iter().zip(&self.maps).enumerate().skip(from) {
            pose[idx] = match *m {
                EntryMap::Linear { scale } => scale * z[i],
                EntryMap::Bounded { lo, hi } => erf_map(z[i], lo, hi).0,
            };
        }
    }

    /// State → full pose.
    ///
    /// # Errors
    /// Shape error for a wrong state length, non-finite error for NaN/inf.
    pub fn to_pose(&self, z: &[f64]) -> Result<Vec<f64>> {
        ensure_len(z.len(), self.n_state(), "state vector")?;
        ensure_finite(z, "state vector")?;
        let mut pose = vec![0.0; self.n_pose];
        self.to_pose_into(z, &mut pose, None);
        Ok(pose)
    }

    /// State → full pose and the diagonal derivative `∂pose[free[i]]/∂z[i]`.
    ///
    /// # Errors
    /// As [`StateMap::to_pose`].
    pub fn to_pose_jacobian(&self, z: &[f64]) -> Result<(Vec<f64>, Vec<f64>)> {
        ensure_len(z.len(), self.n_state(), "state vector")?;
        ensure_finite(z, "state vector")?;
        let mut pose = vec![0.0; self.n_pose];
        let mut d = vec![0.0; self.n_state()];
        self.to_pose_into(z, &mut pose, Some(&mut d));
        Ok((pose, d))
    }

    /// Full pose → state (inverse map), with log-stretch 0 for elastic bones. Fixed entries
    /// are ignored; bounded entries outside their limits are moved just inside (see
    /// [`erf_map_inverse`]).
    ///
    /// # Errors
    /// Shape error for a wrong pose length, non-finite error for NaN/inf.
    pub fn from_pose(&self, pose: &[f64]) -> Result<Vec<f64>> {
        ensure_len(pose.len(), self.n_pose, "pose vector")?;
        ensure_finite(pose, "pose vector")?;
        Ok(self
            .free
            .iter()
            .zip(&self.maps)
            .map(|(&idx, m)| match *m {
                EntryMap::Linear { scale } => pose[idx] / scale,
                EntryMap::Bounded { lo, hi } => erf_map_inverse(pose[idx], lo, hi),
            })
            .chain(std::iter::repeat_n(0.0, self.stretch.len()))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn stretch_entries_follow_the_pose_and_scale_their_bones() {
        let inf = f64::INFINITY;
        let norm = Normalization::default();
        let nb = 4;
        let base =
            StateMap::new(nb, &vec![-inf; 3 * nb], &vec![inf; 3 * nb], &norm, false).unwrap();
        let map = base.clone().with_stretch(&[3, 1]).unwrap();
        assert_eq!(map.n_state(), base.n_state() + 2);
        assert_eq!(map.n_pose_state(), base.n_state());
        let mut z: Vec<f64> = (0..map.n_state()).map(|i| 0.01 * i as f64).collect();
        let nf = map.n_pose_state();
        z[nf] = 0.2; // bone 3
        z[nf + 1] = -0.1; // bone 1
                          // the pose ignores the stretch entries
        assert_eq!(map.to_pose(&z).unwrap(), base.to_pose(&z[..nf]).unwrap());
        let mut len = vec![0.0; nb];
        map.lengths_into(&z, &[1.0, 2.0, 3.0, 4.0], &mut len);
        let want = [1.0, 2.0 * (-0.1f64).exp(), 3.0, 4.0 * 0.2f64.exp()];
        for (a, b) in len.iter().zip(want) {
            assert!((a - b).abs() < 1e-15);
        }
        // inverse: the mean lengths (log-stretch 0)
        let back = map.from_pose(&map.to_pose(&z).unwrap()).unwrap();
        assert_eq!(back.len(), map.n_state());
        assert_eq!(&back[nf..], &[0.0, 0.0]);
        assert!(base.clone().with_stretch(&[1, 1]).is_err());
        assert!(base.with_stretch(&[4]).is_err());
    }

    #[test]
    fn erfinv_inverts_erf() {
        for &y in &[-0.999999, -0.9, -0.3, 0.0, 1e-8, 0.5, 0.99, 0.999999999] {
            assert!((libm::erf(erfinv(y)) - y).abs() < 1e-14, "y={y}");
        }
    }

    #[test]
    fn erf_map_derivative_matches_fd() {
        for &z in &[-3.0, -0.7, 0.0, 0.4, 2.5] {
            let (_, d) = erf_map(z, -0.3, 1.2);
            let h = 1e-6;
            let fd = (erf_map(z + h, -0.3, 1.2).0 - erf_map(z - h, -0.3, 1.2).0) / (2.0 * h);
            assert!((fd - d).abs() < 1e-9);
        }
    }

    proptest! {
        #[test]
        fn erf_map_stays_inside_and_is_monotone(z in -50.0f64..50.0, dz in 1e-3f64..5.0,
                                                b0 in -3.0f64..1.0, w in 1e-3f64..4.0) {
            let b1 = b0 + w;
            let (r, d) = erf_map(z, b0, b1);
            prop_assert!(r >= b0 && r <= b1);
            prop_assert!(d >= 0.0);
            prop_assert!(erf_map(z + dz, b0, b1).0 >= r);
            if z.abs() < 4.0 {
                prop_assert!((erf_map_inverse(r, b0, b1) - z).abs() < 1e-7);
            }
        }
    }

    #[test]
    fn state_map_free_entries_and_round_trip() {
        let inf = f64::INFINITY;
        // bone 0 unbounded; bone 1: x bounded, y fixed at 0, z fixed at 0.2
        let lower = [-inf, -inf, -inf, -0.5, 0.0, 0.2];
        let upper = [inf, inf, inf, 1.5, 0.0, 0.2];
        let norm = Normalization::default();
        let m = StateMap::new(2, &lower, &upper, &norm, true).unwrap();
        assert_eq!(m.free_indices(), &[0, 1, 2, 3, 4, 5, 6]);
        let z = [0.1, -0.2, 0.3, 0.5, -0.1, 0.2, -1.3];
        let pose = m.to_pose(&z).unwrap();
        assert!((pose[0] - 5.0).abs() < 1e-12);
        assert!((pose[3] - 0.5 * norm.rotation).abs() < 1e-12);
        assert!(pose[6] > -0.5 && pose[6] < 1.5);
        assert_eq!(pose[7], 0.0);
        assert_eq!(pose[8], 0.2);
        let back = m.from_pose(&pose).unwrap();
        for (a, b) in back.iter().zip(&z) {
            assert!((a - b).abs() < 1e-9);
        }
        let (_, d) = m.to_pose_jacobian(&z).unwrap();
        let h = 1e-6;
        for i in 0..z.len() {
            let mut zp = z;
            let mut zm = z;
            zp[i] += h;
            zm[i] -= h;
            let fd = (m.to_pose(&zp).unwrap()[m.free_indices()[i]]
                - m.to_pose(&zm).unwrap()[m.free_indices()[i]])
                / (2.0 * h);
            assert!((fd - d[i]).abs() < 1e-6 * (1.0 + fd.abs()));
        }
        // Without limits the bounded entry is linear.
        let lin = StateMap::new(2, &lower, &upper, &norm, false).unwrap();
        assert_eq!(
            lin.entry_maps()[6],
            EntryMap::Linear {
                scale: norm.rotation
            }
        );
    }

    #[test]
    fn bad_limits_are_rejected() {
        let norm = Normalization::default();
        let inf = f64::INFINITY;
        assert!(StateMap::new(1, &[0.0, 0.0, 1.0], &[0.0, 0.0, 0.5], &norm, true).is_err());
        assert!(StateMap::new(1, &[0.0, 0.0, f64::NAN], &[0.0, 0.0, 0.5], &norm, true).is_err());
        assert!(StateMap::new(1, &[0.0, 0.0, 0.0], &[0.0, 0.0, inf], &norm, true).is_err());
        assert!(StateMap::new(1, &[0.0, 0.0, 0.0], &[0.0, 0.0, inf], &norm, false).is_ok());
        assert!(StateMap::new(1, &[0.0; 2], &[0.0; 3], &norm, true).is_err());
        let m = StateMap::new(1, &[0.0; 3], &[0.0; 3], &norm, true).unwrap();
        assert_eq!(m.n_state(), 3);
        assert!(m.to_pose(&[0.0, f64::NAN, 0.0]).is_err());
    }
}
