//! Column-oriented dense kernels shared by the tracker and the gap filler: Cholesky
//! factorisation and triangular solves of small column-major matrices (`n` ≲ 200), compiled
//! twice and chosen at run time — for AVX2 + FMA where the CPU has them (the inner loops
//! are contiguous axpys that then vectorise four wide), else for the baseline target; the
//! Cholesky factor also for AVX-512 (register tiles of 16 rows).
//!
//! At these sizes they beat nalgebra's generic loops (which the baseline target compiles
//! for SSE2) by 2-4× (`benches/README.md`). Triangular solves with many right-hand sides
//! (the smoother's gains: 100 × 100 by 100 columns) are blocked around `matrixmultiply`'s
//! packed GEMM ([`lower_solve_blocked`]), 1.6-2× faster than the column kernels there.

/// Defines `fn $name(...)` whose `$body` runs compiled for AVX2 + FMA when the CPU has them
/// (runtime dispatch), else for the baseline target.
macro_rules! dispatch {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) -> $ret:ty $body:block) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) -> $ret {
            #[inline(always)]
            fn kernel($($arg: $ty),*) -> $ret $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn wide($($arg: $ty),*) -> $ret {
                    kernel($($arg),*)
                }
                if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                    // SAFETY: the CPU supports the enabled features (checked above).
                    return unsafe { wide($($arg),*) };
                }
            }
            kernel($($arg),*)
        }
    };
}
pub(crate) use dispatch;

