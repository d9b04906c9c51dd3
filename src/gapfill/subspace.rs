//! The linear subspace of marker configurations (B&L sec. 3, eq. 4; Algorithm 1, lines 1-3)
//! and the moment estimates of the random-walk process noise Q.

use super::linalg::sorted_eigen;
use super::Criterion;
use crate::error::{AcmError, Result};
use nalgebra::DMatrix;
use rayon::prelude::*;

/// Mean `m̄` (D), orthonormal basis `V̂` (D × d̂) and the covariance eigenvalues of the frames it
/// was learned from (B&L eq. 4: `x̃ = V̂ᵀ (x − m̄)`).
#[derive(Debug, Clone)]
pub struct Subspace {
    /// Column means m̄ of the training frames.
    pub mean: Vec<f64>,
    /// Basis V̂, D × d̂, orthonormal columns (right singular vectors of `X − m̄`).
    pub basis: DMatrix<f64>,
    /// All eigenvalues `s_i² / (n − 1)` of the training covariance, decreasing.
    pub eigvals: Vec<f64>,
}

impl Subspace {
    /// d̂.
    pub fn dim(&self) -> usize {
        self.basis.ncols()
    }

    /// Basis rows `v_i` (row-major D × d̂) for fast per-coordinate access.
    pub fn rows(&self) -> Vec<f64> {
        let (d, k) = self.basis.shape();
        let mut out = vec![0.0; d * k];
        for i in 0..d {
            for c in 0..k {
                out[i * k + c] = self.basis[(i, c)];
            }
        }
        out
    }

    /// Mean reconstruction variance per coordinate of the discarded directions,
    /// `Σ_{i > d̂} λ_i / D` (the initial guess of r).
    pub fn residual_variance(&self) -> f64 {
        let d = self.mean.len() as f64;
        self.eigvals[self.dim()..].iter().sum::<f64>() / d
    }
}

/// The subspace dimension from covariance eigenvalues `λ_i = s_i²/(n−1)` (B&L Alg. 1 line 2:
/// `d̂ = find(cumsum(diag(S)) ≥ γ)`, normalised). `Criterion::SingularValues` applies γ to
/// `s_i` as printed; `Criterion::Energy` applies it to `s_i²`, the energy. Clamped to
/// `1..=max_dim`.
pub fn choose_dim(eigvals: &[f64], criterion: Criterion, gamma: f64, max_dim: usize) -> usize {
    let w: Vec<f64> = match criterion {
        Criterion::Energy => eigvals.to_vec(),
        Criterion::SingularValues => eigvals.iter().map(|v| v.sqrt()).collect(),
    };
    let total: f64 = w.iter().sum();
    let max_dim = max_dim.max(1);
    if total <= 0.0 {
        return 1;
    }
    let mut acc = 0.0;
    for (i, v) in w.iter().enumerate() {
        acc += v;
        if acc >= gamma * total * (1.0 - 1e-12) {
            return (i + 1).clamp(1, max_dim);
        }
    }
    w.len().clamp(1, max_dim)
}

/// Rows per block of the scatter sums of [`fit`] and [`q_from_pairs`].
const SCATTER_BLOCK: usize = 4096;

