//! The low-dimensional method end to end: subspace (from complete frames, or iterated from
//! imputed frames), noise learning, smoothing, back-projection, border-residual correction and
//! the automatic spline / smoother combination.

use super::baselines::{self, Spline};
use super::lowrank;
use super::smoother::{self, Model, Patterns};
use super::subspace::{self, Subspace};
use super::{all_gaps, Combine, Filled, Info, Method, Options, Seq};
use crate::error::{AcmError, Result};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

/// Fills `seq` with [`Method::LowDim`] or [`Method::LowDimPaper`].
pub fn fill_lowdim(seq: &Seq<'_>, opts: &Options) -> Result<Filled> {
    let (d, t) = (seq.d, seq.t);
    let complete = seq.complete_frames();
    let paper = opts.method == Method::LowDimPaper;
    // Default: as many complete frames as markers (D / 3). The earlier 3 × markers sent 85_02
    // (99-161 complete frames of 810, 41 markers) to impute–SVD–smooth on one of five gapped
    // copies, which with the spline on short gaps raised the pooled mean from 34.4 to 49.7 mm.
    let min_complete = if opts.min_complete == 0 {
        d.div_ceil(3).max(10)
    } else {
        opts.min_complete
    };
    let mut info = Info {
        complete_frames: complete.len(),
        ..Info::default()
    };
    // The spline threshold is calibrated with the final model.
    let calibrate = opts.combine == Combine::Auto && opts.short_gap.is_none();
    let Run {
        mut y,
        std,
        short_gap,
    } = if paper || complete.len() >= min_complete {
        if complete.len() < 2 {
            return Err(AcmError::Invalid(format!(
                "the published method learns its subspace from complete frames and found {} \
                 (needs >= 2); use method 'lowdim', which imputes and iterates",
                complete.len()
            )));
        }
        let sub = subspace::fit(seq.x, d, &complete, opts.criterion, opts.gamma, opts.dim)?;
        let q = if paper || opts.paper_q {
            subspace::q_paper(seq.x, d, &complete, &sub)
        } else {
            let pairs: Vec<(usize, usize)> = complete
                .windows(2)
                .filter(|w| w[1] == w[0] + 1)
                .map(|w| (w[0], w[1]))
                .collect();
            if pairs.is_empty() {
                // No consecutive complete frames: estimate Q on an interpolated copy.
                let lin = baselines::linear(seq);
                let all: Vec<(usize, usize)> = (1..t).map(|i| (i - 1, i)).collect();
                subspace::q_from_pairs(&lin, d, &all, &sub)
            } else {
                subspace::q_from_pairs(seq.x, d, &pairs, &sub)
            }
        };
        run(seq, &sub, q, opts, paper, calibrate, &mut info)?
    } else {
        // Beyond the paper (a): too few complete frames. Impute (linear interpolation), learn
        // the subspace from all frames, smooth, and repeat with the smoothed fill.
        info.iterated_subspace = true;
        let mut cur = baselines::linear(seq);
        let all_rows: Vec<usize> = (0..t).collect();
        let all_pairs: Vec<(usize, usize)> = (1..t).map(|i| (i - 1, i)).collect();
        let rounds = opts.subspace_iters.max(1);
        let mut last = None;
        for round in 0..rounds {
            let sub = subspace::fit(&cur, d, &all_rows, opts.criterion, opts.gamma, opts.dim)?;
            let q = if opts.paper_q {
                subspace::q_paper(&cur, d, &all_rows, &sub)
            } else {
                subspace::q_from_pairs(&cur, d, &all_pairs, &sub)
            };
            let mut o = opts.clone();
            let final_round = round + 1 == rounds;
            o.want_std = opts.want_std && final_round;
            let out = run(seq, &sub, q, &o, false, calibrate && final_round, &mut info)?;
            cur = out.y.clone();
            for (c, v) in cur.iter_mut().zip(seq.x) {
                if !v.is_nan() {
                    *c = *v;
                }
            }
            last = Some(out);
        }
        last.expect("at least one round")
    };
    if opts.combine != Combine::None {
        let gaps = all_gaps(seq);
        carry_residuals(seq, &gaps, &mut y);
        if opts.combine == Combine::Auto {
            let l = opts.short_gap.or(short_gap).unwrap_or(0);
            info.short_gap = l;
            splice_short_gaps(seq, &gaps, &mut y, l);
        }
    }
    Ok(Filled { x: y, std, info })
}

