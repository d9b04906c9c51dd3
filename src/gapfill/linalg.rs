//! Small dense helpers on `nalgebra::DMatrix` for the `d̂ × d̂` algebra of the smoother.

use crate::error::{AcmError, Result};
use crate::kernels::{cholesky_in_place as chol_kernel, dispatch};
use nalgebra::{DMatrix, SymmetricEigen};

pub use crate::kernels::{cholesky_in_place, dot};

/// `out = Aᵀ B` (`ma × mb`, column-major) for column-major `A` (`n × ma`) and `B` (`n × mb`),
/// through the `matrixmultiply` kernels.
///
/// # Panics
/// If a slice is shorter than its shape.
pub fn gemm_tn(a: &[f64], b: &[f64], n: usize, ma: usize, mb: usize, out: &mut [f64]) {
    assert!(a.len() >= n * ma && b.len() >= n * mb && out.len() >= ma * mb);
    if ma == 0 || mb == 0 {
        return;
    }
    // SAFETY: the asserts above bound every index the strides reach: Aᵀ (ma × n) has entry
    // (r, c) at r·n + c, B (n × mb) entry (r, c) at r + c·n, out (ma × mb) at r + c·ma.
    unsafe {
        matrixmultiply::dgemm(
            ma,
            n,
            mb,
            1.0,
            a.as_ptr(),
            n as isize,
            1,
            b.as_ptr(),
            1,
            n as isize,
            0.0,
            out.as_mut_ptr(),
            1,
            ma as isize,
        );
    }
}

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

dispatch!(
    fn lower_inverse_kernel(ls: &[f64], ws: &mut [f64], n: usize) -> () {
        let mut dinv = [0.0f64; 128];
        let big = n > dinv.len();
        if !big {
            for j in 0..n {
                dinv[j] = 1.0 / ls[j * n + j];
            }
        }
        for c in 0..n {
            let col = &mut ws[c * n..(c + 1) * n];
            col[c] = 1.0;
            for j in c..n {
                let lj = &ls[j * n..(j + 1) * n];
                let v = if big {
                    col[j] / lj[j]
                } else {
                    col[j] * dinv[j]
                };
                col[j] = v;
                if v != 0.0 {
                    for (x, y) in col[j + 1..].iter_mut().zip(&lj[j + 1..]) {
                        *x -= v * y;
                    }
                }
            }
        }
    }
);

dispatch!(
    fn outer_kernel(g: &mut [f64], v: &[f64], k: usize, idx: &[u32], sign: f64) -> () {
        for &i in idx {
            let row = &v[i as usize * k..(i as usize + 1) * k];
            for (b, &vb) in row.iter().enumerate() {
                let f = sign * vb;
                for (gab, va) in g[b * k..(b + 1) * k].iter_mut().zip(row) {
                    *gab += va * f;
                }
            }
        }
    }
);

/// `G += sign · Σ_{i ∈ idx} v_i v_iᵀ` for the rows `v_i` of the row-major `· × k` matrix `v`.
pub fn add_outer(g: &mut DMatrix<f64>, v: &[f64], k: usize, idx: &[u32], sign: f64) {
    outer_kernel(g.as_mut_slice(), v, k, idx, sign);
}

/// Lower Cholesky factor `L` (`m = L Lᵀ`) of a symmetric positive-definite matrix (only the
/// lower triangle of `m` is read), or `None`. Left-looking, column-oriented (contiguous axpy).
pub fn cholesky_lower(m: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = m.nrows();
    let mut l = m.clone();
    chol_kernel(l.as_mut_slice(), n).then_some(l)
}

/// Inverse `L⁻¹` of a lower-triangular matrix with a positive diagonal (column-oriented).
pub fn lower_inverse(l: &DMatrix<f64>) -> DMatrix<f64> {
    let n = l.nrows();
    let mut w = DMatrix::<f64>::zeros(n, n);
    lower_inverse_kernel(l.as_slice(), w.as_mut_slice(), n);
    w
}