/// Learns the subspace from frames `rows` of the row-major `T × D` matrix `x` (which must be
/// finite on those rows): the SVD of the mean-shifted frames, computed as the eigen-decomposition
/// of the `D × D` scatter matrix (B&L Alg. 1 line 1).
pub fn fit(
    x: &[f64],
    d: usize,
    rows: &[usize],
    criterion: Criterion,
    gamma: f64,
    dim: Option<usize>,
) -> Result<Subspace> {
    let n = rows.len();
    if n < 2 {
        return Err(AcmError::Invalid(format!(
            "the subspace needs at least 2 training frames, got {n}"
        )));
    }
    let mut mean = vec![0.0; d];
    for &r in rows {
        for (m, v) in mean.iter_mut().zip(&x[r * d..(r + 1) * d]) {
            *m += v;
        }
    }
    mean.iter_mut().for_each(|m| *m /= n as f64);
    // The scatter of the centred frames, summed over blocks of rows (memory of one block, not
    // of the n × D training matrix: 0.5 GB for 200,000 frames of 41 markers).
    let scatter = rows
        .par_chunks(SCATTER_BLOCK)
        .map(|blk| {
            let mut c = DMatrix::<f64>::zeros(blk.len(), d);
            for (i, &r) in blk.iter().enumerate() {
                for (j, (v, m)) in x[r * d..(r + 1) * d].iter().zip(&mean).enumerate() {
                    c[(i, j)] = v - m;
                }
            }
            c.transpose() * &c
        })
        .collect::<Vec<_>>()
        .into_iter() // summed in order: the same result on every run
        .fold(DMatrix::zeros(d, d), |a, b| a + b)
        / (n as f64 - 1.0);
    let (eigvals, vecs) = sorted_eigen(scatter);
    let max_dim = d.min(n - 1);
    let k = match dim {
        Some(k) => k.min(max_dim).max(1),
        None => choose_dim(&eigvals, criterion, gamma, max_dim),
    };
    Ok(Subspace {
        mean,
        basis: vecs.columns(0, k).into_owned(),
        eigvals,
    })
}

/// Q as the second moment of projected frame-to-frame differences over the frame `pairs`
/// `(t−1, t)`: `Q = mean_t V̂ᵀ Δx_t Δx_tᵀ V̂` (a covariance, the fix of the published "standard
/// deviation projected into the subspace"). Needs at least one pair.
pub fn q_from_pairs(x: &[f64], d: usize, pairs: &[(usize, usize)], sub: &Subspace) -> DMatrix<f64> {
    let k = sub.dim();
    let n = pairs.len().max(1);
    // Projected differences, summed in blocks of pairs (bounded memory on long recordings).
    let mut q = pairs
        .par_chunks(SCATTER_BLOCK)
        .map(|blk| {
            let mut p = DMatrix::<f64>::zeros(blk.len(), k);
            for (row, &(a, b)) in blk.iter().enumerate() {
                for i in 0..d {
                    let dx = x[b * d + i] - x[a * d + i];
                    for c in 0..k {
                        p[(row, c)] += sub.basis[(i, c)] * dx;
                    }
                }
            }
            p.transpose() * &p
        })
        .collect::<Vec<_>>()
        .into_iter()
        .fold(DMatrix::zeros(k, k), |a, b| a + b)
        / n as f64;
    // A floor keeps Q positive definite when a direction never moves between sampled pairs.
    let floor = 1e-9 * (q.trace() / k as f64).max(1e-12);
    for c in 0..k {
        q[(c, c)] += floor;
    }
    q
}

/// The published Q (authors' code): `V̂ᵀ diag(std(diff(X))) V̂`, with `diff` taken over the
/// stacked complete frames `rows` (consecutive rows of the training matrix, whatever their
/// frame distance) — a standard deviation where a variance belongs; kept for `LowDimPaper`.
pub fn q_paper(x: &[f64], d: usize, rows: &[usize], sub: &Subspace) -> DMatrix<f64> {
    let k = sub.dim();
    let n = rows.len().saturating_sub(1).max(1);
    let mut std = vec![0.0; d];
    for (i, s) in std.iter_mut().enumerate() {
        let diffs: Vec<f64> = rows
            .windows(2)
            .map(|w| x[w[1] * d + i] - x[w[0] * d + i])
            .collect();
        let m = diffs.iter().sum::<f64>() / n as f64;
        *s = (diffs.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / n as f64).sqrt();
    }
    let mut q = DMatrix::zeros(k, k);
    for (i, s) in std.iter().enumerate() {
        for a in 0..k {
            for b in 0..k {
                q[(a, b)] += sub.basis[(i, a)] * s * sub.basis[(i, b)];
            }
        }
    }
    q
}