/// What [`run`] returns.
struct Run {
    /// The back-projected smoothed sequence, row-major T × D.
    y: Vec<f64>,
    /// Predictive standard deviations, if requested.
    std: Option<Vec<f64>>,
    /// The calibrated spline threshold, if requested.
    short_gap: Option<usize>,
}

/// Builds the model, learns the noise (EM) and smooths: returns the back-projection and,
/// if requested, the predictive standard deviations and (`calibrate`) the spline threshold of
/// [`calibrate_short_gap`] for the learned model.
fn run(
    seq: &Seq<'_>,
    sub: &Subspace,
    q: DMatrix<f64>,
    opts: &Options,
    paper: bool,
    calibrate: bool,
    info: &mut Info,
) -> Result<Run> {
    let k = sub.dim();
    let r0 = opts.r.unwrap_or_else(|| {
        if paper {
            1e-3
        } else {
            sub.residual_variance().max(1e-6)
        }
    });
    let p0 = if paper {
        // The authors' code: 1e12·I (Algorithm 1 prints randn(d, d), not a covariance).
        DMatrix::identity(k, k) * 1e12
    } else {
        // The prior of the subspace coordinates: their training covariance.
        DMatrix::from_diagonal(&DVector::from_iterator(
            k,
            sub.eigvals[..k].iter().map(|v| v.max(1e-9)),
        ))
    };
    let mut model = Model {
        v: sub.rows(),
        mean: sub.mean.clone(),
        q,
        r: r0,
        m0: DVector::zeros(k),
        p0,
    };
    if !paper && opts.em_iters > 0 {
        // EM on a centred block of at most EM_FRAMES frames: the noise parameters are global,
        // a few thousand frames determine them, and long sequences stay fast.
        let (a, b) = em_block(seq.t);
        let block = &seq.x[a * seq.d..b * seq.d];
        let bp = Patterns::new(block, seq.d);
        info.em_iters = smoother::em(
            block,
            &mut model,
            &bp,
            opts.em_iters,
            opts.r.is_none(),
            opts.memo_tol,
        )?;
    }
    info.dim = k;
    info.r = model.r;
    info.q_trace = model.q.trace();
    let (y, std) = smooth_with(seq, &model, opts, info)?;
    // (Sequential: run alongside the smoothing with rayon::join it was slower on 2 cores,
    // 25,000 × 47 frames 1.14 vs 1.05 s; both are parallel already.)
    let short_gap = calibrate
        .then(|| calibrate_short_gap(seq, opts, &model))
        .transpose()?;
    Ok(Run { y, std, short_gap })
}

/// Smooths `seq` with a fixed `model` (no learning) and back-projects (Algorithm 1, RTS part
/// and last loop): the smoothed sequence and, if `opts.want_std`, the predictive standard
/// deviations. With `opts.window`, window by window ([`smooth_windows`]).
fn smooth_with(
    seq: &Seq<'_>,
    model: &Model,
    opts: &Options,
    info: &mut Info,
) -> Result<(Vec<f64>, Option<Vec<f64>>)> {
    match opts.window {
        Some(w) if w < seq.t => smooth_windows(seq, model, opts, info, w),
        _ => {
            info.windows = 1;
            smooth_pass(seq, model, opts, info)
        }
    }
}

/// Smallest number of observed frames of context beyond the longest gap that a window keeps
/// on each side of its core.
pub const WINDOW_BURN_IN: usize = 200;

/// Relative influence below which a frame outside a window is ignored: the burn-in is the
/// number of frames `n` with `μⁿ ≤ WINDOW_TOL` for the smoother's slowest decay `μ`
/// ([`smoother::slowest_decay`]).
pub const WINDOW_TOL: f64 = 1e-12;

/// Context (frames) on each side of a window's core: the longest gap of any coordinate, so
/// every gap that touches a core lies inside its window, plus a burn-in of observed frames
/// after which the frames beyond have influence below [`WINDOW_TOL`] (at least
/// [`WINDOW_BURN_IN`]). `None` when no burn-in is short enough (a direction of the subspace
/// that the markers barely see): then the sequence is smoothed whole.
pub fn window_margin(seq: &Seq<'_>, model: &Model) -> Result<Option<usize>> {
    let mu = smoother::slowest_decay(model)?;
    let burn = if mu <= 0.0 {
        0.0
    } else {
        WINDOW_TOL.ln() / mu.ln()
    };
    if !(burn.is_finite() && burn < seq.t as f64) {
        return Ok(None);
    }
    let (t, d) = (seq.t, seq.d);
    let mut run = vec![0usize; d];
    let mut longest = 0;
    for i in 0..t {
        for (j, r) in run.iter_mut().enumerate() {
            if seq.x[i * d + j].is_nan() {
                *r += 1;
                longest = longest.max(*r);
            } else {
                *r = 0;
            }
        }
    }
    Ok(Some(longest + (burn.ceil() as usize).max(WINDOW_BURN_IN)))
}

