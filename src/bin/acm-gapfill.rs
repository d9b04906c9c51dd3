//! `acm-gapfill IN OUT [--method NAME] [--overwrite]`: fills marker gaps in a CSV or TRC file
//! without Python (Burke & Lasenby 2016 low-dimensional Kalman smoothing by default; see
//! `acm_rs::gapfill`).
//!
//! The policy of every acm-rs command (docs/architecture.md): an existing output is kept
//! unless `--overwrite`; the output's format must be known and possible (TRC → CSV is, CSV →
//! TRC is not: a CSV has no frame rate) and its folder writable before any work; the output
//! is written atomically with the permissions of a normal new file; a partly observed point
//! keeps its observed coordinates; the filled values are listed in the sidecar
//! `OUT.acm.json` (the one `acm_rs.gapfill.io` reads).

use acm_rs::gapfill::{self, io, Method, Options};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

const USAGE: &str = "usage: acm-gapfill IN.(csv|trc) OUT.(csv|trc) [--method NAME] [--overwrite]";

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Csv,
    Trc,
}

fn format_of(path: &str) -> Result<Format, String> {
    let lower = path.to_lowercase();
    if lower.ends_with(".csv") {
        Ok(Format::Csv)
    } else if lower.ends_with(".trc") {
        Ok(Format::Trc)
    } else {
        Err(format!(
            "{path}: unsupported file type; expected .csv or .trc"
        ))
    }
}

fn sidecar(out: &Path) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(".acm.json");
    out.with_file_name(name)
}

/// Refuses an existing output (without `--overwrite`) and an unwritable folder, before work.
fn check_output(out: &Path, overwrite: bool) -> Result<(), String> {
    if out.is_dir() {
        return Err(format!("{}: is a folder; give a file name", out.display()));
    }
    for p in [out.to_path_buf(), sidecar(out)] {
        if p.exists() && !overwrite {
            return Err(format!(
                "{} exists; pass --overwrite to replace it",
                p.display()
            ));
        }
    }
    let dir = match out.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if !dir.is_dir() {
        return Err(format!(
            "cannot write {}: the folder {} does not exist",
            out.display(),
            dir.display()
        ));
    }
    let probe = dir.join(format!(".acm-gapfill-probe-{}", std::process::id()));
    std::fs::write(&probe, b"").map_err(|e| {
        format!(
            "cannot write {}: the folder {} is not writable ({e})",
            out.display(),
            dir.display()
        )
    })?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

/// Writes `text` to a temporary file in the target folder, then renames it over `path`.
fn write_atomic(path: &Path, text: &str) -> Result<(), String> {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".tmp-acm-gapfill-{}", std::process::id()));
    let tmp = path.with_file_name(name);
    std::fs::write(&tmp, text).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        format!("cannot write {}: {e}", path.display())
    })
}

fn json_string(s: &str) -> String {
    let mut o = String::from("\"");
    for c in s.chars() {
        match c {
            '"' => o.push_str("\\\""),
            '\\' => o.push_str("\\\\"),
            c if (c as u32) < 0x20 => {
                let _ = write!(o, "\\u{:04x}", c as u32);
            }
            c => o.push(c),
        }
    }
    o.push('"');
    o
}

/// The sidecar of `acm_rs.gapfill.io`: labels, rate, units and the filled frame runs.
fn sidecar_json(
    file: &str,
    labels: &[String],
    rate: Option<f64>,
    units: &str,
    filled: &[bool],
    t: usize,
) -> String {
    let m = labels.len();
    let mut runs = Vec::new();
    for (j, label) in labels.iter().enumerate() {
        let mut spans = Vec::new();
        let mut start = None;
        for i in 0..=t {
            let f = i < t && filled[i * m + j];
            match (f, start) {
                (true, None) => start = Some(i),
                (false, Some(a)) => {
                    spans.push(format!("[{a}, {i}]"));
                    start = None;
                }
                _ => {}
            }
        }
        if !spans.is_empty() {
            runs.push(format!("  {}: [{}]", json_string(label), spans.join(", ")));
        }
    }
    let labels: Vec<String> = labels.iter().map(|l| json_string(l)).collect();
    let rate = rate.map_or_else(|| "null".to_string(), |r| format!("{r}"));
    format!(
        "{{\n \"format\": \"acm-rs-markers\",\n \"version\": 1,\n \"file\": {},\n \
         \"n_frames\": {t},\n \"labels\": [{}],\n \"rate\": {rate},\n \"units\": {},\n \
         \"filled\": {{\n{}\n }}\n}}\n",
        json_string(file),
        labels.join(", "),
        json_string(units),
        runs.join(",\n")
    )
}

fn csv_labels(header: Option<&str>, d: usize) -> Vec<String> {
    match header {
        Some(h) => h
            .split(',')
            .step_by(3)
            .map(|f| {
                let f = f.trim();
                let lower = f.to_lowercase();
                if lower.ends_with("_x") || lower.ends_with(".x") {
                    f[..f.len() - 2].to_string()
                } else {
                    f.to_string()
                }
            })
            .collect(),
        None => (0..d / 3).map(|i| format!("M{i:02}")).collect(),
    }
}

