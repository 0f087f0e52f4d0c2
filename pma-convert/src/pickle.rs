//! A restricted pickle interpreter: bytes in, a tree of plain values out, and
//! nothing in the pickle is ever imported or called.
//!
//! Python's unpickler imports and calls whatever a pickle names. Here a pickle
//! is interpreted by a small stack machine that knows the opcodes (protocols
//! 2–5) that describe dicts, lists, tuples, numbers and strings, and refuses
//! the ones that build arbitrary objects (`INST`, `OBJ`, `NEWOBJ`, `EXT*`, ...)
//! with their byte offset. Globals are where pickles run code, so a [`Policy`]
//! decides which `module.name` a pickle may mention and what `REDUCE` and
//! persistent ids make of them; a policy only builds values. [`PlainData`]
//! accepts nothing beyond `collections.OrderedDict`; `crate::torch` has the
//! policy for `torch.save` checkpoints.
//!
//! ```
//! use pma_convert::pickle::{parse, PlainData, Value};
//! // pickle.dumps({'a': 1}, protocol=2)
//! let p = b"\x80\x02}q\x00X\x01\x00\x00\x00aq\x01K\x01s.";
//! let tree = parse(p, &PlainData, "x.pkl".as_ref(), "x.pkl").unwrap();
//! assert!(matches!(tree.heap.get(&tree.root, "a"), Some(Value::Int(1))));
//! ```

use std::{fmt::Debug, path::Path, rc::Rc};

pub mod numpy;
mod vm;

pub use crate::error::Accepted;
use crate::error::Result;

/// A value a [`Policy`] builds from an allowed global: the global itself, or
/// what `REDUCE` or a persistent id made of it.
pub trait Object: Clone + Debug {
    /// What the value is, for error messages ("tensor", "storage", ...).
    fn kind(&self) -> &'static str;
    /// Whether `REDUCE` may call it.
    fn is_callable(&self) -> bool;
}

/// An unpickled value. Containers live in [`Heap`] and are referred to by
/// index: pickles mutate containers after memoising them, later references
/// must see the result, and a hostile pickle can nest containers millions deep,
/// which an owned tree would drop recursively and overflow the stack.
#[derive(Clone, Debug)]
pub enum Value<O> {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(Rc<str>),
    /// `bytes` (protocol 3+); a Python 2 `str` is a [`Value::Str`] decoded as
    /// Latin-1, as Python 3 reads such pickles with `encoding='latin1'`.
    Bytes(Rc<[u8]>),
    Tuple(usize),
    List(usize),
    /// Insertion-ordered (an OrderedDict's order is kept).
    Dict(usize),
    /// Built by the policy.
    Object(O),
}

impl<O: Object> Value<O> {
    /// What the value is, for error messages.
    pub fn kind(&self) -> &'static str {
        match self {
            Value::None => "None",
            Value::Bool(_) => "bool",
            Value::Int(_) => "int",
            Value::Float(_) => "float",
            Value::Str(_) => "str",
            Value::Bytes(_) => "bytes",
            Value::Tuple(_) => "tuple",
            Value::List(_) => "list",
            Value::Dict(_) => "dict",
            Value::Object(o) => o.kind(),
        }
    }

    /// An int or a float as f64.
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Value::Float(f) => Some(*f),
            Value::Int(i) => Some(*i as f64),
            _ => None,
        }
    }
}

/// The key-value pairs of a dict, in insertion order.
pub type DictItems<O> = Vec<(Value<O>, Value<O>)>;

#[derive(Clone, Debug)]
pub enum Container<O> {
    Tuple(Vec<Value<O>>),
    List(Vec<Value<O>>),
    Dict(DictItems<O>),
}

/// Every container an unpickling created.
#[derive(Clone, Debug)]
pub struct Heap<O>(Vec<Container<O>>);

impl<O> Default for Heap<O> {
    fn default() -> Self {
        Self(Vec::new())
    }
}

impl<O> Heap<O> {
    /// Stores a new container and returns the value that refers to it.
    pub fn alloc(&mut self, c: Container<O>) -> Value<O> {
        let id = self.0.len();
        let v = match &c {
            Container::Tuple(_) => Value::Tuple(id),
            Container::List(_) => Value::List(id),
            Container::Dict(_) => Value::Dict(id),
        };
        self.0.push(c);
        v
    }

    fn container_mut(&mut self, id: usize) -> &mut Container<O> {
        &mut self.0[id]
    }

    /// The items of a list or tuple.
    pub fn seq(&self, v: &Value<O>) -> Option<&[Value<O>]> {
        match v {
            Value::Tuple(i) | Value::List(i) => match &self.0[*i] {
                Container::Tuple(x) | Container::List(x) => Some(x),
                Container::Dict(_) => None,
            },
            _ => None,
        }
    }

