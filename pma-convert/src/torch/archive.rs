//! The torch zip layout: `<archive>/data.pkl` and one entry per storage under
//! `<archive>/data/`, read with every declared size checked before anything of
//! that size is allocated.

use std::{
    fs::File,
    io::{BufReader, Read},
    path::{Path, PathBuf},
};

use safetensors::Dtype;

use super::{unpickle, TensorRef, Unpickled};
use crate::{
    error::{ConvertError, Result},
    raw::RawTensor,
};

fn dtype_size(d: Dtype) -> usize {
    match d {
        Dtype::F64 | Dtype::I64 | Dtype::U64 => 8,
        Dtype::F32 | Dtype::I32 | Dtype::U32 => 4,
        Dtype::F16 | Dtype::BF16 | Dtype::I16 | Dtype::U16 => 2,
        _ => 1,
    }
}

/// An open torch zip checkpoint: the unpickled object graph plus access to the
/// storages it refers to.
pub struct TorchArchive {
    path: PathBuf,
    zip: zip::ZipArchive<BufReader<File>>,
    prefix: String,
    graph: Unpickled,
}

impl TorchArchive {
    pub fn open(path: &Path) -> Result<Self> {
        let mut file = pma_data::fsio::open_input(path).map_err(|e| ConvertError::io(path, e))?;
        let mut magic = [0u8; 2];
        let n = file
            .read(&mut magic)
            .map_err(|e| ConvertError::io(path, e))?;
        if n == 2 && magic[0] == 0x80 {
            return Err(ConvertError::format(
                path,
                "this is a legacy (pre-1.6, non-zip) torch checkpoint; re-save it with a current torch.save",
            ));
        }
        let file = pma_data::fsio::open_input(path).map_err(|e| ConvertError::io(path, e))?;
        let mut zip =
            zip::ZipArchive::new(BufReader::new(file)).map_err(|source| ConvertError::Zip {
                path: path.to_path_buf(),
                cause: source,
            })?;
        let pkl_name = zip
            .file_names_raw()
            .filter_map(|n| std::str::from_utf8(n).ok())
            .find(|n| n.ends_with("/data.pkl") && n.matches('/').count() == 1)
            .map(str::to_string)
            .ok_or_else(|| {
                ConvertError::format(
                    path,
                    "zip archive has no `<archive>/data.pkl` entry: not a torch.save checkpoint",
                )
            })?;
        let prefix = pkl_name.trim_end_matches("data.pkl").to_string();
        if let Ok(bo) = read_entry(
            &mut zip,
            path,
            &format!("{prefix}byteorder"),
            Size::AtMost(64),
        ) {
            if bo != b"little" {
                return Err(ConvertError::format(
                    path,
                    format!(
                        "storages are stored {:?}; only little-endian checkpoints are supported",
                        String::from_utf8_lossy(&bo)
                    ),
                ));
            }
        }
        let pkl = read_entry(&mut zip, path, &pkl_name, Size::AtMost(MAX_PICKLE_BYTES))?;
        let graph = unpickle(&pkl, path, &pkl_name)?;
        Ok(Self {
            path: path.to_path_buf(),
            zip,
            prefix,
            graph,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The unpickled object graph.
    pub fn graph(&self) -> &Unpickled {
        &self.graph
    }

    /// Copies a tensor's bytes out of its storage. `name` labels errors.
    pub fn read_tensor(&mut self, t: &TensorRef, name: &str) -> Result<RawTensor> {
        let es = dtype_size(t.dtype);
        let numel = t
            .shape
            .iter()
            .try_fold(1usize, |a, &b| a.checked_mul(b))
            .ok_or_else(|| {
                ConvertError::invalid(&self.path, name, format!("shape {:?} overflows", t.shape))
            })?;
        // A tensor viewing its storage with gaps or permuted axes would need a
        // gather; checkpoints hold plain contiguous tensors, so refuse others.
        let mut expect = 1usize;
        for (d, (&n, &s)) in t.shape.iter().zip(&t.stride).enumerate().rev() {
            if n > 1 && s != expect {
                return Err(ConvertError::invalid(
                    &self.path,
                    name,
                    format!(
                        "tensor is not contiguous (shape {:?}, stride {:?}, dim {d})",
                        t.shape, t.stride
                    ),
                ));
            }
            expect *= n;
        }
        let end = t
            .offset
            .checked_add(numel)
            .filter(|&e| e <= t.storage_numel);
        let Some(end) = end else {
            return Err(ConvertError::invalid(
                &self.path,
                name,
                format!(
                    "tensor of {numel} elements at offset {} overruns its storage of {} elements",
                    t.offset, t.storage_numel
                ),
            ));
        };
        let entry = format!("{}data/{}", self.prefix, t.key);
        let storage_bytes = t.storage_numel.checked_mul(es).ok_or_else(|| {
            ConvertError::invalid(
                &self.path,
                name,
                format!("storage of {} elements overflows", t.storage_numel),
            )
        })?;
        let bytes = read_entry(
            &mut self.zip,
            &self.path,
            &entry,
            Size::Exactly(storage_bytes as u64),
        )
        .map_err(|e| match e {
            ConvertError::Mismatch { found, .. } => ConvertError::mismatch(
                &self.path,
                format!("{name} (zip entry {entry})"),
                format!(
                    "{} elements of {:?} ({} bytes each)",
                    t.storage_numel, t.dtype, es
                ),
                found,
            ),
            other => other,
        })?;
        let data = bytes[t.offset * es..end * es].to_vec();
        Ok(RawTensor {
            dtype: t.dtype,
            shape: t.shape.clone(),
            data,
        })
    }
}

/// Largest `data.pkl` accepted. The reference checkpoint's is 33 KB (tensor
/// data lives in separate entries); anything near this is not a checkpoint.
const MAX_PICKLE_BYTES: u64 = 64 << 20;

/// Deflate expands by at most 1032:1; an entry claiming more than this ratio
/// is a corrupt header or a zip bomb.
const MAX_EXPANSION: u64 = 1100;

/// What an entry's declared (uncompressed) size must be.
#[derive(Clone, Copy)]
enum Size {
    AtMost(u64),
    Exactly(u64),
}

/// Reads a whole zip entry after checking its declared size, so a lying or
/// hostile header is refused before anything of that size is allocated (the
/// zip reader never returns more than the declared size).
fn read_entry(
    zip: &mut zip::ZipArchive<BufReader<File>>,
    path: &Path,
    name: &str,
    size: Size,
) -> Result<Vec<u8>> {
    let mut f = zip.by_name(name).map_err(|e| match e {
        zip::result::ZipError::FileNotFound => ConvertError::missing(path, name, " (zip entry)"),
        source => ConvertError::Zip {
            path: path.to_path_buf(),
            cause: source,
        },
    })?;
    let (declared, packed) = (f.size(), f.compressed_size());
    let key = || format!("zip entry {name}");
    if declared > packed.saturating_mul(MAX_EXPANSION).max(4096) {
        return Err(ConvertError::mismatch(
            path,
            key(),
            format!("at most {MAX_EXPANSION}x its {packed} compressed bytes"),
            format!("a declared size of {declared} bytes (corrupt header or zip bomb)"),
        ));
    }
    match size {
        Size::AtMost(max) if declared > max => {
            return Err(ConvertError::mismatch(
                path,
                key(),
                format!("at most {max} bytes"),
                format!("{declared} bytes"),
            ))
        }
        Size::Exactly(n) if declared != n => {
            return Err(ConvertError::mismatch(
                path,
                key(),
                format!("{n} bytes"),
                format!("{declared} bytes"),
            ))
        }
        _ => {}
    }
    let mut buf = Vec::new();
    buf.try_reserve_exact(declared as usize).map_err(|_| {
        ConvertError::invalid(path, key(), format!("cannot allocate {declared} bytes"))
    })?;
    f.read_to_end(&mut buf)
        .map_err(|e| ConvertError::io(path, e))?;
    if buf.len() as u64 != declared {
        return Err(ConvertError::mismatch(
            path,
            key(),
            format!("{declared} bytes (its declared size)"),
            format!("{} bytes", buf.len()),
        ));
    }
    Ok(buf)
}
