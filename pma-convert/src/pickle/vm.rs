//! The stack machine that interprets a pickle's opcodes.

use std::{collections::HashMap, path::Path, rc::Rc};

use super::{Container, DictItems, Heap, Object, Policy, Unpickled, Value};
use crate::error::{ConvertError, Result};

/// Interprets `data` under `policy` (see [`super::parse`]).
pub(super) fn run<P: Policy>(
    data: &[u8],
    policy: &P,
    path: &Path,
    entry: &str,
) -> Result<Unpickled<P::Object>> {
    let vm = Vm {
        data,
        pos: 0,
        op_start: 0,
        stack: Vec::new(),
        marks: Vec::new(),
        memo: HashMap::new(),
        heap: Heap::default(),
        policy,
        path,
        entry,
    };
    vm.run()
}

/// Every pickle opcode with its name; the machine refuses those it does not
/// interpret by name.
const OPCODES: &[(u8, &str)] = &[
    (b'(', "MARK"),
    (b'.', "STOP"),
    (b'0', "POP"),
    (b'1', "POP_MARK"),
    (b'2', "DUP"),
    (b'F', "FLOAT"),
    (b'I', "INT"),
    (b'J', "BININT"),
    (b'K', "BININT1"),
    (b'L', "LONG"),
    (b'M', "BININT2"),
    (b'N', "NONE"),
    (b'P', "PERSID"),
    (b'Q', "BINPERSID"),
    (b'R', "REDUCE"),
    (b'S', "STRING"),
    (b'T', "BINSTRING"),
    (b'U', "SHORT_BINSTRING"),
    (b'V', "UNICODE"),
    (b'X', "BINUNICODE"),
    (b'a', "APPEND"),
    (b'b', "BUILD"),
    (b'c', "GLOBAL"),
    (b'd', "DICT"),
    (b'}', "EMPTY_DICT"),
    (b'e', "APPENDS"),
    (b'g', "GET"),
    (b'h', "BINGET"),
    (b'i', "INST"),
    (b'j', "LONG_BINGET"),
    (b'l', "LIST"),
    (b']', "EMPTY_LIST"),
    (b'o', "OBJ"),
    (b'p', "PUT"),
    (b'q', "BINPUT"),
    (b'r', "LONG_BINPUT"),
    (b's', "SETITEM"),
    (b't', "TUPLE"),
    (b')', "EMPTY_TUPLE"),
    (b'u', "SETITEMS"),
    (b'G', "BINFLOAT"),
    (0x80, "PROTO"),
    (0x81, "NEWOBJ"),
    (0x82, "EXT1"),
    (0x83, "EXT2"),
    (0x84, "EXT4"),
    (0x85, "TUPLE1"),
    (0x86, "TUPLE2"),
    (0x87, "TUPLE3"),
    (0x88, "NEWTRUE"),
    (0x89, "NEWFALSE"),
    (0x8a, "LONG1"),
    (0x8b, "LONG4"),
    (b'B', "BINBYTES"),
    (b'C', "SHORT_BINBYTES"),
    (0x8c, "SHORT_BINUNICODE"),
    (0x8d, "BINUNICODE8"),
    (0x8e, "BINBYTES8"),
    (0x8f, "EMPTY_SET"),
    (0x90, "ADDITEMS"),
    (0x91, "FROZENSET"),
    (0x92, "NEWOBJ_EX"),
    (0x93, "STACK_GLOBAL"),
    (0x94, "MEMOIZE"),
    (0x95, "FRAME"),
    (0x96, "BYTEARRAY8"),
    (0x97, "NEXT_BUFFER"),
    (0x98, "READONLY_BUFFER"),
];

fn opcode_name(op: u8) -> &'static str {
    OPCODES
        .iter()
        .find(|(o, _)| *o == op)
        .map_or("unknown", |(_, n)| n)
}

struct Vm<'a, P: Policy> {
    data: &'a [u8],
    pos: usize,
    /// Offset of the opcode being executed.
    op_start: usize,
    stack: Vec<Value<P::Object>>,
    marks: Vec<usize>,
    memo: HashMap<u64, Value<P::Object>>,
    heap: Heap<P::Object>,
    policy: &'a P,
    path: &'a Path,
    entry: &'a str,
}

