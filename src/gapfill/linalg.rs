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
    assert_eq!(n, m.ncols(), "symmetrize needs a square matrix");
    let s = m.as_mut_slice();
    for i in 0..n {
        for j in (i + 1)..n {
            // (i, j) is at j·n + i, (j, i) at i·n + j (column-major).
            let a = 0.5 * (s[j * n + i] + s[i * n + j]);
            s[j * n + i] = a;
            s[i * n + j] = a;
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

/// Columns of a row of `W` accumulated in registers by [`lower_inverse_rows`] and rows of a
/// column of `WᵀW` by [`gram_rows`].
const TILE: usize = 8;

dispatch!(
    /// `W = L⁻¹` of the column-major lower-triangular `L` (`ls`) into `wr`, **row-major** with
    /// zeros above the diagonal: row `i` is `(e_i − Σ_{j<i} L_ij W_j·) / L_ii`, eight columns
    /// at a time in registers. Each entry subtracts its terms in ascending `j` (the terms with
    /// `j` below its column are exact zeros), so the values are those of column-by-column
    /// forward substitution with the reciprocals `1 / L_ii` bit for bit.
    fn lower_inverse_rows(ls: &[f64], wr: &mut [f64], n: usize) -> () {
        let mut stack = [0.0f64; 2 * 128];
        let mut heap = Vec::new();
        let buf: &mut [f64] = if n <= 128 {
            &mut stack[..2 * n]
        } else {
            heap.resize(2 * n, 0.0);
            &mut heap
        };
        let (dinv, lrow) = buf.split_at_mut(n);
        for j in 0..n {
            dinv[j] = 1.0 / ls[j * n + j];
        }
        for i in 0..n {
            for (j, l) in lrow[..i].iter_mut().enumerate() {
                *l = ls[j * n + i];
            }
            let di = dinv[i];
            let (done, rest) = wr.split_at_mut(i * n);
            let row = &mut rest[..n];
            let mut c0 = 0;
            // Whole tiles: fixed-size accumulators and stores (kept in registers).
            while c0 + TILE <= i + 1 {
                let mut acc = [0.0f64; TILE];
                for (q, a) in acc.iter_mut().enumerate() {
                    *a = if c0 + q == i { 1.0 } else { 0.0 };
                }
                for (j, &f) in lrow[..i].iter().enumerate().skip(c0) {
                    let src: &[f64; TILE] = done[j * n + c0..j * n + c0 + TILE].try_into().unwrap();
                    for q in 0..TILE {
                        acc[q] -= f * src[q];
                    }
                }
                let dst: &mut [f64; TILE] = (&mut row[c0..c0 + TILE]).try_into().unwrap();
                for q in 0..TILE {
                    dst[q] = acc[q] * di;
                }
                c0 += TILE;
            }
            // The rest of the row up to the diagonal, in place.
            for (q, o) in row[c0..=i].iter_mut().enumerate() {
                *o = if c0 + q == i { 1.0 } else { 0.0 };
            }
            for (j, &f) in lrow[..i].iter().enumerate().skip(c0) {
                let src = &done[j * n + c0..j * n + i + 1];
                for (o, w) in row[c0..=i].iter_mut().zip(src) {
                    *o -= f * w;
                }
            }
            for o in &mut row[c0..=i] {
                *o *= di;
            }
            row[i + 1..].fill(0.0);
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

/// Inverse `L⁻¹` of a lower-triangular matrix with a positive diagonal.
pub fn lower_inverse(l: &DMatrix<f64>) -> DMatrix<f64> {
    let n = l.nrows();
    let mut wr = vec![0.0; n * n];
    lower_inverse_rows(l.as_slice(), &mut wr, n);
    // Row-major W is column-major Wᵀ.
    DMatrix::from_column_slice(n, n, &wr).transpose()
}

dispatch!(
    /// `WᵀW` (column-major, symmetric) for the row-major lower-triangular `W` (`wr`, zeros above
    /// the diagonal, as [`lower_inverse_rows`] writes it). Each entry
    /// `M[a, b] = Σ_{i ≥ a} W_ia W_ib` (`a ≥ b`) is summed in ascending `i`, eight rows of a
    /// column at a time in registers; the upper triangle is mirrored.
    fn gram_rows(wr: &[f64], out: &mut [f64], n: usize) -> () {
        for b in 0..n {
            let mut a0 = b;
            // Whole tiles: fixed-size accumulators and stores (kept in registers).
            while a0 + TILE <= n {
                let mut acc = [0.0f64; TILE];
                for i in a0..n {
                    let f = wr[i * n + b];
                    let row: &[f64; TILE] = wr[i * n + a0..i * n + a0 + TILE].try_into().unwrap();
                    for q in 0..TILE {
                        acc[q] += f * row[q];
                    }
                }
                let dst: &mut [f64; TILE] = (&mut out[b * n + a0..b * n + a0 + TILE])
                    .try_into()
                    .unwrap();
                *dst = acc;
                a0 += TILE;
            }
            // The rest of the column, in place.
            let dst = &mut out[b * n + a0..(b + 1) * n];
            dst.fill(0.0);
            for i in a0..n {
                let f = wr[i * n + b];
                for (o, t) in dst.iter_mut().zip(&wr[i * n + a0..(i + 1) * n]) {
                    *o += f * t;
                }
            }
        }
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
    let l = cholesky_lower(m)?;
    let mut wr = vec![0.0; n * n];
    let mut inv = DMatrix::<f64>::zeros(n, n);
    inverse_from_cholesky(l.as_slice(), n, &mut wr, inv.as_mut_slice());
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
    unpack_symmetric_into(packed, n, m.as_mut_slice());
    m
}

/// [`unpack_symmetric`] into the column-major `n × n` slice `out`.
pub fn unpack_symmetric_into(packed: &[f64], n: usize, out: &mut [f64]) {
    for j in 0..n {
        let col = &packed[packed_col(n, j)..packed_col(n, j + 1)];
        out[j * n + j..(j + 1) * n].copy_from_slice(col);
        for (i, &v) in col.iter().enumerate().skip(1) {
            out[(j + i) * n + j] = v;
        }
    }
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

dispatch!(
    /// `out += M v` for a symmetric `n × n` matrix `M` given by its packed lower triangle.
    pub fn sym_matvec_packed_add(m: &[f64], n: usize, v: &[f64], out: &mut [f64]) -> () {
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
);

/// `out = A⁻¹` (column-major, symmetric) from the lower Cholesky factor `l` of `A`, using the
/// scratch buffer `w` (`n²`): `W = L⁻¹` by rows, then `WᵀW` (`n³/3` multiply-adds).
pub fn inverse_from_cholesky(l: &[f64], n: usize, w: &mut [f64], out: &mut [f64]) {
    lower_inverse_rows(l, w, n);
    gram_rows(w, out, n);
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
        for n in [1usize, 2, 5, 8, 17, 41, 130] {
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
            // L⁻¹ by rows (whole tiles of 8 and the rest) is a lower-triangular inverse.
            let li = lower_inverse(&l);
            assert!(
                close(&(&li * &l), &DMatrix::identity(n, n), 1e-12),
                "n = {n}"
            );
            assert!((0..n).all(|c| (0..c).all(|r| li[(r, c)] == 0.0)));
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
