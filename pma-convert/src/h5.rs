//! Typed, key-named access to the processed `.h5` files of A-NeRF/DANBO/PM
//! (docs/conventions.md, "A-NeRF/DANBO .h5"), on top of the pure-Rust `hdf5-reader`.
//!
//! Why `hdf5-reader`: it needs no system library (CI installs nothing), it
//! reads gzip-chunked datasets and hyperslabs, and it reads the file with
//! positioned reads instead of loading it, so one image of a multi-gigabyte
//! file can be read at a time. `hdf5-pure` loads the whole file on open, and
//! `hdf5-metno` needs libhdf5.
//!
//! Readers do not rely on chunk shapes, which differ between writers: images
//! are read as row hyperslabs of the flattened `(n, H·W, C)` layout.

use std::path::{Path, PathBuf};

use hdf5_reader::{Datatype, Hdf5File, OpenOptions, SliceInfo, SliceInfoElem};

use crate::error::{ConvertError, Result};

/// Decoded chunks kept between reads. Images are read once, in order, so a
/// large cache would only raise the memory high-water mark.
const CHUNK_CACHE_BYTES: usize = 4 << 20;

/// Deflate expands by at most 1032:1, so data actually stored in a file of
/// `n` bytes decodes to less than `n · 1100`. A dataset claiming more exists
/// only in a corrupt or hostile header (or as never-written fill values, which
/// the reference writer does not produce): refuse it before allocating.
const MAX_EXPANSION: u64 = 1100;
/// Reads below this are always allowed (tiny files with fill-value datasets).
const MIN_READ_LIMIT: u64 = 64 << 20;

/// The element type of a dataset, reduced to what the files use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum H5Kind {
    Float {
        size: u8,
    },
    Int {
        size: u8,
        signed: bool,
    },
    /// Fixed-length byte strings (`img_paths`) and anything else non-numeric.
    Other,
}

impl std::fmt::Display for H5Kind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            H5Kind::Float { size } => write!(f, "float{}", 8 * *size as u32),
            H5Kind::Int { size, signed: true } => write!(f, "int{}", 8 * *size as u32),
            H5Kind::Int {
                size,
                signed: false,
            } => write!(f, "uint{}", 8 * *size as u32),
            H5Kind::Other => f.write_str("a non-numeric type"),
        }
    }
}

/// Shape and element type of a dataset.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct H5Info {
    pub shape: Vec<usize>,
    pub kind: H5Kind,
}

/// A processed `.h5` file opened for reading.
pub struct H5File {
    path: PathBuf,
    file: Hdf5File,
}

