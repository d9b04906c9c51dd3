//! Wall time of repeated gap fills of a CSV sequence, with the diagnostics of the fill
//! (developer tool for profiling, e.g. under `perf record`).
//!
//! `cargo run --release --example gapfill_profile -- IN.csv [METHOD] [REPEATS]`
//! (METHOD: lowdim (default), lowdim-paper, linear, spline, rw, cv, msvd).
use acm_rs::gapfill::{self, Method, Options};
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        eprintln!("usage: gapfill_profile IN.csv [METHOD] [REPEATS]");
        std::process::exit(2);
    };
    let text = std::fs::read_to_string(path).expect("readable CSV file");
    let csv = gapfill::io::read_csv(&text).expect("numeric CSV");
    let method = args.get(2).map(String::as_str).unwrap_or("lowdim");
    let reps: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(5);
    let mut opts = if method == "lowdim-paper" {
        Options::paper()
    } else {
        Options::default()
    };
    opts.method = Method::parse(method).expect("known method");
    for _ in 0..reps {
        let t0 = Instant::now();
        let out = gapfill::fill(&csv.x, csv.t, csv.d, &opts).expect("fill");
        println!(
            "fill {:.1} ms  (d̂ {}, r {:.3e}, filter states {}, low-rank {})",
            t0.elapsed().as_secs_f64() * 1e3,
            out.info.dim,
            out.info.r,
            out.info.distinct_covariances,
            out.info.low_rank,
        );
    }
}
