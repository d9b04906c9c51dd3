//! NumPy `.npz` archives of plain numeric arrays, for the `acm-smooth` binary's bundles.
//!
//! The container is read and written with the `zip` crate (stored or deflated members, as
//! `numpy.savez` / `savez_compressed` write them); the NPY member format (version 1-3 headers,
//! <https://numpy.org/doc/stable/reference/generated/numpy.lib.format.html>) is parsed here
//! for the few little-endian dtypes a bundle uses: `f8`, `f4`, `i8`, `i4`, `u1`, `b1`. Object
//! arrays (pickles) are refused.

use crate::error::{AcmError, Result};
use std::collections::BTreeMap;
use std::io::{Read, Seek, Write};

/// One array: its shape and its values as `f64` (integers and booleans converted exactly).
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    /// Shape in C order (`[]` for a scalar).
    pub shape: Vec<usize>,
    /// Values in C order.
    pub data: Vec<f64>,
}

impl Array {
    /// An array of the given shape (checked against the data length).
    ///
    /// # Errors
    /// Shape error if `shape` does not match `data.len()`.
    pub fn new(shape: Vec<usize>, data: Vec<f64>) -> Result<Self> {
        let n: usize = shape.iter().product();
        if n != data.len() {
            return Err(AcmError::Shape(format!(
                "array of shape {shape:?} needs {n} values, got {}",
                data.len()
            )));
        }
        Ok(Self { shape, data })
    }
    /// A scalar (shape `[]`).
    pub fn scalar(v: f64) -> Self {
        Self {
            shape: vec![],
            data: vec![v],
        }
    }
}

fn bad(name: &str, msg: impl std::fmt::Display) -> AcmError {
    AcmError::Invalid(format!("{name}: {msg}"))
}

/// Parses one `.npy` member.
///
/// # Errors
/// Invalid error for a malformed header, big-endian or object dtype, Fortran order, or a
/// truncated payload.
pub fn parse_npy(bytes: &[u8], name: &str) -> Result<Array> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(bad(name, "not an NPY array (bad magic)"));
    }
    let major = bytes[6];
    let (hlen, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(bad(name, "truncated header"));
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => return Err(bad(name, format!("unsupported NPY version {v}"))),
    };
    let header = bytes
        .get(start..start + hlen)
        .ok_or_else(|| bad(name, "truncated header"))?;
    let header = std::str::from_utf8(header).map_err(|_| bad(name, "header is not text"))?;
    let field = |key: &str| -> Result<&str> {
        let k = format!("'{key}':");
        let i = header
            .find(&k)
            .ok_or_else(|| bad(name, format!("header has no {key}")))?;
        Ok(header[i + k.len()..].trim_start())
    };
    let descr = field("descr")?;
    let descr = descr
        .strip_prefix('\'')
        .and_then(|s| s.split('\'').next())
        .ok_or_else(|| bad(name, "unreadable descr"))?;
    if field("fortran_order")?.starts_with("True") {
        return Err(bad(
            name,
            "Fortran-ordered array; save it with np.ascontiguousarray",
        ));
    }
    let shape_txt = field("shape")?;
    let close = shape_txt
        .find(')')
        .ok_or_else(|| bad(name, "unreadable shape"))?;
    let shape: Vec<usize> = shape_txt[1..close]
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.trim_end_matches('L').parse::<usize>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| bad(name, "unreadable shape"))?;
    let n = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| bad(name, "shape too large"))?;
    let payload = &bytes[start + hlen..];
    let (size, conv): (usize, fn(&[u8]) -> f64) = match descr {
        "<f8" => (8, |b| f64::from_le_bytes(b.try_into().unwrap())),
        "<f4" => (4, |b| f32::from_le_bytes(b.try_into().unwrap()) as f64),
        "<i8" => (8, |b| i64::from_le_bytes(b.try_into().unwrap()) as f64),
        "<i4" => (4, |b| i32::from_le_bytes(b.try_into().unwrap()) as f64),
        "|u1" | "|i1" | "|b1" => (1, |b| b[0] as f64),
        d => {
            return Err(bad(
                name,
                format!("dtype {d} is not supported (use float64, int64, uint8 or bool)"),
            ))
        }
    };
    let n_bytes = n
        .checked_mul(size)
        .ok_or_else(|| bad(name, "shape too large"))?;
    if payload.len() < n_bytes {
        return Err(bad(name, "truncated data"));
    }
    let data = payload[..n_bytes].chunks_exact(size).map(conv).collect();
    Ok(Array { shape, data })
}