/// [`smooth_pass`] over windows of `w` frames plus [`window_margin`] frames on each side,
/// one window at a time (peak memory: one window), keeping each window's core.
fn smooth_windows(
    seq: &Seq<'_>,
    model: &Model,
    opts: &Options,
    info: &mut Info,
    w: usize,
) -> Result<(Vec<f64>, Option<Vec<f64>>)> {
    let (t, d) = (seq.t, seq.d);
    let Some(margin) = window_margin(seq, model)? else {
        info.windows = 1;
        return smooth_pass(seq, model, opts, info);
    };
    let mut y = vec![0.0; t * d];
    let mut std = opts.want_std.then(|| vec![0.0; t * d]);
    let (mut distinct, mut low_rank, mut windows) = (0, true, 0);
    for a in (0..t).step_by(w) {
        let b = (a + w).min(t);
        let (w0, w1) = (a.saturating_sub(margin), (b + margin).min(t));
        // A coordinate may be unobserved in a window: the smoother handles that, so the
        // window is not re-validated (Seq::new would refuse it).
        let win = Seq {
            x: &seq.x[w0 * d..w1 * d],
            t: w1 - w0,
            d,
        };
        let mut wi = Info::default();
        let (wy, ws) = smooth_pass(&win, model, opts, &mut wi)?;
        let core = (a - w0) * d..(b - w0) * d;
        y[a * d..b * d].copy_from_slice(&wy[core.clone()]);
        if let (Some(s), Some(ws)) = (std.as_mut(), ws) {
            s[a * d..b * d].copy_from_slice(&ws[core]);
        }
        distinct = distinct.max(wi.distinct_covariances);
        low_rank &= wi.low_rank;
        windows += 1;
    }
    info.distinct_covariances = distinct;
    info.low_rank = low_rank;
    info.windows = windows;
    info.window_margin = margin;
    Ok((y, std))
}

/// One smoothing pass over all of `seq` (see [`smooth_with`]).
fn smooth_pass(
    seq: &Seq<'_>,
    model: &Model,
    opts: &Options,
    info: &mut Info,
) -> Result<(Vec<f64>, Option<Vec<f64>>)> {
    let pats = Patterns::new(seq.x, seq.d);
    // Small-gain regime (e.g. the published r): low-rank filter states, same means.
    let fast = if opts.want_std {
        None
    } else {
        lowrank::smooth_means(seq.x, model, &pats, opts.memo_tol)?
    };
    if let Some(lr) = fast {
        info.distinct_covariances = lr.states;
        info.low_rank = true;
        // Observed values are kept and no border residual is needed: project only the gaps.
        let only_missing = opts.keep_original && opts.combine == Combine::None;
        return Ok((lr.back_project(model, seq.x, only_missing), None));
    }
    let sm = smoother::smooth(seq.x, model, &pats, opts.want_std, opts.memo_tol)?;
    info.low_rank = false;
    info.distinct_covariances = sm.distinct_filter_covariances();
    let y = smoother::back_project_means(&sm.m, model);
    let std = opts
        .want_std
        .then(|| smoother::missing_std(seq.x, &sm, model));
    Ok((y, std))
}

/// Frames used by EM at most.
pub const EM_FRAMES: usize = 2000;

fn em_block(t: usize) -> (usize, usize) {
    centred_block(t, EM_FRAMES)
}

/// The centred block of at most `max` of `t` frames.
fn centred_block(t: usize, max: usize) -> (usize, usize) {
    if t <= max {
        (0, t)
    } else {
        let a = (t - max) / 2;
        (a, a + max)
    }
}

