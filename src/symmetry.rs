//! Left/right symmetry maps (ACM supp. section 3.4, Alg. 2 and 3).
//!
//! Only the asymmetric (central) and left-sided bone lengths `l*` and marker offsets `v*` are
//! free; each right-sided bone copies the length of its left partner (Alg. 2) and each
//! right-sided marker mirrors the x-component of its left partner's offset (Alg. 3). Both maps
//! are linear, so their derivatives are exact index maps; [`SymmetryMap::reduce_length_grad`]
//! and [`SymmetryMap::reduce_offset_grad`] apply the transposed maps to gradients.

use crate::error::{ensure_len, AcmError, Result};

/// Index bookkeeping of Alg. 2 and 3.
#[derive(Debug, Clone, PartialEq)]
pub struct SymmetryMap {
    /// For each bone, the index of the reduced length it copies.
    bone_source: Vec<usize>,
    /// For each marker, the reduced offset it copies and whether its x is mirrored.
    marker_source: Vec<(usize, bool)>,
    n_reduced_bones: usize,
    n_reduced_markers: usize,
}

fn build(n: usize, pairs: &[(usize, usize)], what: &str) -> Result<(Vec<usize>, Vec<bool>, usize)> {
    let mut partner: Vec<Option<usize>> = vec![None; n];
    let mut is_right = vec![false; n];
    for &(l, r) in pairs {
        if l >= n || r >= n {
            return Err(AcmError::Invalid(format!(
                "{what} symmetry pair ({l}, {r}) is out of range (0..{n})"
            )));
        }
        if l == r {
            return Err(AcmError::Invalid(format!(
                "{what} symmetry pair ({l}, {r}) pairs an element with itself"
            )));
        }
        if partner[l].is_some() || partner[r].is_some() || is_right[l] {
            return Err(AcmError::Invalid(format!(
                "{what} {l} or {r} appears in more than one symmetry pair"
            )));
        }
        partner[r] = Some(l);
        partner[l] = Some(r);
        is_right[r] = true;
    }
    // Reduced order: every non-right element in its original order (Alg. 2 line 2).
    let mut reduced_index = vec![usize::MAX; n];
    let mut count = 0;
    for i in 0..n {
        if !is_right[i] {
            reduced_index[i] = count;
            count += 1;
        }
    }
    let source = (0..n)
        .map(|i| {
            if is_right[i] {
                reduced_index[partner[i].expect("right has partner")]
            } else {
                reduced_index[i]
            }
        })
        .collect();
    Ok((source, is_right, count))
}

impl SymmetryMap {
    /// Builds the maps from `(left, right)` index pairs of bones and of markers.
    ///
    /// # Errors
    /// Invalid error for out-of-range indices, self pairs, or an element in two pairs.
    pub fn new(
        n_bones: usize,
        bone_pairs: &[(usize, usize)],
        n_markers: usize,
        marker_pairs: &[(usize, usize)],
    ) -> Result<Self> {
        let (bone_source, _, n_reduced_bones) = build(n_bones, bone_pairs, "bone")?;
        let (msrc, mirror, n_reduced_markers) = build(n_markers, marker_pairs, "marker")?;
        Ok(Self {
            bone_source,
            marker_source: msrc.into_iter().zip(mirror).collect(),
            n_reduced_bones,
            n_reduced_markers,
        })
    }

    /// Number of free bone lengths `n*_bone`.
    pub fn n_reduced_bones(&self) -> usize {
        self.n_reduced_bones
    }
    /// Number of free marker offsets `n*_marker`.
    pub fn n_reduced_markers(&self) -> usize {
        self.n_reduced_markers
    }
    /// Reduced index each bone copies.
    pub fn bone_source(&self) -> &[usize] {
        &self.bone_source
    }
    /// Reduced index each marker copies and whether x is mirrored.
    pub fn marker_source(&self) -> &[(usize, bool)] {
        &self.marker_source
    }

    /// Alg. 2: `l = f_{l*→l}(l*)`.
    ///
    /// # Errors
    /// Shape error if `reduced.len() != n*_bone`.
    pub fn expand_lengths(&self, reduced: &[f64]) -> Result<Vec<f64>> {
        ensure_len(reduced.len(), self.n_reduced_bones, "reduced bone lengths")?;
        Ok(self.bone_source.iter().map(|&s| reduced[s]).collect())
    }

    /// Alg. 3: `v = f_{v*→v}(v*)`, flat `(n*_marker, 3)` → flat `(M, 3)`.
    ///
    /// # Errors
    /// Shape error if `reduced.len() != 3 n*_marker`.
    pub fn expand_offsets(&self, reduced: &[f64]) -> Result<Vec<f64>> {
        ensure_len(
            reduced.len(),
            3 * self.n_reduced_markers,
            "reduced marker offsets",
        )?;
        Ok(self
            .marker_source
            .iter()
            .flat_map(|&(s, mirror)| {
                let sign = if mirror { -1.0 } else { 1.0 };
                [
                    sign * reduced[3 * s],
                    reduced[3 * s + 1],
                    reduced[3 * s + 2],
                ]
            })
            .collect())
    }