/// Serialises an array as NPY version 1.0 with dtype `<f8` (or `|u1` when `as_u8`).
pub fn npy_bytes(a: &Array, as_u8: bool) -> Vec<u8> {
    let shape = match a.shape.len() {
        0 => "()".to_string(),
        1 => format!("({},)", a.shape[0]),
        _ => format!(
            "({})",
            a.shape
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let descr = if as_u8 { "|u1" } else { "<f8" };
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    // Pad so that magic (6) + version (2) + length (2) + header is a multiple of 64.
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + a.data.len() * 8);
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    if as_u8 {
        out.extend(a.data.iter().map(|&v| v as u8));
    } else {
        for v in &a.data {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Reads every member of an `.npz` archive.
///
/// # Errors
/// Invalid errors naming the file for a corrupt archive or member.
pub fn read_npz<R: Read + Seek>(reader: R, what: &str) -> Result<BTreeMap<String, Array>> {
    let mut zip =
        zip::ZipArchive::new(reader).map_err(|e| bad(what, format!("not an NPZ archive ({e})")))?;
    let mut out = BTreeMap::new();
    for i in 0..zip.len() {
        let mut f = zip.by_index(i).map_err(|e| bad(what, e))?;
        let name = f.name().to_string();
        // The declared size comes from the file: a damaged header must not reserve memory
        // it does not hold (read_to_end grows the buffer as the data really arrive).
        let mut bytes = Vec::with_capacity((f.size() as usize).min(1 << 24));
        f.read_to_end(&mut bytes).map_err(|e| bad(what, e))?;
        let key = name.strip_suffix(".npy").unwrap_or(&name).to_string();
        let arr = parse_npy(&bytes, &format!("{what}[{key}]"))?;
        out.insert(key, arr);
    }
    Ok(out)
}

/// Writes arrays as an uncompressed `.npz` archive (members `<name>.npy`); names listed in
/// `u8_names` are stored as `uint8`.
///
/// # Errors
/// Invalid error if the archive cannot be written.
pub fn write_npz<W: Write + Seek>(
    writer: W,
    arrays: &BTreeMap<String, Array>,
    u8_names: &[&str],
) -> Result<()> {
    let mut zip = zip::ZipWriter::new(writer);
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .large_file(true);
    for (name, a) in arrays {
        zip.start_file(format!("{name}.npy"), opts)
            .map_err(|e| bad(name, e))?;
        zip.write_all(&npy_bytes(a, u8_names.contains(&name.as_str())))
            .map_err(|e| bad(name, e))?;
    }
    zip.finish().map_err(|e| bad("npz", e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    #[test]
    fn npz_round_trip_and_errors() {
        let mut m = BTreeMap::new();
        m.insert(
            "a".to_string(),
            Array::new(vec![2, 3], vec![1.0, -2.5, 3.0, f64::NAN, 5.0, 6.0]).unwrap(),
        );
        m.insert("s".to_string(), Array::scalar(0.25));
        m.insert(
            "mask".to_string(),
            Array::new(vec![4], vec![0.0, 1.0, 2.0, 3.0]).unwrap(),
        );
        let mut buf = Cursor::new(Vec::new());
        write_npz(&mut buf, &m, &["mask"]).unwrap();
        buf.set_position(0);
        let back = read_npz(buf, "test").unwrap();
        assert_eq!(back["a"].shape, vec![2, 3]);
        assert!(back["a"].data[3].is_nan());
        assert_eq!(back["a"].data[1], -2.5);
        assert_eq!(back["s"].shape, Vec::<usize>::new());
        assert_eq!(back["mask"].data, vec![0.0, 1.0, 2.0, 3.0]);
        assert!(Array::new(vec![2], vec![1.0]).is_err());
        assert!(read_npz(Cursor::new(b"not a zip".to_vec()), "x").is_err());
        let mut npy = npy_bytes(&m["a"], false);
        assert!(parse_npy(&npy[..npy.len() - 4], "t").is_err());
        let pos = npy.windows(3).position(|w| w == b"<f8").unwrap();
        npy[pos..pos + 3].copy_from_slice(b"|O8");
        assert!(parse_npy(&npy, "t")
            .unwrap_err()
            .to_string()
            .contains("dtype"));
    }

    fn sample_npz() -> (Vec<u8>, BTreeMap<String, Array>) {
        let mut m = BTreeMap::new();
        m.insert(
            "a".to_string(),
            Array::new(vec![3, 2], vec![1.0, 2.0, 3.0, 4.0, 5.0, f64::NAN]).unwrap(),
        );
        m.insert("b".to_string(), Array::scalar(7.5));
        let mut buf = Cursor::new(Vec::new());
        write_npz(&mut buf, &m, &[]).unwrap();
        (buf.into_inner(), m)
    }

    fn same(a: &BTreeMap<String, Array>, b: &BTreeMap<String, Array>) -> bool {
        a.len() == b.len()
            && a.iter().all(|(k, x)| {
                b.get(k).is_some_and(|y| {
                    x.shape == y.shape
                        && x.data
                            .iter()
                            .zip(&y.data)
                            .all(|(u, v)| u == v || (u.is_nan() && v.is_nan()))
                })
            })
    }

    proptest::proptest! {
        /// Every truncation of an NPZ is refused (the zip directory sits at the end).
        #[test]
        fn truncated_npz_is_refused(cut in 0usize..10_000) {
            let (bytes, _) = sample_npz();
            let cut = cut % bytes.len();
            proptest::prop_assert!(read_npz(Cursor::new(bytes[..cut].to_vec()), "t").is_err());
        }

        /// A corrupted byte never panics; whatever still reads is the same data (no silent
        /// change: the .npy headers, lengths and the zip structure are checked).
        #[test]
        fn corrupted_npz_never_panics_or_changes_values(pos in 0usize..10_000, byte in 0u8..=255) {
            let (mut bytes, m) = sample_npz();
            let pos = pos % bytes.len();
            let old = bytes[pos];
            bytes[pos] = byte;
            if let Ok(back) = read_npz(Cursor::new(bytes), "t") {
                // stored (uncompressed) members: a flipped data byte is caught by the CRC
                proptest::prop_assert!(old == byte || same(&back, &m) || back.keys().ne(m.keys()));
            }
        }
    }
}
