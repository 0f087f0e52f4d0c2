//! Raw `.npz` members: zip (stored or deflated) around NPY payloads.
//!
//! npyz parses and writes the NPY headers; payloads are moved in bulk here
//! because npyz's element-by-element path is far too slow for gigabytes of
//! pixels. Only plain numeric dtypes are accepted: object/pickled, string,
//! structured and complex members are rejected with the key named.

use std::fs::File;
use std::io::{self, BufReader, Read, Write};
use std::path::Path;

use npyz::{DType, Endianness, NpyFile, Order, TypeChar, TypeStr, WriterBuilder};

use crate::error::{one_line, DataError, Result};
use crate::fsio::Latch;

/// Element type of a member.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ElemType {
    F32,
    F64,
    I8,
    I32,
    I64,
    U8,
    Bool,
}

impl ElemType {
    /// numpy's little-endian descriptor (`<f4`, `|u1`, ...).
    pub fn descr(self) -> &'static str {
        match self {
            ElemType::F32 => "<f4",
            ElemType::F64 => "<f8",
            ElemType::I8 => "|i1",
            ElemType::I32 => "<i4",
            ElemType::I64 => "<i8",
            ElemType::U8 => "|u1",
            ElemType::Bool => "|b1",
        }
    }

    pub fn size(self) -> usize {
        match self {
            ElemType::I8 | ElemType::U8 | ElemType::Bool => 1,
            ElemType::F32 | ElemType::I32 => 4,
            ElemType::F64 | ElemType::I64 => 8,
        }
    }
}

/// Header facts of one member, read without its payload.
#[derive(Debug, Clone, PartialEq)]
pub struct MemberInfo {
    pub key: String,
    /// numpy descriptor as stored (e.g. `<f4`, `>f8`, `|O`).
    pub descr: String,
    /// `None` for dtypes pma cannot read.
    pub elem: Option<ElemType>,
    pub shape: Vec<usize>,
    pub fortran_order: bool,
    pub big_endian: bool,
    /// Deflated rather than stored.
    pub compressed: bool,
    /// Uncompressed member size in bytes.
    pub size: u64,
}

impl MemberInfo {
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Payload of a member, C order, native values.
#[derive(Debug, Clone, PartialEq)]
pub enum NpyData {
    F32(Vec<f32>),
    F64(Vec<f64>),
    I8(Vec<i8>),
    I32(Vec<i32>),
    I64(Vec<i64>),
    U8(Vec<u8>),
    Bool(Vec<bool>),
}

impl NpyData {
    pub fn elem(&self) -> ElemType {
        match self {
            NpyData::F32(_) => ElemType::F32,
            NpyData::F64(_) => ElemType::F64,
            NpyData::I8(_) => ElemType::I8,
            NpyData::I32(_) => ElemType::I32,
            NpyData::I64(_) => ElemType::I64,
            NpyData::U8(_) => ElemType::U8,
            NpyData::Bool(_) => ElemType::Bool,
        }
    }
}

/// One decoded member.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    pub shape: Vec<usize>,
    pub data: NpyData,
    /// Conversions applied on the way in (byte order, Fortran order).
    pub notes: Vec<String>,
}

fn elem_of(dtype: &DType) -> (String, Option<ElemType>, bool) {
    match dtype {
        DType::Plain(ts) => {
            let descr = ts.to_string();
            let big = ts.endianness() == Endianness::Big;
            let elem = match (ts.type_char(), ts.size_field()) {
                (TypeChar::Float, 4) => Some(ElemType::F32),
                (TypeChar::Float, 8) => Some(ElemType::F64),
                (TypeChar::Int, 1) => Some(ElemType::I8),
                (TypeChar::Int, 4) => Some(ElemType::I32),
                (TypeChar::Int, 8) => Some(ElemType::I64),
                (TypeChar::Uint, 1) => Some(ElemType::U8),
                (TypeChar::Bool, 1) => Some(ElemType::Bool),
                _ => None,
            };
            (descr, elem, big)
        }
        DType::Array(..) => ("(sub-array dtype)".into(), None, false),
        DType::Record(_) => ("(structured dtype)".into(), None, false),
    }
}

/// Bytes read or written between two checks of the interrupt flag.
const READ_PIECE: usize = 16 << 20;

