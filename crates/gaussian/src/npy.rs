//! A minimal reader for NumPy `.npy` files holding floating-point arrays.
//!
//! Format (NumPy format versions 1.0, 2.0 and 3.0): the magic `\x93NUMPY`, a major and minor
//! version byte, the header length (little-endian `u16` for version 1, `u32` otherwise), then a
//! Python dict literal such as `{'descr': '<f8', 'fortran_order': False, 'shape': (71, 17), }`,
//! then the raw data. Supported dtypes are `f8` and `f4` in either byte order (`<`, `>`, and
//! `=` read as little-endian); the data must be in C order and exactly as long as the shape
//! says. Values are returned as `f64` (exactly, for `f4`).

use std::fs;
use std::path::{Path, PathBuf};

/// An `.npy` file that could not be read.
#[derive(Debug, thiserror::Error)]
#[error("{}: {problem}", path.display())]
pub struct NpyError {
    /// The file that was being read.
    pub path: PathBuf,
    /// What went wrong: I/O error, bad magic or header, unsupported dtype or order, or wrong length.
    pub problem: String,
}

/// A C-order array of floats.
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    /// Array dimensions, outermost first (the header's `shape` tuple; empty for a scalar).
    pub shape: Vec<usize>,
    /// Row-major values.
    pub data: Vec<f64>,
}

/// Reads an `.npy` file.
pub fn read_npy(path: impl AsRef<Path>) -> Result<NpyArray, NpyError> {
    let path = path.as_ref();
    let bytes = fs::read(path).map_err(|e| NpyError {
        path: path.to_path_buf(),
        problem: format!("cannot read: {e}"),
    })?;
    parse_npy(&bytes, path)
}

/// Parses `.npy` bytes. `path` only names the source in errors.
pub fn parse_npy(bytes: &[u8], path: &Path) -> Result<NpyArray, NpyError> {
    let err = |problem: String| NpyError {
        path: path.to_path_buf(),
        problem,
    };
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(err("not an .npy file (missing the \\x93NUMPY magic)".into()));
    }
    let major = bytes[6];
    let (header_len, header_start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10usize),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(err("file ends inside the header length".into()));
            }
            let n = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
            (n as usize, 12)
        }
        v => return Err(err(format!("unsupported .npy format version {v}"))),
    };
    let data_start = header_start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| {
            err(format!(
                "header of {header_len} bytes runs past the end of the file (truncated)"
            ))
        })?;
    let header = std::str::from_utf8(&bytes[header_start..data_start])
        .map_err(|_| err("header is not valid text".into()))?;

    let descr = dict_value(header, "descr").ok_or_else(|| err("header has no 'descr'".into()))?;
    let descr = descr
        .strip_prefix('\'')
        .and_then(|d| d.split('\'').next())
        .ok_or_else(|| err(format!("'descr' is not a string: {descr}")))?;
    let (big_endian, item_size) = match descr {
        "<f8" | "=f8" => (false, 8),
        ">f8" => (true, 8),
        "<f4" | "=f4" => (false, 4),
        ">f4" => (true, 4),
        other => {
            return Err(err(format!(
                "unsupported dtype '{other}' (expected '<f8', '>f8', '<f4' or '>f4')"
            )))
        }
    };
    let fortran = dict_value(header, "fortran_order")
        .ok_or_else(|| err("header has no 'fortran_order'".into()))?;
    if fortran.starts_with("True") {
        return Err(err(
            "array is stored in Fortran order; only C order is supported".into(),
        ));
    } else if !fortran.starts_with("False") {
        return Err(err(format!("'fortran_order' is not a boolean: {fortran}")));
    }
    let shape_text =
        dict_value(header, "shape").ok_or_else(|| err("header has no 'shape'".into()))?;
    let inner = shape_text
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .ok_or_else(|| err(format!("'shape' is not a tuple: {shape_text}")))?;
    let mut shape = Vec::new();
    for dim in inner.split(',').map(str::trim).filter(|d| !d.is_empty()) {
        shape.push(
            dim.parse::<usize>()
                .map_err(|_| err(format!("'shape' has an invalid dimension `{dim}`")))?,
        );
    }
    let count = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| err(format!("shape {shape:?} is too large")))?;
    let data = &bytes[data_start..];
    let expected = count
        .checked_mul(item_size)
        .ok_or_else(|| err(format!("shape {shape:?} is too large")))?;
    if data.len() != expected {
        return Err(err(format!(
            "shape {shape:?} of '{descr}' needs {expected} data bytes, the file has {} (truncated or corrupt)",
            data.len()
        )));
    }
    let values = data
        .chunks_exact(item_size)
        .map(|c| match (item_size, big_endian) {
            (8, false) => f64::from_le_bytes(c.try_into().unwrap_or([0; 8])),
            (8, true) => f64::from_be_bytes(c.try_into().unwrap_or([0; 8])),
            (_, false) => f32::from_le_bytes(c.try_into().unwrap_or([0; 4])) as f64,
            (_, true) => f32::from_be_bytes(c.try_into().unwrap_or([0; 4])) as f64,
        })
        .collect();
    Ok(NpyArray {
        shape,
        data: values,
    })
}

/// The text following `'key':` in a Python dict literal (trimmed at the start).
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let quoted = format!("'{key}'");
    let at = header.find(&quoted)? + quoted.len();
    let rest = header[at..].trim_start().strip_prefix(':')?;
    Some(rest.trim_start())
}