/// Beyond the paper (c): adds to every gap the observed-minus-smoothed residual of its border
/// frames, blended linearly across the gap (one side only at the ends of the sequence), so the
/// fill joins the observed trajectory without a jump.
/// `gaps` = [`all_gaps`]`(seq)`.
pub fn carry_residuals(seq: &Seq<'_>, gaps: &[Vec<(usize, usize)>], y: &mut [f64]) {
    let d = seq.d;
    let cols: Vec<Vec<(usize, f64)>> = (0..d)
        .into_par_iter()
        .map(|j| {
            let mut out = Vec::new();
            for &(a, b) in &gaps[j] {
                let left = (a > 0).then(|| seq.at(a - 1, j) - y[(a - 1) * d + j]);
                let right = (b < seq.t).then(|| seq.at(b, j) - y[b * d + j]);
                for i in a..b {
                    let e = match (left, right) {
                        (Some(l), Some(r)) => {
                            let w = (i + 1 - a) as f64 / (b + 1 - a) as f64;
                            (1.0 - w) * l + w * r
                        }
                        (Some(l), None) => l,
                        (None, Some(r)) => r,
                        (None, None) => 0.0,
                    };
                    out.push((i, e));
                }
            }
            out
        })
        .collect();
    for (j, col) in cols.into_iter().enumerate() {
        for (i, e) in col {
            y[i * d + j] += e;
        }
    }
}

/// Replaces the fill of every gap of at most `max_len` frames (bounded on both sides) by the
/// natural cubic spline through the observed samples of its coordinate (fitted only for the
/// coordinates that have such gaps). `gaps` = [`all_gaps`]`(seq)`.
fn splice_short_gaps(seq: &Seq<'_>, gaps: &[Vec<(usize, usize)>], y: &mut [f64], max_len: usize) {
    if max_len == 0 {
        return;
    }
    let d = seq.d;
    let short = |&(a, b): &(usize, usize)| b - a <= max_len && a > 0 && b < seq.t;
    let cols: Vec<Vec<(usize, f64)>> = (0..d)
        .into_par_iter()
        .map(|j| {
            if !gaps[j].iter().any(short) {
                return Vec::new();
            }
            let sp = Spline::of_column(seq, j);
            gaps[j]
                .iter()
                .filter(|g| short(g))
                .flat_map(|&(a, b)| a..b)
                .map(|i| (i, sp.eval(i as f64)))
                .collect()
        })
        .collect();
    for (j, col) in cols.into_iter().enumerate() {
        for (i, v) in col {
            y[i * d + j] = v;
        }
    }
}

/// A small deterministic generator (SplitMix64) for the calibration gaps.
pub struct SplitMix(pub u64);

