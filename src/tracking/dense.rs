//! Small dense linear-algebra helpers for the tracker: Cholesky with a jitter fallback,
//! symmetric rank-k products and triangular solves on the kernels of [`crate::kernels`]
//! (AVX2/FMA chosen at run time; no heap memory, so a filter step allocates nothing).
//!
//! Matrices are flat `Vec<f64>`/slices; covariances are symmetric so row- and column-major
//! coincide. The factorisations and triangular solves use the run-time dispatched
//! column kernels of [`crate::kernels`] (2-4× nalgebra's generic loops at n ≈ 50-100).

use crate::error::{AcmError, Result};
use crate::kernels::{
    cholesky_in_place, lower_solve_blocked, lower_solve_in_place, lower_tr_solve_blocked,
    lower_tr_solve_in_place, syrk_rows_lower,
};
use crate::team::Team;
use nalgebra::{DMatrix, DVector};

/// Relative jitter levels tried when a covariance is not numerically positive definite
/// (multiples of the mean diagonal entry).
const JITTER: [f64; 4] = [1e-12, 1e-10, 1e-8, 1e-6];

/// Lower Cholesky factor of the symmetric `n × n` matrix `a` (flat), with a jitter fallback.
///
/// The matrix is symmetrised first. If the plain factorisation fails, `ε · mean(diag) · I` is
/// added for increasing `ε` up to 1e-6.
///
/// # Errors
/// [`AcmError::Numerical`] naming `what` if the matrix is not positive definite even with the
/// largest jitter, or contains non-finite values.
pub fn cholesky(a: &[f64], n: usize, what: &dyn Fn() -> String) -> Result<DMatrix<f64>> {
    if a.iter().any(|v| !v.is_finite()) {
        return Err(AcmError::Numerical(format!(
            "{} contains NaN or infinity",
            what()
        )));
    }
    let mut m = DMatrix::from_column_slice(n, n, a);
    symmetrize(&mut m);
    let mut l = m.clone();
    if cholesky_in_place(l.as_mut_slice(), n) {
        return Ok(l);
    }
    let scale = (m.trace() / n as f64).abs().max(f64::MIN_POSITIVE);
    for eps in JITTER {
        l.copy_from(&m);
        for i in 0..n {
            l[(i, i)] += eps * scale;
        }
        if cholesky_in_place(l.as_mut_slice(), n) {
            return Ok(l);
        }
    }
    let min_diag = (0..n).map(|i| m[(i, i)]).fold(f64::INFINITY, f64::min);
    Err(AcmError::Numerical(format!(
        "{} is not positive definite (smallest diagonal entry {min_diag:.3e}, even with a \
         jitter of 1e-6 × mean diagonal)",
        what()
    )))
}

/// [`cholesky`] into a caller buffer (`n × n`, column-major), without allocating unless the
/// plain factorisation fails (then the jitter path of [`cholesky`]).
///
/// # Errors
/// As [`cholesky`].
pub fn cholesky_into(
    a: &[f64],
    n: usize,
    out: &mut [f64],
    what: &dyn Fn() -> String,
) -> Result<()> {
    if a.iter().any(|v| !v.is_finite()) {
        return Err(AcmError::Numerical(format!(
            "{} contains NaN or infinity",
            what()
        )));
    }
    out.copy_from_slice(a);
    symmetrize_slice(out, n);
    if cholesky_in_place(out, n) {
        return Ok(());
    }
    let l = cholesky(a, n, what)?;
    out.copy_from_slice(l.as_slice());
    Ok(())
}

/// `m ← (m + mᵀ) / 2` for a column-major `n × n` slice.
pub fn symmetrize_slice(m: &mut [f64], n: usize) {
    for i in 0..n {
        for j in 0..i {
            let v = 0.5 * (m[j * n + i] + m[i * n + j]);
            m[j * n + i] = v;
            m[i * n + j] = v;
        }
    }
}

