//! A [`Policy`] for numpy payloads: `np.save(..., allow_pickle=True)` object
//! arrays (ZJU-MoCap's `annots.npy`, `params/*.npy`) and the distributed SMPL
//! `.pkl` (numpy arrays, a scipy sparse regressor, chumpy `Ch` objects).
//!
//! Nothing is imported or called: `_reconstruct`, `dtype`, `scalar`,
//! `_codecs.encode` and the accepted classes are recognised by name and their
//! arguments are turned into plain [`NpArray`]s and [`NpObject::Instance`]s
//! whose state is kept as data. Every other global is refused.

use std::rc::Rc;

use super::{ordered_dict, Accepted, Heap, Object, Policy, Value};

/// A numpy element type.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Dtype {
    /// `f`, `i`, `u`, `b` (bool), `O` (objects), `U` (UCS-4 text), `S` (bytes).
    pub kind: char,
    /// Bytes per element (for `U`, four per character).
    pub size: usize,
    pub big_endian: bool,
}

impl Dtype {
    /// From a descriptor such as `<f8`, `f4`, `|u1`, `O8`, `<U12`.
    pub fn parse(descr: &str) -> Option<Dtype> {
        let (big_endian, rest) = match descr.as_bytes().first()? {
            b'<' | b'|' | b'=' => (false, &descr[1..]),
            b'>' => (true, &descr[1..]),
            _ => (false, descr),
        };
        let kind = rest.chars().next()?;
        let n: usize = if rest.len() > 1 {
            rest[1..].parse().ok()?
        } else {
            match kind {
                'O' => 8,
                'b' | '?' => 1,
                _ => return None,
            }
        };
        let (kind, size) = match kind {
            'f' if [2, 4, 8].contains(&n) => ('f', n),
            'i' | 'u' if [1, 2, 4, 8].contains(&n) => (kind, n),
            'b' | '?' => ('b', 1),
            'O' => ('O', 8),
            'U' => ('U', 4 * n),
            'S' => ('S', n),
            _ => return None,
        };
        Some(Dtype {
            kind,
            size,
            big_endian,
        })
    }
}

/// An array's elements: raw bytes in the dtype, or objects.
#[derive(Clone, Debug)]
pub enum ArrayData {
    Raw(Rc<[u8]>),
    Objects(Vec<Value<NpObject>>),
}

/// A reconstructed `numpy.ndarray`.
#[derive(Clone, Debug)]
pub struct NpArray {
    pub shape: Vec<usize>,
    pub dtype: Dtype,
    pub fortran: bool,
    pub data: ArrayData,
}

impl NpArray {
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The elements as f64 in C order (numbers and bools only).
    pub fn to_f64(&self) -> std::result::Result<Vec<f64>, String> {
        let ArrayData::Raw(b) = &self.data else {
            return Err("an object array, expected numbers".into());
        };
        let d = &self.dtype;
        if !matches!(d.kind, 'f' | 'i' | 'u' | 'b') {
            return Err(format!("dtype `{}{}`, expected numbers", d.kind, d.size));
        }
        let n = self.len();
        if b.len() != n * d.size {
            return Err(format!(
                "{} data bytes for {n} elements of {} bytes",
                b.len(),
                d.size
            ));
        }
        let mut v: Vec<f64> = b.chunks_exact(d.size).map(|c| element(d, c)).collect();
        if self.fortran && self.shape.len() > 1 {
            v = fortran_to_c(&v, &self.shape);
        }
        Ok(v)
    }

    /// The elements as strings (`U`/`S` arrays, or objects that are strings).
    pub fn to_strings(&self) -> std::result::Result<Vec<String>, String> {
        match (&self.data, self.dtype.kind) {
            (ArrayData::Raw(b), 'U') => Ok(b
                .chunks_exact(self.dtype.size.max(4))
                .map(|c| {
                    c.chunks_exact(4)
                        .map(|u| {
                            if self.dtype.big_endian {
                                u32::from_be_bytes([u[0], u[1], u[2], u[3]])
                            } else {
                                u32::from_le_bytes([u[0], u[1], u[2], u[3]])
                            }
                        })
                        .take_while(|&x| x != 0)
                        .map(|x| char::from_u32(x).unwrap_or('\u{fffd}'))
                        .collect()
                })
                .collect()),
            (ArrayData::Raw(b), 'S') => Ok(b
                .chunks_exact(self.dtype.size.max(1))
                .map(|c| {
                    c.iter()
                        .take_while(|&&x| x != 0)
                        .map(|&x| x as char)
                        .collect()
                })
                .collect()),
            (ArrayData::Objects(items), _) => items
                .iter()
                .map(|v| match v {
                    Value::Str(s) => Ok(s.to_string()),
                    other => Err(format!("a {} in a string array", other.kind())),
                })
                .collect(),
            _ => Err(format!(
                "dtype `{}{}`, expected strings",
                self.dtype.kind, self.dtype.size
            )),
        }
    }
}