/// Reader over an npz archive.
pub struct NpzReader {
    file: String,
    zip: zip::ZipArchive<BufReader<File>>,
    names: Vec<String>,
}

impl NpzReader {
    pub fn open(path: &Path) -> Result<Self> {
        let f = crate::fsio::open_input(path).map_err(|e| DataError::io(path, e))?;
        let zip = zip::ZipArchive::new(BufReader::new(f)).map_err(|e| DataError::Format {
            file: path.display().to_string(),
            key: "(archive)".into(),
            msg: format!(
                "not a readable npz/zip archive: {}",
                one_line(&e.to_string())
            ),
        })?;
        let names = zip
            .file_names()
            .map(|n| n.map(|c| c.into_owned()))
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|e| DataError::Format {
                file: path.display().to_string(),
                key: "(archive)".into(),
                msg: format!("unreadable member name: {e}"),
            })?;
        Ok(NpzReader {
            file: path.display().to_string(),
            zip,
            names,
        })
    }

    /// The file name used in messages.
    pub fn file(&self) -> &str {
        &self.file
    }

    /// Array keys (members named `<key>.npy`) in archive order.
    pub fn keys(&self) -> Vec<String> {
        self.names
            .iter()
            .filter_map(|n| n.strip_suffix(".npy").map(str::to_owned))
            .collect()
    }

    /// Members that are not `.npy` files (ignored by readers).
    pub fn other_members(&self) -> Vec<String> {
        self.names
            .iter()
            .filter(|n| !n.ends_with(".npy") && !n.ends_with('/'))
            .cloned()
            .collect()
    }

    /// Open a member and parse its NPY header.
    fn open_member(
        &mut self,
        key: &str,
    ) -> Result<(MemberInfo, NpyFile<zip::read::ZipFile<'_, BufReader<File>>>)> {
        let file = self.file.clone();
        let name = format!("{key}.npy");
        let open_err = |e: zip::result::ZipError| DataError::Format {
            file: file.clone(),
            key: key.into(),
            msg: format!("cannot open member {name}: {}", one_line(&e.to_string())),
        };
        // npyz multiplies the shape unchecked (a panic in debug builds, a
        // wrapped count in release), so the claim is checked first.
        let zf = self.zip.by_name(&name).map_err(open_err)?;
        let declared = zf.size();
        check_npy_claim(zf, declared).map_err(|msg| DataError::Format {
            file: file.clone(),
            key: key.into(),
            msg,
        })?;
        let zf = self.zip.by_name(&name).map_err(open_err)?;
        let compressed = zf.compression() != zip::CompressionMethod::Stored;
        let size = zf.size();
        let npy = NpyFile::new(zf).map_err(|e| DataError::Format {
            file: file.clone(),
            key: key.into(),
            msg: format!("bad NPY header: {}", one_line(&e.to_string())),
        })?;
        let (descr, elem, big) = elem_of(&npy.dtype());
        let info = MemberInfo {
            key: key.into(),
            descr,
            elem: if npy.uses_pickled_array() { None } else { elem },
            shape: npy.shape().iter().map(|&d| d as usize).collect(),
            fortran_order: npy.order() == Order::Fortran,
            big_endian: big,
            compressed,
            size,
        };
        Ok((info, npy))
    }

    /// Header facts of a member (reads only the NPY header).
    pub fn info(&mut self, key: &str) -> Result<MemberInfo> {
        Ok(self.open_member(key)?.0)
    }

    /// Decode a member. Big-endian and Fortran-ordered payloads are
    /// converted (noted in [`NpyArray::notes`]); unsupported dtypes are an
    /// error naming the key; a payload shorter than its header says is a
    /// truncation error.
    pub fn read(&mut self, key: &str) -> Result<NpyArray> {
        let file = self.file.clone();
        let (info, npy) = self.open_member(key)?;
        let Some(elem) = info.elem else {
            return Err(DataError::Dtype {
                file,
                key: key.into(),
                expected: "a plain numeric dtype (<f4, <f8, <i4, <i8, |u1, |i1); object, pickled, string and structured members are not allowed".into(),
                found: info.descr,
            });
        };
        let n = info.len();
        let nbytes = n
            .checked_mul(elem.size())
            .ok_or_else(|| DataError::Format {
                file: file.clone(),
                key: key.into(),
                msg: format!("shape {:?} is too large", info.shape),
            })?;
        let mut reader = npy.into_inner();
        let mut bytes = Vec::new();
        bytes
            .try_reserve_exact(nbytes)
            .map_err(|_| DataError::Format {
                file: file.clone(),
                key: key.into(),
                msg: format!("cannot allocate {nbytes} bytes for shape {:?}", info.shape),
            })?;
        // In pieces, so that Ctrl-C stops a multi-gigabyte member within one piece.
        let mut got = 0usize;
        loop {
            crate::interrupt::check()?;
            let want = (nbytes - got).min(READ_PIECE);
            let k = (&mut reader)
                .take(want as u64)
                .read_to_end(&mut bytes)
                .map_err(|e| DataError::Format {
                    file: file.clone(),
                    key: key.into(),
                    msg: format!(
                        "cannot read payload (corrupt or truncated member): {}",
                        one_line(&e.to_string())
                    ),
                })?;
            got += k;
            if k < want || got == nbytes {
                break;
            }
        }
        if got != nbytes {
            return Err(DataError::Format {
                file,
                key: key.into(),
                msg: format!(
                    "truncated payload: header promises {nbytes} bytes ({:?} x {}), member holds {got}",
                    info.shape,
                    info.descr
                ),
            });
        }
        // Drain so the zip reader verifies the member's CRC.
        io::copy(&mut reader, &mut io::sink()).map_err(|e| DataError::Format {
            file: file.clone(),
            key: key.into(),
            msg: format!("corrupt member: {}", one_line(&e.to_string())),
        })?;
        let mut notes = Vec::new();
        if info.big_endian && elem.size() > 1 {
            for c in bytes.chunks_exact_mut(elem.size()) {
                c.reverse();
            }
            notes.push(format!("converted from big-endian {}", info.descr));
        }
        let data = decode(elem, bytes).map_err(|m| DataError::Format {
            file: file.clone(),
            key: key.into(),
            msg: m,
        })?;
        let mut arr = NpyArray {
            shape: info.shape.clone(),
            data,
            notes,
        };
        if info.fortran_order && info.shape.len() > 1 {
            arr = fortran_to_c(arr);
            arr.notes.push("converted from Fortran order".into());
        }
        Ok(arr)
    }
}

