//! # acm_rs
//!
//! Rust core of **acm-rs**: the geometry and kinematics of the Anatomically Constrained Model
//! (ACM; Monsees et al., Nature Methods 2022, supplementary text) with exact derivatives.
//!
//! | module | paper |
//! |---|---|
//! | [`rotation`] | sec. 1, eqs. 1-3 (Rodrigues) |
//! | [`camera`] | sec. 2.1, eqs. 4-6 (pinhole + distortion) |
//! | [`calibration`] | sec. 2.2, eq. 7 (multi-camera calibration, sparse Jacobian) |
//! | [`skeleton`] | sec. 3.1, Alg. 1, eq. 8 (forward kinematics) |
//! | [`symmetry`] | sec. 3.4, Alg. 2-3 |
//! | [`normalization`] | sec. 3.3, eq. 11 |
//! | [`limits`] | sec. 4.4.3, Alg. 10 (joint-angle limits, state map) |
//! | [`emission`] | sec. 4.1, Alg. 4 (emission function `g`) |
//! | [`learning`] | sec. 3.2-3.4, eqs. 9-12 (skeleton learning objective) |
//! | [`tracking`] | sec. 4, Alg. 5-13 (UKF, RTS smoother, EM) |
//! | [`gapfill`] | Burke & Lasenby 2016 (marker gap filling) |
//!
//! The core is pure Rust (no Python); the `python` cargo feature adds the pyo3 bindings in
//! `src/python/`.

pub mod calibration;
pub mod camera;
pub mod emission;
pub mod error;
pub mod gapfill;
pub mod kernels;
pub mod learning;
pub mod limits;
pub mod normalization;
pub mod npz;
pub mod rotation;
pub mod skeleton;
pub mod symmetry;
pub mod team;
pub mod tracking;

#[cfg(feature = "python")]
mod python;

pub use error::{AcmError, Result};
