//! Reader for `torch.save` zip checkpoints that never runs pickle code.
//!
//! A torch zip archive holds `<archive>/data.pkl`, the pickled object graph, and
//! one stored entry `<archive>/data/<key>` per tensor storage ([`TorchArchive`]).
//! The pickle is interpreted by the restricted machine of [`crate::pickle`]
//! under [`TorchPickle`], which accepts only the globals needed to rebuild
//! tensors and turns them into [`TensorRef`]s. Tensor bytes are copied
//! verbatim from the storages, never converted.
//!
//! [`read_reference_checkpoint`] then picks out what the reference trainer
//! saves: `{'model': state_dict, 'optimizer': Adam state_dict, 'global_iter': int}`
//! (docs/reference.md, "Checkpoint and state_dict names").

mod archive;
mod reference;

use std::{path::Path, rc::Rc};

use safetensors::Dtype;

use crate::{
    error::Result,
    pickle::{self, ordered_dict, Accepted, Object, Policy},
};

pub use archive::TorchArchive;
pub use reference::{
    read_reference_checkpoint, ReferenceCheckpoint, TorchAdam, TorchAdamGroup, TorchAdamParam,
};

/// A value of a torch pickle.
pub type Value = pickle::Value<TorchObject>;
/// The containers of a torch pickle.
pub type Heap = pickle::Heap<TorchObject>;
/// An unpickled torch object graph.
pub type Unpickled = pickle::Unpickled<TorchObject>;

/// Interprets a torch pickle with [`TorchPickle`]. `path`/`entry` only label errors.
pub fn unpickle(data: &[u8], path: &Path, entry: &str) -> Result<Unpickled> {
    pickle::parse(data, &TorchPickle, path, entry)
}

/// A tensor as the pickle describes it; its bytes are still in the archive.
#[derive(Clone, Debug, PartialEq)]
pub struct TensorRef {
    pub dtype: Dtype,
    /// Storage entry name under `<archive>/data/`.
    pub key: String,
    /// Elements in the whole storage.
    pub storage_numel: usize,
    /// Element offset of the tensor's first value in the storage.
    pub offset: usize,
    pub shape: Vec<usize>,
    pub stride: Vec<usize>,
}

/// A storage named by a persistent id.
#[derive(Clone, Debug, PartialEq)]
pub struct StorageRef {
    pub dtype: Dtype,
    pub key: String,
    pub numel: usize,
}

/// What [`TorchPickle`] builds from its globals.
#[derive(Clone, Debug)]
pub enum TorchObject {
    /// An allowed global function or class.
    Callable(Callable),
    /// A legacy typed storage class (`torch.FloatStorage`, ...), valid only
    /// inside a persistent id.
    StorageClass(Dtype),
    /// A storage of the archive, from a persistent id.
    Storage(Rc<StorageRef>),
    Tensor(Rc<TensorRef>),
}

impl Object for TorchObject {
    fn kind(&self) -> &'static str {
        match self {
            TorchObject::Callable(_) => "global",
            TorchObject::StorageClass(_) => "storage class",
            TorchObject::Storage(_) => "storage",
            TorchObject::Tensor(_) => "tensor",
        }
    }

    fn is_callable(&self) -> bool {
        matches!(self, TorchObject::Callable(_))
    }
}