/// Checks the shape an NPY header claims before npyz parses it: its element
/// count must not overflow, and its payload must fit in the `declared` size of
/// the member holding it. Headers this scanner cannot read are left to npyz.
pub(crate) fn check_npy_claim(
    mut member: impl Read,
    declared: u64,
) -> std::result::Result<(), String> {
    let mut head = Vec::new();
    // Magic (6) + version (2) + length (2 or 4) + a header of at most 64 KiB in practice.
    (&mut member)
        .take(12 + (1 << 16))
        .read_to_end(&mut head)
        .map_err(|e| format!("cannot read the NPY header: {e}"))?;
    let text = String::from_utf8_lossy(&head);
    let claim = |k: &str| {
        let at = text.find(k)? + k.len();
        let rest = text[at..].trim_start().strip_prefix(':')?.trim_start();
        Some(rest.to_string())
    };
    let Some(shape) = claim("'shape'") else {
        return Ok(());
    };
    let Some(inner) = shape.strip_prefix('(').and_then(|r| r.split(')').next()) else {
        return Ok(());
    };
    let mut count: u64 = 1;
    for d in inner.split(',').map(str::trim).filter(|d| !d.is_empty()) {
        let Ok(d) = d.parse::<u64>() else {
            return Ok(());
        };
        count = count
            .checked_mul(d)
            .ok_or_else(|| format!("shape ({inner}) overflows a 64-bit element count"))?;
    }
    // The item size ends the dtype descriptor (`<f4`, `|u1`); 1 if unreadable.
    let item: u64 = claim("'descr'")
        .and_then(|d| {
            let d = d.trim_start_matches(['\'', '"']);
            let digits: String = d.chars().skip(2).take_while(char::is_ascii_digit).collect();
            digits.parse().ok()
        })
        .unwrap_or(1)
        .max(1);
    match count.checked_mul(item) {
        Some(bytes) if bytes <= declared => Ok(()),
        _ => Err(format!(
            "shape ({inner}) of {item}-byte elements does not fit in the member's {declared} bytes (corrupt or truncated)"
        )),
    }
}

