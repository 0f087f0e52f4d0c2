//! Reader for `torch.save` zip checkpoints that never runs pickle code.
//!
//! A torch zip archive holds `<archive>/data.pkl`, the pickled object graph, and
//! one stored entry `<archive>/data/<key>` per tensor storage. Python's unpickler
//! would import and call whatever the pickle names; here the pickle is
//! interpreted by a small stack machine that knows only the opcodes torch.save
//! emits for dicts, lists, tuples, numbers, strings and tensors, and only the
//! globals needed to rebuild tensors (see [`ALLOWED_GLOBALS`]). Anything else is
//! refused with its byte offset. Tensor bytes are copied verbatim from the
//! storages, never converted.
//!
//! [`read_reference_checkpoint`] then picks out what the reference trainer
//! saves: `{'model': state_dict, 'optimizer': Adam state_dict, 'global_iter': int}`
//! (spec model.md §8.3).

use std::{
    collections::{BTreeMap, HashMap},
    fs::File,
    io::{BufReader, Read},
    path::{Path, PathBuf},
    rc::Rc,
};

use safetensors::Dtype;

use crate::{
    error::{ConvertError, Result},
    raw::RawTensor,
};

/// Globals a checkpoint may name, as `(module, name)`. Storage classes
/// (`torch.FloatStorage`, ...) are accepted as well; see [`storage_dtype`].
pub const ALLOWED_GLOBALS: &[(&str, &str)] = &[
    ("collections", "OrderedDict"),
    ("torch._utils", "_rebuild_tensor_v2"),
    ("torch._utils", "_rebuild_parameter"),
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

fn dtype_size(d: Dtype) -> usize {
    match d {
        Dtype::F64 | Dtype::I64 | Dtype::U64 => 8,
        Dtype::F32 | Dtype::I32 | Dtype::U32 => 4,
        Dtype::F16 | Dtype::BF16 | Dtype::I16 | Dtype::U16 => 2,
        _ => 1,
    }
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

/// An unpickled value. Containers live in [`Heap`] and are referred to by
/// index: pickles mutate containers after memoising them, later references
/// must see the result, and a hostile pickle can nest containers millions deep,
/// which an owned tree would drop recursively and overflow the stack.
#[derive(Clone, Debug)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(Rc<str>),
    Tuple(usize),
    List(usize),
    /// Insertion-ordered (OrderedDict order is the state_dict order).
    Dict(usize),
    Tensor(Rc<TensorRef>),
    /// Internal: an allowed global, a storage class, or a persistent storage.
    Callable(Callable),
    StorageClass(Dtype),
    Storage(Rc<StorageRef>),
}

#[derive(Clone, Debug)]
pub enum Container {
    Tuple(Vec<Value>),
    List(Vec<Value>),
    Dict(Vec<(Value, Value)>),
}

/// Every container an unpickling created.
#[derive(Clone, Debug, Default)]
pub struct Heap(Vec<Container>);

impl Heap {
    fn alloc(&mut self, c: Container) -> usize {
        self.0.push(c);
        self.0.len() - 1
    }

    /// The items of a list or tuple.
    pub fn seq(&self, v: &Value) -> Option<&[Value]> {
        match v {
            Value::Tuple(i) | Value::List(i) => match &self.0[*i] {
                Container::Tuple(x) | Container::List(x) => Some(x),
                Container::Dict(_) => None,
            },
            _ => None,
        }
    }

    pub fn items(&self, v: &Value) -> Option<&[(Value, Value)]> {
        match v {
            Value::Dict(i) => match &self.0[*i] {
                Container::Dict(x) => Some(x),
                _ => None,
            },
            _ => None,
        }
    }

    /// Dict lookup by string key.
    pub fn get(&self, v: &Value, key: &str) -> Option<&Value> {
        self.items(v)?
            .iter()
            .find(|(k, _)| matches!(k, Value::Str(s) if &**s == key))
            .map(|(_, v)| v)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Callable {
    OrderedDict,
    RebuildTensorV2,
    RebuildParameter,
}

#[derive(Clone, Debug, PartialEq)]
pub struct StorageRef {
    pub dtype: Dtype,
    pub key: String,
    pub numel: usize,
}

impl Value {
    fn kind(&self) -> &'static str {
        match self {
            Value::None => "None",
            Value::Bool(_) => "bool",
            Value::Int(_) => "int",
            Value::Float(_) => "float",
            Value::Str(_) => "str",
            Value::Tuple(_) => "tuple",
            Value::List(_) => "list",
            Value::Dict(_) => "dict",
            Value::Tensor(_) => "tensor",
            Value::Callable(_) => "global",
            Value::StorageClass(_) => "storage class",
            Value::Storage(_) => "storage",
        }
    }
}

/// Human-readable names of every pickle opcode, for error messages.
fn opcode_name(op: u8) -> &'static str {
    match op {
        b'(' => "MARK",
        b'.' => "STOP",
        b'0' => "POP",
        b'1' => "POP_MARK",
        b'2' => "DUP",
        b'F' => "FLOAT",
        b'I' => "INT",
        b'J' => "BININT",
        b'K' => "BININT1",
        b'L' => "LONG",
        b'M' => "BININT2",
        b'N' => "NONE",
        b'P' => "PERSID",
        b'Q' => "BINPERSID",
        b'R' => "REDUCE",
        b'S' => "STRING",
        b'T' => "BINSTRING",
        b'U' => "SHORT_BINSTRING",
        b'V' => "UNICODE",
        b'X' => "BINUNICODE",
        b'a' => "APPEND",
        b'b' => "BUILD",
        b'c' => "GLOBAL",
        b'd' => "DICT",
        b'}' => "EMPTY_DICT",
        b'e' => "APPENDS",
        b'g' => "GET",
        b'h' => "BINGET",
        b'i' => "INST",
        b'j' => "LONG_BINGET",
        b'l' => "LIST",
        b']' => "EMPTY_LIST",
        b'o' => "OBJ",
        b'p' => "PUT",
        b'q' => "BINPUT",
        b'r' => "LONG_BINPUT",
        b's' => "SETITEM",
        b't' => "TUPLE",
        b')' => "EMPTY_TUPLE",
        b'u' => "SETITEMS",
        b'G' => "BINFLOAT",
        0x80 => "PROTO",
        0x81 => "NEWOBJ",
        0x82 => "EXT1",
        0x83 => "EXT2",
        0x84 => "EXT4",
        0x85 => "TUPLE1",
        0x86 => "TUPLE2",
        0x87 => "TUPLE3",
        0x88 => "NEWTRUE",
        0x89 => "NEWFALSE",
        0x8a => "LONG1",
        0x8b => "LONG4",
        b'B' => "BINBYTES",
        b'C' => "SHORT_BINBYTES",
        0x8c => "SHORT_BINUNICODE",
        0x8d => "BINUNICODE8",
        0x8e => "BINBYTES8",
        0x8f => "EMPTY_SET",
        0x90 => "ADDITEMS",
        0x91 => "FROZENSET",
        0x92 => "NEWOBJ_EX",
        0x93 => "STACK_GLOBAL",
        0x94 => "MEMOIZE",
        0x95 => "FRAME",
        0x96 => "BYTEARRAY8",
        0x97 => "NEXT_BUFFER",
        0x98 => "READONLY_BUFFER",
        _ => "unknown",
    }
}

/// Where a pickle came from, for error messages.
struct Origin<'a> {
    path: &'a Path,
    entry: &'a str,
}

