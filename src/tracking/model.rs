//! The emission functions the tracker can use: the skeleton model of Alg. 4 with the state map
//! of Alg. 10 (eq. 50), and a linear map (for the golden test against the Kalman filter).

use crate::camera::Camera;
use crate::emission::{emission_batch_into, emission_sigma_into, SigmaPlan};
use crate::error::{ensure_len, AcmError, Result};
use crate::limits::StateMap;
use crate::normalization::Normalization;
use crate::skeleton::Skeleton;

/// A measurement function `x = g(z)` evaluated for batches of states.
pub trait Emission: Send + Sync {
    /// Dimension of the state `n_z`.
    fn n_state(&self) -> usize;
    /// Dimension of one measurement `n_x`.
    fn n_meas(&self) -> usize;
    /// Writes `g(z)` for each row of `states` (`N × n_z`) into `out` (`N × n_x`). An entry may
    /// be NaN (e.g. a marker behind a camera); the tracker then treats it as missing.
    ///
    /// # Errors
    /// Shape errors, or non-finite states.
    fn eval_batch(&self, states: &[f64], out: &mut [f64]) -> Result<()>;
    /// [`Self::eval_batch`] on the calling thread alone, without handing work to a thread
    /// pool (the online tracker's serial mode). The default is `eval_batch`, for emissions
    /// without parallelism of their own.
    ///
    /// # Errors
    /// As [`Self::eval_batch`].
    fn eval_batch_serial(&self, states: &[f64], out: &mut [f64]) -> Result<()> {
        self.eval_batch(states, out)
    }
    /// `g` of the `2n` sigma points `m ± √n L_i` (rows `i` and `n + i` of `sigma`, `2n × n`)
    /// of a lower-triangular factor `L`, whose rows `i`, `n + i` equal the centre `mean` in
    /// the entries before `i`; on the calling thread alone if `serial`. The same values as
    /// [`Self::eval_batch`] of `sigma`, which is the default; an emission may use the shared
    /// entries to skip work.
    ///
    /// # Errors
    /// As [`Self::eval_batch`].
    fn eval_sigma(&self, mean: &[f64], sigma: &[f64], serial: bool, out: &mut [f64]) -> Result<()> {
        let _ = mean;
        if serial {
            self.eval_batch_serial(sigma, out)
        } else {
            self.eval_batch(sigma, out)
        }
    }
    /// Entries are grouped in consecutive blocks of this size for the innovation gate
    /// (2 for image points `(u, v)`).
    fn block(&self) -> usize {
        1
    }
    /// State entries whose transition row is 0 (memoryless, `z_t = ε_t`): the log-stretch
    /// of elastic segments ([`crate::limits::StateMap::with_stretch`]). Default none.
    fn memoryless(&self) -> &[usize] {
        &[]
    }
}

/// Alg. 4 ∘ Alg. 10: state → pose → forward kinematics → normalised pixels in every camera.
/// Measurement layout: camera, marker, coordinate (`n_x = 2 · n_cams · n_markers`).
#[derive(Debug, Clone)]
pub struct SkeletonEmission {
    /// Skeleton with the learned bone lengths and marker offsets.
    pub skeleton: Skeleton,
    /// The calibrated cameras.
    pub cameras: Vec<Camera>,
    /// State ↔ pose map (Alg. 10).
    pub map: StateMap,
    /// Normalisation constants (sec. 3.3).
    pub norm: Normalization,
    /// The map's log-stretch entries (memoryless in the transition).
    stretch_entries: Vec<usize>,
    /// What each sigma point of a step moves ([`Emission::eval_sigma`]).
    sigma_plan: SigmaPlan,
}