impl H5File {
    pub fn open(path: &Path) -> Result<Self> {
        // Opened and checked first: a FIFO or a device is refused before the HDF5 reader opens it.
        let len = pma_data::fsio::open_input(path)
            .and_then(|f| f.metadata())
            .map_err(|e| ConvertError::io(path, e))?
            .len();
        let limit = len.saturating_mul(MAX_EXPANSION).max(MIN_READ_LIMIT);
        let opts = OpenOptions::default()
            .with_chunk_cache_bytes(CHUNK_CACHE_BYTES)
            .with_max_read_bytes(usize::try_from(limit).unwrap_or(usize::MAX));
        let file =
            Hdf5File::open_with_options(path, opts).map_err(|source| ConvertError::Hdf5 {
                path: path.to_path_buf(),
                key: "(file)".into(),
                cause: source,
            })?;
        Ok(Self {
            path: path.to_path_buf(),
            file,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn err(&self, key: &str) -> impl Fn(hdf5_reader::error::Error) -> ConvertError + '_ {
        let key = key.to_string();
        move |source| ConvertError::Hdf5 {
            path: self.path.clone(),
            key: key.clone(),
            cause: source,
        }
    }

    fn kind_mismatch(&self, key: &str, expected: &str, found: H5Kind) -> ConvertError {
        ConvertError::mismatch(&self.path, key, expected, found.to_string())
    }

    /// Names of the datasets in the root group, sorted.
    pub fn keys(&self) -> Result<Vec<String>> {
        let root = self.file.root_group().map_err(self.err("/"))?;
        let (_, mut names) = root.member_names().map_err(self.err("/"))?;
        names.sort();
        Ok(names)
    }

    fn dataset(&self, key: &str) -> Result<hdf5_reader::Dataset> {
        self.file.dataset(key).map_err(|e| match e {
            e if not_found(&e) => ConvertError::missing(&self.path, key, ""),
            source => ConvertError::Hdf5 {
                path: self.path.clone(),
                key: key.to_string(),
                cause: source,
            },
        })
    }

    pub fn info(&self, key: &str) -> Result<H5Info> {
        let ds = self.dataset(key)?;
        let kind = match ds.dtype() {
            Datatype::FloatingPoint { size, .. } => H5Kind::Float { size: *size },
            Datatype::FixedPoint { size, signed, .. } => H5Kind::Int {
                size: *size,
                signed: *signed,
            },
            _ => H5Kind::Other,
        };
        Ok(H5Info {
            shape: ds.shape().iter().map(|&d| d as usize).collect(),
            kind,
        })
    }

    /// A float dataset as f32 (float64 is rounded, as the reference writer does for arrays).
    pub fn read_f32(&self, key: &str) -> Result<(Vec<usize>, Vec<f32>)> {
        let info = self.info(key)?;
        let ds = self.dataset(key)?;
        let values = match info.kind {
            H5Kind::Float { size: 4 } => flat(ds.read_array::<f32>().map_err(self.err(key))?),
            H5Kind::Float { size: 8 } => ds
                .read_array::<f64>()
                .map_err(self.err(key))?
                .iter()
                .map(|&v| v as f32)
                .collect(),
            other => return Err(self.kind_mismatch(key, "float32 or float64", other)),
        };
        Ok((info.shape, values))
    }

    /// A float dataset as f64 (scalars such as `ext_scale` are stored as float64).
    pub fn read_f64(&self, key: &str) -> Result<(Vec<usize>, Vec<f64>)> {
        let info = self.info(key)?;
        let ds = self.dataset(key)?;
        let values = match info.kind {
            H5Kind::Float { size: 4 } => ds
                .read_array::<f32>()
                .map_err(self.err(key))?
                .iter()
                .map(|&v| v as f64)
                .collect(),
            H5Kind::Float { size: 8 } => flat(ds.read_array::<f64>().map_err(self.err(key))?),
            other => return Err(self.kind_mismatch(key, "float32 or float64", other)),
        };
        Ok((info.shape, values))
    }

    /// An index dataset as i64. Integer types are widened; a float dataset
    /// (PerfCap's float32 `bkgd_idxs`) is accepted only if every value is integral.
    pub fn read_i64(&self, key: &str) -> Result<(Vec<usize>, Vec<i64>)> {
        let info = self.info(key)?;
        let ds = self.dataset(key)?;
        macro_rules! widen {
            ($t:ty) => {
                ds.read_array::<$t>()
                    .map_err(self.err(key))?
                    .iter()
                    .map(|&v| v as i64)
                    .collect::<Vec<i64>>()
            };
        }
        let values = match info.kind {
            H5Kind::Int { size: 1, signed } if signed => widen!(i8),
            H5Kind::Int { size: 1, .. } => widen!(u8),
            H5Kind::Int { size: 2, signed } if signed => widen!(i16),
            H5Kind::Int { size: 2, .. } => widen!(u16),
            H5Kind::Int { size: 4, signed } if signed => widen!(i32),
            H5Kind::Int { size: 4, .. } => widen!(u32),
            H5Kind::Int { size: 8, signed } if signed => widen!(i64),
            H5Kind::Int {
                size: 8,
                signed: false,
            } => {
                let v = ds.read_array::<u64>().map_err(self.err(key))?;
                v.iter()
                    .enumerate()
                    .map(|(i, &x)| {
                        i64::try_from(x).map_err(|_| {
                            ConvertError::invalid(
                                &self.path,
                                key,
                                format!("value {x} at flat index {i} exceeds int64"),
                            )
                        })
                    })
                    .collect::<Result<Vec<_>>>()?
            }
            H5Kind::Float { .. } => {
                let (_, f) = self.read_f64(key)?;
                f.iter()
                    .enumerate()
                    .map(|(i, &x)| {
                        if x.is_finite() && x.fract() == 0.0 && x.abs() < 9.0e15 {
                            Ok(x as i64)
                        } else {
                            Err(ConvertError::invalid(
                                &self.path,
                                key,
                                format!("index {x} at flat index {i} is not an integer"),
                            ))
                        }
                    })
                    .collect::<Result<Vec<_>>>()?
            }
            other => return Err(self.kind_mismatch(key, "an integer type", other)),
        };
        Ok((info.shape, values))
    }

    /// Rows `start..end` of a uint8 dataset of rank >= 1 (one or more images
    /// of the flattened `(n, H·W, C)` layout), C order.
    pub fn read_u8_rows(&self, key: &str, start: usize, end: usize) -> Result<Vec<u8>> {
        let ds = self.dataset(key)?;
        match ds.dtype() {
            Datatype::FixedPoint {
                size: 1,
                signed: false,
                ..
            } => {}
            _ => {
                let kind = self.info(key)?.kind;
                return Err(ConvertError::mismatch(
                    &self.path,
                    key,
                    "uint8 pixels",
                    kind.to_string(),
                ));
            }
        }
        let shape = ds.shape();
        if shape.is_empty() || end as u64 > shape[0] || start > end {
            return Err(ConvertError::invalid(
                &self.path,
                key,
                format!("rows {start}..{end} requested from shape {shape:?}"),
            ));
        }
        let mut sel = SliceInfo::all(shape.len());
        sel.selections[0] = SliceInfoElem::Slice {
            start: start as u64,
            end: end as u64,
            step: 1,
        };
        let a = ds.read_slice::<u8>(&sel).map_err(self.err(key))?;
        Ok(flat(a))
    }
}

/// The elements of an array in C order, without a copy when it is already laid out so.
fn flat<T: Clone>(a: ndarray::ArrayD<T>) -> Vec<T> {
    if !a.is_standard_layout() {
        return a.iter().cloned().collect();
    }
    let len = a.len();
    let (mut v, off) = a.into_raw_vec_and_offset();
    let off = off.unwrap_or(0);
    if off > 0 {
        v.drain(..off);
    }
    v.truncate(len);
    v
}

fn not_found(e: &hdf5_reader::error::Error) -> bool {
    use hdf5_reader::error::Error as E;
    match e {
        E::DatasetNotFound(_) => true,
        E::Context { source, .. } => not_found(source),
        _ => false,
    }
}
