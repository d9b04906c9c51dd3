//! `acm-gapfill IN OUT [--method NAME]`: fills marker gaps in a CSV or TRC file without Python
//! (Burke & Lasenby 2016 low-dimensional Kalman smoothing by default; see `acm_rs::gapfill`).

use acm_rs::gapfill::{self, io, Method, Options};
use std::process::ExitCode;

fn run() -> Result<String, String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut pos = Vec::new();
    let mut method = "lowdim".to_string();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--method" => method = it.next().ok_or("--method needs a value")?.clone(),
            "-h" | "--help" => {
                return Ok(format!(
                    "usage: acm-gapfill IN.(csv|trc) OUT.(csv|trc) [--method {}]",
                    Method::NAMES.join("|")
                ))
            }
            _ => pos.push(a.clone()),
        }
    }
    if pos.len() != 2 {
        return Err("usage: acm-gapfill IN OUT [--method NAME] (see --help)".into());
    }
    let m = Method::parse(&method).map_err(|e| e.to_string())?;
    let opts = if m == Method::LowDimPaper {
        Options::paper()
    } else {
        Options {
            method: m,
            ..Options::default()
        }
    };
    let text = std::fs::read_to_string(&pos[0]).map_err(|e| format!("{}: {e}", pos[0]))?;
    let is_trc = pos[0].to_lowercase().ends_with(".trc");
    let (out_text, t, d) = if is_trc {
        let trc = io::read_trc(&text).map_err(|e| e.to_string())?;
        let (t, d) = (trc.t(), trc.d());
        let f = gapfill::fill(&trc.x, t, d, &opts).map_err(|e| e.to_string())?;
        (io::write_trc(&trc, &f.x), t, d)
    } else {
        let csv = io::read_csv(&text).map_err(|e| e.to_string())?;
        let f = gapfill::fill(&csv.x, csv.t, csv.d, &opts).map_err(|e| e.to_string())?;
        (
            io::write_csv(csv.header.as_deref(), &f.x, csv.d),
            csv.t,
            csv.d,
        )
    };
    // Atomic write: temporary file in the target folder, then rename.
    let tmp = format!("{}.tmp-acm-gapfill", pos[1]);
    std::fs::write(&tmp, out_text).map_err(|e| format!("{tmp}: {e}"))?;
    std::fs::rename(&tmp, &pos[1]).map_err(|e| format!("{}: {e}", pos[1]))?;
    Ok(format!(
        "acm-gapfill: {} ({t} frames, {d} coordinates) -> {} with {method}",
        pos[0], pos[1]
    ))
}

fn main() -> ExitCode {
    match run() {
        Ok(msg) => {
            println!("{msg}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("acm-gapfill: error: {e}");
            ExitCode::FAILURE
        }
    }
}
