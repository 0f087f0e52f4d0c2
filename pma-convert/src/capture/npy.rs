//! `.npy` files: a numeric array, or (dtype `|O`, `np.save(..., allow_pickle=True)`)
//! an object array whose elements follow the header as a pickle, which is
//! read with the numpy [`NumpyData`] policy.

use std::{path::Path, rc::Rc};

use crate::{
    error::{ConvertError, Result},
    pickle::{
        self,
        numpy::{ArrayData, Dtype, NpArray, NpObject, NumpyData},
        Unpickled,
    },
};

pub(crate) enum NpyContent {
    Array(NpArray),
    /// An object array; the pickle's root is the array itself.
    Pickled(Unpickled<NpObject>),
}

/// Parses `bytes` (a whole `.npy`); `path`/`key` label errors.
pub(crate) fn read_npy_bytes(bytes: &[u8], path: &Path, key: &str) -> Result<NpyContent> {
    let bad = |m: String| ConvertError::invalid(path, key, m);
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(bad("not an .npy file (no \\x93NUMPY magic)".into()));
    }
    let (hlen, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => return Err(bad(format!("unsupported .npy version {v}"))),
    };
    let end = start
        .checked_add(hlen)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| bad("truncated .npy header".into()))?;
    let header = String::from_utf8_lossy(&bytes[start..end]);
    let descr = header_field(&header, "descr")
        .and_then(|s| {
            let q = s.chars().next().filter(|c| *c == '\'' || *c == '"')?;
            let body = &s[1..];
            Some(body[..body.find(q)?].to_string())
        })
        .ok_or_else(|| bad(format!("no `descr` in the .npy header {header:?}")))?;
    let fortran = header_field(&header, "fortran_order").is_some_and(|s| s.starts_with("True"));
    let shape = header_shape(&header)
        .ok_or_else(|| bad(format!("no readable `shape` in the .npy header {header:?}")))?;
    let dtype = Dtype::parse(&descr).ok_or_else(|| bad(format!("unsupported dtype `{descr}`")))?;
    let payload = &bytes[end..];
    if dtype.kind == 'O' {
        let tree = pickle::parse(payload, &NumpyData, path, key)?;
        return Ok(NpyContent::Pickled(tree));
    }
    let n = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .and_then(|n| n.checked_mul(dtype.size))
        .ok_or_else(|| bad(format!("shape {shape:?} overflows")))?;
    if payload.len() < n {
        return Err(bad(format!(
            "{} data bytes for shape {shape:?} of {}-byte elements (truncated?)",
            payload.len(),
            dtype.size
        )));
    }
    Ok(NpyContent::Array(NpArray {
        shape,
        dtype,
        fortran,
        data: ArrayData::Raw(Rc::from(&payload[..n])),
    }))
}

/// Reads a `.npy` from disk.
pub(crate) fn read_npy(path: &Path) -> Result<NpyContent> {
    let bytes = pma_data::fsio::read_input(path, crate::MAX_INPUT_BYTES)
        .map_err(|e| ConvertError::io(path, e))?;
    let name = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    read_npy_bytes(&bytes, path, &name)
}

/// The text after `'key':` up to the next top-level comma.
fn header_field<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let i = header.find(&format!("'{key}'"))?;
    let rest = header[i + key.len() + 2..].trim_start().strip_prefix(':')?;
    Some(rest.trim_start())
}

fn header_shape(header: &str) -> Option<Vec<usize>> {
    let rest = header_field(header, "shape")?.strip_prefix('(')?;
    let inner = &rest[..rest.find(')')?];
    inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.trim_end_matches('L').parse().ok())
        .collect()
}
