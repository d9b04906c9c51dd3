//! Normalisation constants of ACM supp. section 3.3 (eq. 11), as configuration.
//!
//! The paper scales translations by `c_t = 50 cm`, rotations by `c_r = π/2` and pixels by
//! `c_1 = 640 px`, `c_2 = 512 px` (half of a 1280×1024 sensor) so that every optimised
//! quantity lies roughly in `[-1, 1]`. Those are the defaults here; every consumer takes a
//! [`Normalization`] value instead of literals.

use crate::error::{AcmError, Result};

/// Scales of the normalised variables `t* = t / c_t`, `r* = r / c_r`, `m* = m / c − 1`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Normalization {
    /// `c_t`: translation scale, in world units (50 for centimetres).
    pub translation: f64,
    /// `c_r`: rotation scale (rad).
    pub rotation: f64,
    /// `(c_1, c_2)`: pixel scales (px), usually half the sensor size.
    pub pixel: [f64; 2],
}

impl Default for Normalization {
    fn default() -> Self {
        Self {
            translation: 50.0,
            rotation: std::f64::consts::FRAC_PI_2,
            pixel: [640.0, 512.0],
        }
    }
}

impl Normalization {
    /// Checks that all scales are finite and positive.
    ///
    /// # Errors
    /// Invalid error naming the offending constant.
    pub fn validate(&self) -> Result<()> {
        let named = [
            ("translation", self.translation),
            ("rotation", self.rotation),
            ("pixel x", self.pixel[0]),
            ("pixel y", self.pixel[1]),
        ];
        for (name, v) in named {
            if !(v.is_finite() && v > 0.0) {
                return Err(AcmError::Invalid(format!(
                    "normalisation constant '{name}' must be finite and positive, got {v}"
                )));
            }
        }
        Ok(())
    }

    /// Eq. 11: normalised pixel `(u / c_1 − 1, v / c_2 − 1)`.
    pub fn normalize_pixel(&self, u: f64, v: f64) -> (f64, f64) {
        (u / self.pixel[0] - 1.0, v / self.pixel[1] - 1.0)
    }

    /// Inverse of eq. 11.
    pub fn denormalize_pixel(&self, un: f64, vn: f64) -> (f64, f64) {
        ((un + 1.0) * self.pixel[0], (vn + 1.0) * self.pixel[1])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_papers_and_round_trip() {
        let n = Normalization::default();
        assert_eq!(n.translation, 50.0);
        assert_eq!(n.normalize_pixel(640.0, 0.0), (0.0, -1.0));
        let (u, v) = n.denormalize_pixel(0.25, -0.5);
        assert_eq!(n.normalize_pixel(u, v), (0.25, -0.5));
        let bad = Normalization { rotation: 0.0, ..n };
        assert!(bad.validate().is_err());
    }
}
