//! Plain-text marker files for the standalone binary: CSV (one row per frame, x, y, z per
//! marker, optional header row, `NaN` or empty = missing) and TRC (OpenSim / Motion Analysis:
//! 5 header lines, then `Frame#`, `Time`, x, y, z per marker; empty fields = missing).
//! C3D is handled by the Python package (ezc3d).

use crate::error::{AcmError, Result};

fn parse_value(s: &str) -> Option<f64> {
    let s = s.trim();
    if s.is_empty() || s.eq_ignore_ascii_case("nan") {
        return Some(f64::NAN);
    }
    s.parse::<f64>().ok()
}

/// A CSV marker table.
#[derive(Debug, Clone, PartialEq)]
pub struct Csv {
    /// The header line, if the first line is not numeric.
    pub header: Option<String>,
    /// Row-major `T × D` values, NaN = missing.
    pub x: Vec<f64>,
    /// Frames.
    pub t: usize,
    /// Columns.
    pub d: usize,
}

/// Parses a CSV marker table (comma-separated; a first line with a non-numeric field is a
/// header). Errors name the line and column of a bad value or a row of the wrong length.
pub fn read_csv(text: &str) -> Result<Csv> {
    let mut lines = text.lines().filter(|l| !l.trim().is_empty()).peekable();
    let mut header = None;
    if let Some(first) = lines.peek() {
        if first.split(',').any(|f| parse_value(f).is_none()) {
            header = Some(first.to_string());
            lines.next();
        }
    }
    let mut x = Vec::new();
    let mut d = 0;
    let mut t = 0;
    for (n, line) in lines.enumerate() {
        let fields: Vec<&str> = line.split(',').collect();
        if t == 0 {
            d = fields.len();
        } else if fields.len() != d {
            return Err(AcmError::Shape(format!(
                "CSV data row {} has {} fields, expected {d}",
                n + 1,
                fields.len()
            )));
        }
        for (c, f) in fields.iter().enumerate() {
            x.push(parse_value(f).ok_or_else(|| {
                AcmError::Invalid(format!(
                    "CSV data row {}, column {}: {f:?} is not a number",
                    n + 1,
                    c + 1
                ))
            })?);
        }
        t += 1;
    }
    if t == 0 {
        return Err(AcmError::Shape("CSV file has no data rows".into()));
    }
    Ok(Csv { header, x, t, d })
}

/// Writes a CSV marker table (full precision, `NaN` for missing values).
pub fn write_csv(header: Option<&str>, x: &[f64], d: usize) -> String {
    let mut s = String::new();
    if let Some(h) = header {
        s.push_str(h);
        s.push('\n');
    }
    for row in x.chunks_exact(d) {
        let fields: Vec<String> = row.iter().map(|v| format!("{v}")).collect();
        s.push_str(&fields.join(","));
        s.push('\n');
    }
    s
}

/// A TRC file: the five header lines are kept verbatim (NumFrames is rewritten on output).
#[derive(Debug, Clone, PartialEq)]
pub struct Trc {
    /// Header lines 1-5.
    pub header: Vec<String>,
    /// Marker names (line 4).
    pub names: Vec<String>,
    /// `Frame#` column as written.
    pub frames: Vec<String>,
    /// `Time` column as written.
    pub times: Vec<String>,
    /// Row-major `T × 3N` values, NaN = missing.
    pub x: Vec<f64>,
}

impl Trc {
    /// Frames.
    pub fn t(&self) -> usize {
        self.frames.len()
    }
    /// Coordinates (3 × markers).
    pub fn d(&self) -> usize {
        3 * self.names.len()
    }
}