    /// Least-squares inverse of Alg. 2 (mean over each pair): `l → l*`.
    ///
    /// # Errors
    /// Shape error if `full.len()` is not the number of bones.
    pub fn reduce_lengths(&self, full: &[f64]) -> Result<Vec<f64>> {
        ensure_len(full.len(), self.bone_source.len(), "bone lengths")?;
        let mut sum = vec![0.0; self.n_reduced_bones];
        let mut cnt = vec![0.0; self.n_reduced_bones];
        for (&s, &l) in self.bone_source.iter().zip(full) {
            sum[s] += l;
            cnt[s] += 1.0;
        }
        Ok(sum.iter().zip(&cnt).map(|(s, c)| s / c).collect())
    }

    /// Least-squares inverse of Alg. 3 (mean over each mirrored pair): `v → v*`.
    ///
    /// # Errors
    /// Shape error if `full.len()` is not `3 M`.
    pub fn reduce_offsets(&self, full: &[f64]) -> Result<Vec<f64>> {
        ensure_len(full.len(), 3 * self.marker_source.len(), "marker offsets")?;
        let g = self.reduce_offset_grad(full)?;
        let mut cnt = vec![0.0; self.n_reduced_markers];
        for &(s, _) in &self.marker_source {
            cnt[s] += 1.0;
        }
        Ok(g.iter().enumerate().map(|(i, v)| v / cnt[i / 3]).collect())
    }

    /// Gradient pull-back through Alg. 2: `∂f/∂l* = (∂l/∂l*)ᵀ ∂f/∂l`.
    ///
    /// # Errors
    /// Shape error if `grad.len()` is not the number of bones.
    pub fn reduce_length_grad(&self, grad: &[f64]) -> Result<Vec<f64>> {
        ensure_len(grad.len(), self.bone_source.len(), "bone-length gradient")?;
        let mut out = vec![0.0; self.n_reduced_bones];
        for (&s, &g) in self.bone_source.iter().zip(grad) {
            out[s] += g;
        }
        Ok(out)
    }

    /// Gradient pull-back through Alg. 3 (x-components of mirrored markers change sign).
    ///
    /// # Errors
    /// Shape error if `grad.len()` is not `3 M`.
    pub fn reduce_offset_grad(&self, grad: &[f64]) -> Result<Vec<f64>> {
        ensure_len(
            grad.len(),
            3 * self.marker_source.len(),
            "marker-offset gradient",
        )?;
        let mut out = vec![0.0; 3 * self.n_reduced_markers];
        for (k, &(s, mirror)) in self.marker_source.iter().enumerate() {
            let sign = if mirror { -1.0 } else { 1.0 };
            out[3 * s] += sign * grad[3 * k];
            out[3 * s + 1] += grad[3 * k + 1];
            out[3 * s + 2] += grad[3 * k + 2];
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn expand_follows_alg2_and_alg3() {
        // bones: 0 central, 1 left, 2 right(of 1), 3 central
        let m = SymmetryMap::new(4, &[(1, 2)], 3, &[(0, 2)]).unwrap();
        assert_eq!(m.n_reduced_bones(), 3);
        assert_eq!(
            m.expand_lengths(&[1.0, 2.0, 3.0]).unwrap(),
            vec![1.0, 2.0, 2.0, 3.0]
        );
        assert_eq!(m.n_reduced_markers(), 2);
        let v = m.expand_offsets(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]).unwrap();
        assert_eq!(v, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0, -1.0, 2.0, 3.0]);
        // Round trip of a symmetric configuration.
        assert_eq!(
            m.reduce_offsets(&v).unwrap(),
            vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
        );
        assert_eq!(
            m.reduce_lengths(&[1.0, 2.0, 2.0, 3.0]).unwrap(),
            vec![1.0, 2.0, 3.0]
        );
    }

    #[test]
    fn gradients_are_transposed_maps() {
        // <expand(x), g> == <x, reduce_grad(g)> for the linear maps.
        let m = SymmetryMap::new(4, &[(1, 2)], 3, &[(2, 0)]).unwrap();
        let x = [0.3, -1.2, 0.7, 2.0, 0.1, -0.4];
        let g = [0.5, 1.5, -2.0, 0.25, -0.5, 1.0, 3.0, -1.0, 0.2];
        let lhs: f64 = m
            .expand_offsets(&x)
            .unwrap()
            .iter()
            .zip(&g)
            .map(|(a, b)| a * b)
            .sum();
        let rhs: f64 = x
            .iter()
            .zip(m.reduce_offset_grad(&g).unwrap())
            .map(|(a, b)| a * b)
            .sum();
        assert!((lhs - rhs).abs() < 1e-14);
        let xl = [1.0, 2.0, 3.0];
        let gl = [0.1, 0.2, 0.3, 0.4];
        let lhs: f64 = m
            .expand_lengths(&xl)
            .unwrap()
            .iter()
            .zip(&gl)
            .map(|(a, b)| a * b)
            .sum();
        let rhs: f64 = xl
            .iter()
            .zip(m.reduce_length_grad(&gl).unwrap())
            .map(|(a, b)| a * b)
            .sum();
        assert!((lhs - rhs).abs() < 1e-14);
    }

    #[test]
    fn bad_pairs_are_rejected() {
        assert!(SymmetryMap::new(3, &[(0, 3)], 0, &[]).is_err());
        assert!(SymmetryMap::new(3, &[(1, 1)], 0, &[]).is_err());
        assert!(SymmetryMap::new(3, &[(0, 1), (1, 2)], 0, &[]).is_err());
        let m = SymmetryMap::new(3, &[], 2, &[]).unwrap();
        assert!(m.expand_lengths(&[1.0]).is_err());
    }
}