fn decode(elem: ElemType, bytes: Vec<u8>) -> std::result::Result<NpyData, String> {
    fn le<const K: usize, T>(b: &[u8], f: fn([u8; K]) -> T) -> Vec<T> {
        b.chunks_exact(K)
            .map(|c| f(c.try_into().expect("chunk of K bytes")))
            .collect()
    }
    Ok(match elem {
        ElemType::U8 => NpyData::U8(bytes),
        ElemType::I8 => NpyData::I8(bytes.into_iter().map(|b| b as i8).collect()),
        ElemType::Bool => {
            if let Some(b) = bytes.iter().find(|&&b| b > 1) {
                return Err(format!("bool payload holds byte {b}, expected 0 or 1"));
            }
            NpyData::Bool(bytes.into_iter().map(|b| b == 1).collect())
        }
        ElemType::F32 => NpyData::F32(le(&bytes, f32::from_le_bytes)),
        ElemType::F64 => NpyData::F64(le(&bytes, f64::from_le_bytes)),
        ElemType::I32 => NpyData::I32(le(&bytes, i32::from_le_bytes)),
        ElemType::I64 => NpyData::I64(le(&bytes, i64::from_le_bytes)),
    })
}

fn fortran_to_c(arr: NpyArray) -> NpyArray {
    use ndarray::{ArrayD, IxDyn, ShapeBuilder};
    fn conv<T: Clone>(v: Vec<T>, shape: &[usize]) -> Vec<T> {
        let a = ArrayD::from_shape_vec(IxDyn(shape).f(), v).expect("length matches shape");
        a.as_standard_layout().iter().cloned().collect()
    }
    let s = arr.shape.clone();
    let data = match arr.data {
        NpyData::F32(v) => NpyData::F32(conv(v, &s)),
        NpyData::F64(v) => NpyData::F64(conv(v, &s)),
        NpyData::I8(v) => NpyData::I8(conv(v, &s)),
        NpyData::I32(v) => NpyData::I32(conv(v, &s)),
        NpyData::I64(v) => NpyData::I64(conv(v, &s)),
        NpyData::U8(v) => NpyData::U8(conv(v, &s)),
        NpyData::Bool(v) => NpyData::Bool(conv(v, &s)),
    };
    NpyArray {
        shape: s,
        data,
        notes: arr.notes,
    }
}

// ---------------------------------------------------------------------------
// Writing