dispatch!(
    fn gram_lower_kernel(ws: &[f64], ts: &mut [f64], out: &mut [f64], n: usize) -> () {
        // ts = Wᵀ (column i of ts = row i of W: entries 0..=i contiguous).
        for c in 0..n {
            for r in c..n {
                ts[r * n + c] = ws[c * n + r];
            }
        }
        // Column b of the lower triangle: M[b..=i, b] += W_ib · W[i, b..=i] over i ≥ b.
        for b in 0..n {
            let (wb, ob) = (&ws[b * n..(b + 1) * n], b * n);
            for i in b..n {
                let f = wb[i];
                if f != 0.0 {
                    let src = &ts[i * n + b..i * n + i + 1];
                    for (o, t) in out[ob + b..ob + i + 1].iter_mut().zip(src) {
                        *o += f * t;
                    }
                }
            }
        }
        // Mirror to the upper triangle.
        for c in 0..n {
            for r in c + 1..n {
                out[r * n + c] = out[c * n + r];
            }
        }
    }
);

/// Inverse of a symmetric positive-definite matrix, `A⁻¹ = L⁻ᵀ L⁻¹` (exactly symmetric), or
/// `None`: Cholesky, triangular inverse and the triangular Gram product (`n³` flops in all).
pub fn spd_inverse_lower(m: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = m.nrows();
    let w = lower_inverse(&cholesky_lower(m)?);
    let mut t = vec![0.0; n * n];
    let mut inv = DMatrix::<f64>::zeros(n, n);
    gram_lower_kernel(w.as_slice(), &mut t, inv.as_mut_slice(), n);
    Some(inv)
}

/// Solves `L Lᵀ x = b` in place for a lower Cholesky factor `L`.
pub fn chol_solve_in_place(l: &DMatrix<f64>, b: &mut [f64]) {
    let n = l.nrows();
    // L y = b (column-oriented forward substitution).
    let ls = l.as_slice();
    for c in 0..n {
        let col = &ls[c * n..(c + 1) * n];
        let yc = b[c] / col[c];
        b[c] = yc;
        for (x, y) in b[c + 1..].iter_mut().zip(&col[c + 1..]) {
            *x -= y * yc;
        }
    }
    // Lᵀ x = y (row r of Lᵀ is column r of L).
    let ls = l.as_slice();
    for r in (0..n).rev() {
        let s = dot(&ls[r * n + r + 1..(r + 1) * n], &b[r + 1..]);
        b[r] = (b[r] - s) / l[(r, r)];
    }
}

/// Values of a packed lower triangle of an `n × n` matrix (`n (n + 1) / 2`).
#[inline]
pub fn packed_len(n: usize) -> usize {
    n * (n + 1) / 2
}

/// Start of column `j` in a packed lower triangle (column `j` holds rows `j..n`).
#[inline]
pub fn packed_col(n: usize, j: usize) -> usize {
    j * (2 * n + 1 - j) / 2
}

/// Appends the lower triangle of the column-major `n × n` matrix `full` to `dst`, packed.
pub fn pack_lower(full: &[f64], n: usize, dst: &mut Vec<f64>) {
    for j in 0..n {
        dst.extend_from_slice(&full[j * n + j..(j + 1) * n]);
    }
}

/// The symmetric `n × n` matrix (column-major) whose lower triangle is `packed`.
pub fn unpack_symmetric(packed: &[f64], n: usize) -> DMatrix<f64> {
    let mut m = DMatrix::zeros(n, n);
    for j in 0..n {
        let col = &packed[packed_col(n, j)..packed_col(n, j + 1)];
        for (i, &v) in col.iter().enumerate() {
            m[(j + i, j)] = v;
            m[(j, j + i)] = v;
        }
    }
    m
}

/// The lower-triangular `n × n` matrix (column-major) stored packed in `packed`.
pub fn unpack_lower(packed: &[f64], n: usize) -> DMatrix<f64> {
    let mut m = DMatrix::zeros(n, n);
    for j in 0..n {
        let col = &packed[packed_col(n, j)..packed_col(n, j + 1)];
        for (i, &v) in col.iter().enumerate() {
            m[(j + i, j)] = v;
        }
    }
    m
}