fn element(d: &Dtype, c: &[u8]) -> f64 {
    let mut b = [0u8; 8];
    b[..c.len()].copy_from_slice(c);
    if d.big_endian {
        b[..c.len()].reverse();
    }
    match (d.kind, d.size) {
        ('f', 2) => half_to_f64(u16::from_le_bytes([b[0], b[1]])),
        ('f', 4) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
        ('f', _) => f64::from_le_bytes(b),
        ('i', n) => {
            let shift = 64 - 8 * n as u32;
            ((i64::from_le_bytes(b) << shift) >> shift) as f64
        }
        ('u', _) => u64::from_le_bytes(b) as f64,
        _ => (b[0] != 0) as u8 as f64,
    }
}

fn half_to_f64(h: u16) -> f64 {
    let s = if h >> 15 == 1 { -1.0 } else { 1.0 };
    let e = ((h >> 10) & 0x1f) as i32;
    let m = (h & 0x3ff) as f64;
    match e {
        0 => s * m * 2f64.powi(-24),
        31 if m == 0.0 => s * f64::INFINITY,
        31 => f64::NAN,
        _ => s * (1.0 + m / 1024.0) * 2f64.powi(e - 15),
    }
}

/// Column-major elements of `shape` → row-major.
fn fortran_to_c(v: &[f64], shape: &[usize]) -> Vec<f64> {
    let n = v.len();
    let mut out = vec![0.0; n];
    let mut idx = vec![0usize; shape.len()];
    for slot in out.iter_mut() {
        // Fortran offset of the current C-order index.
        let mut off = 0;
        let mut stride = 1;
        for (i, &d) in idx.iter().zip(shape) {
            off += i * stride;
            stride *= d;
        }
        *slot = v[off];
        for k in (0..shape.len()).rev() {
            idx[k] += 1;
            if idx[k] < shape[k] {
                break;
            }
            idx[k] = 0;
        }
    }
    out
}

/// Classes whose instances are kept as their pickled state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StateClass {
    /// `scipy.sparse` `csc_matrix`/`csr_matrix`: state `{data, indices, indptr, _shape}`.
    Sparse { csr: bool },
    /// `chumpy.ch.Ch`: state `{'x': ndarray, ...}`.
    Chumpy,
}

/// What the numpy policy builds.
#[derive(Clone, Debug)]
pub enum NpObject {
    Reconstruct,
    NdarrayClass,
    DtypeClass,
    Scalar,
    CodecsEncode,
    Reconstructor,
    OrderedDict,
    Class(StateClass),
    Dtype(Dtype),
    /// `_reconstruct(ndarray, ...)` before its `BUILD`.
    EmptyArray,
    Array(Rc<NpArray>),
    Instance {
        class: StateClass,
        state: Option<Rc<Value<NpObject>>>,
    },
}

impl Object for NpObject {
    fn kind(&self) -> &'static str {
        match self {
            NpObject::Dtype(_) => "numpy dtype",
            NpObject::EmptyArray | NpObject::Array(_) => "numpy array",
            NpObject::Instance { .. } => "object",
            _ => "global",
        }
    }
    fn is_callable(&self) -> bool {
        matches!(
            self,
            NpObject::Reconstruct
                | NpObject::DtypeClass
                | NpObject::Scalar
                | NpObject::CodecsEncode
                | NpObject::Reconstructor
                | NpObject::OrderedDict
        )
    }
}

/// numpy arrays, dtypes and scalars, `_codecs.encode` (how Python 3 pickles
/// bytes at protocol 2), scipy sparse matrices, chumpy `Ch` and plain data.
#[derive(Clone, Copy, Debug, Default)]
pub struct NumpyData;

const ACCEPTED: Accepted = Accepted(
    "numpy arrays/dtypes/scalars (numpy.core.multiarray._reconstruct, numpy._core.multiarray._reconstruct, numpy.ndarray, numpy.dtype, numpy.core.multiarray.scalar), _codecs.encode, copy_reg._reconstructor, scipy.sparse csc_matrix/csr_matrix, chumpy.ch.Ch and collections.OrderedDict",
);