/// In-place lower Cholesky factor of the column-major `n × n` matrix `a` (left-looking;
/// only the lower triangle is read, the upper one is zeroed); `false` if `a` is not positive
/// definite.
///
/// Columns are computed four at a time: a register tile of rows × 4 columns (16 rows with
/// AVX-512, 8 with AVX2, then 4 and 1 for the last rows) is held while every earlier column
/// is subtracted from it (each earlier column's entries loaded once for the four columns);
/// then the four columns are finished among themselves. Each entry is still updated column
/// by column in order, with a separate multiply and subtract, so the factor is the
/// one-column-at-a-time one bit for bit on every path (`tests`). The 174 × 174 factor of the
/// 87-entry skeleton's update: 224 → 91 µs, the 87 × 87 one 25 → 17 µs (criterion,
/// `benches/README.md`).
pub fn cholesky_in_place(a: &mut [f64], n: usize) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        if is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the enabled features (checked above).
            return unsafe { cholesky_avx512(a, n) };
        }
        if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { cholesky_avx2(a, n) };
        }
    }
    cholesky_tiled::<8>(a, n)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn cholesky_avx512(a: &mut [f64], n: usize) -> bool {
    cholesky_tiled::<16>(a, n)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn cholesky_avx2(a: &mut [f64], n: usize) -> bool {
    cholesky_tiled::<8>(a, n)
}

/// [`cholesky_in_place`] with register tiles of `R` rows.
#[inline(always)]
fn cholesky_tiled<const R: usize>(a: &mut [f64], n: usize) -> bool {
    let mut j0 = 0;
    while j0 < n {
        let b = 4.min(n - j0);
        // 1. columns j0..j0 + b minus the columns p < j0, in order (the rows above a column's
        //    diagonal are computed too, and zeroed in 2.)
        let (done, rest) = a.split_at_mut(j0 * n);
        if j0 > 0 {
            match b {
                4 => cholesky_rows::<R, 4>(done, rest, n, j0),
                3 => cholesky_rows::<R, 3>(done, rest, n, j0),
                2 => cholesky_rows::<R, 2>(done, rest, n, j0),
                _ => cholesky_rows::<R, 1>(done, rest, n, j0),
            }
        }
        // 2. the block's own columns, one after the other
        for k in 0..b {
            let j = j0 + k;
            let (left, cj) = rest.split_at_mut(k * n);
            let cj = &mut cj[..n];
            for cp in left.chunks_exact(n) {
                let f = cp[j];
                for (x, y) in cj[j..].iter_mut().zip(&cp[j..]) {
                    *x -= f * y;
                }
            }
            let djj = cj[j];
            if !(djj > 0.0 && djj.is_finite()) {
                return false;
            }
            let d = djj.sqrt();
            cj[j] = d;
            let inv = 1.0 / d;
            cj[j + 1..].iter_mut().for_each(|x| *x *= inv);
            cj[..j].iter_mut().for_each(|x| *x = 0.0);
        }
        j0 += b;
    }
    true
}

/// Rows `j0..n` of the `C` columns at the start of `rest` minus the columns of `done`
/// (`j0` columns of `n`), by tiles of `R`, 4 and 1 rows.
#[inline(always)]
fn cholesky_rows<const R: usize, const C: usize>(
    done: &[f64],
    rest: &mut [f64],
    n: usize,
    j0: usize,
) {
    let mut i = j0;
    while i + R <= n {
        cholesky_tile::<R, C>(done, rest, n, j0, i);
        i += R;
    }
    while i + 4 <= n {
        cholesky_tile::<4, C>(done, rest, n, j0, i);
        i += 4;
    }
    while i < n {
        cholesky_tile::<1, C>(done, rest, n, j0, i);
        i += 1;
    }
}

/// Rows `i..i + R` of the `C` columns at the start of `rest` minus every column of `done`,
/// in order, held in registers.
#[inline(always)]
fn cholesky_tile<const R: usize, const C: usize>(
    done: &[f64],
    rest: &mut [f64],
    n: usize,
    j0: usize,
    i: usize,
) {
    let mut acc = [[0.0; R]; C];
    for (k, row) in acc.iter_mut().enumerate() {
        row.copy_from_slice(&rest[k * n + i..k * n + i + R]);
    }
    for col in done.chunks_exact(n) {
        let mut f = [0.0; C];
        f.copy_from_slice(&col[j0..j0 + C]);
        let mut y = [0.0; R];
        y.copy_from_slice(&col[i..i + R]);
        for (row, fk) in acc.iter_mut().zip(f) {
            for (x, yr) in row.iter_mut().zip(y) {
                *x -= fk * yr;
            }
        }
    }
    for (k, row) in acc.iter().enumerate() {
        rest[k * n + i..k * n + i + R].copy_from_slice(row);
    }
}

dispatch!(
    /// Solves `L X = B` in place for the column-major lower-triangular `n × n` matrix `l` (non-zero
    /// diagonal) and the column-major `n × k` matrix `b` (`k = b.len() / n`): forward substitution,
    /// four columns of `B` at a time (each column of `L` loaded once for the four), with
    /// contiguous axpys down the columns of `L`. Each column's arithmetic is that of a
    /// one-column solve (the same result bit for bit).
    pub fn lower_solve_in_place(l: &[f64], n: usize, b: &mut [f64]) -> () {
        if n == 0 {
            return;
        }
        let mut quads = b.chunks_exact_mut(4 * n);
        for quad in &mut quads {
            let [c0, c1, c2, c3] = four_columns(quad, n);
            // two columns of L per pass over the rows below them (each entry of the four
            // right-hand sides loaded and stored once for both; updated in the same order)
            let mut j = 0;
            while j + 2 <= n {
                let (la, lb) = (&l[j * n..(j + 1) * n], &l[(j + 1) * n..(j + 2) * n]);
                let mut v = [0.0; 4];
                let mut w = [0.0; 4];
                for (k, c) in [&mut *c0, &mut *c1, &mut *c2, &mut *c3]
                    .into_iter()
                    .enumerate()
                {
                    v[k] = c[j] / la[j];
                    c[j] = v[k];
                    let x = c[j + 1] - v[k] * la[j + 1];
                    w[k] = x / lb[j + 1];
                    c[j + 1] = w[k];
                }
                let t = j + 2;
                let rows = c0[t..]
                    .iter_mut()
                    .zip(&mut c1[t..])
                    .zip(&mut c2[t..])
                    .zip(&mut c3[t..])
                    .zip(la[t..].iter().zip(&lb[t..]));
                for ((((x0, x1), x2), x3), (ya, yb)) in rows {
                    *x0 = (*x0 - v[0] * ya) - w[0] * yb;
                    *x1 = (*x1 - v[1] * ya) - w[1] * yb;
                    *x2 = (*x2 - v[2] * ya) - w[2] * yb;
                    *x3 = (*x3 - v[3] * ya) - w[3] * yb;
                }
                j += 2;
            }
            for j in j..n {
                let lj = &l[j * n..(j + 1) * n];
                let d = lj[j];
                let v = [c0[j] / d, c1[j] / d, c2[j] / d, c3[j] / d];
                c0[j] = v[0];
                c1[j] = v[1];
                c2[j] = v[2];
                c3[j] = v[3];
                let rows = c0[j + 1..]
                    .iter_mut()
                    .zip(&mut c1[j + 1..])
                    .zip(&mut c2[j + 1..])
                    .zip(&mut c3[j + 1..])
                    .zip(&lj[j + 1..]);
                for ((((x0, x1), x2), x3), y) in rows {
                    *x0 -= v[0] * y;
                    *x1 -= v[1] * y;
                    *x2 -= v[2] * y;
                    *x3 -= v[3] * y;
                }
            }
        }
        for col in quads.into_remainder().chunks_exact_mut(n) {
            for j in 0..n {
                let lj = &l[j * n..(j + 1) * n];
                let v = col[j] / lj[j];
                col[j] = v;
                for (x, y) in col[j + 1..].iter_mut().zip(&lj[j + 1..]) {
                    *x -= v * y;
                }
            }
        }
    }
);

dispatch!(
    /// Solves `Lᵀ X = B` in place for `l`, `b` as in [`lower_solve_in_place`] (back
    /// substitution; row `r` of `Lᵀ` is column `r` of `L`, so each step is a contiguous dot;
    /// four columns of `B` at a time by [`dot4`], the same result as one at a time).
    pub fn lower_tr_solve_in_place(l: &[f64], n: usize, b: &mut [f64]) -> () {
        if n == 0 {
            return;
        }
        let mut quads = b.chunks_exact_mut(4 * n);
        for quad in &mut quads {
            let [c0, c1, c2, c3] = four_columns(quad, n);
            for r in (0..n).rev() {
                let lr = &l[r * n..(r + 1) * n];
                let t = r + 1;
                let s = dot4(&lr[t..], [&c0[t..], &c1[t..], &c2[t..], &c3[t..]]);
                let d = lr[r];
                c0[r] = (c0[r] - s[0]) / d;
                c1[r] = (c1[r] - s[1]) / d;
                c2[r] = (c2[r] - s[2]) / d;
                c3[r] = (c3[r] - s[3]) / d;
            }
        }
        for col in quads.into_remainder().chunks_exact_mut(n) {
            for r in (0..n).rev() {
                let lr = &l[r * n..(r + 1) * n];
                let s = dot(&lr[r + 1..], &col[r + 1..]);
                col[r] = (col[r] - s) / lr[r];
            }
        }
    }
);

/// Diagonal blocks of [`lower_solve_blocked`] and [`lower_tr_solve_blocked`].
const TRSM_BLOCK: usize = 16;

/// The inverse of the diagonal block `j0..j1` of the column-major lower-triangular `n × n`
/// matrix `l`, into `li` (column-major `nb × nb`, lower; `nb = j1 − j0`): column `j` by
/// forward substitution against `e_j`.
fn invert_diagonal_block(l: &[f64], n: usize, j0: usize, j1: usize, li: &mut Vec<f64>) {
    let nb = j1 - j0;
    li.clear();
    li.resize(nb * nb, 0.0);
    for j in 0..nb {
        let col = &mut li[j * nb..(j + 1) * nb];
        col[j] = 1.0 / l[(j0 + j) * n + j0 + j];
        for i in j + 1..nb {
            let mut s = 0.0;
            for (p, x) in col.iter().enumerate().take(i).skip(j) {
                s += l[(j0 + p) * n + j0 + i] * x;
            }
            col[i] = -s / l[(j0 + i) * n + j0 + i];
        }
    }
}

/// Writes the column-major `nb × k` scratch `xb` into the rows `j0..j0 + nb` of `b`.
fn unpack_rows(xb: &[f64], n: usize, j0: usize, b: &mut [f64]) {
    let nb = xb.len() / (b.len() / n).max(1);
    for (col, x) in b.chunks_exact_mut(n).zip(xb.chunks_exact(nb)) {
        col[j0..j0 + nb].copy_from_slice(x);
    }
}

/// `C ← α op(A) B + β C` by `matrixmultiply`'s packed GEMM for column-major operands given by
/// pointer and column stride (`op(A)` is `m × kk`; `a_trans` reads `A` transposed).
///
/// # Safety
/// Every operand must lie inside its allocation for the given sizes and strides, and `c`
/// must not overlap `a` or `b`.
#[allow(clippy::too_many_arguments)]
pub(crate) unsafe fn gemm(
    (m, kk, k): (usize, usize, usize),
    alpha: f64,
    (a, lda, a_trans): (*const f64, usize, bool),
    (b, ldb): (*const f64, usize),
    beta: f64,
    (c, ldc): (*mut f64, usize),
) {
    let (rsa, csa) = if a_trans {
        (lda as isize, 1)
    } else {
        (1, lda as isize)
    };
    matrixmultiply::dgemm(
        m,
        kk,
        k,
        alpha,
        a,
        rsa,
        csa,
        b,
        1,
        ldb as isize,
        beta,
        c,
        1,
        ldc as isize,
    );
}

/// The number of right-hand sides `k` of a blocked solve with `l` (`n × n`) and `b`
/// (`n × k`), or `None` where the column kernel is as fast (small `n` or few columns).
///
/// # Panics
/// If the sizes do not fit.
fn blocked_columns(l: &[f64], n: usize, b: &[f64]) -> Option<usize> {
    let k = b.len().checked_div(n).unwrap_or(0);
    assert!(l.len() >= n * n && b.len() == n * k);
    (n > TRSM_BLOCK && k >= 4).then_some(k)
}

/// [`lower_solve_in_place`] for many right-hand sides, blocked: each diagonal block of
/// [`TRSM_BLOCK`] rows is inverted (a few hundred multiply-adds) and applied, and the rows
/// below it are updated, by packed GEMMs (`matrixmultiply`: ~25 GFLOP/s of multiply-adds at
/// these sizes against ~6 for the column kernel, whose short inner loops dominate at
/// `n ≈ 100`). The same solution up to rounding (another summation order, and the small
/// blocks' inverses: for the well-conditioned factors of covariances that is ~1e-13
/// relative, tested); allocates its scratch, so not for the online filter's step.
pub fn lower_solve_blocked(l: &[f64], n: usize, b: &mut [f64]) {
    let Some(k) = blocked_columns(l, n, b) else {
        lower_solve_in_place(l, n, b);
        return;
    };
    let nbk = TRSM_BLOCK;
    let (mut li, mut xb) = (Vec::new(), Vec::new());
    let mut j0 = 0;
    while j0 < n {
        let j1 = (j0 + nbk).min(n);
        let nb = j1 - j0;
        invert_diagonal_block(l, n, j0, j1, &mut li);
        xb.clear();
        xb.resize(nb * k, 0.0);
        let bp = b.as_mut_ptr();
        // SAFETY: every operand lies in `li`, `b`, `xb` or `l` for these sizes (asserted
        // above; column-major strides); `xb` is separate, and the rows of `b` read (j0..j1)
        // and written (j1..n) by the second product are disjoint.
        unsafe {
            // X[j0..j1] = L_blk⁻¹ B[j0..j1]
            gemm(
                (nb, nb, k),
                1.0,
                (li.as_ptr(), nb, false),
                (bp.add(j0), n),
                0.0,
                (xb.as_mut_ptr(), nb),
            );
            unpack_rows(&xb, n, j0, b);
            let bp = b.as_mut_ptr();
            if j1 < n {
                // B[j1.., :] −= L[j1.., j0..j1] X[j0..j1, :]
                gemm(
                    (n - j1, nb, k),
                    -1.0,
                    (l.as_ptr().add(j0 * n + j1), n, false),
                    (bp.add(j0), n),
                    1.0,
                    (bp.add(j1), n),
                );
            }
        }
        j0 = j1;
    }
}

/// [`lower_tr_solve_in_place`] (`Lᵀ X = B`) for many right-hand sides, blocked as
/// [`lower_solve_blocked`]: from the last diagonal block up, the block's rows lose
/// `L[below, block]ᵀ X[below]`, then get the transposed inverse of the block, both by packed
/// GEMMs.
pub fn lower_tr_solve_blocked(l: &[f64], n: usize, b: &mut [f64]) {
    let Some(k) = blocked_columns(l, n, b) else {
        lower_tr_solve_in_place(l, n, b);
        return;
    };
    let nbk = TRSM_BLOCK;
    let (mut li, mut xb) = (Vec::new(), Vec::new());
    let mut j1 = n;
    while j1 > 0 {
        let j0 = j1.saturating_sub(nbk);
        let nb = j1 - j0;
        invert_diagonal_block(l, n, j0, j1, &mut li);
        xb.clear();
        xb.resize(nb * k, 0.0);
        let bp = b.as_mut_ptr();
        // SAFETY: as in `lower_solve_blocked_nb`; the rows read (j1..n) and written (j0..j1)
        // by the first product are disjoint.
        unsafe {
            if j1 < n {
                // B[j0..j1, :] −= L[j1..n, j0..j1]ᵀ X[j1..n, :]
                gemm(
                    (nb, n - j1, k),
                    -1.0,
                    (l.as_ptr().add(j0 * n + j1), n, true),
                    (bp.add(j1), n),
                    1.0,
                    (bp.add(j0), n),
                );
            }
            // X[j0..j1] = L_blk⁻ᵀ B[j0..j1]
            gemm(
                (nb, nb, k),
                1.0,
                (li.as_ptr(), nb, true),
                (bp.add(j0), n),
                0.0,
                (xb.as_mut_ptr(), nb),
            );
        }
        unpack_rows(&xb, n, j0, b);
        j1 = j0;
    }
}

/// `C[i, j] += Σ_l A[i, l] A[j, l]` for the row-major `rows × k` matrix `a`, the lower
/// triangle `i ≥ j` of the column-major `rows × rows` matrix `C`, columns `j` in `cols` only,
/// `c` holding those columns (so that two threads can share the work). Blocks of 4 × 2 rows;
/// with AVX2 + FMA (chosen at run time) each block keeps eight 4-wide accumulators in
/// registers. No heap memory (unlike a packing GEMM), which keeps the online filter's step
/// allocation-free.
pub fn syrk_rows_lower(
    a: &[f64],
    rows: usize,
    k: usize,
    cols: std::ops::Range<usize>,
    c: &mut [f64],
) {
    assert!(a.len() >= rows * k && cols.end <= rows && c.len() >= cols.len() * rows);
    #[cfg(target_arch = "x86_64")]
    {
        // (eight lanes pay only for long rows: at k = 50 the 16 horizontal sums of a 4 × 4
        // block cost as much as its multiply-adds, and the rat's velocity E-step lost 12 %)
        if k >= AVX512_MIN_K && is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has the feature; the slices are in bounds (asserted above).
            unsafe { syrk_avx512(a, rows, k, cols, c) };
            return;
        }
        if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has the features; the slices are in bounds (asserted above).
            unsafe { syrk_avx2(a, rows, k, cols, c) };
            return;
        }
    }
    syrk_generic(a, rows, k, cols, c);
}

