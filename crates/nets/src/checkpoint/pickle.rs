//! A restricted pickle virtual machine for PyTorch state dicts.
//!
//! It runs the subset of the pickle protocol (versions 2 to 5) that `torch.save` emits for state
//! dicts, and nothing else: any other opcode, and any global outside a fixed whitelist, is an
//! error naming it and its byte offset. Globals are never imported or called: the whitelisted
//! ones are recognised by name and interpreted here.
//!
//! Whitelisted globals:
//! * `collections.OrderedDict`, called with no arguments (items follow as SETITEMS; a later
//!   BUILD that sets the `_metadata` attribute is accepted and ignored);
//! * `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks[, metadata])`
//!   and the older `torch._utils._rebuild_tensor(storage, offset, size, stride)`;
//! * `torch._utils._rebuild_parameter(data, requires_grad, hooks)` and
//!   `_rebuild_parameter_with_state(data, requires_grad, hooks, state)`, which return `data`;
//! * `torch.<T>Storage` (also `torch.cuda.<T>Storage`) for the storage types in [`DType`], used
//!   only as the type field of a persistent id.
//!
//! Persistent ids (BINPERSID) must be `('storage', storage_type, key, location, numel)` (zip
//! format) or the same with a sixth `view_metadata` field, `None` or `(view_key, offset, size)`
//! (legacy format). Storages are only declared here; their bytes are read by the format modules.
//!
//! Resources are bounded: every length is checked against the bytes left before anything is
//! allocated; the stack, the MARK stack, the memo and the tuple nesting depth have fixed
//! limits, and so has the length of string dict keys (which are hashed on every insertion).
//! Lists and dicts live in an arena and are referred to by index, so a memo reference is
//! a cheap copy and a self-containing dict cannot make a reference cycle.

use std::collections::{BTreeMap, HashMap};
use std::rc::Rc;

use super::error::FormatError;

/// Most values the pickle stack may hold at once.
pub(crate) const MAX_STACK: usize = 1 << 20;
/// Most MARKs open at once.
pub(crate) const MAX_MARKS: usize = 1 << 12;
/// Most memo entries.
pub(crate) const MAX_MEMO: usize = 1 << 20;
/// Deepest tuple nesting (a state dict needs 3: arguments, persistent id, view metadata).
pub(crate) const MAX_TUPLE_DEPTH: u32 = 64;
/// Longest string dict key, in bytes; bounds the time spent hashing keys.
pub(crate) const MAX_KEY_LEN: usize = 1024;
/// Longest module or name line of a GLOBAL opcode.
const MAX_GLOBAL_LINE: usize = 256;

/// Element type of a storage, from its `torch.<T>Storage` class name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum DType {
    F32,
    F64,
    F16,
    BF16,
    I64,
    I32,
    I16,
    I8,
    U8,
    Bool,
}

impl DType {
    fn from_storage_name(name: &str) -> Option<DType> {
        Some(match name {
            "FloatStorage" => DType::F32,
            "DoubleStorage" => DType::F64,
            "HalfStorage" => DType::F16,
            "BFloat16Storage" => DType::BF16,
            "LongStorage" => DType::I64,
            "IntStorage" => DType::I32,
            "ShortStorage" => DType::I16,
            "CharStorage" => DType::I8,
            "ByteStorage" => DType::U8,
            "BoolStorage" => DType::Bool,
            _ => return None,
        })
    }

    /// Bytes per element.
    pub(crate) fn size(self) -> u64 {
        match self {
            DType::F64 | DType::I64 => 8,
            DType::F32 | DType::I32 => 4,
            DType::F16 | DType::BF16 | DType::I16 => 2,
            DType::I8 | DType::U8 | DType::Bool => 1,
        }
    }

    /// Whether tensors of this type are imported (converted to `f32`).
    pub(crate) fn is_float(self) -> bool {
        matches!(self, DType::F32 | DType::F64 | DType::F16 | DType::BF16)
    }
}

/// A whitelisted global, recognised by module and name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Global {
    OrderedDict,
    RebuildTensorV2,
    RebuildTensor,
    RebuildParameter,
    RebuildParameterWithState,
    Storage(DType),
}