impl Origin<'_> {
    fn err(&self, offset: usize, msg: impl Into<String>) -> ConvertError {
        ConvertError::Pickle {
            path: self.path.to_path_buf(),
            entry: self.entry.to_string(),
            offset,
            msg: msg.into(),
        }
    }
}

struct Vm<'a> {
    data: &'a [u8],
    pos: usize,
    /// Offset of the opcode being executed.
    op_start: usize,
    stack: Vec<Value>,
    marks: Vec<usize>,
    memo: HashMap<u64, Value>,
    heap: Heap,
    origin: Origin<'a>,
}

impl<'a> Vm<'a> {
    fn err(&self, msg: impl Into<String>) -> ConvertError {
        self.origin.err(self.op_start, msg)
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.data.len());
        match end {
            Some(end) => {
                let s = &self.data[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(self.err(format!(
                "needs {n} more bytes but the pickle ends at byte {} (truncated?)",
                self.data.len()
            ))),
        }
    }

    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }

    fn le<const N: usize>(&mut self) -> Result<[u8; N]> {
        let mut b = [0u8; N];
        b.copy_from_slice(self.take(N)?);
        Ok(b)
    }

    fn line(&mut self) -> Result<&'a str> {
        let rest = &self.data[self.pos..];
        let n = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| self.err("GLOBAL name is not newline-terminated"))?;
        let s =
            std::str::from_utf8(&rest[..n]).map_err(|_| self.err("GLOBAL name is not UTF-8"))?;
        self.pos += n + 1;
        Ok(s)
    }

    fn string(&mut self, n: usize) -> Result<Value> {
        let b = self.take(n)?;
        let s = std::str::from_utf8(b).map_err(|_| self.err("string is not valid UTF-8"))?;
        Ok(Value::Str(Rc::from(s)))
    }

    fn pop(&mut self) -> Result<Value> {
        self.stack.pop().ok_or_else(|| self.err("stack underflow"))
    }

    fn top(&self) -> Result<&Value> {
        self.stack.last().ok_or_else(|| self.err("stack underflow"))
    }

    fn pop_mark(&mut self) -> Result<Vec<Value>> {
        let m = self
            .marks
            .pop()
            .ok_or_else(|| self.err("no MARK on the stack"))?;
        if m > self.stack.len() {
            return Err(self.err("MARK points past the stack"));
        }
        Ok(self.stack.split_off(m))
    }

    fn dict_mut(&mut self) -> Result<&mut Vec<(Value, Value)>> {
        match self.stack.last() {
            Some(Value::Dict(i)) => match &mut self.heap.0[*i] {
                Container::Dict(d) => Ok(d),
                _ => Err(self.origin.err(self.op_start, "corrupt heap")),
            },
            Some(other) => Err(self.err(format!("setting a dict item on a {}", other.kind()))),
            None => Err(self.err("stack underflow")),
        }
    }

    fn list_mut(&mut self) -> Result<&mut Vec<Value>> {
        match self.stack.last() {
            Some(Value::List(i)) => match &mut self.heap.0[*i] {
                Container::List(l) => Ok(l),
                _ => Err(self.origin.err(self.op_start, "corrupt heap")),
            },
            Some(other) => Err(self.err(format!("appending to a {}", other.kind()))),
            None => Err(self.err("stack underflow")),
        }
    }

    fn memo_put(&mut self, idx: u64) -> Result<()> {
        let v = self.top()?.clone();
        self.memo.insert(idx, v);
        Ok(())
    }

    fn memo_get(&mut self, idx: u64) -> Result<()> {
        let v = self
            .memo
            .get(&idx)
            .cloned()
            .ok_or_else(|| self.err(format!("memo slot {idx} is empty")))?;
        self.stack.push(v);
        Ok(())
    }

    fn global(&self, module: &str, name: &str) -> Result<Value> {
        if module == "torch" {
            if let Some(d) = storage_dtype(name) {
                return Ok(Value::StorageClass(d));
            }
        }
        let callable = match (module, name) {
            ("collections", "OrderedDict") => Callable::OrderedDict,
            ("torch._utils", "_rebuild_tensor_v2") => Callable::RebuildTensorV2,
            ("torch._utils", "_rebuild_parameter") => Callable::RebuildParameter,
            _ => {
                return Err(ConvertError::ForbiddenGlobal {
                    path: self.origin.path.to_path_buf(),
                    entry: self.origin.entry.to_string(),
                    offset: self.op_start,
                    module: module.to_string(),
                    name: name.to_string(),
                })
            }
        };
        Ok(Value::Callable(callable))
    }

    fn reduce(&mut self, f: Value, args: Value) -> Result<Value> {
        let Value::Callable(f) = f else {
            return Err(self.err(format!("REDUCE on a {}, which is not callable", f.kind())));
        };
        let Value::Tuple(id) = args else {
            return Err(self.err(format!(
                "REDUCE arguments are a {}, expected a tuple",
                args.kind()
            )));
        };
        let args = self.heap.seq(&Value::Tuple(id)).unwrap_or_default();
        match f {
            Callable::OrderedDict => {
                if !args.is_empty() {
                    return Err(self.err("collections.OrderedDict called with arguments"));
                }
                Ok(Value::Dict(self.heap.alloc(Container::Dict(Vec::new()))))
            }
            Callable::RebuildTensorV2 => self.rebuild_tensor(args),
            Callable::RebuildParameter => match args.first() {
                Some(Value::Tensor(t)) if args.len() == 3 => Ok(Value::Tensor(t.clone())),
                _ => Err(self.err("_rebuild_parameter expects (tensor, requires_grad, hooks)")),
            },
        }
    }

    fn rebuild_tensor(&self, args: &[Value]) -> Result<Value> {
        if !(6..=7).contains(&args.len()) {
            return Err(self.err(format!(
                "_rebuild_tensor_v2 takes 6 or 7 arguments, got {}",
                args.len()
            )));
        }
        let Value::Storage(storage) = &args[0] else {
            return Err(self.err(format!(
                "_rebuild_tensor_v2: argument 0 is a {}, expected a storage",
                args[0].kind()
            )));
        };
        let usize_of = |v: &Value, what: &str| -> Result<usize> {
            match v {
                Value::Int(i) if *i >= 0 => Ok(*i as usize),
                Value::Int(i) => Err(self.err(format!(
                    "_rebuild_tensor_v2: {what} must be non-negative, got {i}"
                ))),
                other => Err(self.err(format!(
                    "_rebuild_tensor_v2: {what} must be an int, got a {}",
                    other.kind()
                ))),
            }
        };
        let tuple_of = |v: &Value, what: &str| -> Result<Vec<usize>> {
            match (v, self.heap.seq(v)) {
                (Value::Tuple(_), Some(t)) => t.iter().map(|x| usize_of(x, what)).collect(),
                (other, _) => Err(self.err(format!(
                    "_rebuild_tensor_v2: {what} must be a tuple, got a {}",
                    other.kind()
                ))),
            }
        };
        let offset = usize_of(&args[1], "storage offset")?;
        let shape = tuple_of(&args[2], "size")?;
        let stride = tuple_of(&args[3], "stride")?;
        if shape.len() != stride.len() {
            return Err(self.err(format!(
                "_rebuild_tensor_v2: size {shape:?} and stride {stride:?} differ in rank"
            )));
        }
        if !matches!(args[4], Value::Bool(_)) {
            return Err(self.err("_rebuild_tensor_v2: requires_grad must be a bool"));
        }
        Ok(Value::Tensor(Rc::new(TensorRef {
            dtype: storage.dtype,
            key: storage.key.clone(),
            storage_numel: storage.numel,
            offset,
            shape,
            stride,
        })))
    }

    fn persistent_load(&self, pid: Value) -> Result<Value> {
        let bad = || {
            self.err(
                "persistent id is not ('storage', <torch storage class>, key, location, numel)",
            )
        };
        let t = match pid {
            Value::Tuple(_) => self.heap.seq(&pid).unwrap_or_default(),
            _ => return Err(bad()),
        };
        match t {
            [Value::Str(tag), Value::StorageClass(dtype), Value::Str(key), Value::Str(_location), Value::Int(numel)]
                if &**tag == "storage" && *numel >= 0 =>
            {
                // The key becomes part of an archive path: keep it a plain name.
                if key.is_empty() || !key.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
                    return Err(self.err(format!("storage key {key:?} is not a plain name")));
                }
                Ok(Value::Storage(Rc::new(StorageRef {
                    dtype: *dtype,
                    key: key.to_string(),
                    numel: *numel as usize,
                })))
            }
            _ => Err(bad()),
        }
    }

    fn run(mut self) -> Result<Unpickled> {
        loop {
            self.op_start = self.pos;
            let op = self.u8()?;
            match op {
                0x80 => {
                    let proto = self.u8()?;
                    if proto > 5 {
                        return Err(self.err(format!("unsupported pickle protocol {proto}")));
                    }
                }
                // Framing is only a read-ahead hint; the content follows inline.
                0x95 => {
                    self.le::<8>()?;
                }
                b'.' => {
                    let root = self.pop()?;
                    return Ok(Unpickled {
                        root,
                        heap: self.heap,
                    });
                }
                b'(' => self.marks.push(self.stack.len()),
                b'}' => {
                    let id = self.heap.alloc(Container::Dict(Vec::new()));
                    self.stack.push(Value::Dict(id));
                }
                b']' => {
                    let id = self.heap.alloc(Container::List(Vec::new()));
                    self.stack.push(Value::List(id));
                }
                b')' => {
                    let id = self.heap.alloc(Container::Tuple(Vec::new()));
                    self.stack.push(Value::Tuple(id));
                }
                b't' => {
                    let items = self.pop_mark()?;
                    let id = self.heap.alloc(Container::Tuple(items));
                    self.stack.push(Value::Tuple(id));
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    if self.stack.len() < n {
                        return Err(self.err("stack underflow"));
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    let id = self.heap.alloc(Container::Tuple(items));
                    self.stack.push(Value::Tuple(id));
                }
                b'X' => {
                    let n = u32::from_le_bytes(self.le()?) as usize;
                    let v = self.string(n)?;
                    self.stack.push(v);
                }
                0x8c => {
                    let n = self.u8()? as usize;
                    let v = self.string(n)?;
                    self.stack.push(v);
                }
                0x8d => {
                    let n = u64::from_le_bytes(self.le()?);
                    let n = usize::try_from(n).map_err(|_| self.err("string length overflows"))?;
                    let v = self.string(n)?;
                    self.stack.push(v);
                }
                b'J' => {
                    let v = i32::from_le_bytes(self.le()?);
                    self.stack.push(Value::Int(v as i64));
                }
                b'K' => {
                    let v = self.u8()?;
                    self.stack.push(Value::Int(v as i64));
                }
                b'M' => {
                    let v = u16::from_le_bytes(self.le()?);
                    self.stack.push(Value::Int(v as i64));
                }
                0x8a => {
                    let n = self.u8()? as usize;
                    if n > 8 {
                        return Err(self.err(format!(
                            "LONG1 integer of {n} bytes does not fit in 64 bits"
                        )));
                    }
                    let b = self.take(n)?;
                    let mut buf = if b.last().is_some_and(|&x| x & 0x80 != 0) {
                        [0xffu8; 8]
                    } else {
                        [0u8; 8]
                    };
                    buf[..n].copy_from_slice(b);
                    self.stack.push(Value::Int(i64::from_le_bytes(buf)));
                }
                b'G' => {
                    let v = f64::from_be_bytes(self.le()?);
                    self.stack.push(Value::Float(v));
                }
                b'N' => self.stack.push(Value::None),
                0x88 => self.stack.push(Value::Bool(true)),
                0x89 => self.stack.push(Value::Bool(false)),
                b's' => {
                    let v = self.pop()?;
                    let k = self.pop()?;
                    self.dict_mut()?.push((k, v));
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    if items.len() % 2 != 0 {
                        return Err(self.err("SETITEMS with an odd number of items"));
                    }
                    let d = self.dict_mut()?;
                    let mut it = items.into_iter();
                    while let (Some(k), Some(v)) = (it.next(), it.next()) {
                        d.push((k, v));
                    }
                }
                b'a' => {
                    let v = self.pop()?;
                    self.list_mut()?.push(v);
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    self.list_mut()?.extend(items);
                }
                b'q' => {
                    let i = self.u8()? as u64;
                    self.memo_put(i)?;
                }
                b'r' => {
                    let i = u32::from_le_bytes(self.le()?) as u64;
                    self.memo_put(i)?;
                }
                0x94 => {
                    let i = self.memo.len() as u64;
                    self.memo_put(i)?;
                }
                b'h' => {
                    let i = self.u8()? as u64;
                    self.memo_get(i)?;
                }
                b'j' => {
                    let i = u32::from_le_bytes(self.le()?) as u64;
                    self.memo_get(i)?;
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    let v = self.global(module, name)?;
                    self.stack.push(v);
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    let (Value::Str(module), Value::Str(name)) = (module, name) else {
                        return Err(self.err("STACK_GLOBAL needs two strings"));
                    };
                    let v = self.global(&module, &name)?;
                    self.stack.push(v);
                }
                b'R' => {
                    let args = self.pop()?;
                    let f = self.pop()?;
                    let v = self.reduce(f, args)?;
                    self.stack.push(v);
                }
                b'b' => {
                    // torch pickles a state_dict's `_metadata` (module versions) as
                    // the OrderedDict's instance state; it carries no tensor data.
                    let state = self.pop()?;
                    let target_ok = matches!(self.top()?, Value::Dict(_));
                    let state_ok = matches!(state, Value::Dict(_) | Value::None);
                    if !(target_ok && state_ok) {
                        return Err(self.err(format!(
                            "BUILD is only accepted on a dict with dict state, got {} on a {}",
                            state.kind(),
                            self.top()?.kind()
                        )));
                    }
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let v = self.persistent_load(pid)?;
                    self.stack.push(v);
                }
                _ => {
                    return Err(ConvertError::ForbiddenOpcode {
                        path: self.origin.path.to_path_buf(),
                        entry: self.origin.entry.to_string(),
                        offset: self.op_start,
                        opcode: op,
                        name: opcode_name(op),
                    })
                }
            }
        }
    }
}

