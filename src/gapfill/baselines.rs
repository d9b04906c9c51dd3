//! Baselines of B&L sec. 4 (Table 1): linear and cubic-spline interpolation, random-walk and
//! constant-velocity RTS smoothing per coordinate (Wu & Boulanger 2011), and mSVD iterative
//! low-rank imputation (Srebro & Jaakkola 2003). Coordinates are independent and run in
//! parallel (rayon).

use super::linalg::sorted_eigen;
use super::subspace::choose_dim;
use super::{Filled, Info, Options, Seq};
use crate::error::Result;
use nalgebra::DMatrix;
use rayon::prelude::*;

/// Applies `f(times, values) -> filled column` to every coordinate and reassembles the
/// row-major `T × D` result. `times`/`values` are the observed samples.
fn per_column<F>(seq: &Seq<'_>, f: F) -> Vec<f64>
where
    F: Fn(&[f64], &[Option<f64>]) -> Vec<f64> + Sync,
{
    let (t, d) = (seq.t, seq.d);
    let cols: Vec<Vec<f64>> = (0..d)
        .into_par_iter()
        .map(|j| {
            let col: Vec<Option<f64>> = (0..t)
                .map(|i| {
                    let v = seq.at(i, j);
                    (!v.is_nan()).then_some(v)
                })
                .collect();
            let times: Vec<f64> = (0..t).map(|i| i as f64).collect();
            f(&times, &col)
        })
        .collect();
    let mut out = vec![0.0; t * d];
    for (j, c) in cols.iter().enumerate() {
        for (i, v) in c.iter().enumerate() {
            out[i * d + j] = *v;
        }
    }
    out
}

fn observed(col: &[Option<f64>]) -> (Vec<f64>, Vec<f64>) {
    col.iter()
        .enumerate()
        .filter_map(|(i, v)| v.map(|v| (i as f64, v)))
        .unzip()
}

/// Linear interpolation per coordinate; constant extrapolation before the first and after the
/// last observation. Observed values are returned unchanged.
pub fn linear(seq: &Seq<'_>) -> Vec<f64> {
    per_column(seq, |_, col| {
        let (ts, vs) = observed(col);
        let mut out = Vec::with_capacity(col.len());
        let mut k = 0;
        for (i, c) in col.iter().enumerate() {
            if let Some(v) = *c {
                out.push(v);
                continue;
            }
            let x = i as f64;
            while k + 1 < ts.len() && ts[k + 1] < x {
                k += 1;
            }
            out.push(if x < ts[0] {
                vs[0]
            } else if x > ts[ts.len() - 1] {
                vs[vs.len() - 1]
            } else {
                let w = (x - ts[k]) / (ts[k + 1] - ts[k]);
                (1.0 - w) * vs[k] + w * vs[k + 1]
            });
        }
        out
    })
}

/// Natural cubic spline through all observed samples of each coordinate (second derivative 0
/// at the first and last observation; constant extrapolation beyond them; linear with 2
/// samples, constant with 1).
pub fn spline(seq: &Seq<'_>) -> Vec<f64> {
    per_column(seq, |_, col| {
        let (ts, vs) = observed(col);
        let sp = Spline::new(ts, vs);
        col.iter()
            .enumerate()
            .map(|(i, c)| c.unwrap_or_else(|| sp.eval(i as f64)))
            .collect()
    })
}

/// The natural cubic spline through the observed samples `(ts, vs)` of one coordinate
/// (`ts` increasing; at least one sample).
pub struct Spline {
    ts: Vec<f64>,
    vs: Vec<f64>,
    m2: Vec<f64>,
}

impl Spline {
    /// Fits the spline (one tridiagonal solve).
    pub fn new(ts: Vec<f64>, vs: Vec<f64>) -> Self {
        let m2 = natural_second_derivatives(&ts, &vs);
        Self { ts, vs, m2 }
    }

    /// The spline through the observed samples of coordinate `j` of `seq`.
    pub fn of_column(seq: &Seq<'_>, j: usize) -> Self {
        let (ts, vs) = (0..seq.t)
            .map(|i| (i as f64, seq.at(i, j)))
            .filter(|(_, v)| !v.is_nan())
            .unzip();
        Self::new(ts, vs)
    }

    /// Value at `x` (constant beyond the first and last sample).
    pub fn eval(&self, x: f64) -> f64 {
        let (ts, vs, n) = (&self.ts, &self.vs, self.ts.len());
        if n == 1 || x <= ts[0] {
            return vs[0];
        }
        if x >= ts[n - 1] {
            return vs[n - 1];
        }
        // ts[k] < x <= ts[k + 1]
        let k = ts.partition_point(|&t| t < x) - 1;
        let h = ts[k + 1] - ts[k];
        let a = (ts[k + 1] - x) / h;
        let b = (x - ts[k]) / h;
        a * vs[k]
            + b * vs[k + 1]
            + ((a * a * a - a) * self.m2[k] + (b * b * b - b) * self.m2[k + 1]) * h * h / 6.0
    }
}

/// Second derivatives of the natural cubic spline through `(ts, vs)` (tridiagonal solve).
fn natural_second_derivatives(ts: &[f64], vs: &[f64]) -> Vec<f64> {
    let n = ts.len();
    let mut m = vec![0.0; n];
    if n < 3 {
        return m;
    }
    // Thomas algorithm on rows 1..n-1.
    let mut c = vec![0.0; n];
    let mut r = vec![0.0; n];
    for i in 1..n - 1 {
        let h0 = ts[i] - ts[i - 1];
        let h1 = ts[i + 1] - ts[i];
        let rhs = 6.0 * ((vs[i + 1] - vs[i]) / h1 - (vs[i] - vs[i - 1]) / h0);
        let diag = 2.0 * (h0 + h1) - h0 * c[i - 1];
        c[i] = h1 / diag;
        r[i] = (rhs - h0 * r[i - 1]) / diag;
    }
    for i in (1..n - 1).rev() {
        m[i] = r[i] - c[i] * m[i + 1];
    }
    m
}

/// Mean squared difference of observed samples `lag` frames apart (`order` = 1: first
/// differences, 2: second differences), floored.
fn diff_power(col: &[Option<f64>], order: usize) -> f64 {
    let mut s = 0.0;
    let mut n = 0usize;
    for i in order..col.len() {
        let v = match order {
            1 => col[i].zip(col[i - 1]).map(|(a, b)| a - b),
            _ => match (col[i], col[i - 1], col[i - 2]) {
                (Some(a), Some(b), Some(c)) => Some(a - 2.0 * b + c),
                _ => None,
            },
        };
        if let Some(v) = v {
            s += v * v;
            n += 1;
        }
    }
    if n == 0 {
        1.0
    } else {
        (s / n as f64).max(1e-9)
    }
}

/// Random-walk RTS smoother per coordinate (B&L sec. 2.1 with `F = I`; per-marker state as
/// Wu & Boulanger): q = mean squared frame difference of the coordinate, R = r (default 1e-3).
pub fn random_walk(seq: &Seq<'_>, r: Option<f64>, want_std: bool) -> Result<Filled> {
    let r = r.unwrap_or(1e-3);
    let both = per_column_pair(seq, |col| {
        let q = diff_power(col, 1);
        scalar_rts(col, q, r)
    });
    Ok(assemble(seq, both, want_std))
}

fn scalar_rts(col: &[Option<f64>], q: f64, r: f64) -> (Vec<f64>, Vec<f64>) {
    let t = col.len();
    let first = col.iter().flatten().next().copied().unwrap_or(0.0);
    let (mut m, mut p) = (first, 1e12);
    let mut mf = vec![0.0; t];
    let mut pf = vec![0.0; t];
    for i in 0..t {
        if i > 0 {
            p += q;
        }
        if let Some(z) = col[i] {
            let k = p / (p + r);
            m += k * (z - m);
            p *= 1.0 - k;
        }
        mf[i] = m;
        pf[i] = p;
    }
    let mut ms = mf.clone();
    let mut ps = pf.clone();
    for i in (0..t.saturating_sub(1)).rev() {
        let c = pf[i] / (pf[i] + q);
        ms[i] = mf[i] + c * (ms[i + 1] - mf[i]);
        ps[i] = pf[i] + c * c * (ps[i + 1] - (pf[i] + q));
    }
    (ms, ps)
}

/// Constant-velocity RTS smoother per coordinate (Wu & Boulanger 2011): state (position,
/// velocity), white-noise acceleration with variance = mean squared second difference,
/// R = r (default 1e-3).
pub fn constant_velocity(seq: &Seq<'_>, r: Option<f64>, want_std: bool) -> Result<Filled> {
    let r = r.unwrap_or(1e-3);
    let both = per_column_pair(seq, |col| {
        let qa = diff_power(col, 2);
        cv_rts(col, qa, r)
    });
    Ok(assemble(seq, both, want_std))
}

type M2 = [[f64; 2]; 2];

fn mm(a: &M2, b: &M2) -> M2 {
    let mut o = [[0.0; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            o[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j];
        }
    }
    o
}
fn tr(a: &M2) -> M2 {
    [[a[0][0], a[1][0]], [a[0][1], a[1][1]]]
}
fn inv2(a: &M2) -> M2 {
    let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    [
        [a[1][1] / det, -a[0][1] / det],
        [-a[1][0] / det, a[0][0] / det],
    ]
}

fn cv_rts(col: &[Option<f64>], qa: f64, r: f64) -> (Vec<f64>, Vec<f64>) {
    let t = col.len();
    let f: M2 = [[1.0, 1.0], [0.0, 1.0]];
    let q: M2 = [[qa / 4.0, qa / 2.0], [qa / 2.0, qa]];
    let first = col.iter().flatten().next().copied().unwrap_or(0.0);
    let mut m = [first, 0.0];
    let mut p: M2 = [[1e12, 0.0], [0.0, 1e12]];
    let mut mf = vec![[0.0; 2]; t];
    let mut pf = vec![[[0.0; 2]; 2]; t];
    let mut pp = vec![[[0.0; 2]; 2]; t]; // predicted covariances
    for i in 0..t {
        if i > 0 {
            m = [m[0] + m[1], m[1]];
            let fp = mm(&mm(&f, &p), &tr(&f));
            p = [
                [fp[0][0] + q[0][0], fp[0][1] + q[0][1]],
                [fp[1][0] + q[1][0], fp[1][1] + q[1][1]],
            ];
        }
        pp[i] = p;
        if let Some(z) = col[i] {
            let s = p[0][0] + r;
            let k = [p[0][0] / s, p[1][0] / s];
            let e = z - m[0];
            m = [m[0] + k[0] * e, m[1] + k[1] * e];
            p = [
                [p[0][0] - k[0] * p[0][0], p[0][1] - k[0] * p[0][1]],
                [p[1][0] - k[1] * p[0][0], p[1][1] - k[1] * p[0][1]],
            ];
        }
        mf[i] = m;
        pf[i] = p;
    }
    let mut ms = mf.clone();
    let mut ps = pf.clone();
    for i in (0..t.saturating_sub(1)).rev() {
        let c = mm(&mm(&pf[i], &tr(&f)), &inv2(&pp[i + 1]));
        let pred = [mf[i][0] + mf[i][1], mf[i][1]];
        let dm = [ms[i + 1][0] - pred[0], ms[i + 1][1] - pred[1]];
        ms[i] = [
            mf[i][0] + c[0][0] * dm[0] + c[0][1] * dm[1],
            mf[i][1] + c[1][0] * dm[0] + c[1][1] * dm[1],
        ];
        let dp = [
            [
                ps[i + 1][0][0] - pp[i + 1][0][0],
                ps[i + 1][0][1] - pp[i + 1][0][1],
            ],
            [
                ps[i + 1][1][0] - pp[i + 1][1][0],
                ps[i + 1][1][1] - pp[i + 1][1][1],
            ],
        ];
        let corr = mm(&mm(&c, &dp), &tr(&c));
        ps[i] = [
            [pf[i][0][0] + corr[0][0], pf[i][0][1] + corr[0][1]],
            [pf[i][1][0] + corr[1][0], pf[i][1][1] + corr[1][1]],
        ];
    }
    (
        ms.iter().map(|v| v[0]).collect(),
        ps.iter().map(|v| v[0][0]).collect(),
    )
}

fn per_column_pair<F>(seq: &Seq<'_>, f: F) -> Vec<(Vec<f64>, Vec<f64>)>
where
    F: Fn(&[Option<f64>]) -> (Vec<f64>, Vec<f64>) + Sync,
{
    (0..seq.d)
        .into_par_iter()
        .map(|j| {
            let col: Vec<Option<f64>> = (0..seq.t)
                .map(|i| {
                    let v = seq.at(i, j);
                    (!v.is_nan()).then_some(v)
                })
                .collect();
            f(&col)
        })
        .collect()
}

fn assemble(seq: &Seq<'_>, cols: Vec<(Vec<f64>, Vec<f64>)>, want_std: bool) -> Filled {
    let (t, d) = (seq.t, seq.d);
    let mut x = vec![0.0; t * d];
    let mut s = vec![0.0; t * d];
    for (j, (m, p)) in cols.iter().enumerate() {
        for i in 0..t {
            x[i * d + j] = m[i];
            s[i * d + j] = p[i].max(0.0).sqrt();
        }
    }
    Filled {
        x,
        std: want_std.then_some(s),
        info: Info::default(),
    }
}

/// mSVD (Srebro & Jaakkola 2003, as in B&L sec. 2.2): start from the spline fill, then repeat
/// {mean-shift, SVD, keep d̂ components (γ, criterion of `opts`), replace the missing values by
/// the rank-d̂ reconstruction} until the missing values change by less than 1e-6 of the data
/// scale (at most 100 iterations).
pub fn msvd(seq: &Seq<'_>, opts: &Options) -> Result<Filled> {
    let (t, d) = (seq.t, seq.d);
    let mut x = spline(seq);
    let missing: Vec<usize> = (0..t * d).filter(|&i| seq.x[i].is_nan()).collect();
    let scale = seq
        .x
        .iter()
        .filter(|v| !v.is_nan())
        .fold(0.0_f64, |a, v| a.max(v.abs()))
        .max(1e-12);
    let mut info = Info::default();
    for it in 0..100 {
        let mut mean = vec![0.0; d];
        for row in x.chunks_exact(d) {
            for (m, v) in mean.iter_mut().zip(row) {
                *m += v;
            }
        }
        mean.iter_mut().for_each(|m| *m /= t as f64);
        let centred: Vec<f64> = x
            .chunks_exact(d)
            .flat_map(|row| row.iter().zip(&mean).map(|(v, m)| v - m))
            .collect();
        let at = DMatrix::from_column_slice(d, t, &centred);
        let scatter = &at * at.transpose() / (t as f64 - 1.0).max(1.0);
        let (vals, vecs) = sorted_eigen(scatter);
        let k = match opts.dim {
            Some(k) => k.min(d),
            None => choose_dim(&vals, opts.criterion, opts.gamma, d.min(t - 1)),
        };
        let v = vecs.columns(0, k).into_owned();
        let rec = &v * (v.transpose() * &at); // D × T, column-major = row-major T × D
        let mut change = 0.0_f64;
        for &i in &missing {
            let (fr, j) = (i / d, i % d);
            let new = rec[(j, fr)] + mean[j];
            change = change.max((new - x[i]).abs());
            x[i] = new;
        }
        info.dim = k;
        info.em_iters = it + 1;
        if change < 1e-6 * scale {
            break;
        }
    }
    Ok(Filled { x, std: None, info })
}