/// `m ← (m + mᵀ) / 2`.
pub fn symmetrize(m: &mut DMatrix<f64>) {
    let n = m.nrows();
    for i in 0..n {
        for j in 0..i {
            let v = 0.5 * (m[(i, j)] + m[(j, i)]);
            m[(i, j)] = v;
            m[(j, i)] = v;
        }
    }
}

/// Solves `L Lᵀ x = b` in place for a lower Cholesky factor `l`.
pub fn chol_solve_vec(l: &DMatrix<f64>, b: &mut DVector<f64>) {
    let n = l.nrows();
    lower_solve_in_place(l.as_slice(), n, b.as_mut_slice());
    lower_tr_solve_in_place(l.as_slice(), n, b.as_mut_slice());
}

/// Solves `L Lᵀ X = B` in place for a lower Cholesky factor `l` (columns of `b`; blocked
/// solves with packed GEMMs for many columns).
pub fn chol_solve_mat(l: &DMatrix<f64>, b: &mut DMatrix<f64>) {
    let n = l.nrows();
    lower_solve_blocked(l.as_slice(), n, b.as_mut_slice());
    lower_tr_solve_blocked(l.as_slice(), n, b.as_mut_slice());
}

/// `c ← c + a aᵀ` for `a` stored row-major as `rows × k` (each row one vector), `c` the
/// `rows × rows` column-major result (exactly symmetric). The lower triangle by the
/// allocation-free kernel of [`crate::kernels::syrk_rows_lower`], split between two threads
/// by columns (equal shares of the triangle) when large and `parallel`, then mirrored.
pub fn add_gram_rows(a: &[f64], rows: usize, k: usize, c: &mut [f64], parallel: bool) {
    add_gram_rows_lower(a, rows, k, c, parallel);
    mirror_lower(c, rows);
}

/// [`add_gram_rows`] into the lower triangle of `c` only (the upper one is left as it was),
/// e.g. for a Cholesky factorisation that reads only the lower triangle.
pub fn add_gram_rows_lower(a: &[f64], rows: usize, k: usize, c: &mut [f64], parallel: bool) {
    debug_assert_eq!(a.len(), rows * k);
    debug_assert_eq!(c.len(), rows * rows);
    if rows == 0 || k == 0 {
        return;
    }
    // column j holds rows − j entries of the triangle: split where the shares are equal
    let split = ((rows as f64) * (1.0 - std::f64::consts::FRAC_1_SQRT_2)).round() as usize;
    let split = split.clamp(1, rows) & !1; // even, so the 2-column blocks stay aligned
    let (c0, c1) = c.split_at_mut(split * rows);
    if parallel && rows * rows * k > 200_000 {
        // on the spinning team (see `crate::team`: rayon's wake-ups cost more than a region
        // of ~40 µs gains)
        let ranges = [0..split, split..rows];
        Team::global().run_pair(rayon::current_num_threads(), [c0, c1], &|i, c| {
            syrk_rows_lower(a, rows, k, ranges[i].clone(), c);
        });
    } else {
        syrk_rows_lower(a, rows, k, 0..split, c0);
        syrk_rows_lower(a, rows, k, split..rows, c1);
    }
}

/// Copies the lower triangle of the column-major `n × n` slice onto its upper triangle.
pub fn mirror_lower(c: &mut [f64], n: usize) {
    for j in 0..n {
        for i in j + 1..n {
            c[i * n + j] = c[j * n + i];
        }
    }
}

/// `Aᵀ A` for a column-major `a` (`rows × cols`).
pub fn at_a(a: &DMatrix<f64>) -> DMatrix<f64> {
    let (rows, cols) = a.shape();
    let mut c = DMatrix::zeros(cols, cols);
    at_a_into(a.as_slice(), rows, cols, c.as_mut_slice(), true);
    c
}