fn seq_of<'h>(
    heap: &'h Heap<NpObject>,
    v: &Value<NpObject>,
    what: &str,
) -> Result<&'h [Value<NpObject>], String> {
    heap.seq(v)
        .ok_or_else(|| format!("{what}: expected a tuple, got a {}", v.kind()))
}

fn bytes_of(v: &Value<NpObject>) -> Option<Rc<[u8]>> {
    match v {
        Value::Bytes(b) => Some(b.clone()),
        // Python 2 str, read as Latin-1: every char is one byte.
        Value::Str(s) => s
            .chars()
            .map(|c| u8::try_from(c as u32).ok())
            .collect::<Option<Vec<u8>>>()
            .map(Rc::from),
        _ => None,
    }
}

impl Policy for NumpyData {
    type Object = NpObject;
    const NEWOBJ: bool = true;

    fn accepted(&self) -> &'static Accepted {
        &ACCEPTED
    }

    fn global(&self, module: &str, name: &str) -> Option<NpObject> {
        let numpy_core = matches!(
            module,
            "numpy.core.multiarray" | "numpy._core.multiarray" | "numpy"
        );
        Some(match (module, name) {
            (_, "_reconstruct") if numpy_core => NpObject::Reconstruct,
            (_, "scalar") if numpy_core => NpObject::Scalar,
            ("numpy", "ndarray") => NpObject::NdarrayClass,
            ("numpy", "dtype") => NpObject::DtypeClass,
            ("_codecs", "encode") => NpObject::CodecsEncode,
            ("copy_reg" | "copyreg", "_reconstructor") => NpObject::Reconstructor,
            ("collections", "OrderedDict") => NpObject::OrderedDict,
            ("chumpy.ch", "Ch") => NpObject::Class(StateClass::Chumpy),
            (
                "scipy.sparse.csc" | "scipy.sparse._csc" | "scipy.sparse.csr" | "scipy.sparse._csr"
                | "scipy.sparse",
                "csc_matrix" | "csr_matrix",
            ) => NpObject::Class(StateClass::Sparse {
                csr: name == "csr_matrix",
            }),
            _ => return None,
        })
    }

    fn reduce(
        &self,
        heap: &mut Heap<NpObject>,
        f: &NpObject,
        args: &Value<NpObject>,
    ) -> Result<Value<NpObject>, String> {
        let a = seq_of(heap, args, "arguments")?.to_vec();
        match f {
            NpObject::Reconstruct => match a.first() {
                Some(Value::Object(NpObject::NdarrayClass)) => {
                    Ok(Value::Object(NpObject::EmptyArray))
                }
                _ => Err("_reconstruct of something other than numpy.ndarray".into()),
            },
            NpObject::DtypeClass => match a.first() {
                Some(Value::Str(s)) => Dtype::parse(s)
                    .map(|d| Value::Object(NpObject::Dtype(d)))
                    .ok_or_else(|| format!("unsupported numpy dtype `{s}`")),
                _ => Err("numpy.dtype needs a descriptor string".into()),
            },
            NpObject::Scalar => {
                let (Some(Value::Object(NpObject::Dtype(d))), Some(b)) =
                    (a.first(), a.get(1).and_then(bytes_of))
                else {
                    return Err("numpy scalar needs a dtype and bytes".into());
                };
                if !matches!(d.kind, 'f' | 'i' | 'u' | 'b') || b.len() != d.size {
                    return Err(format!(
                        "numpy scalar of dtype `{}{}` with {} bytes",
                        d.kind,
                        d.size,
                        b.len()
                    ));
                }
                let x = element(d, &b);
                Ok(match d.kind {
                    'f' => Value::Float(x),
                    'b' => Value::Bool(x != 0.0),
                    _ => Value::Int(x as i64),
                })
            }
            NpObject::CodecsEncode => match (a.first(), a.get(1)) {
                (Some(s @ Value::Str(_)), Some(Value::Str(enc)))
                    if &**enc == "latin1" || &**enc == "latin-1" =>
                {
                    bytes_of(s)
                        .map(Value::Bytes)
                        .ok_or_else(|| "_codecs.encode of a non-Latin-1 string".into())
                }
                _ => Err("_codecs.encode is only accepted as (str, 'latin1')".into()),
            },
            NpObject::Reconstructor => match a.first() {
                Some(Value::Object(NpObject::Class(c))) => Ok(Value::Object(NpObject::Instance {
                    class: *c,
                    state: None,
                })),
                _ => Err("copy_reg._reconstructor of a class that is not accepted".into()),
            },
            NpObject::OrderedDict => ordered_dict(heap, args),
            _ => Err(format!("{} is not callable", f.kind())),
        }
    }

    fn new_object(
        &self,
        _heap: &mut Heap<NpObject>,
        cls: &NpObject,
        _args: &Value<NpObject>,
    ) -> Result<Value<NpObject>, String> {
        match cls {
            NpObject::Class(c) => Ok(Value::Object(NpObject::Instance {
                class: *c,
                state: None,
            })),
            other => Err(format!("NEWOBJ of a {}", other.kind())),
        }
    }

    fn build(
        &self,
        heap: &mut Heap<NpObject>,
        target: &Value<NpObject>,
        state: &Value<NpObject>,
    ) -> Option<Result<Value<NpObject>, String>> {
        let Value::Object(t) = target else {
            return None;
        };
        Some(match t {
            NpObject::EmptyArray => array_state(heap, state),
            NpObject::Dtype(d) => {
                let mut d = d.clone();
                if let Some(Value::Str(order)) =
                    heap.seq(state).and_then(|s| s.get(1)).cloned().as_ref()
                {
                    d.big_endian = &**order == ">";
                }
                Ok(Value::Object(NpObject::Dtype(d)))
            }
            NpObject::Instance { class, .. } => Ok(Value::Object(NpObject::Instance {
                class: *class,
                state: Some(Rc::new(state.clone())),
            })),
            other => Err(format!("BUILD on a {}", other.kind())),
        })
    }
}