/// Parses a TRC file (tab-separated).
pub fn read_trc(text: &str) -> Result<Trc> {
    let lines: Vec<&str> = text.lines().collect();
    if lines.len() < 5 || !lines[0].starts_with("PathFileType") {
        return Err(AcmError::Invalid(
            "not a TRC file (expected 5 header lines starting with PathFileType)".into(),
        ));
    }
    let names: Vec<String> = lines[3]
        .split('\t')
        .skip(2)
        .map(|s| s.trim())
        .filter(|s| !s.is_empty())
        .map(String::from)
        .collect();
    if names.is_empty() {
        return Err(AcmError::Invalid("TRC line 4 names no markers".into()));
    }
    let d = 3 * names.len();
    let mut x = Vec::new();
    let (mut frames, mut times) = (Vec::new(), Vec::new());
    for (n, line) in lines[5..].iter().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split('\t').collect();
        if fields.len() < 2 || fields.len() > d + 2 {
            return Err(AcmError::Shape(format!(
                "TRC data line {} has {} fields, expected at most {}",
                n + 6,
                fields.len(),
                d + 2
            )));
        }
        frames.push(fields[0].trim().to_string());
        times.push(fields[1].trim().to_string());
        for c in 0..d {
            let f = fields.get(c + 2).copied().unwrap_or("");
            x.push(parse_value(f).ok_or_else(|| {
                AcmError::Invalid(format!("TRC data line {}: {f:?} is not a number", n + 6))
            })?);
        }
    }
    if frames.is_empty() {
        return Err(AcmError::Shape("TRC file has no data rows".into()));
    }
    Ok(Trc {
        header: lines[..5].iter().map(|s| s.to_string()).collect(),
        names,
        frames,
        times,
        x,
    })
}

/// Writes a TRC file with the values `x` (row-major `T × 3N`; NaN written as empty fields).
pub fn write_trc(trc: &Trc, x: &[f64]) -> String {
    let mut s = String::new();
    for (i, h) in trc.header.iter().enumerate() {
        if i == 2 {
            // NumFrames is the third value of line 3 (DataRate CameraRate NumFrames ...).
            let mut f: Vec<String> = h.split('\t').map(String::from).collect();
            if f.len() > 2 {
                f[2] = trc.t().to_string();
            }
            s.push_str(&f.join("\t"));
        } else {
            s.push_str(h);
        }
        s.push('\n');
    }
    let d = trc.d();
    for (i, row) in x.chunks_exact(d).enumerate() {
        s.push_str(&trc.frames[i]);
        s.push('\t');
        s.push_str(&trc.times[i]);
        for v in row {
            s.push('\t');
            if !v.is_nan() {
                s.push_str(&format!("{v}"));
            }
        }
        s.push('\n');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_round_trip_with_header_and_missing() {
        let text = "a_x,a_y,a_z\n1,2,3\nNaN,,6\n";
        let c = read_csv(text).unwrap();
        assert_eq!((c.t, c.d), (2, 3));
        assert!(c.x[3].is_nan() && c.x[4].is_nan());
        let back = read_csv(&write_csv(c.header.as_deref(), &c.x, c.d)).unwrap();
        assert_eq!(back.header, c.header);
        assert_eq!(back.x[..3], c.x[..3]);
    }

    #[test]
    fn csv_bad_rows_are_errors() {
        assert!(read_csv("1,2,3\n4,5\n").is_err());
        assert!(read_csv("1,2,3\n4,x,5\n").is_err());
        assert!(read_csv("").is_err());
    }

    #[test]
    fn trc_round_trip() {
        let text = "PathFileType\t4\t(X/Y/Z)\tt.trc\n\
DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n\
100\t100\t2\t2\tmm\t100\t1\t2\n\
Frame#\tTime\tA\t\t\tB\t\t\n\
\t\tX1\tY1\tZ1\tX2\tY2\tZ2\n\
1\t0.00\t1\t2\t3\t4\t5\t6\n\
2\t0.01\t1.5\t2\t3\t\t\t\n";
        let trc = read_trc(text).unwrap();
        assert_eq!(trc.names, vec!["A", "B"]);
        assert_eq!(trc.t(), 2);
        assert!(trc.x[9].is_nan());
        let again = read_trc(&write_trc(&trc, &trc.x)).unwrap();
        assert_eq!(again.names, trc.names);
        assert_eq!(again.x[..9], trc.x[..9]);
        assert!(read_trc("hello\n").is_err());
    }
}