fn resolve_global(module: &str, name: &str) -> Option<Global> {
    match (module, name) {
        ("collections", "OrderedDict") => Some(Global::OrderedDict),
        ("torch._utils", "_rebuild_tensor_v2") => Some(Global::RebuildTensorV2),
        ("torch._utils", "_rebuild_tensor") => Some(Global::RebuildTensor),
        ("torch._utils", "_rebuild_parameter") => Some(Global::RebuildParameter),
        ("torch._utils", "_rebuild_parameter_with_state") => {
            Some(Global::RebuildParameterWithState)
        }
        ("torch" | "torch.cuda", _) => DType::from_storage_name(name).map(Global::Storage),
        _ => None,
    }
}

/// A storage (or a view of one) named by a persistent id.
#[derive(Debug)]
pub(crate) struct StorageRef {
    /// Key of the root storage whose bytes are in the file.
    pub key: String,
    pub dtype: DType,
    /// First element of this view within the root storage.
    pub start: u64,
    /// Elements in this view.
    pub len: u64,
}

/// A root storage as declared by the persistent ids: its type and element count.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct StorageDecl {
    pub dtype: DType,
    pub numel: u64,
}

/// A tensor as rebuilt by `_rebuild_tensor_v2`: a strided window into a storage.
#[derive(Debug)]
pub(crate) struct TensorRef {
    pub storage: Rc<StorageRef>,
    /// Storage offset, in elements, relative to the storage view.
    pub offset: u64,
    pub shape: Vec<u64>,
    pub stride: Vec<u64>,
}

/// An immutable tuple, with its nesting depth.
#[derive(Debug)]
pub(crate) struct Tuple {
    pub items: Vec<Value>,
    depth: u32,
}

/// A value on the pickle stack.
#[derive(Clone, Debug)]
pub(crate) enum Value {
    None,
    Bool(bool),
    Int(i128),
    Float(f64),
    Str(Rc<str>),
    Tuple(Rc<Tuple>),
    /// Index into [`Arena::lists`].
    List(usize),
    /// Index into [`Arena::dicts`].
    Dict(usize),
    Global(Global),
    Storage(Rc<StorageRef>),
    Tensor(Rc<TensorRef>),
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
            Value::Global(_) => "global",
            Value::Storage(_) => "storage",
            Value::Tensor(_) => "tensor",
        }
    }

    /// A short description for error messages: the value of a number or short string, else
    /// the kind.
    pub(crate) fn describe(&self) -> String {
        match self {
            Value::Int(i) => format!("the int {i}"),
            Value::Bool(b) => format!("the bool {b}"),
            Value::Float(x) => format!("the float {x}"),
            Value::Str(s) if s.len() <= 64 => format!("the string {s:?}"),
            other => format!("a {}", other.kind()),
        }
    }

    fn depth(&self) -> u32 {
        match self {
            Value::Tuple(t) => t.depth,
            _ => 0,
        }
    }
}

/// A hashable dict key.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub(crate) enum Key {
    Str(Rc<str>),
    Int(i128),
    None,
}

impl std::fmt::Display for Key {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Key::Str(s) => f.write_str(s),
            Key::Int(i) => write!(f, "{i}"),
            Key::None => f.write_str("None"),
        }
    }
}

/// A dict in insertion order; setting an existing key replaces its value in place.
#[derive(Debug, Default)]
pub(crate) struct Dict {
    pub entries: Vec<(Key, Value)>,
    index: HashMap<Key, usize>,
}

impl Dict {
    fn insert(&mut self, key: Key, value: Value) {
        match self.index.get(&key) {
            Some(&i) => self.entries[i].1 = value,
            None => {
                self.index.insert(key.clone(), self.entries.len());
                self.entries.push((key, value));
            }
        }
    }

    /// The value stored under a string key.
    pub(crate) fn get_str(&self, key: &str) -> Option<&Value> {
        self.index
            .get(&Key::Str(key.into()))
            .map(|&i| &self.entries[i].1)
    }
}

/// The mutable containers of one pickle.
#[derive(Debug, Default)]
pub(crate) struct Arena {
    pub lists: Vec<Vec<Value>>,
    pub dicts: Vec<Dict>,
}