impl SplitMix {
    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform integer in `0..n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

/// Gap lengths (frames) probed by [`calibrate_short_gap`] (those up to a quarter of the
/// sequence).
const PROBE_LENGTHS: [usize; 13] = [1, 2, 3, 5, 8, 12, 20, 30, 50, 80, 120, 180, 270];
/// Largest fraction of the marker-frames of the probe block hidden in one probe copy.
const PROBE_FRACTION: f64 = 0.2;
/// Most probe copies (short recordings need several to stay under [`PROBE_FRACTION`]).
const MAX_PROBE_ROUNDS: usize = 8;
/// Frames of the block in which [`calibrate_short_gap`] probes (the centred block EM learns on,
/// [`EM_FRAMES`]; 2000 frames with 20 % hidden per copy calibrated as well as 4000 and 6000 with
/// 10 % on 85_02 and 135_02 and costs a third of the 6000-frame probe).
const PROBE_FRAMES: usize = EM_FRAMES;
/// Probe gaps hidden per length (over all copies).
const PROBES_PER_LENGTH: usize = 20;

/// Beyond the paper (c): calibrates the spline/smoother threshold on the data itself. In a
/// centred block of at most [`PROBE_FRAMES`] frames, hides extra marker gaps of the lengths
/// [`PROBE_LENGTHS`] (up to a quarter of the block) where the marker is observed, in as many
/// copies as needed to hide at most [`PROBE_FRACTION`] of the marker-frames in each (at most
/// [`MAX_PROBE_ROUNDS`]), fills them with the spline and with the smoother *of the model
/// learned from the data* (`model`: the probe only tests the fill; re-learning the subspace
/// and noise from a copy with hundreds of extra gaps made the smoother look worse than it is),
/// and returns the length up to which the spline wins on balance (0 if the smoother is never
/// worse).
pub fn calibrate_short_gap(seq: &Seq<'_>, opts: &Options, model: &Model) -> Result<usize> {
    // A centred block is enough to compare the two fills (and bounds the cost on long
    // recordings); the whole sequence if some coordinate is never observed in the block.
    let (a, b) = centred_block(seq.t, PROBE_FRAMES);
    let seq = &Seq::new(&seq.x[a * seq.d..b * seq.d], b - a, seq.d).unwrap_or(*seq);
    let (t, d) = (seq.t, seq.d);
    let n_markers = d / 3;
    if n_markers == 0 || d % 3 != 0 {
        return Ok(0);
    }
    let lengths: Vec<usize> = PROBE_LENGTHS
        .into_iter()
        .filter(|&l| l + 2 <= t / 4)
        .collect();
    if lengths.is_empty() {
        return Ok(0);
    }
    // Rounds, so that one probe copy hides at most PROBE_FRACTION of the marker-frames.
    let demand: usize = lengths.iter().map(|&l| l * PROBES_PER_LENGTH).sum();
    let budget = ((PROBE_FRACTION * (t * n_markers) as f64) as usize).max(1);
    let rounds = demand.div_ceil(budget).clamp(1, MAX_PROBE_ROUNDS);
    let mut o = opts.clone();
    o.combine = Combine::Residual;
    o.want_std = false;
    let mut rng = SplitMix(opts.seed ^ 0x5EED_CA11);
    // Per probed length: summed marker error of the spline and of the smoother, values hidden.
    let mut sums = vec![(0.0, 0.0, 0usize); lengths.len()];
    for _ in 0..rounds {
        let mut x = seq.x.to_vec();
        let mut hidden: Vec<(usize, usize, usize)> = Vec::new(); // (length index, marker, start)
        for (li, &l) in lengths.iter().enumerate() {
            let want = PROBES_PER_LENGTH.div_ceil(rounds);
            let mut placed = 0;
            for _ in 0..20 * want {
                if placed >= want {
                    break;
                }
                let m = rng.below(n_markers);
                let s = 1 + rng.below(t - l - 1);
                let free =
                    (s - 1..s + l + 1).all(|i| (0..3).all(|c| !x[i * d + 3 * m + c].is_nan()));
                if free {
                    for i in s..s + l {
                        x[i * d + 3 * m..i * d + 3 * m + 3].fill(f64::NAN);
                    }
                    hidden.push((li, m, s));
                    placed += 1;
                }
            }
        }
        if hidden.is_empty() {
            continue;
        }
        let probe = Seq::new(&x, t, d)?;
        let (mut lowdim, _) = smooth_with(&probe, model, &o, &mut Info::default())?;
        carry_residuals(&probe, &all_gaps(&probe), &mut lowdim);
        let sp = baselines::spline(&probe);
        let err = |f: &[f64], m: usize, s: usize, l: usize| -> f64 {
            (s..s + l)
                .map(|i| {
                    (0..3)
                        .map(|c| {
                            let e = f[i * d + 3 * m + c] - seq.x[i * d + 3 * m + c];
                            e * e
                        })
                        .sum::<f64>()
                        .sqrt()
                })
                .sum::<f64>()
        };
        for &(li, m, s) in &hidden {
            let l = lengths[li];
            sums[li].0 += err(&sp, m, s, l);
            sums[li].1 += err(&lowdim, m, s, l);
            sums[li].2 += l;
        }
    }
    // Threshold = the length that maximises the spline's cumulative advantage (mean error
    // per hidden value, smoother minus spline, summed over the probed lengths up to it): one
    // noisy length does not cut the threshold short, and 0 when the smoother never loses.
    let (mut best, mut gain, mut best_gain) = (0, 0.0, 0.0);
    for (&l, &(es, el, count)) in lengths.iter().zip(&sums) {
        if count == 0 {
            continue;
        }
        gain += (el - es) / count as f64;
        if gain > best_gain {
            (best, best_gain) = (l, gain);
        }
    }
    Ok(best)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gapfill::gaps_of;

    /// A smooth 3-marker sequence with gaps of 1-40 frames, some at the ends.
    fn gapped(t: usize, seed: u64) -> Vec<f64> {
        let d = 9;
        let mut x: Vec<f64> = (0..t * d)
            .map(|k| {
                let (i, j) = ((k / d) as f64, (k % d) as f64);
                100.0 * (0.02 * i * (1.0 + 0.1 * j)).sin() + 10.0 * j
            })
            .collect();
        let mut rng = SplitMix(seed);
        for g in 0..30 {
            let m = rng.below(3);
            let len = 1 + rng.below(40);
            let s = if g == 0 { 0 } else { rng.below(t - len) };
            for i in s..s + len {
                x[i * d + 3 * m..i * d + 3 * m + 3].fill(f64::NAN);
            }
        }
        x
    }

    #[test]
    fn windowed_smoothing_equals_one_pass() {
        // Gaps of 1-40 frames everywhere, some across window borders, plus a chain of
        // overlapping gaps of two markers (frames 900-1000 and 950-1100) and a gap at the start.
        let t = 3000;
        let mut x = gapped(t, 7);
        for i in 900..1000 {
            x[i * 9..i * 9 + 3].fill(f64::NAN);
        }
        for i in 950..1100 {
            x[i * 9 + 3..i * 9 + 6].fill(f64::NAN);
        }
        // memo_tol 0: no covariance is shared between frames, so the comparison is not blurred
        // by the memo tolerance (1e-6 of the scale with the default).
        let whole = Options {
            want_std: true,
            memo_tol: 0.0,
            ..Options::default()
        };
        let a = crate::gapfill::fill(&x, t, 9, &whole).unwrap();
        let windowed = Options {
            window: Some(400),
            ..whole.clone()
        };
        let b = crate::gapfill::fill(&x, t, 9, &windowed).unwrap();
        // the same input gives the same output, bit for bit (no run-dependent summation order)
        assert_eq!(a.x, crate::gapfill::fill(&x, t, 9, &whole).unwrap().x);
        assert_eq!(a.info.windows, 1);
        assert_eq!(b.info.windows, 8);
        assert!(b.info.window_margin >= 150 + WINDOW_BURN_IN);
        let scale = x
            .iter()
            .filter(|v| !v.is_nan())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        let dy =
            a.x.iter()
                .zip(&b.x)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0, f64::max);
        assert!(
            dy <= 1e-9 * scale,
            "largest difference {dy} (scale {scale})"
        );
        let (sa, sb) = (a.std.unwrap(), b.std.unwrap());
        let ds = sa
            .iter()
            .zip(&sb)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0, f64::max);
        let smax = sa.iter().cloned().fold(0.0, f64::max);
        assert!(
            ds <= 1e-9 * smax,
            "largest std difference {ds} (largest std {smax})"
        );
        // a window longer than the sequence is one pass
        let one = Options {
            window: Some(t),
            ..whole
        };
        assert_eq!(
            crate::gapfill::fill(&x, t, 9, &one).unwrap().info.windows,
            1
        );
    }

    #[test]
    fn all_gaps_equals_gaps_of_every_column() {
        let x = gapped(300, 1);
        let seq = Seq::new(&x, 300, 9).unwrap();
        let gaps = all_gaps(&seq);
        assert!(gaps.iter().any(|g| g.first().is_some_and(|&(a, _)| a == 0)));
        for (j, g) in gaps.iter().enumerate() {
            assert_eq!(g, &gaps_of(&seq, j));
        }
    }

    #[test]
    fn splice_puts_the_spline_exactly_in_short_bounded_gaps() {
        let x = gapped(300, 2);
        let seq = Seq::new(&x, 300, 9).unwrap();
        let gaps = all_gaps(&seq);
        let sp = baselines::spline(&seq);
        let before = vec![-1e9; x.len()];
        let mut y = before.clone();
        splice_short_gaps(&seq, &gaps, &mut y, 12);
        let (mut spliced, mut kept) = (0, 0);
        for (j, g) in gaps.iter().enumerate() {
            for &(a, b) in g {
                let short = b - a <= 12 && a > 0 && b < seq.t;
                for i in a..b {
                    let v = y[i * 9 + j];
                    if short {
                        assert!((v - sp[i * 9 + j]).abs() < 1e-9, "frame {i} coordinate {j}");
                        spliced += 1;
                    } else {
                        assert_eq!(v, -1e9);
                        kept += 1;
                    }
                }
            }
        }
        assert!(spliced > 0 && kept > 0);
        // Observed values are never touched.
        for (k, v) in x.iter().enumerate() {
            if !v.is_nan() {
                assert_eq!(y[k], before[k]);
            }
        }
        // Threshold 0: nothing changes.
        let mut z = before.clone();
        splice_short_gaps(&seq, &gaps, &mut z, 0);
        assert_eq!(z, before);
    }
}