impl Value {
    /// The tensor this value is, if it is one.
    pub fn as_tensor(&self) -> Option<&TensorRef> {
        match self {
            pickle::Value::Object(TorchObject::Tensor(t)) => Some(t),
            _ => None,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Callable {
    OrderedDict,
    RebuildTensorV2,
    RebuildParameter,
}

/// Globals a checkpoint may name besides the storage classes of [`storage_dtype`].
const ALLOWED_GLOBALS: &[(&str, &str, Callable)] = &[
    ("collections", "OrderedDict", Callable::OrderedDict),
    (
        "torch._utils",
        "_rebuild_tensor_v2",
        Callable::RebuildTensorV2,
    ),
    (
        "torch._utils",
        "_rebuild_parameter",
        Callable::RebuildParameter,
    ),
];

/// The dtype a legacy typed storage class stands for.
fn storage_dtype(name: &str) -> Option<Dtype> {
    Some(match name {
        "FloatStorage" => Dtype::F32,
        "DoubleStorage" => Dtype::F64,
        "HalfStorage" => Dtype::F16,
        "BFloat16Storage" => Dtype::BF16,
        "LongStorage" => Dtype::I64,
        "IntStorage" => Dtype::I32,
        "ShortStorage" => Dtype::I16,
        "CharStorage" => Dtype::I8,
        "ByteStorage" => Dtype::U8,
        "BoolStorage" => Dtype::BOOL,
        _ => return None,
    })
}

/// The pickle policy of `torch.save`: tensors (`_rebuild_tensor_v2`,
/// `_rebuild_parameter`) over storages named by persistent ids, and
/// `collections.OrderedDict` for state_dicts.
#[derive(Clone, Copy, Debug, Default)]
pub struct TorchPickle;

type Built = std::result::Result<Value, String>;

impl Policy for TorchPickle {
    type Object = TorchObject;

    fn accepted(&self) -> &'static Accepted {
        &Accepted("torch tensor/storage rebuilders and collections.OrderedDict")
    }

    fn global(&self, module: &str, name: &str) -> Option<TorchObject> {
        if module == "torch" {
            if let Some(d) = storage_dtype(name) {
                return Some(TorchObject::StorageClass(d));
            }
        }
        ALLOWED_GLOBALS
            .iter()
            .find(|(m, n, _)| (*m, *n) == (module, name))
            .map(|&(_, _, c)| TorchObject::Callable(c))
    }

    fn reduce(&self, heap: &mut Heap, f: &TorchObject, args: &Value) -> Built {
        match f {
            TorchObject::Callable(Callable::OrderedDict) => ordered_dict(heap, args),
            TorchObject::Callable(Callable::RebuildTensorV2) => {
                rebuild_tensor(heap, heap.seq(args).unwrap_or_default())
            }
            TorchObject::Callable(Callable::RebuildParameter) => {
                match heap.seq(args).unwrap_or_default() {
                    [t @ pickle::Value::Object(TorchObject::Tensor(_)), _, _] => Ok(t.clone()),
                    _ => Err("_rebuild_parameter expects (tensor, requires_grad, hooks)".into()),
                }
            }
            other => Err(format!(
                "REDUCE on a {}, which is not callable",
                other.kind()
            )),
        }
    }

    /// `('storage', <storage class>, key, location, numel)`.
    fn persistent_load(&self, heap: &Heap, pid: Value) -> Built {
        let bad = || {
            "persistent id is not ('storage', <torch storage class>, key, location, numel)"
                .to_string()
        };
        let t = match pid {
            pickle::Value::Tuple(_) => heap.seq(&pid).unwrap_or_default(),
            _ => return Err(bad()),
        };
        use pickle::Value::{Int, Object as Obj, Str};
        match t {
            [Str(tag), Obj(TorchObject::StorageClass(dtype)), Str(key), Str(_location), Int(numel)]
                if &**tag == "storage" && *numel >= 0 =>
            {
                // The key becomes part of an archive path: keep it a plain name.
                if key.is_empty() || !key.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
                    return Err(format!("storage key {key:?} is not a plain name"));
                }
                Ok(Obj(TorchObject::Storage(Rc::new(StorageRef {
                    dtype: *dtype,
                    key: key.to_string(),
                    numel: *numel as usize,
                }))))
            }
            _ => Err(bad()),
        }
    }
}

/// `_rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks[, metadata])`.
fn rebuild_tensor(heap: &Heap, args: &[Value]) -> Built {
    if !(6..=7).contains(&args.len()) {
        return Err(format!(
            "_rebuild_tensor_v2 takes 6 or 7 arguments, got {}",
            args.len()
        ));
    }
    let pickle::Value::Object(TorchObject::Storage(storage)) = &args[0] else {
        return Err(format!(
            "_rebuild_tensor_v2: argument 0 is a {}, expected a storage",
            args[0].kind()
        ));
    };
    let offset = usize_arg(&args[1], "storage offset")?;
    let shape = tuple_arg(heap, &args[2], "size")?;
    let stride = tuple_arg(heap, &args[3], "stride")?;
    if shape.len() != stride.len() {
        return Err(format!(
            "_rebuild_tensor_v2: size {shape:?} and stride {stride:?} differ in rank"
        ));
    }
    if !matches!(args[4], pickle::Value::Bool(_)) {
        return Err("_rebuild_tensor_v2: requires_grad must be a bool".into());
    }
    Ok(pickle::Value::Object(TorchObject::Tensor(Rc::new(
        TensorRef {
            dtype: storage.dtype,
            key: storage.key.clone(),
            storage_numel: storage.numel,
            offset,
            shape,
            stride,
        },
    ))))
}

fn usize_arg(v: &Value, what: &str) -> std::result::Result<usize, String> {
    match v {
        pickle::Value::Int(i) if *i >= 0 => Ok(*i as usize),
        pickle::Value::Int(i) => Err(format!(
            "_rebuild_tensor_v2: {what} must be non-negative, got {i}"
        )),
        other => Err(format!(
            "_rebuild_tensor_v2: {what} must be an int, got a {}",
            other.kind()
        )),
    }
}

fn tuple_arg(heap: &Heap, v: &Value, what: &str) -> std::result::Result<Vec<usize>, String> {
    match (v, heap.seq(v)) {
        (pickle::Value::Tuple(_), Some(t)) => t.iter().map(|x| usize_arg(x, what)).collect(),
        (other, _) => Err(format!(
            "_rebuild_tensor_v2: {what} must be a tuple, got a {}",
            other.kind()
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ConvertError;

    fn run(bytes: &[u8]) -> Result<Unpickled> {
        unpickle(bytes, Path::new("t.pkl"), "data.pkl")
    }

    #[test]
    fn reduce_on_a_non_callable_is_refused() {
        // torch.FloatStorage is only valid inside a persistent id.
        let msg = run(b"\x80\x02ctorch\nFloatStorage\n)R.")
            .unwrap_err()
            .to_string();
        assert!(
            msg.contains("REDUCE") && msg.contains("not callable"),
            "{msg}"
        );
    }

    #[test]
    fn bad_persistent_ids_are_refused() {
        let msg = run(b"\x80\x02X\x03\x00\x00\x00abcQ.")
            .unwrap_err()
            .to_string();
        assert!(msg.contains("persistent id"), "{msg}");
        // A storage key that would escape the archive's data/ folder.
        let p = b"\x80\x02(X\x07\x00\x00\x00storagectorch\nFloatStorage\nX\x06\x00\x00\x00../../X\x03\x00\x00\x00cpuK\x01tQ.";
        let msg = run(p).unwrap_err().to_string();
        assert!(msg.contains("plain name"), "{msg}");
    }

    #[test]
    fn forbidden_global_names_what_torch_accepts() {
        let p = b"\x80\x04\x8c\x08builtins\x8c\x04eval\x93.";
        match run(p) {
            Err(e @ ConvertError::ForbiddenGlobal { .. }) => assert!(
                e.to_string().ends_with(
                    "only torch tensor/storage rebuilders and collections.OrderedDict are accepted"
                ),
                "{e}"
            ),
            other => panic!("{other:?}"),
        }
    }
}