/// The result of running one pickle.
#[derive(Debug)]
pub(crate) struct Pickle {
    pub root: Value,
    pub arena: Arena,
    /// Root storages declared by persistent ids, by key.
    pub storages: BTreeMap<String, StorageDecl>,
    /// Bytes consumed, up to and including STOP.
    pub len: usize,
}

/// Runs the pickle at the start of `data`, whose first byte is at file offset `base`.
pub(crate) fn unpickle(data: &[u8], base: u64) -> Result<Pickle, FormatError> {
    let mut m = Machine {
        data,
        pos: 0,
        base,
        stack: Vec::new(),
        marks: Vec::new(),
        memo: HashMap::new(),
        arena: Arena::default(),
        storages: BTreeMap::new(),
    };
    let root = m.run()?;
    Ok(Pickle {
        root,
        arena: m.arena,
        storages: m.storages,
        len: m.pos,
    })
}

struct Machine<'a> {
    data: &'a [u8],
    pos: usize,
    base: u64,
    stack: Vec<Value>,
    /// Stack heights at each open MARK.
    marks: Vec<usize>,
    memo: HashMap<u32, Value>,
    arena: Arena,
    storages: BTreeMap<String, StorageDecl>,
}

impl<'a> Machine<'a> {
    fn run(&mut self) -> Result<Value, FormatError> {
        loop {
            let at = self.pos;
            let op = self.take(1, "opcode")?[0];
            match op {
                // PROTO
                0x80 => {
                    let version = self.take(1, "PROTO version")?[0];
                    if !(2..=5).contains(&version) {
                        return Err(self.bad(at, format!("unsupported pickle protocol {version}")));
                    }
                }
                // FRAME: a read-ahead hint only; the opcodes inside are read as usual.
                0x95 => {
                    self.take(8, "FRAME length")?;
                }
                b'.' => return self.pop(at),
                b'(' => {
                    if self.marks.len() >= MAX_MARKS {
                        return Err(self.limit(at, "open MARKs", MAX_MARKS));
                    }
                    self.marks.push(self.stack.len());
                }
                b'}' => {
                    let id = self.arena.dicts.len();
                    self.arena.dicts.push(Dict::default());
                    self.push(at, Value::Dict(id))?;
                }
                b']' => {
                    let id = self.arena.lists.len();
                    self.arena.lists.push(Vec::new());
                    self.push(at, Value::List(id))?;
                }
                b')' => self.push_tuple(at, Vec::new())?,
                b't' => {
                    let items = self.pop_mark(at)?;
                    self.push_tuple(at, items)?;
                }
                // TUPLE1, TUPLE2, TUPLE3
                0x85..=0x87 => {
                    let n = usize::from(op - 0x84);
                    let mut items = Vec::with_capacity(n);
                    for _ in 0..n {
                        items.push(self.pop(at)?);
                    }
                    items.reverse();
                    self.push_tuple(at, items)?;
                }
                // BINPUT, LONG_BINPUT, MEMOIZE
                b'q' => {
                    let i = self.take(1, "BINPUT index")?[0];
                    self.memo_put(at, u32::from(i))?;
                }
                b'r' => {
                    let i = self.u32_le("LONG_BINPUT index")?;
                    self.memo_put(at, i)?;
                }
                0x94 => {
                    let i = u32::try_from(self.memo.len()).expect("memo size is bounded");
                    self.memo_put(at, i)?;
                }
                // BINGET, LONG_BINGET
                b'h' => {
                    let i = self.take(1, "BINGET index")?[0];
                    self.memo_get(at, u32::from(i))?;
                }
                b'j' => {
                    let i = self.u32_le("LONG_BINGET index")?;
                    self.memo_get(at, i)?;
                }
                // BININT, BININT1, BININT2, LONG1
                b'J' => {
                    let b = self.take(4, "BININT")?;
                    let v = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                    self.push(at, Value::Int(v.into()))?;
                }
                b'K' => {
                    let v = self.take(1, "BININT1")?[0];
                    self.push(at, Value::Int(v.into()))?;
                }
                b'M' => {
                    let b = self.take(2, "BININT2")?;
                    let v = u16::from_le_bytes([b[0], b[1]]);
                    self.push(at, Value::Int(v.into()))?;
                }
                0x8a => {
                    let n = usize::from(self.take(1, "LONG1 length")?[0]);
                    if n > 16 {
                        return Err(
                            self.bad(at, format!("LONG1 integer of {n} bytes is too large"))
                        );
                    }
                    let bytes = self.take(n, "LONG1 digits")?;
                    self.push(at, Value::Int(long_from_le(bytes)))?;
                }
                // BINUNICODE, SHORT_BINUNICODE, BINSTRING, SHORT_BINSTRING (strings decode
                // as UTF-8, as torch.load does for Python 2 pickles)
                b'X' => {
                    let n = self.u32_le("BINUNICODE length")? as usize;
                    self.push_str(at, n)?;
                }
                0x8c => {
                    let n = usize::from(self.take(1, "SHORT_BINUNICODE length")?[0]);
                    self.push_str(at, n)?;
                }
                b'T' => {
                    let n = self.u32_le("BINSTRING length")?;
                    if n > i32::MAX as u32 {
                        return Err(self.bad(at, "negative BINSTRING length".into()));
                    }
                    self.push_str(at, n as usize)?;
                }
                b'U' => {
                    let n = usize::from(self.take(1, "SHORT_BINSTRING length")?[0]);
                    self.push_str(at, n)?;
                }
                b'G' => {
                    let b = self.take(8, "BINFLOAT")?;
                    let v = f64::from_be_bytes(b.try_into().expect("8 bytes"));
                    self.push(at, Value::Float(v))?;
                }
                0x88 => self.push(at, Value::Bool(true))?,
                0x89 => self.push(at, Value::Bool(false))?,
                b'N' => self.push(at, Value::None)?,
                b'c' => {
                    let module = self.line(at)?;
                    let name = self.line(at)?;
                    let g = self.global(at, &module, &name)?;
                    self.push(at, Value::Global(g))?;
                }
                // STACK_GLOBAL
                0x93 => {
                    let name = self.pop(at)?;
                    let module = self.pop(at)?;
                    let (Value::Str(module), Value::Str(name)) = (module, name) else {
                        return Err(self.bad(at, "STACK_GLOBAL needs two strings".into()));
                    };
                    let g = self.global(at, &module, &name)?;
                    self.push(at, Value::Global(g))?;
                }
                b'R' => self.reduce(at)?,
                b'b' => self.build(at)?,
                b's' => {
                    let value = self.pop(at)?;
                    let key = self.pop(at)?;
                    let dict = self.top_dict(at, "SETITEM")?;
                    let key = self.key(at, key)?;
                    self.arena.dicts[dict].insert(key, value);
                }
                b'u' => {
                    let items = self.pop_mark(at)?;
                    if items.len() % 2 != 0 {
                        return Err(self.bad(at, "SETITEMS with an odd number of items".into()));
                    }
                    let dict = self.top_dict(at, "SETITEMS")?;
                    let mut items = items.into_iter();
                    while let (Some(k), Some(v)) = (items.next(), items.next()) {
                        let k = self.key(at, k)?;
                        self.arena.dicts[dict].insert(k, v);
                    }
                }
                b'a' => {
                    let value = self.pop(at)?;
                    let list = self.top_list(at, "APPEND")?;
                    self.arena.lists[list].push(value);
                }
                b'e' => {
                    let items = self.pop_mark(at)?;
                    let list = self.top_list(at, "APPENDS")?;
                    self.arena.lists[list].extend(items);
                }
                b'Q' => {
                    let pid = self.pop(at)?;
                    let storage = self.persistent_load(at, pid)?;
                    self.push(at, Value::Storage(storage))?;
                }
                _ => {
                    return Err(FormatError::UnsupportedOpcode {
                        opcode: op,
                        offset: self.abs(at),
                    })
                }
            }
        }
    }