/// Solves `L Lᵀ x = b` in place for a packed lower Cholesky factor `L` (`n × n`).
pub fn chol_solve_packed(l: &[f64], n: usize, b: &mut [f64]) {
    // L y = b (column-oriented forward substitution).
    for c in 0..n {
        let col = &l[packed_col(n, c)..packed_col(n, c + 1)];
        let yc = b[c] / col[0];
        b[c] = yc;
        for (x, y) in b[c + 1..n].iter_mut().zip(&col[1..]) {
            *x -= y * yc;
        }
    }
    // Lᵀ x = y (row r of Lᵀ is column r of L).
    for r in (0..n).rev() {
        let col = &l[packed_col(n, r)..packed_col(n, r + 1)];
        let s = dot(&col[1..], &b[r + 1..n]);
        b[r] = (b[r] - s) / col[0];
    }
}

/// `out += M v` for a symmetric `n × n` matrix `M` given by its packed lower triangle.
pub fn sym_matvec_packed_add(m: &[f64], n: usize, v: &[f64], out: &mut [f64]) {
    for j in 0..n {
        let col = &m[packed_col(n, j)..packed_col(n, j + 1)];
        // Row j of M (its lower part is column j): diagonal and below.
        out[j] += dot(col, &v[j..n]);
        let vj = v[j];
        if vj != 0.0 {
            for (o, c) in out[j + 1..n].iter_mut().zip(&col[1..]) {
                *o += c * vj;
            }
        }
    }
}

/// `out = A⁻¹` (column-major, symmetric) from the lower Cholesky factor `l` of `A`, using the
/// scratch buffers `w`, `t` (each `n²`).
pub fn inverse_from_cholesky(l: &[f64], n: usize, w: &mut [f64], t: &mut [f64], out: &mut [f64]) {
    w.iter_mut().for_each(|x| *x = 0.0);
    lower_inverse_kernel(l, w, n);
    out.iter_mut().for_each(|x| *x = 0.0);
    gram_lower_kernel(w, t, out, n);
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DVector;

    #[test]
    fn gemm_tn_matches_nalgebra() {
        for (n, ma, mb) in [(73usize, 21usize, 40usize), (5, 1, 3), (1, 4, 4)] {
            let a = DMatrix::from_fn(n, ma, |r, c| ((r * 5 + c * 3) % 7) as f64 - 3.0);
            let b = DMatrix::from_fn(n, mb, |r, c| ((r * 11 + c) % 13) as f64 * 0.25);
            let mut out = vec![f64::NAN; ma * mb];
            gemm_tn(a.as_slice(), b.as_slice(), n, ma, mb, &mut out);
            let reference = a.transpose() * &b;
            assert!(close(
                &DMatrix::from_column_slice(ma, mb, &out),
                &reference,
                1e-12
            ));
        }
    }

    #[test]
    fn spd_inverse_lower_matches_nalgebra() {
        for n in [1usize, 2, 5, 17, 41] {
            let a = DMatrix::from_fn(n, n, |r, c| ((r * 7 + c * 13) % 11) as f64 - 5.0);
            let spd = &a * a.transpose() + DMatrix::identity(n, n) * 0.5;
            let inv = spd_inverse_lower(&spd).unwrap();
            let reference = spd.clone().try_inverse().unwrap();
            assert!(close(&inv, &reference, 1e-10), "n = {n}");
            assert_eq!(inv, inv.transpose());
            // packed storage round trip and packed kernels
            let mut packed = Vec::new();
            pack_lower(inv.as_slice(), n, &mut packed);
            assert_eq!(packed.len(), packed_len(n));
            assert_eq!(unpack_symmetric(&packed, n), inv);
            let v: Vec<f64> = (0..n).map(|i| (i as f64 * 0.37).sin()).collect();
            let mut out = vec![1.0; n];
            sym_matvec_packed_add(&packed, n, &v, &mut out);
            let expect = &inv * DVector::from_column_slice(&v);
            for i in 0..n {
                assert!((out[i] - 1.0 - expect[i]).abs() < 1e-9 * (1.0 + expect[i].abs()));
            }
            let l = cholesky_lower(&spd).unwrap();
            let mut lp = Vec::new();
            pack_lower(l.as_slice(), n, &mut lp);
            assert_eq!(unpack_lower(&lp, n), l);
            let mut b = v.clone();
            chol_solve_packed(&lp, n, &mut b);
            let x = &inv * DVector::from_column_slice(&v);
            for i in 0..n {
                assert!((b[i] - x[i]).abs() < 1e-8 * (1.0 + x[i].abs()));
            }
        }
        assert!(spd_inverse_lower(&DMatrix::from_element(2, 2, 1.0)).is_none());
    }
}