/// `ndarray.__setstate__((version,) shape, dtype, is_fortran, data)`.
fn array_state(heap: &Heap<NpObject>, state: &Value<NpObject>) -> Result<Value<NpObject>, String> {
    let s = seq_of(heap, state, "numpy array state")?;
    let s = match s.len() {
        5 => &s[1..],
        4 => s,
        n => return Err(format!("numpy array state has {n} items, expected 4 or 5")),
    };
    let shape = seq_of(heap, &s[0], "numpy array shape")?
        .iter()
        .map(|v| match v {
            Value::Int(i) if *i >= 0 => Ok(*i as usize),
            other => Err(format!("numpy array shape entry {other:?}")),
        })
        .collect::<Result<Vec<usize>, String>>()?;
    let Value::Object(NpObject::Dtype(dtype)) = &s[1] else {
        return Err(format!("numpy array dtype is a {}", s[1].kind()));
    };
    let fortran = matches!(s[2], Value::Bool(true) | Value::Int(1));
    let n = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or("numpy array shape overflows")?;
    let data = if dtype.kind == 'O' {
        let items = heap
            .seq(&s[3])
            .ok_or("object array data is not a list")?
            .to_vec();
        if items.len() != n {
            return Err(format!(
                "object array of shape {shape:?} holds {} items",
                items.len()
            ));
        }
        ArrayData::Objects(items)
    } else {
        let b = bytes_of(&s[3]).ok_or_else(|| format!("array data is a {}", s[3].kind()))?;
        if Some(b.len()) != n.checked_mul(dtype.size) {
            return Err(format!(
                "array of shape {shape:?} and {}-byte elements has {} data bytes",
                dtype.size,
                b.len()
            ));
        }
        ArrayData::Raw(b)
    };
    Ok(Value::Object(NpObject::Array(Rc::new(NpArray {
        shape,
        dtype: dtype.clone(),
        fortran,
        data,
    }))))
}