impl<'a, P: Policy> Vm<'a, P> {
    fn err(&self, msg: impl Into<String>) -> ConvertError {
        ConvertError::Pickle {
            path: self.path.to_path_buf(),
            entry: self.entry.to_string(),
            offset: self.op_start,
            msg: msg.into(),
        }
    }

    fn run(mut self) -> Result<Unpickled<P::Object>> {
        loop {
            self.op_start = self.pos;
            let op = self.u8()?;
            if op == b'.' {
                let root = self.pop()?;
                return Ok(Unpickled {
                    root,
                    heap: self.heap,
                });
            }
            self.step(op)?;
        }
    }

    /// Interprets one opcode (other than STOP).
    fn step(&mut self, op: u8) -> Result<()> {
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
            b'(' => self.marks.push(self.stack.len()),
            b'}' | b']' | b')' | b't' | 0x85..=0x87 => self.new_container(op)?,
            b's' | b'u' | b'a' | b'e' => self.fill_container(op)?,
            b'X' | 0x8c | 0x8d | b'J' | b'K' | b'M' | 0x8a | b'G' | b'N' | 0x88 | 0x89 => {
                let v = self.constant(op)?;
                self.stack.push(v);
            }
            // Python 2 strings (numpy's raw data in Python 2 pickles) and bytes.
            b'T' | b'U' | b'B' | b'C' | 0x8e => {
                let v = self.byte_string(op)?;
                self.stack.push(v);
            }
            b'q' | b'r' | 0x94 | b'h' | b'j' => self.memo_op(op)?,
            0x81 => self.new_object(op)?,
            b'c' | 0x93 | b'R' | b'b' | b'Q' => self.object_op(op)?,
            _ => {
                return Err(ConvertError::ForbiddenOpcode {
                    path: self.path.to_path_buf(),
                    entry: self.entry.to_string(),
                    offset: self.op_start,
                    opcode: op,
                    name: opcode_name(op),
                })
            }
        }
        Ok(())
    }

    /// EMPTY_DICT, EMPTY_LIST, EMPTY_TUPLE, TUPLE, TUPLE1..3.
    fn new_container(&mut self, op: u8) -> Result<()> {
        let c = match op {
            b'}' => Container::Dict(Vec::new()),
            b']' => Container::List(Vec::new()),
            b')' => Container::Tuple(Vec::new()),
            b't' => Container::Tuple(self.pop_mark()?),
            _ => {
                let n = (op - 0x84) as usize;
                if self.stack.len() < n {
                    return Err(self.err("stack underflow"));
                }
                Container::Tuple(self.stack.split_off(self.stack.len() - n))
            }
        };
        let v = self.heap.alloc(c);
        self.stack.push(v);
        Ok(())
    }

    /// SETITEM, SETITEMS, APPEND, APPENDS.
    fn fill_container(&mut self, op: u8) -> Result<()> {
        match op {
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
            _ => {
                let items = self.pop_mark()?;
                self.list_mut()?.extend(items);
            }
        }
        Ok(())
    }

    /// Strings, ints, floats, None and the booleans.
    fn constant(&mut self, op: u8) -> Result<Value<P::Object>> {
        Ok(match op {
            b'X' => {
                let n = u32::from_le_bytes(self.le()?) as usize;
                self.string(n)?
            }
            0x8c => {
                let n = self.u8()? as usize;
                self.string(n)?
            }
            0x8d => {
                let n = u64::from_le_bytes(self.le()?);
                let n = usize::try_from(n).map_err(|_| self.err("string length overflows"))?;
                self.string(n)?
            }
            b'J' => Value::Int(i32::from_le_bytes(self.le()?) as i64),
            b'K' => Value::Int(self.u8()? as i64),
            b'M' => Value::Int(u16::from_le_bytes(self.le()?) as i64),
            0x8a => self.long1()?,
            b'G' => Value::Float(f64::from_be_bytes(self.le()?)),
            b'N' => Value::None,
            0x88 => Value::Bool(true),
            _ => Value::Bool(false),
        })
    }

    /// BINSTRING, SHORT_BINSTRING (Latin-1 text), BINBYTES, SHORT_BINBYTES, BINBYTES8.
    fn byte_string(&mut self, op: u8) -> Result<Value<P::Object>> {
        let n = match op {
            b'T' => i32::from_le_bytes(self.le()?) as i64,
            b'B' => u32::from_le_bytes(self.le()?) as i64,
            b'U' | b'C' => self.u8()? as i64,
            _ => i64::try_from(u64::from_le_bytes(self.le()?)).unwrap_or(-1),
        };
        let n = usize::try_from(n).map_err(|_| self.err("negative or huge string length"))?;
        let b = self.take(n)?;
        Ok(match op {
            b'T' | b'U' => Value::Str(Rc::from(b.iter().map(|&c| c as char).collect::<String>())),
            _ => Value::Bytes(Rc::from(b)),
        })
    }

    /// NEWOBJ, where the policy allows it; refused as an opcode otherwise.
    fn new_object(&mut self, op: u8) -> Result<()> {
        if !P::NEWOBJ {
            return Err(ConvertError::ForbiddenOpcode {
                path: self.path.to_path_buf(),
                entry: self.entry.to_string(),
                offset: self.op_start,
                opcode: op,
                name: opcode_name(op),
            });
        }
        let args = self.pop()?;
        let cls = self.pop()?;
        let Value::Object(c) = &cls else {
            return Err(self.err(format!("NEWOBJ on a {}", cls.kind())));
        };
        let r = self.policy.new_object(&mut self.heap, c, &args);
        let v = r.map_err(|m| self.err(m))?;
        self.stack.push(v);
        Ok(())
    }

    /// LONG1: a little-endian two's-complement integer of up to 8 bytes here.
    fn long1(&mut self) -> Result<Value<P::Object>> {
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
        Ok(Value::Int(i64::from_le_bytes(buf)))
    }

    /// BINPUT, LONG_BINPUT, MEMOIZE, BINGET, LONG_BINGET.
    fn memo_op(&mut self, op: u8) -> Result<()> {
        match op {
            b'q' => {
                let i = self.u8()? as u64;
                self.memo_put(i)
            }
            b'r' => {
                let i = u32::from_le_bytes(self.le()?) as u64;
                self.memo_put(i)
            }
            0x94 => self.memo_put(self.memo.len() as u64),
            b'h' => {
                let i = self.u8()? as u64;
                self.memo_get(i)
            }
            _ => {
                let i = u32::from_le_bytes(self.le()?) as u64;
                self.memo_get(i)
            }
        }
    }

    /// GLOBAL, STACK_GLOBAL, REDUCE, BUILD, BINPERSID: where the policy decides.
    fn object_op(&mut self, op: u8) -> Result<()> {
        let v = match op {
            b'c' => {
                let module = self.line()?;
                let name = self.line()?;
                self.global(module, name)?
            }
            0x93 => {
                let name = self.pop()?;
                let module = self.pop()?;
                let (Value::Str(module), Value::Str(name)) = (module, name) else {
                    return Err(self.err("STACK_GLOBAL needs two strings"));
                };
                self.global(&module, &name)?
            }
            b'R' => {
                let args = self.pop()?;
                let f = self.pop()?;
                self.reduce(f, args)?
            }
            b'b' => return self.build(),
            _ => {
                let pid = self.pop()?;
                let r = self.policy.persistent_load(&self.heap, pid);
                r.map_err(|m| self.err(m))?
            }
        };
        self.stack.push(v);
        Ok(())
    }

    fn global(&self, module: &str, name: &str) -> Result<Value<P::Object>> {
        match self.policy.global(module, name) {
            Some(o) => Ok(Value::Object(o)),
            None => Err(ConvertError::ForbiddenGlobal {
                path: self.path.to_path_buf(),
                entry: self.entry.to_string(),
                offset: self.op_start,
                module: module.to_string(),
                name: name.to_string(),
                accepted: self.policy.accepted(),
            }),
        }
    }

    fn reduce(&mut self, f: Value<P::Object>, args: Value<P::Object>) -> Result<Value<P::Object>> {
        let f = match f {
            Value::Object(o) if o.is_callable() => o,
            other => {
                return Err(self.err(format!(
                    "REDUCE on a {}, which is not callable",
                    other.kind()
                )))
            }
        };
        if !matches!(args, Value::Tuple(_)) {
            return Err(self.err(format!(
                "REDUCE arguments are a {}, expected a tuple",
                args.kind()
            )));
        }
        let r = self.policy.reduce(&mut self.heap, &f, &args);
        r.map_err(|m| self.err(m))
    }

    /// torch pickles a state_dict's `_metadata` (module versions) as the
    /// OrderedDict's instance state; it carries no data and is dropped.
    fn build(&mut self) -> Result<()> {
        let state = self.pop()?;
        let target = self.top()?.clone();
        if let Some(r) = self.policy.build(&mut self.heap, &target, &state) {
            let v = r.map_err(|m| self.err(m))?;
            *self.stack.last_mut().expect("top was checked") = v;
            return Ok(());
        }
        let target_ok = matches!(self.top()?, Value::Dict(_));
        let state_ok = matches!(state, Value::Dict(_) | Value::None);
        if !(target_ok && state_ok) {
            return Err(self.err(format!(
                "BUILD is only accepted on a dict with dict state, got {} on a {}",
                state.kind(),
                self.top()?.kind()
            )));
        }
        Ok(())
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

    fn string(&mut self, n: usize) -> Result<Value<P::Object>> {
        let b = self.take(n)?;
        let s = std::str::from_utf8(b).map_err(|_| self.err("string is not valid UTF-8"))?;
        Ok(Value::Str(Rc::from(s)))
    }

    fn pop(&mut self) -> Result<Value<P::Object>> {
        self.stack.pop().ok_or_else(|| self.err("stack underflow"))
    }

    fn top(&self) -> Result<&Value<P::Object>> {
        self.stack.last().ok_or_else(|| self.err("stack underflow"))
    }

    fn pop_mark(&mut self) -> Result<Vec<Value<P::Object>>> {
        let m = self
            .marks
            .pop()
            .ok_or_else(|| self.err("no MARK on the stack"))?;
        if m > self.stack.len() {
            return Err(self.err("MARK points past the stack"));
        }
        Ok(self.stack.split_off(m))
    }

    fn dict_mut(&mut self) -> Result<&mut DictItems<P::Object>> {
        match self.stack.last() {
            Some(Value::Dict(i)) => match self.heap.container_mut(*i) {
                Container::Dict(d) => Ok(d),
                _ => Err(corrupt_heap(self.path, self.entry, self.op_start)),
            },
            Some(other) => Err(self.err(format!("setting a dict item on a {}", other.kind()))),
            None => Err(self.err("stack underflow")),
        }
    }

    fn list_mut(&mut self) -> Result<&mut Vec<Value<P::Object>>> {
        match self.stack.last() {
            Some(Value::List(i)) => match self.heap.container_mut(*i) {
                Container::List(l) => Ok(l),
                _ => Err(corrupt_heap(self.path, self.entry, self.op_start)),
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
}

/// A container index that names the wrong kind of container (cannot happen:
/// values are only made by [`Heap::alloc`]); reported rather than panicking.
fn corrupt_heap(path: &Path, entry: &str, offset: usize) -> ConvertError {
    ConvertError::Pickle {
        path: path.to_path_buf(),
        entry: entry.to_string(),
        offset,
        msg: "corrupt heap".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pickle::{parse, OrderedDictClass, PlainData};

    fn run(bytes: &[u8]) -> Result<Unpickled<OrderedDictClass>> {
        parse(bytes, &PlainData, Path::new("t.pkl"), "data.pkl")
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
    fn plain_data_refuses_persistent_ids() {
        let msg = run(b"\x80\x02X\x03\x00\x00\x00abcQ.")
            .unwrap_err()
            .to_string();
        assert!(msg.contains("persistent id"), "{msg}");
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
