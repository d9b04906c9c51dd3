//! `acm-smooth`: EM + unscented RTS smoothing of ACM bundles without Python.
//!
//! Reads one or more bundle NPZ files (skeleton, cameras, detections, μ0 and options; written
//! by `acm_rs.tracking.write_bundle`, layout in `docs/tracking.md`), runs the tracker of
//! ACM supp. sec. 4 on each, and writes `<stem>.smoothed.npz` next to each input (or into
//! `--out-dir`). Files are processed in parallel; a failing file is reported and does not stop
//! the others.

use acm_rs::tracking::bundle::smooth_file;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

const HELP: &str = "\
usage: acm-smooth [OPTIONS] BUNDLE.npz [BUNDLE.npz ...]

Runs expectation maximisation with the unscented Kalman filter and RTS smoother (ACM
supplement sec. 4, Alg. 5-13) on each bundle and writes the smoothed posterior.

Input bundle (NPZ; write it with acm_rs.tracking.write_bundle; see docs/tracking.md):
  parents (J,), rest_frames (B,3,3), bone_lengths (B,), marker_joints (M,),
  marker_offsets (M,3), joint_limits (B,3,2) rad, cameras (C,16), normalization (4,),
  detections (C,T,M,2) px with NaN = missing, mu0 (n,); optional likelihood (C,T,M),
  pcutoff, max_iter, tol, ll_tol (log-likelihood stop, nats per measurement; NaN = Alg. 13
  with tol), gate (chi-square threshold; NaN = off), noise (start of V0, V_z; 2e-4),
  vx_init (C*M*2,) start of diag(V_x) (default: noise), joint_limits_on.

Output (NPZ, written atomically): t (T,3), r (T,B,3), joints (T,J,3), joints_std,
  markers (T,M,3), markers_std, state_mean (T,n), state_cov (T,n,n) unless --no-cov,
  status (C,T,M) (0 missing, 1 used, 2 gated, 3 not predictable), em_delta, em_seconds,
  converged, mu0, V0, Vz, Vx_diag, mean_reprojection_px.

options:
  -o, --out-dir DIR   write results into DIR (default: next to each input)
  --no-cov            do not store the (T, n, n) posterior covariances
  --overwrite         replace existing results (default: refuse before any work)
  -q, --quiet         no per-iteration lines
  -h, --help          show this help

Threads: RAYON_NUM_THREADS (default: all cores). Exit status 1 if any file failed.";

fn output_path(input: &Path, out_dir: Option<&Path>) -> PathBuf {
    let stem = input
        .file_stem()
        .map_or_else(|| "bundle".into(), |s| s.to_string_lossy().into_owned());
    let name = format!("{stem}.smoothed.npz");
    match out_dir {
        Some(d) => d.join(name),
        None => input.with_file_name(name),
    }
}

fn main() -> ExitCode {
    let mut inputs = Vec::new();
    let (mut out_dir, mut keep_cov, mut quiet, mut overwrite) = (None, true, false, false);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "-h" | "--help" => {
                println!("{HELP}");
                return ExitCode::SUCCESS;
            }
            "-o" | "--out-dir" => match args.next() {
                Some(d) => out_dir = Some(PathBuf::from(d)),
                None => {
                    eprintln!("acm-smooth: --out-dir needs a folder");
                    return ExitCode::from(2);
                }
            },
            "--no-cov" => keep_cov = false,
            "--overwrite" => overwrite = true,
            "-q" | "--quiet" => quiet = true,
            s if s.starts_with('-') => {
                eprintln!("acm-smooth: unknown option {s} (see --help)");
                return ExitCode::from(2);
            }
            _ => inputs.push(PathBuf::from(a)),
        }
    }
    if inputs.is_empty() {
        eprintln!("acm-smooth: no input bundle (see --help)");
        return ExitCode::from(2);
    }
    if let Some(d) = &out_dir {
        if let Err(e) = std::fs::create_dir_all(d) {
            eprintln!("acm-smooth: {}: {e}", d.display());
            return ExitCode::FAILURE;
        }
    }
    // The overwrite policy of every acm-rs command: check all outputs before any work.
    let mut seen = std::collections::HashSet::new();
    for input in &inputs {
        let out = output_path(input, out_dir.as_deref());
        if !seen.insert(out.clone()) {
            eprintln!(
                "acm-smooth: two inputs would write {}; give inputs with distinct names",
                out.display()
            );
            return ExitCode::FAILURE;
        }
        if out.exists() && !overwrite {
            eprintln!(
                "acm-smooth: {} exists; pass --overwrite to replace it",
                out.display()
            );
            return ExitCode::FAILURE;
        }
    }
    let failures: usize = inputs
        .par_iter()
        .map(|input| {
            let out = output_path(input, out_dir.as_deref());
            let name = input.display().to_string();
            let res = smooth_file(input, &out, keep_cov, |it| {
                if !quiet {
                    eprintln!(
                        "{name}: EM iteration {:3}: delta {:.4} ({:.2} s)",
                        it.iteration, it.delta, it.seconds
                    );
                }
                true
            });
            match res {
                Ok(s) => {
                    println!(
                        "{name}: {} frames, {} EM iterations, {}, mean reprojection error \
                         {:.2} px -> {}",
                        s.n_frames,
                        s.outcome.history.len(),
                        if s.outcome.converged {
                            "converged"
                        } else {
                            "NOT converged"
                        },
                        s.mean_reprojection_px,
                        out.display()
                    );
                    0
                }
                Err(e) => {
                    eprintln!("acm-smooth: {name}: {e}");
                    1
                }
            }
        })
        .sum();
    if failures > 0 {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    }
}