impl SkeletonEmission {
    /// Bundles the model, checking that the state map fits the skeleton.
    ///
    /// # Errors
    /// Shape error if the map was built for another skeleton; invalid error without cameras.
    pub fn new(
        skeleton: Skeleton,
        cameras: Vec<Camera>,
        map: StateMap,
        norm: Normalization,
    ) -> Result<Self> {
        ensure_len(map.n_pose(), skeleton.n_pose(), "state map pose length")?;
        norm.validate()?;
        if cameras.is_empty() {
            return Err(AcmError::Invalid(
                "the tracker needs at least one camera".into(),
            ));
        }
        if skeleton.n_markers() == 0 {
            return Err(AcmError::Invalid("the skeleton has no markers".into()));
        }
        let nf = map.n_pose_state();
        let stretch_entries = (nf..nf + map.stretch_bones().len()).collect();
        let sigma_plan = SigmaPlan::new(&skeleton, &map);
        Ok(Self {
            skeleton,
            cameras,
            map,
            norm,
            stretch_entries,
            sigma_plan,
        })
    }
}

impl SkeletonEmission {
    /// The sigma plan of the skeleton and map, if they are still the ones it was made for
    /// (the public fields can be replaced after [`Self::new`]).
    pub(crate) fn sigma_plan(&self) -> Option<&SigmaPlan> {
        self.sigma_plan
            .fits(&self.skeleton, &self.map)
            .then_some(&self.sigma_plan)
    }
}

impl Emission for SkeletonEmission {
    fn n_state(&self) -> usize {
        self.map.n_state()
    }
    fn n_meas(&self) -> usize {
        2 * self.cameras.len() * self.skeleton.n_markers()
    }
    fn eval_batch(&self, states: &[f64], out: &mut [f64]) -> Result<()> {
        let (sk, cams, map, norm) = (&self.skeleton, &self.cameras, &self.map, &self.norm);
        emission_batch_into(sk, cams, map, norm, states, out, true)
    }
    fn eval_batch_serial(&self, states: &[f64], out: &mut [f64]) -> Result<()> {
        let (sk, cams, map, norm) = (&self.skeleton, &self.cameras, &self.map, &self.norm);
        emission_batch_into(sk, cams, map, norm, states, out, false)
    }
    fn eval_sigma(&self, mean: &[f64], sigma: &[f64], serial: bool, out: &mut [f64]) -> Result<()> {
        let (sk, cams, map, norm) = (&self.skeleton, &self.cameras, &self.map, &self.norm);
        let plan = &self.sigma_plan;
        if !plan.fits(sk, map) {
            // the public fields were replaced after `new`: no shortcut
            return emission_batch_into(sk, cams, map, norm, sigma, out, !serial);
        }
        emission_sigma_into(sk, cams, map, norm, plan, mean, sigma, out, !serial)
    }
    fn block(&self) -> usize {
        2
    }
    fn memoryless(&self) -> &[usize] {
        &self.stretch_entries
    }
}

/// `x = H z + b` with a dense `H` (`n_x × n_z`, row-major).
#[derive(Debug, Clone)]
pub struct LinearEmission {
    /// Row-major `n_x × n_z` matrix.
    pub h: Vec<f64>,
    /// Offset `(n_x,)`.
    pub b: Vec<f64>,
    /// State dimension.
    pub n_z: usize,
}

impl Emission for LinearEmission {
    fn n_state(&self) -> usize {
        self.n_z
    }
    fn n_meas(&self) -> usize {
        self.b.len()
    }
    fn eval_batch(&self, states: &[f64], out: &mut [f64]) -> Result<()> {
        let (nz, nx) = (self.n_z, self.b.len());
        ensure_len(out.len(), states.len() / nz * nx, "emission output")?;
        for (z, o) in states.chunks_exact(nz).zip(out.chunks_exact_mut(nx)) {
            for (j, oj) in o.iter_mut().enumerate() {
                let row = &self.h[j * nz..(j + 1) * nz];
                *oj = self.b[j] + row.iter().zip(z).map(|(a, b)| a * b).sum::<f64>();
            }
        }
        Ok(())
    }
}