/// The result of an unpickling: the top-level value and the containers it refers to.
#[derive(Clone, Debug)]
pub struct Unpickled {
    pub root: Value,
    pub heap: Heap,
}

/// Interprets a pickle with the restricted machine. `path`/`entry` only label errors.
pub fn unpickle(data: &[u8], path: &Path, entry: &str) -> Result<Unpickled> {
    let vm = Vm {
        data,
        pos: 0,
        op_start: 0,
        stack: Vec::new(),
        marks: Vec::new(),
        memo: HashMap::new(),
        heap: Heap::default(),
        origin: Origin { path, entry },
    };
    vm.run()
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
        let mut file = File::open(path).map_err(|e| ConvertError::io(path, e))?;
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
        let file = File::open(path).map_err(|e| ConvertError::io(path, e))?;
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

/// The Adam state of one parameter, as torch saves it.
#[derive(Clone, Debug, PartialEq)]
pub struct TorchAdamParam {
    /// Steps taken; torch stores a float, an int or a 0-d tensor depending on its version.
    pub step: f64,
    pub exp_avg: RawTensor,
    pub exp_avg_sq: RawTensor,
}

/// One Adam parameter group (`param_groups[g]`).
#[derive(Clone, Debug, PartialEq)]
pub struct TorchAdamGroup {
    pub lr: f64,
    pub betas: (f64, f64),
    pub eps: f64,
    pub weight_decay: f64,
    pub amsgrad: bool,
    /// Optimiser ids of the group's parameters, in order.
    pub params: Vec<usize>,
}

/// `optimizer.state_dict()` of a torch Adam.
#[derive(Clone, Debug, PartialEq)]
pub struct TorchAdam {
    pub state: BTreeMap<usize, TorchAdamParam>,
    pub param_groups: Vec<TorchAdamGroup>,
}

/// What the reference trainer saves (spec model.md §8.3).
#[derive(Clone, Debug)]
pub struct ReferenceCheckpoint {
    pub path: PathBuf,
    /// The state_dict in its saved (module registration) order.
    pub model: Vec<(String, RawTensor)>,
    pub optimizer: Option<TorchAdam>,
    pub global_iter: Option<i64>,
}

/// Reads `{'model', 'optimizer', 'global_iter'}` from a reference `.th` file.
/// `optimizer` and `global_iter` are optional here; callers that need them say so.
pub fn read_reference_checkpoint(path: &Path) -> Result<ReferenceCheckpoint> {
    let mut ar = TorchArchive::open(path)?;
    let g = ar.graph().clone();
    if g.heap.items(&g.root).is_none() {
        return Err(ConvertError::mismatch(
            path,
            "<top level>",
            "a dict",
            g.root.kind(),
        ));
    }
    let model_v = g.heap.get(&g.root, "model").ok_or_else(|| {
        ConvertError::missing(
            path,
            "model",
            " (the checkpoint's top-level dict must hold the state_dict under `model`)",
        )
    })?;
    let model = read_tensor_dict(&mut ar, &g.heap, model_v, "model")?;

    let global_iter = match g.heap.get(&g.root, "global_iter") {
        None => None,
        Some(Value::Int(i)) => Some(*i),
        Some(other) => {
            return Err(ConvertError::mismatch(
                path,
                "global_iter",
                "an int",
                other.kind(),
            ))
        }
    };
    let optimizer = match g.heap.get(&g.root, "optimizer") {
        None | Some(Value::None) => None,
        Some(v) => Some(read_adam(&mut ar, &g.heap, v)?),
    };
    Ok(ReferenceCheckpoint {
        path: path.to_path_buf(),
        model,
        optimizer,
        global_iter,
    })
}

fn read_tensor_dict(
    ar: &mut TorchArchive,
    heap: &Heap,
    v: &Value,
    key: &str,
) -> Result<Vec<(String, RawTensor)>> {
    let path = ar.path().to_path_buf();
    let items = heap
        .items(v)
        .ok_or_else(|| ConvertError::mismatch(&path, key, "a dict of tensors", v.kind()))?;
    let mut out: Vec<(String, RawTensor)> = Vec::with_capacity(items.len());
    for (k, t) in items {
        let Value::Str(name) = k else {
            return Err(ConvertError::mismatch(&path, key, "string keys", k.kind()));
        };
        let full = format!("{key}.{name}");
        let Value::Tensor(tr) = t else {
            return Err(ConvertError::mismatch(&path, full, "a tensor", t.kind()));
        };
        if out.iter().any(|(n, _)| n == &**name) {
            return Err(ConvertError::invalid(&path, full, "duplicate key"));
        }
        let raw = ar.read_tensor(tr, &full)?;
        out.push((name.to_string(), raw));
    }
    Ok(out)
}

fn as_f64(v: &Value) -> Option<f64> {
    match v {
        Value::Float(f) => Some(*f),
        Value::Int(i) => Some(*i as f64),
        _ => None,
    }
}

fn read_adam(ar: &mut TorchArchive, heap: &Heap, v: &Value) -> Result<TorchAdam> {
    let path = ar.path().to_path_buf();
    if heap.items(v).is_none() {
        return Err(ConvertError::mismatch(
            &path,
            "optimizer",
            "a dict",
            v.kind(),
        ));
    }
    let state_v = heap
        .get(v, "state")
        .ok_or_else(|| ConvertError::missing(&path, "optimizer.state", ""))?;
    let groups_v = heap
        .get(v, "param_groups")
        .ok_or_else(|| ConvertError::missing(&path, "optimizer.param_groups", ""))?;

    let groups = match groups_v {
        Value::List(_) => heap.seq(groups_v).unwrap_or_default(),
        other => {
            return Err(ConvertError::mismatch(
                &path,
                "optimizer.param_groups",
                "a list",
                other.kind(),
            ))
        }
    };
    let mut param_groups = Vec::new();
    for (g, gv) in groups.iter().enumerate() {
        let key = |k: &str| format!("optimizer.param_groups[{g}].{k}");
        if heap.items(gv).is_none() {
            return Err(ConvertError::mismatch(
                &path,
                format!("optimizer.param_groups[{g}]"),
                "a dict",
                gv.kind(),
            ));
        }
        let num = |k: &str| -> Result<f64> {
            let x = heap
                .get(gv, k)
                .ok_or_else(|| ConvertError::missing(&path, key(k), ""))?;
            as_f64(x).ok_or_else(|| ConvertError::mismatch(&path, key(k), "a number", x.kind()))
        };
        let betas = match heap.get(gv, "betas") {
            Some(t @ Value::Tuple(_)) => match heap.seq(t).unwrap_or_default() {
                [a, b] => match (as_f64(a), as_f64(b)) {
                    (Some(a), Some(b)) => (a, b),
                    _ => {
                        return Err(ConvertError::mismatch(
                            &path,
                            key("betas"),
                            "two numbers",
                            "other values",
                        ))
                    }
                },
                other => {
                    return Err(ConvertError::mismatch(
                        &path,
                        key("betas"),
                        "a 2-tuple",
                        format!("{} items", other.len()),
                    ))
                }
            },
            Some(other) => {
                return Err(ConvertError::mismatch(
                    &path,
                    key("betas"),
                    "a 2-tuple",
                    other.kind(),
                ))
            }
            None => return Err(ConvertError::missing(&path, key("betas"), "")),
        };
        let amsgrad = match heap.get(gv, "amsgrad") {
            None | Some(Value::Bool(false)) => false,
            Some(Value::Bool(true)) => true,
            Some(other) => {
                return Err(ConvertError::mismatch(
                    &path,
                    key("amsgrad"),
                    "a bool",
                    other.kind(),
                ))
            }
        };
        let params = match heap.get(gv, "params") {
            Some(l @ Value::List(_)) => heap
                .seq(l)
                .unwrap_or_default()
                .iter()
                .map(|x| match x {
                    Value::Int(i) if *i >= 0 => Ok(*i as usize),
                    other => Err(ConvertError::mismatch(
                        &path,
                        key("params"),
                        "non-negative ints",
                        other.kind(),
                    )),
                })
                .collect::<Result<Vec<_>>>()?,
            Some(other) => {
                return Err(ConvertError::mismatch(
                    &path,
                    key("params"),
                    "a list",
                    other.kind(),
                ))
            }
            None => return Err(ConvertError::missing(&path, key("params"), "")),
        };
        let weight_decay = match heap.get(gv, "weight_decay") {
            None => 0.0,
            Some(_) => num("weight_decay")?,
        };
        param_groups.push(TorchAdamGroup {
            lr: num("lr")?,
            betas,
            eps: num("eps")?,
            weight_decay,
            amsgrad,
            params,
        });
    }

    let entries = heap.items(state_v).ok_or_else(|| {
        ConvertError::mismatch(&path, "optimizer.state", "a dict", state_v.kind())
    })?;
    let mut state = BTreeMap::new();
    for (k, sv) in entries {
        let id = match k {
            Value::Int(id) if *id >= 0 => *id as usize,
            Value::Int(id) => {
                return Err(ConvertError::invalid(
                    &path,
                    "optimizer.state",
                    format!("negative parameter id {id}"),
                ))
            }
            other => {
                return Err(ConvertError::mismatch(
                    &path,
                    "optimizer.state",
                    "int keys",
                    other.kind(),
                ))
            }
        };
        let key = |k: &str| format!("optimizer.state[{id}].{k}");
        if heap.items(sv).is_none() {
            return Err(ConvertError::mismatch(
                &path,
                format!("optimizer.state[{id}]"),
                "a dict",
                sv.kind(),
            ));
        }
        let mut tensor = |k: &str| -> Result<RawTensor> {
            match heap.get(sv, k) {
                Some(Value::Tensor(t)) => ar.read_tensor(t, &key(k)),
                Some(other) => Err(ConvertError::mismatch(
                    &path,
                    key(k),
                    "a tensor",
                    other.kind(),
                )),
                None => Err(ConvertError::missing(&path, key(k), "")),
            }
        };
        let exp_avg = tensor("exp_avg")?;
        let exp_avg_sq = tensor("exp_avg_sq")?;
        let step = match heap.get(sv, "step") {
            Some(Value::Tensor(t)) => {
                let raw = ar.read_tensor(t, &key("step"))?;
                scalar_of(&raw).ok_or_else(|| {
                    ConvertError::mismatch(
                        &path,
                        key("step"),
                        "a one-element float or int tensor",
                        format!("{:?} of shape {:?}", raw.dtype, raw.shape),
                    )
                })?
            }
            Some(other) => as_f64(other).ok_or_else(|| {
                ConvertError::mismatch(&path, key("step"), "a number", other.kind())
            })?,
            None => return Err(ConvertError::missing(&path, key("step"), "")),
        };
        state.insert(
            id,
            TorchAdamParam {
                step,
                exp_avg,
                exp_avg_sq,
            },
        );
    }
    Ok(TorchAdam {
        state,
        param_groups,
    })
}

fn scalar_of(t: &RawTensor) -> Option<f64> {
    if t.numel() != 1 {
        return None;
    }
    let b = &t.data;
    Some(match t.dtype {
        Dtype::F32 => f32::from_le_bytes(b.get(..4)?.try_into().ok()?) as f64,
        Dtype::F64 => f64::from_le_bytes(b.get(..8)?.try_into().ok()?),
        Dtype::I64 => i64::from_le_bytes(b.get(..8)?.try_into().ok()?) as f64,
        Dtype::I32 => i32::from_le_bytes(b.get(..4)?.try_into().ok()?) as f64,
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(bytes: &[u8]) -> Result<Unpickled> {
        unpickle(bytes, Path::new("t.pkl"), "data.pkl")
    }

    #[test]
    fn plain_values_and_memo() {
        // {'a': [1, -2, 2**40, 1.5, True, None], 'b': <memo of the list>}
        let mut p = b"\x80\x02}q\x00(X\x01\x00\x00\x00a]q\x01(K\x01J\xfe\xff\xff\xff\x8a\x06\x00\x00\x00\x00\x00\x01".to_vec();
        p.extend_from_slice(b"G\x3f\xf8\x00\x00\x00\x00\x00\x00\x88Ne");
        p.extend_from_slice(b"\x8c\x01bh\x01u.");
        let g = run(&p).unwrap();
        let a = g.heap.get(&g.root, "a").unwrap();
        let items = g.heap.seq(a).unwrap();
        assert!(matches!(items[0], Value::Int(1)));
        assert!(matches!(items[1], Value::Int(-2)));
        assert!(matches!(items[2], Value::Int(x) if x == 1 << 40));
        assert!(matches!(items[3], Value::Float(x) if x == 1.5));
        assert!(matches!(items[4], Value::Bool(true)));
        assert!(matches!(items[5], Value::None));
        // The memo refers to the same list, mutated after it was memoised.
        let b = g.heap.get(&g.root, "b").unwrap();
        assert_eq!(g.heap.seq(b).unwrap().len(), 6);
    }

    #[test]
    fn negative_long1_and_stack_global() {
        // LONG1 of 2 bytes 0xff7f = -129; STACK_GLOBAL collections.OrderedDict() → {}.
        let p = b"\x80\x04\x95\x00\x00\x00\x00\x00\x00\x00\x00(\x8a\x02\x7f\xff\x8c\x0bcollections\x8c\x0bOrderedDict\x93)Rt.";
        let g = run(p).unwrap();
        let t = g.heap.seq(&g.root).unwrap();
        assert!(matches!(t[0], Value::Int(-129)));
        assert!(g.heap.items(&t[1]).unwrap().is_empty());
    }

    #[test]
    fn forbidden_stack_global_names_the_callable() {
        let p = b"\x80\x04\x8c\x08builtins\x8c\x04eval\x93.";
        match run(p) {
            Err(ConvertError::ForbiddenGlobal {
                module,
                name,
                offset,
                ..
            }) => {
                assert_eq!(
                    (module.as_str(), name.as_str(), offset),
                    ("builtins", "eval", 18)
                );
            }
            other => panic!("{other:?}"),
        }
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
    fn truncated_and_malformed_pickles_do_not_panic() {
        let cases: &[&[u8]] = &[
            b"",
            b"\x80",
            b"\x80\x02X\xff\xff\xff\xff",
            b"\x80\x02h\x05.",
            b"\x80\x02s.",
            b"\x80\x02u.",
            b"\x80\x02cposix",
            b"\x80\x02]K\x01K\x02u.",
            b"\x80\x06.",
            b"\x80\x02\x8a\x09\x00\x00\x00\x00\x00\x00\x00\x00\x00.",
        ];
        for c in cases {
            assert!(run(c).is_err(), "{c:?} was accepted");
        }
    }

    #[test]
    fn deep_nesting_is_harmless() {
        // 200,000 nested lists: ] (] ... a) would overflow a recursive drop.
        let mut p = b"\x80\x02".to_vec();
        let n = 200_000;
        p.extend(std::iter::repeat_n(b']', n));
        p.extend(std::iter::repeat_n(b'a', n - 1));
        p.push(b'.');
        let g = run(&p).unwrap();
        assert_eq!(g.heap.seq(&g.root).unwrap().len(), 1);
    }

    #[test]
    fn every_refused_opcode_is_named() {
        for (op, name) in [
            (b'i', "INST"),
            (b'o', "OBJ"),
            (0x81u8, "NEWOBJ"),
            (0x82, "EXT1"),
            (b'P', "PERSID"),
            (0x92, "NEWOBJ_EX"),
        ] {
            match run(&[0x80, 0x02, op]) {
                Err(ConvertError::ForbiddenOpcode {
                    opcode,
                    name: n,
                    offset,
                    ..
                }) => {
                    assert_eq!((opcode, n, offset), (op, name, 2));
                }
                other => panic!("{op:#x}: {other:?}"),
            }
        }
    }
}