fn run() -> Result<String, String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut pos = Vec::new();
    let mut method = "lowdim".to_string();
    let mut overwrite = false;
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--method" => method = it.next().ok_or("--method needs a value")?.clone(),
            "--overwrite" => overwrite = true,
            "-h" | "--help" => {
                return Ok(format!(
                    "{USAGE}\n  --method {}\n  --overwrite  replace an existing output",
                    Method::NAMES.join("|")
                ))
            }
            s if s.starts_with("--") => return Err(format!("unknown option {s} ({USAGE})")),
            _ => pos.push(a.clone()),
        }
    }
    if pos.len() != 2 {
        return Err(USAGE.into());
    }
    let (input, output) = (&pos[0], &pos[1]);
    let m = Method::parse(&method).map_err(|e| e.to_string())?;
    let (fin, fout) = (format_of(input)?, format_of(output)?);
    if fin == Format::Csv && fout == Format::Trc {
        return Err(format!(
            "{output}: a TRC file needs a frame rate and {input} (CSV) has none; write a CSV, \
             or use `acm-rs gapfill {input} -o {output} --rate HZ`"
        ));
    }
    if Path::new(input) == Path::new(output) {
        return Err(format!("{output} is the input; give another output file"));
    }
    check_output(Path::new(output), overwrite)?;
    let opts = if m == Method::LowDimPaper {
        Options::paper()
    } else {
        Options {
            method: m,
            ..Options::default()
        }
    };
    let text = std::fs::read(input).map_err(|e| format!("{input}: {e}"))?;
    let text = String::from_utf8(text).map_err(|e| {
        format!(
            "{input}: not a text file (byte {} is not UTF-8)",
            e.utf8_error().valid_up_to()
        )
    })?;
    let (x, t, d, labels, rate, units, trc) = if fin == Format::Trc {
        let trc = io::read_trc(&text).map_err(|e| format!("{input}: {e}"))?;
        let keys: Vec<&str> = trc.header[1].split('\t').map(str::trim).collect();
        let vals: Vec<&str> = trc.header[2].split('\t').map(str::trim).collect();
        let get = |k: &str| keys.iter().position(|x| *x == k).and_then(|i| vals.get(i));
        let rate = get("DataRate").and_then(|v| v.parse::<f64>().ok());
        let units = get("Units").map_or("mm", |v| v).to_string();
        (
            trc.x.clone(),
            trc.t(),
            trc.d(),
            trc.names.clone(),
            rate,
            units,
            Some(trc),
        )
    } else {
        let csv = io::read_csv(&text).map_err(|e| format!("{input}: {e}"))?;
        if csv.d % 3 != 0 {
            return Err(format!(
                "{input}: {} columns is not a multiple of 3 (x, y, z per marker)",
                csv.d
            ));
        }
        let labels = csv_labels(csv.header.as_deref(), csv.d);
        (csv.x, csv.t, csv.d, labels, None, "mm".to_string(), None)
    };
    // Long recordings are smoothed in windows (the same fill, memory of one window).
    let opts = Options {
        window: (t > 2 * gapfill::AUTO_WINDOW).then_some(gapfill::AUTO_WINDOW),
        ..opts
    };
    let f = gapfill::fill(&x, t, d, &opts).map_err(|e| format!("{input}: {e}"))?;
    // A fill never changes an observed coordinate (also of a partly observed point); a point
    // is filled where any of its coordinates was missing and now has a value.
    let mut filled_x = f.x;
    let n_markers = d / 3;
    let mut filled = vec![false; t * n_markers];
    for (k, v) in filled_x.iter_mut().enumerate() {
        if !x[k].is_nan() {
            *v = x[k];
        } else if !v.is_nan() {
            filled[k / 3] = true;
        }
    }
    let out_text = match (&trc, fout) {
        (Some(trc), Format::Trc) => io::write_trc(trc, &filled_x),
        (Some(_), Format::Csv) => {
            let header: Vec<String> = labels
                .iter()
                .flat_map(|l| ["x", "y", "z"].map(|a| format!("{l}_{a}")))
                .collect();
            io::write_csv(Some(&header.join(",")), &filled_x, d)
        }
        (None, _) => {
            let header = if text.lines().next().is_some_and(|l| {
                l.split(',')
                    .any(|f| !f.trim().is_empty() && f.trim().parse::<f64>().is_err())
            }) {
                text.lines().next().map(str::to_string)
            } else {
                let h: Vec<String> = labels
                    .iter()
                    .flat_map(|l| ["x", "y", "z"].map(|a| format!("{l}_{a}")))
                    .collect();
                Some(h.join(","))
            };
            io::write_csv(header.as_deref(), &filled_x, d)
        }
    };
    let out = Path::new(output);
    let name = out
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    write_atomic(out, &out_text)?;
    write_atomic(
        &sidecar(out),
        &sidecar_json(&name, &labels, rate, &units, &filled, t),
    )?;
    Ok(format!(
        "acm-gapfill: {input} ({t} frames, {d} coordinates) -> {output} with {method}: filled {} \
         marker-frames (listed in {})",
        filled.iter().filter(|f| **f).count(),
        sidecar(out).display()
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