/// A borrowed member to write: C-order data with its shape.
pub enum MemberData<'a> {
    F32(&'a [f32]),
    F64(&'a [f64]),
    I8(&'a [i8]),
    I32(&'a [i32]),
    I64(&'a [i64]),
    U8(&'a [u8]),
}

impl MemberData<'_> {
    fn elem(&self) -> ElemType {
        match self {
            MemberData::F32(_) => ElemType::F32,
            MemberData::F64(_) => ElemType::F64,
            MemberData::I8(_) => ElemType::I8,
            MemberData::I32(_) => ElemType::I32,
            MemberData::I64(_) => ElemType::I64,
            MemberData::U8(_) => ElemType::U8,
        }
    }
    fn len(&self) -> usize {
        match self {
            MemberData::F32(v) => v.len(),
            MemberData::F64(v) => v.len(),
            MemberData::I8(v) => v.len(),
            MemberData::I32(v) => v.len(),
            MemberData::I64(v) => v.len(),
            MemberData::U8(v) => v.len(),
        }
    }
}

/// Writer of deterministic npz archives: members in call order, fixed
/// timestamps (1980-01-01) and permissions, so equal inputs give equal bytes.
///
/// A failed write (a full disk) is [`FileError::Write`](crate::FileError::Write) naming the file; the archive is
/// then abandoned quietly (see [`crate::fsio::Latch`]).
pub struct NpzWriter<W: Write + io::Seek> {
    zip: zip::ZipWriter<Latch<W>>,
    failure: crate::fsio::LatchWatch,
    deflate: bool,
    file: String,
}

impl<W: Write + io::Seek> NpzWriter<W> {
    /// `file` names the destination in error messages.
    pub fn new(inner: W, deflate: bool, file: impl Into<String>) -> Self {
        let latch = Latch::new(inner);
        NpzWriter {
            failure: latch.watch(),
            zip: zip::ZipWriter::new(latch),
            deflate,
            file: file.into(),
        }
    }

    /// The error for `e`, met writing `key`: an I/O failure of the sink is a write failure,
    /// anything else a format problem.
    fn error(&self, key: &str, e: &dyn std::fmt::Display) -> DataError {
        match self.failure.failure() {
            Some(io) => DataError::write(&self.file, io),
            None => DataError::Format {
                file: self.file.clone(),
                key: key.to_string(),
                msg: format!("cannot write member: {e}"),
            },
        }
    }

    /// Append `<key>.npy`. Panics never: a data length that does not match
    /// the shape is an error.
    pub fn add(&mut self, key: &str, shape: &[usize], data: MemberData<'_>) -> Result<()> {
        let want: usize = shape.iter().product();
        if data.len() != want {
            return Err(DataError::arg(
                key,
                format!("{want} elements for shape {shape:?}"),
                data.len(),
            ));
        }
        let elem = data.elem();
        let payload = want as u64 * elem.size() as u64;
        let method = if self.deflate {
            zip::CompressionMethod::Deflated
        } else {
            zip::CompressionMethod::Stored
        };
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(method)
            .last_modified_time(zip::DateTime::default())
            .unix_permissions(0o644)
            // Members over 4 GiB need zip64 records.
            .large_file(payload + 4096 >= u32::MAX as u64);
        if let Err(e) = self.zip.start_file(format!("{key}.npy"), opts) {
            return Err(self.error(key, &e));
        }
        let ts: TypeStr = elem.descr().parse().expect("static dtype descriptor");
        let shape64: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
        let header = npyz::WriteOptions::new_header_only()
            .dtype(DType::Plain(ts))
            .shape(&shape64)
            .writer(&mut self.zip)
            .write_header_only();
        if let Err(e) = header {
            return Err(self.error(key, &e));
        }
        if let Err(e) = write_payload(&mut self.zip, &data) {
            if crate::interrupt::requested() {
                return Err(crate::interrupt::Interrupted.into());
            }
            return Err(self.error(key, &e));
        }
        Ok(())
    }

    /// Finish the archive and return the inner writer.
    pub fn finish(self) -> Result<W> {
        let file = self.file.clone();
        let failure = self.failure.clone();
        match self.zip.finish() {
            Ok(latch) => match failure.failure() {
                Some(io) => Err(DataError::write(file, io)),
                None => Ok(latch.into_inner()),
            },
            Err(e) => {
                let io = failure.failure().unwrap_or_else(|| match e {
                    zip::result::ZipError::Io(io) => io,
                    other => io::Error::other(other.to_string()),
                });
                Err(DataError::write(file, io))
            }
        }
    }
}

fn write_payload<W: Write>(w: &mut W, data: &MemberData<'_>) -> io::Result<()> {
    // Chunked so that a multi-gigabyte f32 member never needs a second full copy.
    const CHUNK: usize = 1 << 16;
    fn interrupted() -> io::Result<()> {
        match crate::interrupt::requested() {
            true => Err(io::Error::other("interrupted")),
            false => Ok(()),
        }
    }
    fn chunks<T: Copy, const K: usize>(
        w: &mut impl Write,
        v: &[T],
        f: fn(T) -> [u8; K],
    ) -> io::Result<()> {
        let mut buf = Vec::with_capacity(CHUNK * K);
        for (i, c) in v.chunks(CHUNK).enumerate() {
            if i % 64 == 0 {
                interrupted()?;
            }
            buf.clear();
            for &x in c {
                buf.extend_from_slice(&f(x));
            }
            w.write_all(&buf)?;
        }
        Ok(())
    }
    match data {
        MemberData::U8(v) => {
            for c in v.chunks(READ_PIECE) {
                interrupted()?;
                w.write_all(c)?;
            }
            Ok(())
        }
        MemberData::I8(v) => chunks(w, v, |x: i8| x.to_le_bytes()),
        MemberData::F32(v) => chunks(w, v, |x: f32| x.to_le_bytes()),
        MemberData::F64(v) => chunks(w, v, |x: f64| x.to_le_bytes()),
        MemberData::I32(v) => chunks(w, v, |x: i32| x.to_le_bytes()),
        MemberData::I64(v) => chunks(w, v, |x: i64| x.to_le_bytes()),
    }
}
