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

/// True when the text does not end with a line break: its last line may have been cut.
fn cut_at_end(text: &str) -> bool {
    !text.is_empty() && !text.ends_with('\n') && !text.ends_with('\r')
}

/// Parses a CSV marker table (comma-separated; a first line with a non-numeric field is a
/// header). Errors name the line and column of a bad value or a row of the wrong length (a
/// cut last line: the file is incomplete).
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
    let mut d = header.as_ref().map_or(0, |h| h.split(',').count());
    let mut t = 0;
    let mut lines = lines.peekable();
    let mut n = 0;
    while let Some(line) = lines.next() {
        n += 1;
        let fields: Vec<&str> = line.split(',').collect();
        if lines.peek().is_none() && cut_at_end(text) {
            return Err(AcmError::Shape(format!(
                "CSV data row {n} has no line end: the file may be cut; if it is complete, \
                 end it with a line break"
            )));
        }
        if t == 0 && d == 0 {
            d = fields.len();
        } else if fields.len() != d {
            let cut = lines.peek().is_none() && cut_at_end(text);
            return Err(AcmError::Shape(format!(
                "CSV data row {n} has {} fields, expected {d}{}",
                fields.len(),
                if cut {
                    "; the last line is cut: the file is incomplete"
                } else {
                    ""
                }
            )));
        }
        for (c, f) in fields.iter().enumerate() {
            x.push(parse_value(f).ok_or_else(|| {
                AcmError::Invalid(format!(
                    "CSV data row {n}, column {}: {f:?} is not a number",
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

/// Parses a TRC file (tab-separated). A file with another number of data rows than its
/// NumFrames, or whose last line is cut, is refused.
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
    let last = lines.len() - 1;
    for (n, line) in lines[5..].iter().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split('\t').collect();
        if n + 5 == last && cut_at_end(text) {
            return Err(AcmError::Shape(format!(
                "TRC data line {} has no line end ({} of {} fields): the file may be cut; if it \
                 is complete, end it with a line break",
                n + 6,
                fields.len(),
                d + 2
            )));
        }
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
    let keys: Vec<&str> = lines[1].split('\t').map(str::trim).collect();
    let vals: Vec<&str> = lines[2].split('\t').map(str::trim).collect();
    if let Some(k) = keys.iter().position(|k| *k == "NumFrames") {
        if let Some(v) = vals.get(k).filter(|v| !v.is_empty()) {
            let declared: usize = v.parse().map_err(|_| {
                AcmError::Invalid(format!("TRC NumFrames {v:?} is not a whole number"))
            })?;
            if declared != frames.len() {
                return Err(AcmError::Shape(format!(
                    "TRC NumFrames says {declared} frames but the file holds {} data rows; the \
                     file is incomplete or was edited (fix NumFrames or restore the file)",
                    frames.len()
                )));
            }
        }
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

/// Appends Python's `repr(v)` of a float: the shortest digits that read back to `v` (as
/// CPython's `float_repr_style = 'short'`, `PyOS_double_to_string(v, 'r', 0,
/// Py_DTSF_ADD_DOT_0)`), in positional notation for decimal exponents -4 <= e < 16
/// (`1000000000000000.0`, `0.0001`, with `.0` on whole numbers) and otherwise as `1.5e-05`,
/// `1e+16` (sign and at least two exponent digits); `nan`, `inf`, `-inf`, `-0.0`.
///
/// The digits are Rust's shortest round-trip digits (`{:e}`), which are CPython's dtoa mode 0
/// digits except when `v` lies exactly halfway between two shortest candidates: dtoa then takes
/// the even last digit (`1140579860715907.25` → `…907.2`), Rust the upper one; such ties are
/// found exactly (see [`exact_tie`]) and resolved as dtoa does. `scratch` is a reusable buffer.
pub fn push_py_repr(out: &mut String, scratch: &mut String, v: f64) {
    use std::fmt::Write;
    if v.is_nan() {
        out.push_str("nan");
        return;
    }
    if v.is_infinite() {
        out.push_str(if v > 0.0 { "inf" } else { "-inf" });
        return;
    }
    if v.is_sign_negative() {
        out.push('-');
    }
    if v == 0.0 {
        out.push_str("0.0");
        return;
    }
    let a = v.abs();
    scratch.clear();
    let _ = write!(scratch, "{a:e}"); // "d[.ddd]e[-]x"
    let (mant, exp) = scratch.split_once('e').unwrap_or((scratch.as_str(), "0"));
    let exp: i32 = exp.parse().unwrap_or(0);
    let mut digits: Vec<u8> = mant.bytes().filter(|c| c.is_ascii_digit()).collect();
    let n = digits.len() as i32;
    let decpt = exp + 1; // the value is 0.DIGITS x 10^decpt
    if exact_tie(a, n - decpt) {
        // the exact value has n + 1 digits ending in 5: keep the n first, rounded to even
        let exact = format!("{a:.*e}", n as usize);
        let low: Vec<u8> = exact
            .bytes()
            .take_while(|&c| c != b'e')
            .filter(u8::is_ascii_digit)
            .collect();
        if low.len() == digits.len() + 1 && low[low.len() - 1] == b'5' {
            let mut even = low[..low.len() - 1].to_vec();
            let last = even.len() - 1;
            if (even[last] - b'0') % 2 == 1 {
                even[last] += 1; // 1..7 -> 2..8 (a 9 would make a shorter candidate)
            }
            // only if it reads back to `a` (below a power of two the interval is narrower)
            let text = format!("0.{}e{decpt}", std::str::from_utf8(&even).unwrap_or("x"));
            if text.parse::<f64>() == Ok(a) {
                digits = even;
            }
        }
    }
    let digits = std::str::from_utf8(&digits).unwrap_or("0");
    if decpt <= -4 || decpt > 16 {
        out.push_str(&digits[..1]);
        if n > 1 {
            out.push('.');
            out.push_str(&digits[1..]);
        }
        let _ = write!(out, "e{}{:02}", if exp < 0 { '-' } else { '+' }, exp.abs());
    } else if decpt <= 0 {
        out.push_str("0.");
        (0..-decpt).for_each(|_| out.push('0'));
        out.push_str(digits);
    } else if decpt >= n {
        out.push_str(digits);
        (0..decpt - n).for_each(|_| out.push('0'));
        out.push_str(".0");
    } else {
        out.push_str(&digits[..decpt as usize]);
        out.push('.');
        out.push_str(&digits[decpt as usize..]);
    }
}

/// True when the positive finite `a` times `10^s` is exactly an odd multiple of 1/2, i.e. `a`
/// lies halfway between two decimals with `s` digits after the point. With `a = m·2^e`, `m`
/// odd: `a·10^s = m·5^s·2^(e+s)`, a half-integer iff `e + s = -1` and, for `s < 0`, `5^-s`
/// divides `m`.
fn exact_tie(a: f64, s: i32) -> bool {
    let bits = a.to_bits();
    let (frac, biased) = (bits & ((1 << 52) - 1), ((bits >> 52) & 0x7ff) as i32);
    let (mut m, mut e) = if biased == 0 {
        (frac, -1074)
    } else {
        (frac | (1 << 52), biased - 1075)
    };
    if m == 0 {
        return false;
    }
    let tz = m.trailing_zeros();
    m >>= tz;
    e += tz as i32;
    if e + s != -1 {
        return false;
    }
    s >= 0 || (-s <= 22 && m % 5u64.pow((-s) as u32) == 0)
}

/// Rows of a row-major `T × d` table as text: each value as Python's `repr` (see
/// [`push_py_repr`]), NaN as `nan_text`, values joined by `sep`, one string per row (no line
/// end). Rows are formatted in parallel (rayon).
pub fn format_rows(x: &[f64], d: usize, sep: &str, nan_text: &str) -> Vec<String> {
    use rayon::prelude::*;
    x.par_chunks(d.max(1))
        .map_init(String::new, |scratch, row| {
            let mut s = String::with_capacity(row.len() * 20);
            for (i, &v) in row.iter().enumerate() {
                if i > 0 {
                    s.push_str(sep);
                }
                if v.is_nan() {
                    s.push_str(nan_text);
                } else {
                    push_py_repr(&mut s, scratch, v);
                }
            }
            s
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn py_repr_of_floats() {
        let cases = [
            (0.0, "0.0"),
            (-0.0, "-0.0"),
            (1.0, "1.0"),
            (-2.5, "-2.5"),
            (0.1, "0.1"),
            (1e16, "1e+16"),
            (1e15, "1000000000000000.0"),
            (123456789012345.6, "123456789012345.6"),
            (1234567890123456.7, "1234567890123456.8"),
            (0.0001, "0.0001"),
            (0.00001, "1e-05"),
            (1.5e-7, "1.5e-07"),
            (1e22, "1e+22"),
            (1.7976931348623157e308, "1.7976931348623157e+308"),
            (4562319442863629.0 / 4.0, "1140579860715907.2"),
            (4562319442863631.0 / 4.0, "1140579860715907.8"),
            (2f64.powi(-24), "5.960464477539063e-08"),
            (5e-324, "5e-324"),
            (f64::INFINITY, "inf"),
            (f64::NEG_INFINITY, "-inf"),
            (f64::NAN, "nan"),
        ];
        let (mut s, mut scratch) = (String::new(), String::new());
        for (v, want) in cases {
            s.clear();
            push_py_repr(&mut s, &mut scratch, v);
            assert_eq!(s, want, "{v:e}");
        }
        assert_eq!(
            format_rows(&[1.0, f64::NAN, -3.25, 0.5], 2, "\t", ""),
            vec!["1.0\t".to_string(), "-3.25\t0.5".to_string()]
        );
    }

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
        // a truncated copy: NumFrames says 2, one row and a cut one are present
        let cut = &text[..text.len() - 8];
        let err = read_trc(cut).unwrap_err().to_string();
        assert!(err.contains("cut"), "{err}");
        let one_row = text.replace("\n2\t0.01\t1.5\t2\t3\t\t\t\n", "\n");
        let err = read_trc(&one_row).unwrap_err().to_string();
        assert!(err.contains("NumFrames says 2"), "{err}");
    }

    #[test]
    fn csv_cut_last_line_is_named() {
        let err = read_csv("a_x,a_y,a_z\n1,2,3\n4,5").unwrap_err().to_string();
        assert!(err.contains("cut"), "{err}");
        let err = read_csv("a_x,a_y,a_z\n1,2,3\n4,5,6")
            .unwrap_err()
            .to_string();
        assert!(err.contains("no line end"), "{err}");
        assert!(read_csv("a_x,a_y\n1,2,3\n").is_err()); // wider than the header
    }

    fn fuzz_bytes(seed: u64, n: usize) -> Vec<u8> {
        // xorshift: deterministic pseudo-random bytes, mostly from the TRC/CSV alphabet
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let alphabet = b"0123456789.-,\t\nNaEe x";
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                if s.is_multiple_of(17) {
                    (s >> 8) as u8
                } else {
                    alphabet[(s >> 8) as usize % alphabet.len()]
                }
            })
            .collect()
    }

    proptest::proptest! {
        /// Any text: the readers return a table or an error, never panic.
        #[test]
        fn arbitrary_text_never_panics(s in "[0-9a-zA-Z.,\t\n\r -]{0,300}") {
            let _ = read_csv(&s);
            let _ = read_trc(&s);
            let _ = read_trc(&format!("PathFileType\t4\nNumFrames\n2\nFrame#\tTime\tA\n\n{s}"));
        }

        /// A written table cut anywhere reads back whole or not at all (TRC: NumFrames and
        /// the line end; CSV: the line end, or whole rows only).
        #[test]
        fn truncated_tables_are_refused_or_whole(
            vals in proptest::collection::vec(-1e6f64..1e6, 3..30),
            frac in 0.0f64..1.0,
        ) {
            let t = vals.len() / 3;
            let x = &vals[..3 * t];
            let csv = write_csv(Some("a_x,a_y,a_z"), x, 3);
            let cut = &csv[..(csv.len() as f64 * frac) as usize];
            if let Ok(c) = read_csv(cut) {
                proptest::prop_assert!(cut.ends_with('\n'));
                proptest::prop_assert_eq!(&c.x[..], &x[..c.x.len()]);
            }
            let trc = Trc {
                header: vec![
                    "PathFileType\t4\t(X/Y/Z)\tp.trc".into(),
                    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits".into(),
                    format!("100\t100\t{t}\t1\tmm"),
                    "Frame#\tTime\tA\t\t".into(),
                    "\t\tX1\tY1\tZ1".into(),
                ],
                names: vec!["A".into()],
                frames: (1..=t).map(|i| i.to_string()).collect(),
                times: (0..t).map(|i| format!("{}", i as f64 / 100.0)).collect(),
                x: x.to_vec(),
            };
            let text = write_trc(&trc, x);
            let cut = &text[..(text.len() as f64 * frac) as usize];
            if let Ok(back) = read_trc(cut) {
                proptest::prop_assert_eq!(&back.x[..], x);
            }
        }
    }

    #[test]
    fn truncated_and_corrupted_text_never_panics_or_passes_short() {
        let text = write_trc(
            &read_trc(
                "PathFileType\t4\t(X/Y/Z)\tt.trc\n\
DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n\
100\t100\t3\t1\tmm\n\
Frame#\tTime\tA\t\t\n\
\t\tX1\tY1\tZ1\n\
1\t0\t1.25\t2.5\t3.75\n\
2\t0.01\t1.5\t2.5\t3.75\n\
3\t0.02\t1.75\t2.5\t3.75\n",
            )
            .unwrap(),
            &[1.25, 2.5, 3.75, 1.5, 2.5, 3.75, 1.75, 2.5, 3.75],
        );
        let full = read_trc(&text).unwrap();
        for cut in 0..text.len() {
            // every truncation is refused or (cut inside the final line break) complete
            if let Ok(t) = read_trc(&text[..cut]) {
                assert_eq!(t.x, full.x, "cut at {cut} passed with other values");
            }
        }
        let csv = write_csv(Some("A_x,A_y,A_z"), &full.x, 3);
        let whole = read_csv(&csv).unwrap();
        for cut in 0..csv.len() {
            if let Ok(c) = read_csv(&csv[..cut]) {
                // only a cut right after a line break passes: whole rows, same values
                assert!(csv[..cut].ends_with('\n'), "cut {cut} passed");
                assert!(
                    c.t <= whole.t && c.x[..] == whole.x[..c.x.len()],
                    "cut {cut}"
                );
            }
        }
        for seed in 0..300 {
            let bytes = fuzz_bytes(seed, 200);
            let s = String::from_utf8_lossy(&bytes);
            let _ = read_csv(&s);
            let _ = read_trc(&format!("{}{s}", &text[..text.len() / 2]));
        }
    }
}