/// A dense matrix from a value: a numpy array, a chumpy `Ch` (its `x`), a
/// scipy sparse matrix (densified), a number or a nested list of numbers.
/// Returns the shape and the row-major elements.
pub fn dense(heap: &Heap<NpObject>, v: &Value<NpObject>) -> Result<(Vec<usize>, Vec<f64>), String> {
    match v {
        Value::Int(_) | Value::Float(_) => Ok((vec![], vec![v.as_f64().unwrap_or(0.0)])),
        Value::Object(NpObject::Array(a)) => Ok((a.shape.clone(), a.to_f64()?)),
        Value::Object(NpObject::Instance {
            class: StateClass::Chumpy,
            state,
        }) => {
            let st = state.as_deref().ok_or("chumpy object without state")?;
            let x = heap
                .get(st, "x")
                .ok_or("chumpy object state has no `x` array")?;
            dense(heap, x)
        }
        Value::Object(NpObject::Instance {
            class: StateClass::Sparse { csr },
            state,
        }) => {
            let st = state.as_deref().ok_or("sparse matrix without state")?;
            let get = |k: &str| {
                heap.get(st, k)
                    .ok_or_else(|| format!("sparse matrix state has no `{k}`"))
            };
            let (_, data) = dense(heap, get("data")?)?;
            let (_, indices) = dense(heap, get("indices")?)?;
            let (_, indptr) = dense(heap, get("indptr")?)?;
            let shape_v = heap
                .get(st, "_shape")
                .or_else(|| heap.get(st, "shape"))
                .ok_or("sparse matrix state has no `_shape`")?;
            let (_, sh) = dense(heap, shape_v)?;
            let [r, c] = sh[..] else {
                return Err(format!("sparse matrix shape has {} entries", sh.len()));
            };
            let shape = [r as usize, c as usize];
            sparse_to_dense(&data, &indices, &indptr, shape, *csr).map(|d| (shape.to_vec(), d))
        }
        Value::List(_) | Value::Tuple(_) => {
            let items = heap.seq(v).unwrap_or_default();
            let mut shape = None;
            let mut out = Vec::new();
            for it in items {
                let (s, d) = dense(heap, it)?;
                if shape.get_or_insert_with(|| s.clone()) != &s {
                    return Err("ragged nested list".into());
                }
                out.extend(d);
            }
            let mut full = vec![items.len()];
            full.extend(shape.unwrap_or_default());
            Ok((full, out))
        }
        other => Err(format!("a {}, expected an array", other.kind())),
    }
}

/// Compressed sparse columns (or rows) → a dense row-major matrix.
pub fn sparse_to_dense(
    data: &[f64],
    indices: &[f64],
    indptr: &[f64],
    shape: [usize; 2],
    csr: bool,
) -> Result<Vec<f64>, String> {
    let [r, c] = shape;
    let (major, minor) = if csr { (r, c) } else { (c, r) };
    if indptr.len() != major + 1 || data.len() != indices.len() {
        return Err(format!(
            "sparse matrix of shape {shape:?}: indptr has {} entries (expected {}), data {} and indices {}",
            indptr.len(),
            major + 1,
            data.len(),
            indices.len()
        ));
    }
    let mut out = vec![0.0; r * c];
    for m in 0..major {
        let (a, b) = (indptr[m], indptr[m + 1]);
        if !(a >= 0.0 && a <= b && (b as usize) <= data.len()) {
            return Err(format!("sparse matrix indptr[{m}..{}] out of order", m + 1));
        }
        for k in a as usize..b as usize {
            let i = indices[k];
            if !(i >= 0.0 && (i as usize) < minor) {
                return Err(format!("sparse matrix index {i} out of range 0..{minor}"));
            }
            let (row, col) = if csr {
                (m, i as usize)
            } else {
                (i as usize, m)
            };
            out[row * c + col] += data[k];
        }
    }
    Ok(out)
}

/// The single element of a 0-d object array (`np.save` of a dict), or the
/// value itself.
pub fn item(v: &Value<NpObject>) -> Value<NpObject> {
    if let Value::Object(NpObject::Array(a)) = v {
        if let ArrayData::Objects(items) = &a.data {
            if a.shape.is_empty() && items.len() == 1 {
                return items[0].clone();
            }
        }
    }
    v.clone()
}

/// A list of strings from a list/tuple of `str` or a string/object array.
pub fn strings(heap: &Heap<NpObject>, v: &Value<NpObject>) -> Result<Vec<String>, String> {
    match v {
        Value::Object(NpObject::Array(a)) => a.to_strings(),
        Value::List(_) | Value::Tuple(_) => heap
            .seq(v)
            .unwrap_or_default()
            .iter()
            .map(|x| match x {
                Value::Str(s) => Ok(s.to_string()),
                other => Err(format!("a {} in a list of paths", other.kind())),
            })
            .collect(),
        other => Err(format!("a {}, expected a list of strings", other.kind())),
    }
}

/// The items of a list/tuple or a 1-d object array.
pub fn items(heap: &Heap<NpObject>, v: &Value<NpObject>) -> Option<Vec<Value<NpObject>>> {
    match v {
        Value::Object(NpObject::Array(a)) => match &a.data {
            ArrayData::Objects(x) => Some(x.clone()),
            ArrayData::Raw(_) => None,
        },
        _ => heap.seq(v).map(|s| s.to_vec()),
    }
}