/// The shortest rows for which [`syrk_rows_lower`] takes the AVX-512 kernel.
const AVX512_MIN_K: usize = 128;

/// Portable [`syrk_rows_lower`]: one dot product per entry.
fn syrk_generic(a: &[f64], rows: usize, k: usize, cols: std::ops::Range<usize>, c: &mut [f64]) {
    let j0 = cols.start;
    for j in cols {
        let y = &a[j * k..(j + 1) * k];
        for i in j..rows {
            c[(j - j0) * rows + i] += dot(&a[i * k..(i + 1) * k], y);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn syrk_avx2(a: &[f64], rows: usize, k: usize, cols: std::ops::Range<usize>, c: &mut [f64]) {
    use std::arch::x86_64::*;
    #[inline(always)]
    unsafe fn hsum(v: __m256d) -> f64 {
        let lo = _mm256_castpd256_pd128(v);
        let hi = _mm256_extractf128_pd(v, 1);
        let s = _mm_add_pd(lo, hi);
        _mm_cvtsd_f64(_mm_add_sd(s, _mm_unpackhi_pd(s, s)))
    }
    /// The four-lane part of the dot products of rows `xs` with rows `ys` (`NX × NY`).
    #[inline(always)]
    unsafe fn block<const NX: usize, const NY: usize>(
        xs: [*const f64; NX],
        ys: [*const f64; NY],
        kc: usize,
    ) -> [[f64; NY]; NX] {
        let mut acc = [[_mm256_setzero_pd(); NY]; NX];
        let mut l = 0;
        while l < kc {
            let mut yv = [_mm256_setzero_pd(); NY];
            for (q, y) in ys.iter().enumerate() {
                yv[q] = _mm256_loadu_pd(y.add(l));
            }
            for (p, x) in xs.iter().enumerate() {
                let xv = _mm256_loadu_pd(x.add(l));
                for q in 0..NY {
                    acc[p][q] = _mm256_fmadd_pd(xv, yv[q], acc[p][q]);
                }
            }
            l += 4;
        }
        let mut out = [[0.0; NY]; NX];
        for p in 0..NX {
            for q in 0..NY {
                out[p][q] = hsum(acc[p][q]);
            }
        }
        out
    }
    let kc = k / 4 * 4;
    let tail =
        |i: usize, j: usize| -> f64 { (kc..k).map(|l| a[i * k + l] * a[j * k + l]).sum::<f64>() };
    let row = |i: usize| a.as_ptr().add(i * k);
    let j0 = cols.start;
    let mut j = cols.start;
    while j < cols.end {
        let nj = if j + 2 <= cols.end { 2 } else { 1 };
        // rows i ≥ j of columns j .. j + nj, in blocks of 4 rows
        let mut i = j;
        while i < rows {
            let ni = (rows - i).min(4);
            if ni == 4 && nj == 2 {
                let r = block::<4, 2>(
                    [row(i), row(i + 1), row(i + 2), row(i + 3)],
                    [row(j), row(j + 1)],
                    kc,
                );
                for p in 0..4 {
                    for q in 0..2 {
                        if i + p >= j + q {
                            c[(j + q - j0) * rows + i + p] += r[p][q] + tail(i + p, j + q);
                        }
                    }
                }
            } else {
                for p in 0..ni {
                    for q in 0..nj {
                        if i + p >= j + q {
                            let r = block::<1, 1>([row(i + p)], [row(j + q)], kc);
                            c[(j + q - j0) * rows + i + p] += r[0][0] + tail(i + p, j + q);
                        }
                    }
                }
            }
            i += 4;
        }
        j += nj;
    }
}

/// [`syrk_rows_lower`] with AVX-512: the blocks of [`syrk_avx2`] eight lanes wide, the last
/// `k mod 8` entries of each row by masked loads (no scalar tail).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn syrk_avx512(
    a: &[f64],
    rows: usize,
    k: usize,
    cols: std::ops::Range<usize>,
    c: &mut [f64],
) {
    use std::arch::x86_64::*;
    /// The dot products of rows `xs` with rows `ys` (`NX × NY`), each `k` long.
    #[inline(always)]
    unsafe fn block<const NX: usize, const NY: usize>(
        xs: [*const f64; NX],
        ys: [*const f64; NY],
        k: usize,
    ) -> [[f64; NY]; NX] {
        let mut acc = [[_mm512_setzero_pd(); NY]; NX];
        let kc = k / 8 * 8;
        let mut l = 0;
        while l < kc {
            let mut yv = [_mm512_setzero_pd(); NY];
            for (q, y) in ys.iter().enumerate() {
                yv[q] = _mm512_loadu_pd(y.add(l));
            }
            for (p, x) in xs.iter().enumerate() {
                let xv = _mm512_loadu_pd(x.add(l));
                for q in 0..NY {
                    acc[p][q] = _mm512_fmadd_pd(xv, yv[q], acc[p][q]);
                }
            }
            l += 8;
        }
        if kc < k {
            // lanes past the row's end are masked off (neither read nor counted)
            let m: __mmask8 = (1u8 << (k - kc)) - 1;
            let mut yv = [_mm512_setzero_pd(); NY];
            for (q, y) in ys.iter().enumerate() {
                yv[q] = _mm512_maskz_loadu_pd(m, y.add(kc));
            }
            for (p, x) in xs.iter().enumerate() {
                let xv = _mm512_maskz_loadu_pd(m, x.add(kc));
                for q in 0..NY {
                    acc[p][q] = _mm512_fmadd_pd(xv, yv[q], acc[p][q]);
                }
            }
        }
        let mut out = [[0.0; NY]; NX];
        for p in 0..NX {
            for q in 0..NY {
                out[p][q] = _mm512_reduce_add_pd(acc[p][q]);
            }
        }
        out
    }
    let row = |i: usize| a.as_ptr().add(i * k);
    let j0 = cols.start;
    let mut j = cols.start;
    // adds the block's entries on or below the diagonal to `c`
    let mut put = |i: usize, j: usize, r: &[f64], nq: usize| {
        for (e, v) in r.iter().enumerate() {
            let (p, q) = (e / nq, e % nq);
            if i + p >= j + q {
                c[(j + q - j0) * rows + i + p] += v;
            }
        }
    };
    while j < cols.end {
        // four columns at a time (each row block loaded once for the four), then two, one
        let nj = match cols.end - j {
            r if r >= 4 => 4,
            r if r >= 2 => 2,
            _ => 1,
        };
        // rows i ≥ j of columns j .. j + nj, in blocks of 4 rows
        let mut i = j;
        while i < rows {
            let ni = (rows - i).min(4);
            let xs = [
                row(i),
                row(i + ni.min(2) - 1),
                row(i + ni.min(3) - 1),
                row(i + ni - 1),
            ];
            if ni == 4 && nj == 4 {
                let r = block::<4, 4>(xs, [row(j), row(j + 1), row(j + 2), row(j + 3)], k);
                put(i, j, r.as_flattened(), 4);
            } else if ni == 4 && nj == 2 {
                let r = block::<4, 2>(xs, [row(j), row(j + 1)], k);
                put(i, j, r.as_flattened(), 2);
            } else {
                for p in 0..ni {
                    for q in 0..nj {
                        if i + p >= j + q {
                            let r = block::<1, 1>([row(i + p)], [row(j + q)], k);
                            put(i + p, j + q, &r[0], 1);
                        }
                    }
                }
            }
            i += 4;
        }
        j += nj;
    }
}

/// Dot product with eight independent accumulators (vectorises without reassociation flags).
#[inline(always)]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 8];
    let ca = a.chunks_exact(8);
    let cb = b.chunks_exact(8);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    let mut s = ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

/// The four columns of length `n` of `quad` (`4n` values).
#[inline(always)]
fn four_columns(quad: &mut [f64], n: usize) -> [&mut [f64]; 4] {
    let (c0, rest) = quad.split_at_mut(n);
    let (c1, rest) = rest.split_at_mut(n);
    let (c2, c3) = rest.split_at_mut(n);
    [c0, c1, c2, c3]
}

/// [`dot`] of `a` with four vectors at once (each `a` element loaded once), every result
/// summed in `dot`'s order: the same four values bit for bit.
#[inline(always)]
pub fn dot4(a: &[f64], bs: [&[f64]; 4]) -> [f64; 4] {
    let n = bs.iter().fold(a.len(), |m, b| m.min(b.len()));
    let a = &a[..n];
    let bs = bs.map(|b| &b[..n]);
    let mut acc = [[0.0f64; 8]; 4];
    let full = n - n % 8;
    let mut l = 0;
    while l < full {
        let x = &a[l..l + 8];
        for (k, b) in bs.iter().enumerate() {
            let y = &b[l..l + 8];
            for i in 0..8 {
                acc[k][i] += x[i] * y[i];
            }
        }
        l += 8;
    }
    let mut out = [0.0; 4];
    for (k, b) in bs.iter().enumerate() {
        let c = &acc[k];
        let mut s = ((c[0] + c[4]) + (c[1] + c[5])) + ((c[2] + c[6]) + (c[3] + c[7]));
        for (x, y) in a[full..].iter().zip(&b[full..]) {
            s += x * y;
        }
        out[k] = s;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    /// The factor one column at a time, each entry updated in column order: what
    /// [`cholesky_in_place`] must give bit for bit.
    fn cholesky_columns(a: &mut [f64], n: usize) -> bool {
        for j in 0..n {
            for i in j..n {
                let mut x = a[j * n + i];
                for p in 0..j {
                    x -= a[p * n + j] * a[p * n + i];
                }
                a[j * n + i] = x;
            }
            let d = a[j * n + j];
            if !(d > 0.0 && d.is_finite()) {
                return false;
            }
            let d = d.sqrt();
            a[j * n + j] = d;
            for i in j + 1..n {
                a[j * n + i] *= 1.0 / d;
            }
            for i in 0..j {
                a[j * n + i] = 0.0;
            }
        }
        true
    }

    #[test]
    fn the_tiled_cholesky_is_the_column_one_bit_for_bit() {
        let sizes = (1usize..=41).chain([87, 100, 173, 174, 175]);
        for n in sizes {
            let a = DMatrix::from_fn(n, n, |r, c| (((r * 7 + c * 13) % 11) as f64 - 5.0) * 0.31);
            let spd = &a * a.transpose() + DMatrix::identity(n, n) * 0.5;
            let mut want = spd.clone();
            assert!(cholesky_columns(want.as_mut_slice(), n));
            let mut got = spd.clone();
            // the upper triangle is not read
            for c in 0..n {
                for r in 0..c {
                    got[(r, c)] = f64::NAN;
                }
            }
            type Factor = fn(&mut [f64], usize) -> bool;
            let mut paths: Vec<(&str, Factor)> = vec![
                ("dispatched", cholesky_in_place),
                ("baseline", cholesky_tiled::<8>),
                ("16-row tiles", cholesky_tiled::<16>),
            ];
            #[cfg(target_arch = "x86_64")]
            if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                // SAFETY: the CPU has the features
                paths.push(("avx2", |a, n| unsafe { cholesky_avx2(a, n) }));
            }
            for (name, path) in paths {
                let mut mine = got.clone();
                assert!(path(mine.as_mut_slice(), n));
                for (g, w) in mine.iter().zip(want.iter()) {
                    assert_eq!(g.to_bits(), w.to_bits(), "n = {n}, {name}");
                }
            }
        }
        // a matrix that is not positive definite fails in any block of four columns
        for (n, bad) in [(9usize, 0usize), (9, 5), (30, 17), (30, 29)] {
            let mut m = DMatrix::<f64>::identity(n, n);
            m[(bad, bad)] = -1.0;
            assert!(
                !cholesky_in_place(m.as_mut_slice(), n),
                "n = {n}, bad = {bad}"
            );
        }
    }

    #[test]
    fn kernels_match_nalgebra() {
        for n in [1usize, 2, 7, 33, 100] {
            let a = DMatrix::from_fn(n, n, |r, c| ((r * 7 + c * 13) % 11) as f64 - 5.0);
            let spd = &a * a.transpose() + DMatrix::identity(n, n) * 0.5;
            let want = spd.clone().cholesky().unwrap().unpack();
            let mut l = spd.clone();
            assert!(cholesky_in_place(l.as_mut_slice(), n));
            assert!(
                (&l - &want).abs().max() < 1e-9 * want.abs().max(),
                "n = {n}"
            );
            let k = 3;
            let b = DMatrix::from_fn(n, k, |r, c| ((r * 5 + c * 3) % 7) as f64 - 3.0);
            let mut x = b.clone();
            lower_solve_in_place(l.as_slice(), n, x.as_mut_slice());
            assert!((&l * &x - &b).abs().max() < 1e-8, "n = {n}");
            let mut y = b.clone();
            lower_tr_solve_in_place(l.as_slice(), n, y.as_mut_slice());
            assert!((l.transpose() * &y - &b).abs().max() < 1e-8, "n = {n}");
        }
        // the Gram kernel: lower triangle of A Aᵀ, split over two column ranges
        for (rows, k) in [
            (1usize, 1usize),
            (7, 13),
            (100, 301),
            (9, 4),
            (10, 16),
            (6, 8),
        ] {
            let a: Vec<f64> = (0..rows * k)
                .map(|i| ((i * 37 % 23) as f64) * 0.1 - 1.1)
                .collect();
            let mut c = vec![0.5; rows * rows];
            let half = rows / 2;
            let (c0, c1) = c.split_at_mut(half * rows);
            syrk_rows_lower(&a, rows, k, 0..half, c0);
            syrk_rows_lower(&a, rows, k, half..rows, c1);
            // the portable path gives the same
            let mut g = vec![0.5; rows * rows];
            syrk_generic(&a, rows, k, 0..rows, &mut g);
            assert!(c
                .iter()
                .zip(&g)
                .all(|(x, y)| (x - y).abs() < 1e-9 * (1.0 + y.abs())));
            // and each SIMD path the CPU has (the dispatch takes only the widest)
            #[cfg(target_arch = "x86_64")]
            {
                type Kernel = unsafe fn(&[f64], usize, usize, std::ops::Range<usize>, &mut [f64]);
                let mut paths: Vec<(&str, Kernel)> = Vec::new();
                if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
                    paths.push(("avx2", syrk_avx2));
                }
                if is_x86_feature_detected!("avx512f") {
                    paths.push(("avx512", syrk_avx512));
                }
                for (name, kernel) in paths {
                    let mut w = vec![0.5; rows * rows];
                    // SAFETY: the CPU has the kernel's features; the sizes are consistent.
                    unsafe { kernel(&a, rows, k, 0..rows, &mut w) };
                    assert!(
                        w.iter()
                            .zip(&g)
                            .all(|(x, y)| (x - y).abs() < 1e-9 * (1.0 + y.abs())),
                        "{name} {rows}x{k}"
                    );
                }
            }
            for j in 0..rows {
                for i in 0..rows {
                    let want: f64 = (0..k).map(|l| a[i * k + l] * a[j * k + l]).sum::<f64>() + 0.5;
                    let got = c[j * rows + i];
                    if i >= j {
                        assert!(
                            (got - want).abs() < 1e-9 * (1.0 + want.abs()),
                            "{rows}x{k} ({i},{j})"
                        );
                    } else {
                        assert_eq!(got, 0.5, "upper triangle untouched");
                    }
                }
            }
        }
        let mut neg = [1.0, 0.0, 0.0, -1.0];
        assert!(!cholesky_in_place(&mut neg, 2));
        let mut nan = [f64::NAN, 0.0, 0.0, 1.0];
        assert!(!cholesky_in_place(&mut nan, 1 + 1));
        // four columns at a time give what one at a time gives, bit for bit
        for n in [1usize, 3, 9, 37] {
            let a = DMatrix::from_fn(n, n, |r, c| ((r * 7 + c * 13) % 11) as f64 - 5.0);
            let spd = &a * a.transpose() + DMatrix::identity(n, n) * 0.5;
            let mut l = spd.clone();
            assert!(cholesky_in_place(l.as_mut_slice(), n));
            let b = DMatrix::from_fn(n, 9, |r, c| ((r * 5 + c * 3) % 7) as f64 - 3.1);
            for solve in [lower_solve_in_place, lower_tr_solve_in_place] {
                let mut all = b.clone();
                solve(l.as_slice(), n, all.as_mut_slice());
                for c in 0..9 {
                    let mut one = b.column(c).into_owned();
                    solve(l.as_slice(), n, one.as_mut_slice());
                    assert_eq!(all.column(c), one.column(0), "n = {n}, column {c}");
                }
            }
            let v: Vec<Vec<f64>> = (0..4)
                .map(|k| {
                    (0..n)
                        .map(|i| ((i * 3 + k) % 5) as f64 * 0.37 - 0.6)
                        .collect()
                })
                .collect();
            let d = dot4(b.column(0).as_slice(), [&v[0], &v[1], &v[2], &v[3]]);
            for k in 0..4 {
                assert_eq!(d[k], dot(b.column(0).as_slice(), &v[k]));
            }
        }
        // the blocked solves equal the column kernels up to rounding (sizes around the block)
        for (n, k) in [
            (33usize, 5usize),
            (64, 4),
            (100, 100),
            (100, 3),
            (87, 87),
            (130, 9),
        ] {
            let a = DMatrix::from_fn(n, n, |r, c| ((r * 7 + c * 13) % 11) as f64 - 5.0);
            let spd = &a * a.transpose() + DMatrix::identity(n, n) * (n as f64);
            let mut l = spd.clone();
            assert!(cholesky_in_place(l.as_mut_slice(), n));
            let b = DMatrix::from_fn(n, k, |r, c| ((r * 5 + c * 3) % 7) as f64 - 3.1);
            type Solve = fn(&[f64], usize, &mut [f64]);
            let pairs: [(Solve, Solve); 2] = [
                (lower_solve_blocked, lower_solve_in_place),
                (lower_tr_solve_blocked, lower_tr_solve_in_place),
            ];
            for (blocked, column) in pairs {
                let mut x = b.clone();
                blocked(l.as_slice(), n, x.as_mut_slice());
                let mut y = b.clone();
                column(l.as_slice(), n, y.as_mut_slice());
                let scale = y.abs().max();
                assert!((&x - &y).abs().max() < 1e-12 * scale, "n = {n}, k = {k}");
            }
            let mut x = b.clone();
            lower_solve_blocked(l.as_slice(), n, x.as_mut_slice());
            assert!((&l * &x - &b).abs().max() < 1e-9, "n = {n}");
            let mut y = b.clone();
            lower_tr_solve_blocked(l.as_slice(), n, y.as_mut_slice());
            assert!((l.transpose() * &y - &b).abs().max() < 1e-9, "n = {n}");
        }
        // empty systems are no-ops
        let mut empty: [f64; 0] = [];
        lower_solve_in_place(&[], 0, &mut empty);
        lower_tr_solve_in_place(&[], 0, &mut empty);
        assert!(cholesky_in_place(&mut empty, 0));
    }
}
