//! Column-oriented dense kernels shared by the tracker and the gap filler: Cholesky
//! factorisation and triangular solves of small column-major matrices (`n` ≲ 200), compiled
//! twice and chosen at run time — for AVX2 + FMA where the CPU has them (the inner loops
//! are contiguous axpys that then vectorise four wide), else for the baseline target.
//!
//! At these sizes they beat nalgebra's generic loops (which the baseline target compiles
//! for SSE2) by 2-4× (`benches/README.md`); blocked factorisations are not faster here.

/// Defines `fn $name(...)` whose `$body` runs compiled for AVX2 + FMA when the CPU has them
/// (runtime dispatch), else for the baseline target.
macro_rules! dispatch {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),*) -> $ret:ty $body:block) => {
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

dispatch!(
    /// In-place lower Cholesky factor of the column-major `n × n` matrix `a` (left-looking,
    /// column axpys; only the lower triangle is read, the upper one is zeroed); `false` if `a` is
    /// not positive definite.
    pub fn cholesky_in_place(a: &mut [f64], n: usize) -> bool {
        for j in 0..n {
            let (done, rest) = a.split_at_mut(j * n);
            let cj = &mut rest[..n];
            for p in 0..j {
                let cp = &done[p * n..(p + 1) * n];
                let f = cp[j];
                if f != 0.0 {
                    for (x, y) in cj[j..].iter_mut().zip(&cp[j..]) {
                        *x -= f * y;
                    }
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
        true
    }
);

dispatch!(
    /// Solves `L X = B` in place for the column-major lower-triangular `n × n` matrix `l` (non-zero
    /// diagonal) and the column-major `n × k` matrix `b` (`k = b.len() / n`): forward substitution
    /// column by column, with contiguous axpys down the columns of `L`.
    pub fn lower_solve_in_place(l: &[f64], n: usize, b: &mut [f64]) -> () {
        for col in b.chunks_exact_mut(n) {
            for j in 0..n {
                let lj = &l[j * n..(j + 1) * n];
                let v = col[j] / lj[j];
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
    /// Solves `Lᵀ X = B` in place for `l`, `b` as in [`lower_solve_in_place`] (back
    /// substitution; row `r` of `Lᵀ` is column `r` of `L`, so each step is a contiguous dot).
    pub fn lower_tr_solve_in_place(l: &[f64], n: usize, b: &mut [f64]) -> () {
        for col in b.chunks_exact_mut(n) {
            for r in (0..n).rev() {
                let lr = &l[r * n..(r + 1) * n];
                let s = dot(&lr[r + 1..], &col[r + 1..]);
                col[r] = (col[r] - s) / lr[r];
            }
        }
    }
);

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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

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
        let mut neg = [1.0, 0.0, 0.0, -1.0];
        assert!(!cholesky_in_place(&mut neg, 2));
        let mut nan = [f64::NAN, 0.0, 0.0, 1.0];
        assert!(!cholesky_in_place(&mut nan, 1 + 1));
    }
}
