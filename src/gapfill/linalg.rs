//! Small dense helpers on `nalgebra::DMatrix` for the `d̂ × d̂` algebra of the smoother.

use crate::error::{AcmError, Result};
use nalgebra::{DMatrix, SymmetricEigen};

/// Inverse of a symmetric positive-definite matrix by Cholesky; the result is symmetrised.
pub fn spd_inverse(m: &DMatrix<f64>, what: &str) -> Result<DMatrix<f64>> {
    let chol = m.clone().cholesky().ok_or_else(|| {
        AcmError::Numerical(format!("{what} is not positive definite (Cholesky failed)"))
    })?;
    let mut inv = chol.inverse();
    symmetrize(&mut inv);
    Ok(inv)
}

/// Replaces `m` by `(m + mᵀ) / 2`.
pub fn symmetrize(m: &mut DMatrix<f64>) {
    let n = m.nrows();
    for i in 0..n {
        for j in (i + 1)..n {
            let a = 0.5 * (m[(i, j)] + m[(j, i)]);
            m[(i, j)] = a;
            m[(j, i)] = a;
        }
    }
}

/// Largest absolute entry.
pub fn max_abs(m: &DMatrix<f64>) -> f64 {
    m.iter().fold(0.0_f64, |a, v| a.max(v.abs()))
}

/// `true` if `max |a - b| <= tol * max(max|a|, max|b|)`.
pub fn close(a: &DMatrix<f64>, b: &DMatrix<f64>, tol: f64) -> bool {
    let scale = max_abs(a).max(max_abs(b));
    a.iter()
        .zip(b.iter())
        .all(|(x, y)| (x - y).abs() <= tol * scale)
}

/// Eigen-decomposition of a symmetric matrix with eigenvalues sorted in decreasing order
/// (negative round-off clamped to 0). Returns `(eigenvalues, eigenvectors as columns)`.
pub fn sorted_eigen(m: DMatrix<f64>) -> (Vec<f64>, DMatrix<f64>) {
    let n = m.nrows();
    let eig = SymmetricEigen::new(m);
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let vals = order.iter().map(|&i| eig.eigenvalues[i].max(0.0)).collect();
    let vecs = DMatrix::from_fn(n, n, |r, c| eig.eigenvectors[(r, order[c])]);
    (vals, vecs)
}