    /// The items of a dict, in insertion order.
    pub fn items(&self, v: &Value<O>) -> Option<&[(Value<O>, Value<O>)]> {
        match v {
            Value::Dict(i) => match &self.0[*i] {
                Container::Dict(x) => Some(x),
                _ => None,
            },
            _ => None,
        }
    }

    /// Dict lookup by string key.
    pub fn get(&self, v: &Value<O>, key: &str) -> Option<&Value<O>> {
        self.items(v)?
            .iter()
            .find(|(k, _)| matches!(k, Value::Str(s) if &**s == key))
            .map(|(_, v)| v)
    }
}

/// The result of an unpickling: the top-level value and the containers it refers to.
#[derive(Clone, Debug)]
pub struct Unpickled<O> {
    pub root: Value<O>,
    pub heap: Heap<O>,
}

/// Which globals a pickle may name and what is built from them. Every method
/// builds plain values; an `Err` message becomes a [`crate::ConvertError::Pickle`] at
/// the offset of the opcode being interpreted.
pub trait Policy {
    type Object: Object;

    /// What the policy accepts, completing "only ... are accepted" in the
    /// [`crate::ConvertError::ForbiddenGlobal`] message.
    fn accepted(&self) -> &'static Accepted;

    /// The value `module.name` stands for, or `None` to refuse it.
    fn global(&self, module: &str, name: &str) -> Option<Self::Object>;

    /// `REDUCE`: `f` is a callable object from [`Policy::global`] and `args`
    /// a tuple in `heap`.
    fn reduce(
        &self,
        heap: &mut Heap<Self::Object>,
        f: &Self::Object,
        args: &Value<Self::Object>,
    ) -> std::result::Result<Value<Self::Object>, String>;

    /// Whether `NEWOBJ` is interpreted (by [`Policy::new_object`]) rather
    /// than refused as an opcode; only the numpy policy needs it.
    const NEWOBJ: bool = false;

    /// `NEWOBJ` (`cls.__new__(cls, *args)`), when [`Policy::NEWOBJ`] is set.
    fn new_object(
        &self,
        _heap: &mut Heap<Self::Object>,
        _cls: &Self::Object,
        _args: &Value<Self::Object>,
    ) -> std::result::Result<Value<Self::Object>, String> {
        Err("NEWOBJ is not accepted".into())
    }

    /// `BUILD` (`target.__setstate__(state)`): `None` keeps the default, which
    /// accepts only a dict with dict state and drops the state; `Some` replaces
    /// the target with the value returned.
    fn build(
        &self,
        _heap: &mut Heap<Self::Object>,
        _target: &Value<Self::Object>,
        _state: &Value<Self::Object>,
    ) -> Option<std::result::Result<Value<Self::Object>, String>> {
        None
    }

    /// `BINPERSID`: what a persistent id refers to (outside the pickle).
    fn persistent_load(
        &self,
        _heap: &Heap<Self::Object>,
        _pid: Value<Self::Object>,
    ) -> std::result::Result<Value<Self::Object>, String> {
        Err("persistent ids are not accepted".into())
    }
}

/// `collections.OrderedDict()` as an empty dict, the one global plain data
/// needs (every policy can use it).
pub fn ordered_dict<O>(
    heap: &mut Heap<O>,
    args: &Value<O>,
) -> std::result::Result<Value<O>, String> {
    if heap.seq(args).is_some_and(|a| !a.is_empty()) {
        return Err("collections.OrderedDict called with arguments".into());
    }
    Ok(heap.alloc(Container::Dict(Vec::new())))
}

/// Plain data only: containers, numbers, strings and `collections.OrderedDict`.
#[derive(Clone, Copy, Debug, Default)]
pub struct PlainData;

/// The one global [`PlainData`] accepts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OrderedDictClass;

impl Object for OrderedDictClass {
    fn kind(&self) -> &'static str {
        "global"
    }
    fn is_callable(&self) -> bool {
        true
    }
}

impl Policy for PlainData {
    type Object = OrderedDictClass;

    fn accepted(&self) -> &'static Accepted {
        &Accepted("collections.OrderedDict")
    }

    fn global(&self, module: &str, name: &str) -> Option<OrderedDictClass> {
        ((module, name) == ("collections", "OrderedDict")).then_some(OrderedDictClass)
    }

    fn reduce(
        &self,
        heap: &mut Heap<OrderedDictClass>,
        _f: &OrderedDictClass,
        args: &Value<OrderedDictClass>,
    ) -> std::result::Result<Value<OrderedDictClass>, String> {
        ordered_dict(heap, args)
    }
}

/// Interprets `data` under `policy`. `path`/`entry` (the file, and the member
/// of an archive or the file name again) only label errors.
pub fn parse<P: Policy>(
    data: &[u8],
    policy: &P,
    path: &Path,
    entry: &str,
) -> Result<Unpickled<P::Object>> {
    vm::run(data, policy, path, entry)
}