/// `out ← Aᵀ A` for a column-major `a` (`rows × cols`) into the `cols × cols` `out`
/// (exactly symmetric; allocation-free: column `i` of `A` is row `i` of `Aᵀ`, so this is
/// [`add_gram_rows`] of the columns, split between two threads when large and `parallel`).
pub fn at_a_into(a: &[f64], rows: usize, cols: usize, out: &mut [f64], parallel: bool) {
    debug_assert!(a.len() >= rows * cols && out.len() >= cols * cols);
    out[..cols * cols].iter_mut().for_each(|v| *v = 0.0);
    if rows == 0 || cols == 0 {
        return;
    }
    add_gram_rows(
        &a[..rows * cols],
        cols,
        rows,
        &mut out[..cols * cols],
        parallel,
    );
}

/// `out ← out + A Aᵀ` for a column-major `a` (`rows × cols`) and the `rows × rows`
/// `out` (by rank-1 updates of the lower triangle, then mirrored; allocation-free).
pub fn add_a_at(a: &[f64], rows: usize, cols: usize, out: &mut [f64]) {
    debug_assert!(a.len() >= rows * cols && out.len() >= rows * rows);
    for col in a[..rows * cols].chunks_exact(rows) {
        for j in 0..rows {
            let f = col[j];
            if f != 0.0 {
                for (o, x) in out[j * rows + j..(j + 1) * rows].iter_mut().zip(&col[j..]) {
                    *o += f * x;
                }
            }
        }
    }
    mirror_lower(out, rows);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gram_matches_naive_product() {
        // small (one thread) and large (split between two threads unless serial)
        for (rows, k) in [(7, 13), (66, 61)] {
            let a: Vec<f64> = (0..rows * k)
                .map(|i| ((i * 31 % 17) as f64) - 8.0)
                .collect();
            let mut results = Vec::new();
            for parallel in [true, false] {
                let mut c = vec![0.0; rows * rows];
                for i in 0..rows {
                    c[i * rows + i] = 1.0;
                }
                add_gram_rows(&a, rows, k, &mut c, parallel);
                for i in 0..rows {
                    for j in 0..rows {
                        let want: f64 = (0..k).map(|l| a[i * k + l] * a[j * k + l]).sum::<f64>()
                            + if i == j { 1.0 } else { 0.0 };
                        assert!((c[j * rows + i] - want).abs() < 1e-9, "{rows}x{k}");
                    }
                }
                results.push(c);
            }
            assert_eq!(results[0], results[1], "serial and parallel differ");
            // the lower-only product: the same lower triangle, the upper one untouched
            let mut lower = vec![f64::NAN; rows * rows];
            for j in 0..rows {
                for i in j..rows {
                    lower[j * rows + i] = if i == j { 1.0 } else { 0.0 };
                }
            }
            add_gram_rows_lower(&a, rows, k, &mut lower, true);
            for j in 0..rows {
                for i in 0..rows {
                    let v = lower[j * rows + i];
                    if i >= j {
                        assert_eq!(v, results[0][j * rows + i]);
                    } else {
                        assert!(v.is_nan());
                    }
                }
            }
        }
    }

    #[test]
    fn at_a_matches_nalgebra() {
        let a = DMatrix::from_fn(9, 4, |i, j| ((i * 7 + j * 3) % 5) as f64 - 2.0);
        let want = a.transpose() * &a;
        assert!((at_a(&a) - want).abs().max() < 1e-12);
    }

    #[test]
    fn cholesky_jitter_and_errors() {
        // Rank-deficient PSD matrix: plain Cholesky may fail, the jitter makes it work.
        let v = [1.0, 2.0, 3.0];
        let a: Vec<f64> = (0..9).map(|i| v[i / 3] * v[i % 3]).collect();
        let l = cholesky(&a, 3, &|| "test".into()).unwrap();
        let back = &l * l.transpose();
        for i in 0..9 {
            assert!((back[(i % 3, i / 3)] - a[i]).abs() < 1e-5);
        }
        let neg = [1.0, 0.0, 0.0, -1.0];
        let e = cholesky(&neg, 2, &|| "V_z".into()).unwrap_err();
        assert!(matches!(e, AcmError::Numerical(ref s) if s.contains("V_z")));
        let nan = [f64::NAN, 0.0, 0.0, 1.0];
        assert!(cholesky(&nan, 2, &|| "x".into()).is_err());
    }
}