    fn abs(&self, at: usize) -> u64 {
        self.base + at as u64
    }

    fn bad(&self, at: usize, reason: String) -> FormatError {
        FormatError::Pickle {
            offset: self.abs(at),
            reason,
        }
    }

    fn limit(&self, at: usize, what: &'static str, limit: usize) -> FormatError {
        FormatError::Limit {
            offset: self.abs(at),
            what,
            limit: limit as u64,
        }
    }

    /// The next `n` bytes, or a truncation error naming `what`.
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], FormatError> {
        let left = self.data.len() - self.pos;
        if n > left {
            return Err(FormatError::Truncated {
                what: format!("pickle {what}"),
                offset: self.abs(self.pos),
                needed: (n - left) as u64,
            });
        }
        let bytes = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(bytes)
    }

    fn u32_le(&mut self, what: &str) -> Result<u32, FormatError> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// A newline-terminated ASCII line of a GLOBAL opcode.
    fn line(&mut self, at: usize) -> Result<String, FormatError> {
        let rest = &self.data[self.pos..];
        let window = &rest[..rest.len().min(MAX_GLOBAL_LINE + 1)];
        let Some(end) = window.iter().position(|&b| b == b'\n') else {
            return Err(if rest.len() <= MAX_GLOBAL_LINE {
                FormatError::Truncated {
                    what: "pickle GLOBAL name".into(),
                    offset: self.abs(self.data.len()),
                    needed: 1,
                }
            } else {
                self.bad(
                    at,
                    format!("GLOBAL name longer than {MAX_GLOBAL_LINE} bytes"),
                )
            });
        };
        let text = std::str::from_utf8(&window[..end])
            .ok()
            .filter(|s| s.is_ascii())
            .ok_or_else(|| self.bad(at, "GLOBAL name is not ASCII".into()))?
            .to_owned();
        self.pos += end + 1;
        Ok(text)
    }

    fn global(&self, at: usize, module: &str, name: &str) -> Result<Global, FormatError> {
        resolve_global(module, name).ok_or_else(|| FormatError::UnsupportedGlobal {
            module: module.to_owned(),
            name: name.to_owned(),
            offset: self.abs(at),
        })
    }

    fn push(&mut self, at: usize, v: Value) -> Result<(), FormatError> {
        if self.stack.len() >= MAX_STACK {
            return Err(self.limit(at, "stack values", MAX_STACK));
        }
        self.stack.push(v);
        Ok(())
    }

    fn push_str(&mut self, at: usize, n: usize) -> Result<(), FormatError> {
        let bytes = self.take(n, "string")?;
        let s = std::str::from_utf8(bytes)
            .map_err(|_| self.bad(at, "string is not valid UTF-8".into()))?;
        self.push(at, Value::Str(s.into()))
    }

    fn push_tuple(&mut self, at: usize, items: Vec<Value>) -> Result<(), FormatError> {
        let depth = 1 + items.iter().map(Value::depth).max().unwrap_or(0);
        if depth > MAX_TUPLE_DEPTH {
            return Err(self.limit(at, "nested tuples", MAX_TUPLE_DEPTH as usize));
        }
        self.push(at, Value::Tuple(Rc::new(Tuple { items, depth })))
    }

    /// Height below which the stack belongs to an enclosing MARK.
    fn floor(&self) -> usize {
        self.marks.last().copied().unwrap_or(0)
    }

    fn pop(&mut self, at: usize) -> Result<Value, FormatError> {
        if self.stack.len() <= self.floor() {
            return Err(self.bad(at, "stack underflow".into()));
        }
        Ok(self.stack.pop().expect("checked non-empty"))
    }

    fn peek(&self, at: usize) -> Result<&Value, FormatError> {
        if self.stack.len() <= self.floor() {
            return Err(self.bad(at, "stack underflow".into()));
        }
        Ok(self.stack.last().expect("checked non-empty"))
    }

    fn pop_mark(&mut self, at: usize) -> Result<Vec<Value>, FormatError> {
        let mark = self
            .marks
            .pop()
            .ok_or_else(|| self.bad(at, "no MARK to pop to".into()))?;
        Ok(self.stack.split_off(mark))
    }

    fn top_dict(&self, at: usize, op: &str) -> Result<usize, FormatError> {
        match self.peek(at)? {
            Value::Dict(id) => Ok(*id),
            other => Err(self.bad(at, format!("{op} on a {}, not a dict", other.kind()))),
        }
    }

    fn top_list(&self, at: usize, op: &str) -> Result<usize, FormatError> {
        match self.peek(at)? {
            Value::List(id) => Ok(*id),
            other => Err(self.bad(at, format!("{op} on a {}, not a list", other.kind()))),
        }
    }

    fn key(&self, at: usize, v: Value) -> Result<Key, FormatError> {
        match v {
            Value::Str(s) if s.len() > MAX_KEY_LEN => {
                Err(self.limit(at, "bytes in a dict key", MAX_KEY_LEN))
            }
            Value::Str(s) => Ok(Key::Str(s)),
            Value::Int(i) => Ok(Key::Int(i)),
            Value::Bool(b) => Ok(Key::Int(b.into())),
            Value::None => Ok(Key::None),
            other => Err(self.bad(at, format!("a {} cannot be a dict key", other.kind()))),
        }
    }

    fn memo_put(&mut self, at: usize, i: u32) -> Result<(), FormatError> {
        let v = self.peek(at)?.clone();
        if self.memo.len() >= MAX_MEMO && !self.memo.contains_key(&i) {
            return Err(self.limit(at, "memo entries", MAX_MEMO));
        }
        self.memo.insert(i, v);
        Ok(())
    }

    fn memo_get(&mut self, at: usize, i: u32) -> Result<(), FormatError> {
        let v = self
            .memo
            .get(&i)
            .cloned()
            .ok_or_else(|| self.bad(at, format!("memo entry {i} was never set")))?;
        self.push(at, v)
    }

    fn reduce(&mut self, at: usize) -> Result<(), FormatError> {
        let args = self.pop(at)?;
        let func = self.pop(at)?;
        let Value::Global(g) = func else {
            return Err(self.bad(at, format!("REDUCE calls a {}", func.kind())));
        };
        let Value::Tuple(args) = args else {
            return Err(self.bad(at, format!("REDUCE arguments are a {}", args.kind())));
        };
        let args = &args.items;
        let arity = |ok: bool, want: &str| {
            if ok {
                Ok(())
            } else {
                Err(self.bad(
                    at,
                    format!(
                        "{g:?} called with {} arguments, expected {want}",
                        args.len()
                    ),
                ))
            }
        };
        let out = match g {
            Global::OrderedDict => {
                arity(args.is_empty(), "0")?;
                let id = self.arena.dicts.len();
                self.arena.dicts.push(Dict::default());
                Value::Dict(id)
            }
            Global::RebuildTensorV2 => {
                arity(args.len() == 6 || args.len() == 7, "6 or 7")?;
                self.rebuild_tensor(at, &args[..4])?
            }
            Global::RebuildTensor => {
                arity(args.len() == 4, "4")?;
                self.rebuild_tensor(at, args)?
            }
            Global::RebuildParameter | Global::RebuildParameterWithState => {
                let n = if g == Global::RebuildParameter { 3 } else { 4 };
                arity(args.len() == n, if n == 3 { "3" } else { "4" })?;
                match &args[0] {
                    t @ Value::Tensor(_) => t.clone(),
                    other => {
                        return Err(self.bad(at, format!("parameter data is a {}", other.kind())))
                    }
                }
            }
            Global::Storage(_) => {
                return Err(self.bad(at, "a storage type cannot be called".into()));
            }
        };
        self.push(at, out)
    }

    /// `(storage, storage_offset, size, stride)` to a tensor.
    fn rebuild_tensor(&self, at: usize, args: &[Value]) -> Result<Value, FormatError> {
        let Value::Storage(storage) = &args[0] else {
            return Err(self.bad(
                at,
                format!("tensor storage is a {}, not a storage", args[0].kind()),
            ));
        };
        let offset = self.count(at, &args[1], "storage offset")?;
        let shape = self.counts(at, &args[2], "size")?;
        let stride = self.counts(at, &args[3], "stride")?;
        if shape.len() != stride.len() {
            return Err(self.bad(
                at,
                format!("size {shape:?} and stride {stride:?} differ in length"),
            ));
        }
        Ok(Value::Tensor(Rc::new(TensorRef {
            storage: storage.clone(),
            offset,
            shape,
            stride,
        })))
    }

    /// A non-negative integer that fits in `u64`.
    fn count(&self, at: usize, v: &Value, what: &str) -> Result<u64, FormatError> {
        match v {
            Value::Int(i) => u64::try_from(*i)
                .map_err(|_| self.bad(at, format!("{what} {i} is negative or too large"))),
            other => Err(self.bad(at, format!("{what} is a {}, not an int", other.kind()))),
        }
    }

    fn counts(&self, at: usize, v: &Value, what: &str) -> Result<Vec<u64>, FormatError> {
        match v {
            Value::Tuple(t) => t.items.iter().map(|x| self.count(at, x, what)).collect(),
            other => Err(self.bad(at, format!("{what} is a {}, not a tuple", other.kind()))),
        }
    }

    /// BUILD: only the attribute state of an (Ordered)Dict, which is ignored (`_metadata`).
    fn build(&mut self, at: usize) -> Result<(), FormatError> {
        let _state = self.pop(at)?;
        match self.peek(at)? {
            Value::Dict(_) => Ok(()),
            other => Err(self.bad(at, format!("BUILD on a {}", other.kind()))),
        }
    }

    /// `('storage', storage_type, key, location, numel[, view_metadata])` to a storage reference.
    fn persistent_load(&mut self, at: usize, pid: Value) -> Result<Rc<StorageRef>, FormatError> {
        let Value::Tuple(pid) = pid else {
            return Err(self.bad(at, format!("persistent id is a {}", pid.kind())));
        };
        let items = &pid.items;
        if !matches!(items.first(), Some(Value::Str(s)) if &**s == "storage") {
            return Err(self.bad(at, "persistent id is not a ('storage', ...) tuple".into()));
        }
        if items.len() != 5 && items.len() != 6 {
            return Err(self.bad(
                at,
                format!(
                    "storage persistent id has {} fields, expected 5 or 6",
                    items.len()
                ),
            ));
        }
        let Value::Global(Global::Storage(dtype)) = items[1] else {
            return Err(self.bad(
                at,
                format!("storage type is a {}, not a storage class", items[1].kind()),
            ));
        };
        let key = match &items[2] {
            Value::Str(s) => s.to_string(),
            Value::Int(i) => i.to_string(),
            other => return Err(self.bad(at, format!("storage key is a {}", other.kind()))),
        };
        if !matches!(items[3], Value::Str(_)) {
            return Err(self.bad(at, "storage location is not a string".into()));
        }
        let numel = self.count(at, &items[4], "storage size")?;
        let decl = StorageDecl { dtype, numel };
        match self.storages.get(&key) {
            Some(prev) if *prev != decl => {
                return Err(self.bad(
                    at,
                    format!("storage {key} declared as {prev:?} and as {decl:?}"),
                ))
            }
            Some(_) => {}
            None => {
                self.storages.insert(key.clone(), decl);
            }
        }
        let (start, len) = match items.get(5) {
            None | Some(Value::None) => (0, numel),
            Some(Value::Tuple(view)) if view.items.len() == 3 => {
                let start = self.count(at, &view.items[1], "view offset")?;
                let len = self.count(at, &view.items[2], "view size")?;
                if start.checked_add(len).is_none_or(|end| end > numel) {
                    return Err(self.bad(
                        at,
                        format!("view [{start}, +{len}) outside storage {key} of {numel} elements"),
                    ));
                }
                (start, len)
            }
            Some(other) => {
                return Err(self.bad(at, format!("storage view metadata is a {}", other.kind())))
            }
        };
        Ok(Rc::new(StorageRef {
            key,
            dtype,
            start,
            len,
        }))
    }
}

/// A little-endian two's-complement integer of at most 16 bytes.
fn long_from_le(bytes: &[u8]) -> i128 {
    let Some(&last) = bytes.last() else {
        return 0;
    };
    let fill = if last & 0x80 != 0 { 0xff } else { 0 };
    let mut buf = [fill; 16];
    buf[..bytes.len()].copy_from_slice(bytes);
    i128::from_le_bytes(buf)
}
