//! PyTorch `.pt` files in the zip format of `torch.save`: a reader and a writer for plain data.
//!
//! A file is a zip archive (entries stored, not compressed) whose entries share one top folder
//! (torch names it after the file stem, or `archive`):
//!
//! - `PREFIX/data.pkl`: the object, pickled with protocol 2. Tensors appear as calls of
//!   `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks)`,
//!   where `storage` is a persistent id `('storage', torch.FloatStorage, key, location, numel)`;
//! - `PREFIX/data/KEY`: the raw bytes of storage `KEY`, `numel` elements, little-endian;
//! - `PREFIX/version`, `PREFIX/byteorder` (`little`; `big` is rejected) and other bookkeeping.
//!
//! The reader runs its own small pickle machine over the opcodes torch writes (protocol 0–2,
//! plus the protocol-4 `FRAME`, `MEMOIZE`, `SHORT_BINUNICODE` and `STACK_GLOBAL`). It calls no
//! code: the only globals it accepts are the tensor and storage constructors above,
//! `torch._utils._rebuild_parameter`, `collections.OrderedDict` and `torch.Size`. The result
//! is a [`PtValue`]: dicts with string keys, lists, tuples, ints, floats, bools, `None`,
//! strings and tensors (float32/float64/int32/int64/uint8, any shape, read through their
//! offset and strides into row-major order). Sizes are checked against fixed limits before
//! anything is allocated. Files from `torch.save(..., _use_new_zipfile_serialization=False)`
//! (the legacy format) are recognised and rejected with [`TorchError::LegacyFormat`].
//!
//! The writer ([`write_pt`]) produces the same format for [`PtValue`]s, one storage per tensor,
//! so `torch.load` reads it (with the default `weights_only=True`).

use std::collections::HashMap;
use std::fs::File;
use std::io::{self, Cursor, Read, Seek, Write};
use std::path::{Path, PathBuf};
use std::rc::Rc;

use matloc_core::fsutil::write_atomic;
use thiserror::Error;

/// Largest `data.pkl` read, in bytes.
pub const MAX_PICKLE_BYTES: u64 = 16 << 20;
/// Largest single storage read, in bytes.
pub const MAX_STORAGE_BYTES: u64 = 1 << 30;
/// Largest number of tensor elements in one file (each tensor, and all of them together as
/// read, counting a tensor once per reference to it).
pub const MAX_TENSOR_ELEMENTS: u64 = 1 << 27;
/// Largest number of string bytes in the read object, counting a string once per reference.
pub const MAX_STRING_BYTES: u64 = 64 << 20;
/// Largest number of entries in the zip archive.
pub const MAX_ZIP_ENTRIES: usize = 1 << 16;
/// Largest number of values (every list item, dict entry, tuple member) in the read object,
/// counting shared ones once per reference.
pub const MAX_VALUES: usize = 1 << 22;
/// Deepest nesting of lists, tuples and dicts in the read object.
pub const MAX_DEPTH: usize = 64;

/// Legacy (non-zip) `torch.save` files start with protocol 2 and a 10-byte magic number.
const LEGACY_MAGIC: [u8; 14] = [
    0x80, 0x02, 0x8a, 0x0a, 0x6c, 0xfc, 0x9c, 0x46, 0xf9, 0x20, 0x6a, 0xa8, 0x50, 0x19,
];

/// Errors raised when reading or writing `.pt` files. Every variant names the file.
#[derive(Debug, Error)]
pub enum TorchError {
    /// Reading or writing failed at the operating-system level.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The file is a `torch.save` file in the legacy (pre-1.6, non-zip) format.
    #[error(
        "{path} is a torch file in the legacy (non-zip) format, which is not supported; \
         re-save it with torch.save(torch.load(f), f) from torch >= 1.6"
    )]
    LegacyFormat {
        /// The file.
        path: PathBuf,
    },
    /// The file is not a zip archive of the `torch.save` layout.
    #[error("{path} is not a torch .pt file: {reason}")]
    NotTorch {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// An archive entry or an object is larger than the reader accepts.
    #[error("{path}: {what} is {size}, more than the limit of {limit}")]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// What is too large.
        what: String,
        /// Its size.
        size: u64,
        /// The limit.
        limit: u64,
    },
    /// `data.pkl` is malformed or uses something this reader does not support.
    #[error("{path}: data.pkl at byte {offset}: {reason}")]
    Pickle {
        /// The file.
        path: PathBuf,
        /// Byte offset of the opcode in `data.pkl`.
        offset: usize,
        /// What is wrong.
        reason: String,
    },
    /// A tensor's storage or layout is inconsistent.
    #[error("{path}: storage `{key}`: {reason}")]
    Storage {
        /// The file.
        path: PathBuf,
        /// The storage key.
        key: String,
        /// What is wrong.
        reason: String,
    },
    /// The value cannot be written (a tensor whose data does not fill its shape, ...).
    #[error("cannot write {path}: {reason}")]
    Unwritable {
        /// The file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
}

/// Element type of a tensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DType {
    /// `torch.float32` (`FloatStorage`).
    F32,
    /// `torch.float64` (`DoubleStorage`).
    F64,
    /// `torch.int32` (`IntStorage`).
    I32,
    /// `torch.int64` (`LongStorage`).
    I64,
    /// `torch.uint8` (`ByteStorage`).
    U8,
}

impl DType {
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::F32 | DType::I32 => 4,
            DType::F64 | DType::I64 => 8,
            DType::U8 => 1,
        }
    }

    /// The storage class torch pickles for this type.
    pub fn storage_name(self) -> &'static str {
        match self {
            DType::F32 => "FloatStorage",
            DType::F64 => "DoubleStorage",
            DType::I32 => "IntStorage",
            DType::I64 => "LongStorage",
            DType::U8 => "ByteStorage",
        }
    }

    fn from_storage_name(name: &str) -> Option<DType> {
        [DType::F32, DType::F64, DType::I32, DType::I64, DType::U8]
            .into_iter()
            .find(|d| d.storage_name() == name)
    }
}

/// Tensor elements in row-major order.
#[derive(Clone, Debug, PartialEq)]
pub enum TensorData {
    /// float32 elements.
    F32(Vec<f32>),
    /// float64 elements.
    F64(Vec<f64>),
    /// int32 elements.
    I32(Vec<i32>),
    /// int64 elements.
    I64(Vec<i64>),
    /// uint8 elements.
    U8(Vec<u8>),
}

/// A dense tensor: shape and row-major elements.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// Size of each dimension (empty for a 0-dimensional tensor).
    pub shape: Vec<usize>,
    /// The elements, `shape.iter().product()` of them.
    pub data: TensorData,
}

impl Tensor {
    /// A float64 tensor.
    pub fn f64(shape: Vec<usize>, data: Vec<f64>) -> Self {
        Tensor {
            shape,
            data: TensorData::F64(data),
        }
    }

    /// A float32 tensor.
    pub fn f32(shape: Vec<usize>, data: Vec<f32>) -> Self {
        Tensor {
            shape,
            data: TensorData::F32(data),
        }
    }

    /// The element type.
    pub fn dtype(&self) -> DType {
        match &self.data {
            TensorData::F32(_) => DType::F32,
            TensorData::F64(_) => DType::F64,
            TensorData::I32(_) => DType::I32,
            TensorData::I64(_) => DType::I64,
            TensorData::U8(_) => DType::U8,
        }
    }

    /// Number of elements stored.
    pub fn len(&self) -> usize {
        match &self.data {
            TensorData::F32(v) => v.len(),
            TensorData::F64(v) => v.len(),
            TensorData::I32(v) => v.len(),
            TensorData::I64(v) => v.len(),
            TensorData::U8(v) => v.len(),
        }
    }

    /// True when the tensor has no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The elements as f64 (int64 values beyond 2^53 round).
    pub fn to_f64(&self) -> Vec<f64> {
        match &self.data {
            TensorData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
            TensorData::F64(v) => v.clone(),
            TensorData::I32(v) => v.iter().map(|&x| f64::from(x)).collect(),
            TensorData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
        }
    }
}

/// A value read from (or to be written to) a `.pt` file.
#[derive(Clone, Debug, PartialEq)]
pub enum PtValue {
    /// Python `None`.
    None,
    /// A bool.
    Bool(bool),
    /// An int (within i64).
    Int(i64),
    /// A float.
    Float(f64),
    /// A string.
    Str(String),
    /// A list.
    List(Vec<PtValue>),
    /// A tuple (also `torch.Size`).
    Tuple(Vec<PtValue>),
    /// A dict (also `OrderedDict`) with string keys, in file order.
    Dict(Vec<(String, PtValue)>),
    /// A tensor.
    Tensor(Tensor),
}

impl PtValue {
    /// The value of `key` when `self` is a dict.
    pub fn get(&self, key: &str) -> Option<&PtValue> {
        match self {
            PtValue::Dict(items) => items.iter().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }

    /// A short description of the type, for error messages.
    pub fn kind(&self) -> String {
        match self {
            PtValue::None => "None".into(),
            PtValue::Bool(_) => "bool".into(),
            PtValue::Int(_) => "int".into(),
            PtValue::Float(_) => "float".into(),
            PtValue::Str(_) => "str".into(),
            PtValue::List(v) => format!("list of {}", v.len()),
            PtValue::Tuple(v) => format!("tuple of {}", v.len()),
            PtValue::Dict(v) => format!("dict of {}", v.len()),
            PtValue::Tensor(t) => format!("{:?} tensor of shape {:?}", t.dtype(), t.shape),
        }
    }

    /// A number: an int, a float, a bool, or a tensor with exactly one element.
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            PtValue::Int(i) => Some(*i as f64),
            PtValue::Float(f) => Some(*f),
            PtValue::Bool(b) => Some(f64::from(u8::from(*b))),
            PtValue::Tensor(t) if t.len() == 1 => t.to_f64().first().copied(),
            _ => None,
        }
    }

    /// The numbers of a tensor, or of a list or tuple of numbers, with the tensor's shape
    /// (`[n]` for a list).
    pub fn as_f64_array(&self) -> Option<(Vec<usize>, Vec<f64>)> {
        match self {
            PtValue::Tensor(t) => Some((t.shape.clone(), t.to_f64())),
            PtValue::List(v) | PtValue::Tuple(v) => {
                let data: Option<Vec<f64>> = v.iter().map(PtValue::as_f64).collect();
                data.map(|d| (vec![d.len()], d))
            }
            _ => None,
        }
    }
}

/// Reads a `.pt` file.
pub fn read_pt(path: &Path) -> Result<PtValue, TorchError> {
    let io_err = |source| TorchError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = File::open(path).map_err(io_err)?;
    let mut head = [0u8; LEGACY_MAGIC.len()];
    let n = read_up_to(&mut file, &mut head).map_err(io_err)?;
    check_magic(&head[..n], path)?;
    file.rewind().map_err(io_err)?;
    parse_archive(file, path)
}

/// Parses the bytes of a `.pt` file; `path` names it in errors.
pub fn parse_pt(bytes: &[u8], path: &Path) -> Result<PtValue, TorchError> {
    check_magic(&bytes[..bytes.len().min(LEGACY_MAGIC.len())], path)?;
    parse_archive(Cursor::new(bytes), path)
}

fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

fn check_magic(head: &[u8], path: &Path) -> Result<(), TorchError> {
    if head.starts_with(b"PK\x03\x04") {
        return Ok(());
    }
    if head == LEGACY_MAGIC {
        return Err(TorchError::LegacyFormat {
            path: path.to_path_buf(),
        });
    }
    Err(TorchError::NotTorch {
        path: path.to_path_buf(),
        reason: "not a zip archive (torch.save writes zip archives since torch 1.6)".into(),
    })
}

/// The archive entries of one file.
struct Archive<R: Read + Seek> {
    zip: zip::ZipArchive<R>,
    prefix: String,
    path: PathBuf,
}

impl<R: Read + Seek> Archive<R> {
    fn read_entry(&mut self, name: &str, limit: u64) -> Result<Option<Vec<u8>>, TorchError> {
        let full = format!("{}/{name}", self.prefix);
        let mut entry = match self.zip.by_name(&full) {
            Ok(e) => e,
            Err(zip::result::ZipError::FileNotFound) => return Ok(None),
            Err(e) => {
                return Err(TorchError::NotTorch {
                    path: self.path.clone(),
                    reason: format!("entry {full}: {e}"),
                });
            }
        };
        let size = entry.size();
        if size > limit {
            return Err(TorchError::TooLarge {
                path: self.path.clone(),
                what: format!("entry {full}"),
                size,
                limit,
            });
        }
        let mut bytes = Vec::with_capacity(size as usize);
        (&mut entry)
            .take(limit + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| TorchError::NotTorch {
                path: self.path.clone(),
                reason: format!("entry {full}: {e}"),
            })?;
        if bytes.len() as u64 > limit {
            return Err(TorchError::TooLarge {
                path: self.path.clone(),
                what: format!("entry {full}"),
                size: bytes.len() as u64,
                limit,
            });
        }
        Ok(Some(bytes))
    }
}

fn parse_archive<R: Read + Seek>(reader: R, path: &Path) -> Result<PtValue, TorchError> {
    let not_torch = |reason: String| TorchError::NotTorch {
        path: path.to_path_buf(),
        reason,
    };
    let zip =
        zip::ZipArchive::new(reader).map_err(|e| not_torch(format!("bad zip archive: {e}")))?;
    if zip.len() > MAX_ZIP_ENTRIES {
        return Err(TorchError::TooLarge {
            path: path.to_path_buf(),
            what: "number of archive entries".into(),
            size: zip.len() as u64,
            limit: MAX_ZIP_ENTRIES as u64,
        });
    }
    // Like torch: the folder of the first entry is the archive's prefix.
    let prefix = zip
        .file_names()
        .next()
        .and_then(|n| n.split_once('/'))
        .map(|(p, _)| p.to_string())
        .ok_or_else(|| not_torch("the archive has no top folder".into()))?;
    let mut archive = Archive {
        zip,
        prefix,
        path: path.to_path_buf(),
    };
    if let Some(order) = archive.read_entry("byteorder", 64)?
        && order.trim_ascii() != b"little"
    {
        return Err(not_torch(format!(
            "byte order `{}` (only little-endian files are supported)",
            String::from_utf8_lossy(&order)
        )));
    }
    let pickle = archive
        .read_entry("data.pkl", MAX_PICKLE_BYTES)?
        .ok_or_else(|| not_torch(format!("no {}/data.pkl entry", archive.prefix)))?;
    let mut machine = Machine::new(&pickle, archive);
    let root = machine.run()?;
    let mut budget = Budget {
        values: MAX_VALUES as u64,
        elements: MAX_TENSOR_ELEMENTS,
        string_bytes: MAX_STRING_BYTES,
    };
    machine.to_value(&root, 0, &mut budget)
}

/// A value on the pickle stack. Containers live in the arena (`Machine::nodes`), so memo
/// copies share them the way Python objects are shared.
#[derive(Clone, Debug)]
enum Obj {
    Mark,
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(Rc<str>),
    Node(usize),
    Global(Rc<str>, Rc<str>),
    Storage(StorageRef),
}

#[derive(Clone, Debug)]
struct StorageRef {
    key: Rc<str>,
    dtype: DType,
    numel: u64,
}

#[derive(Debug)]
enum Node {
    List(Vec<Obj>),
    Tuple(Vec<Obj>),
    Dict(Vec<(Obj, Obj)>),
    Tensor(Tensor),
}

struct Machine<'a, R: Read + Seek> {
    code: &'a [u8],
    pos: usize,
    op_pos: usize,
    stack: Vec<Obj>,
    memo: HashMap<u32, Obj>,
    nodes: Vec<Node>,
    /// Values held by all nodes, for [`MAX_VALUES`].
    values: usize,
    /// Tensor elements materialised, for [`MAX_TENSOR_ELEMENTS`].
    elements: u64,
    archive: Archive<R>,
    storages: HashMap<String, Rc<Vec<u8>>>,
    /// Storage bytes read so far.
    storage_bytes: u64,
}

impl<'a, R: Read + Seek> Machine<'a, R> {
    fn new(code: &'a [u8], archive: Archive<R>) -> Self {
        Machine {
            code,
            pos: 0,
            op_pos: 0,
            stack: Vec::new(),
            memo: HashMap::new(),
            nodes: Vec::new(),
            values: 0,
            elements: 0,
            archive,
            storages: HashMap::new(),
            storage_bytes: 0,
        }
    }

    fn err(&self, reason: impl Into<String>) -> TorchError {
        TorchError::Pickle {
            path: self.archive.path.clone(),
            offset: self.op_pos,
            reason: reason.into(),
        }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], TorchError> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.code.len())
            .ok_or_else(|| self.err(format!("truncated: {n} more bytes expected")))?;
        let s = &self.code[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u8(&mut self) -> Result<u8, TorchError> {
        Ok(self.take(1)?[0])
    }

    fn u16(&mut self) -> Result<u16, TorchError> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    fn u32(&mut self) -> Result<u32, TorchError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u64(&mut self) -> Result<u64, TorchError> {
        let b = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(u64::from_le_bytes(a))
    }

    /// A newline-terminated text argument (protocol 0 opcodes).
    fn line(&mut self) -> Result<&'a str, TorchError> {
        let rest = &self.code[self.pos..];
        let n = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| self.err("truncated: newline expected"))?;
        let s = std::str::from_utf8(&rest[..n]).map_err(|_| self.err("text is not UTF-8"))?;
        self.pos += n + 1;
        Ok(s)
    }

    fn utf8(&mut self, n: u64) -> Result<Obj, TorchError> {
        let n = usize::try_from(n).map_err(|_| self.err("string length overflows"))?;
        let b = self.take(n)?;
        let s = std::str::from_utf8(b).map_err(|_| self.err("string is not UTF-8"))?;
        Ok(Obj::Str(Rc::from(s)))
    }

    fn latin1(&mut self, n: usize) -> Result<Obj, TorchError> {
        let b = self.take(n)?;
        let s: String = b.iter().map(|&c| char::from(c)).collect();
        Ok(Obj::Str(Rc::from(s)))
    }

    fn push(&mut self, o: Obj) -> Result<(), TorchError> {
        if self.stack.len() >= MAX_VALUES {
            return Err(self.err("stack too deep"));
        }
        self.stack.push(o);
        Ok(())
    }

    fn pop(&mut self) -> Result<Obj, TorchError> {
        match self.stack.pop() {
            Some(Obj::Mark) => Err(self.err("unexpected mark")),
            Some(o) => Ok(o),
            None => Err(self.err("stack underflow")),
        }
    }

    fn top(&self) -> Result<&Obj, TorchError> {
        match self.stack.last() {
            Some(Obj::Mark) => Err(self.err("unexpected mark")),
            Some(o) => Ok(o),
            None => Err(self.err("stack underflow")),
        }
    }

    /// Pops everything above the topmost mark, and the mark.
    fn pop_mark(&mut self) -> Result<Vec<Obj>, TorchError> {
        let m = self
            .stack
            .iter()
            .rposition(|o| matches!(o, Obj::Mark))
            .ok_or_else(|| self.err("no mark on the stack"))?;
        let items = self.stack.split_off(m + 1);
        self.stack.pop();
        Ok(items)
    }

    fn count(&mut self, n: usize) -> Result<(), TorchError> {
        self.values = self.values.saturating_add(n);
        if self.values > MAX_VALUES {
            return Err(TorchError::TooLarge {
                path: self.archive.path.clone(),
                what: "number of values in data.pkl".into(),
                size: self.values as u64,
                limit: MAX_VALUES as u64,
            });
        }
        Ok(())
    }

    fn node(&mut self, n: Node) -> Result<Obj, TorchError> {
        let len = match &n {
            Node::List(v) | Node::Tuple(v) => v.len(),
            Node::Dict(v) => v.len(),
            Node::Tensor(_) => 1,
        };
        self.count(len.max(1))?;
        self.nodes.push(n);
        Ok(Obj::Node(self.nodes.len() - 1))
    }

    fn tuple(&mut self, items: Vec<Obj>) -> Result<Obj, TorchError> {
        self.node(Node::Tuple(items))
    }

    fn memo_put(&mut self, id: u32) -> Result<(), TorchError> {
        let top = self.top()?.clone();
        if self.memo.len() >= MAX_VALUES {
            return Err(self.err("memo too large"));
        }
        self.memo.insert(id, top);
        Ok(())
    }

    fn memo_get(&mut self, id: u32) -> Result<(), TorchError> {
        let o = self
            .memo
            .get(&id)
            .cloned()
            .ok_or_else(|| self.err(format!("memo entry {id} was never stored")))?;
        self.push(o)
    }

    /// The list or dict node `obj` refers to, for in-place appends.
    fn node_mut(&mut self, obj: &Obj) -> Result<&mut Node, TorchError> {
        match obj {
            Obj::Node(i) => Ok(&mut self.nodes[*i]),
            _ => Err(self.err("append or setitem on something that is not a list or dict")),
        }
    }

    fn extend_list(&mut self, list: Obj, items: Vec<Obj>) -> Result<(), TorchError> {
        self.count(items.len())?;
        let err = self.err("append on something that is not a list");
        match self.node_mut(&list)? {
            Node::List(v) => {
                v.extend(items);
                Ok(())
            }
            _ => Err(err),
        }
    }

    fn extend_dict(&mut self, dict: Obj, items: Vec<Obj>) -> Result<(), TorchError> {
        if !items.len().is_multiple_of(2) {
            return Err(self.err("setitems with an odd number of values"));
        }
        self.count(items.len() / 2)?;
        let err = self.err("setitem on something that is not a dict");
        let mut it = items.into_iter();
        let pairs: Vec<(Obj, Obj)> =
            std::iter::from_fn(|| Some((it.next()?, it.next()?))).collect();
        match self.node_mut(&dict)? {
            Node::Dict(v) => {
                v.extend(pairs);
                Ok(())
            }
            _ => Err(err),
        }
    }

    fn int_arg(&self, o: &Obj, what: &str) -> Result<i64, TorchError> {
        match o {
            Obj::Int(i) => Ok(*i),
            _ => Err(self.err(format!("{what}: expected an int"))),
        }
    }

    fn tuple_items(&self, o: &Obj, what: &str) -> Result<Vec<Obj>, TorchError> {
        match o {
            Obj::Node(i) => match &self.nodes[*i] {
                Node::Tuple(v) | Node::List(v) => Ok(v.clone()),
                _ => Err(self.err(format!("{what}: expected a tuple"))),
            },
            _ => Err(self.err(format!("{what}: expected a tuple"))),
        }
    }

    fn run(&mut self) -> Result<Obj, TorchError> {
        loop {
            self.op_pos = self.pos;
            let op = self.u8()?;
            match op {
                0x80 => {
                    let proto = self.u8()?;
                    if proto > 5 {
                        return Err(self.err(format!("pickle protocol {proto}")));
                    }
                }
                0x95 => {
                    self.u64()?; // FRAME: a length hint only.
                }
                b'.' => {
                    let root = self.pop()?;
                    return Ok(root);
                }
                b'(' => self.push(Obj::Mark)?,
                b'0' => {
                    self.stack
                        .pop()
                        .ok_or_else(|| self.err("stack underflow"))?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let o = self.top()?.clone();
                    self.push(o)?;
                }
                b'N' => self.push(Obj::None)?,
                0x88 => self.push(Obj::Bool(true))?,
                0x89 => self.push(Obj::Bool(false))?,
                b'K' => {
                    let v = self.u8()?;
                    self.push(Obj::Int(i64::from(v)))?;
                }
                b'M' => {
                    let v = self.u16()?;
                    self.push(Obj::Int(i64::from(v)))?;
                }
                b'J' => {
                    let v = self.u32()? as i32;
                    self.push(Obj::Int(i64::from(v)))?;
                }
                0x8a | 0x8b => {
                    let n = if op == 0x8a {
                        usize::from(self.u8()?)
                    } else {
                        self.u32()? as usize
                    };
                    if n > 8 {
                        return Err(self.err(format!("integer of {n} bytes does not fit in i64")));
                    }
                    let b = self.take(n)?;
                    let mut v: i64 = 0;
                    for (k, &byte) in b.iter().enumerate() {
                        v |= i64::from(byte) << (8 * k);
                    }
                    if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                        v -= 1i64 << (8 * n); // two's complement sign
                    }
                    self.push(Obj::Int(v))?;
                }
                b'I' => {
                    let s = self.line()?;
                    let o = match s {
                        "00" => Obj::Bool(false),
                        "01" => Obj::Bool(true),
                        _ => Obj::Int(s.parse().map_err(|_| self.err(format!("bad int `{s}`")))?),
                    };
                    self.push(o)?;
                }
                b'L' => {
                    let s = self.line()?;
                    let v = s
                        .trim_end_matches('L')
                        .parse()
                        .map_err(|_| self.err(format!("bad or too large int `{s}`")))?;
                    self.push(Obj::Int(v))?;
                }
                b'G' => {
                    let b = self.take(8)?;
                    let mut a = [0u8; 8];
                    a.copy_from_slice(b);
                    self.push(Obj::Float(f64::from_be_bytes(a)))?;
                }
                b'F' => {
                    let s = self.line()?;
                    let v = s
                        .parse()
                        .map_err(|_| self.err(format!("bad float `{s}`")))?;
                    self.push(Obj::Float(v))?;
                }
                b'X' => {
                    let n = self.u32()?;
                    let o = self.utf8(u64::from(n))?;
                    self.push(o)?;
                }
                0x8c => {
                    let n = self.u8()?;
                    let o = self.utf8(u64::from(n))?;
                    self.push(o)?;
                }
                0x8d => {
                    let n = self.u64()?;
                    let o = self.utf8(n)?;
                    self.push(o)?;
                }
                b'U' => {
                    let n = usize::from(self.u8()?);
                    let o = self.latin1(n)?;
                    self.push(o)?;
                }
                b'T' => {
                    let n = self.u32()? as i32;
                    let n = usize::try_from(n).map_err(|_| self.err("negative string length"))?;
                    let o = self.latin1(n)?;
                    self.push(o)?;
                }
                b']' => {
                    let o = self.node(Node::List(Vec::new()))?;
                    self.push(o)?;
                }
                b'l' => {
                    let items = self.pop_mark()?;
                    let o = self.node(Node::List(items))?;
                    self.push(o)?;
                }
                b'a' => {
                    let item = self.pop()?;
                    let list = self.top()?.clone();
                    self.extend_list(list, vec![item])?;
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    let list = self.top()?.clone();
                    self.extend_list(list, items)?;
                }
                b')' => {
                    let o = self.tuple(Vec::new())?;
                    self.push(o)?;
                }
                b't' => {
                    let items = self.pop_mark()?;
                    let o = self.tuple(items)?;
                    self.push(o)?;
                }
                0x85..=0x87 => {
                    let n = usize::from(op - 0x84);
                    if self.stack.len() < n
                        || self.stack[self.stack.len() - n..]
                            .iter()
                            .any(|o| matches!(o, Obj::Mark))
                    {
                        return Err(self.err("stack underflow"));
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    let o = self.tuple(items)?;
                    self.push(o)?;
                }
                b'}' => {
                    let o = self.node(Node::Dict(Vec::new()))?;
                    self.push(o)?;
                }
                b'd' => {
                    let items = self.pop_mark()?;
                    let o = self.node(Node::Dict(Vec::new()))?;
                    self.extend_dict(o.clone(), items)?;
                    self.push(o)?;
                }
                b's' => {
                    let v = self.pop()?;
                    let k = self.pop()?;
                    let dict = self.top()?.clone();
                    self.extend_dict(dict, vec![k, v])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    let dict = self.top()?.clone();
                    self.extend_dict(dict, items)?;
                }
                b'q' => {
                    let id = u32::from(self.u8()?);
                    self.memo_put(id)?;
                }
                b'r' => {
                    let id = self.u32()?;
                    self.memo_put(id)?;
                }
                b'p' => {
                    let s = self.line()?;
                    let id = s
                        .parse()
                        .map_err(|_| self.err(format!("bad memo id `{s}`")))?;
                    self.memo_put(id)?;
                }
                0x94 => {
                    let id = u32::try_from(self.memo.len()).map_err(|_| self.err("memo full"))?;
                    self.memo_put(id)?;
                }
                b'h' => {
                    let id = u32::from(self.u8()?);
                    self.memo_get(id)?;
                }
                b'j' => {
                    let id = self.u32()?;
                    self.memo_get(id)?;
                }
                b'g' => {
                    let s = self.line()?;
                    let id = s
                        .parse()
                        .map_err(|_| self.err(format!("bad memo id `{s}`")))?;
                    self.memo_get(id)?;
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    let o = self.global(module, name)?;
                    self.push(o)?;
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    let (Obj::Str(module), Obj::Str(name)) = (module, name) else {
                        return Err(self.err("STACK_GLOBAL needs two strings"));
                    };
                    let o = self.global(&module, &name)?;
                    self.push(o)?;
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let o = self.persistent_load(&pid)?;
                    self.push(o)?;
                }
                b'R' | 0x81 => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let o = self.call(&callable, &args)?;
                    self.push(o)?;
                }
                _ => {
                    return Err(self.err(format!("unsupported pickle opcode 0x{op:02x}")));
                }
            }
        }
    }

    /// The globals this reader accepts; anything else is an error naming it.
    fn global(&self, module: &str, name: &str) -> Result<Obj, TorchError> {
        let ok = matches!(
            (module, name),
            ("torch._utils", "_rebuild_tensor_v2")
                | ("torch._utils", "_rebuild_parameter")
                | ("collections", "OrderedDict")
                | ("torch", "Size")
        ) || (module == "torch" && DType::from_storage_name(name).is_some());
        if !ok {
            return Err(self.err(format!(
                "unsupported global `{module}.{name}` (only tensors, storages of float32/float64/\
                 int32/int64/uint8, OrderedDict and torch.Size are read)"
            )));
        }
        Ok(Obj::Global(Rc::from(module), Rc::from(name)))
    }

    /// `('storage', torch.XStorage, key, location, numel)` → a storage reference.
    fn persistent_load(&self, pid: &Obj) -> Result<Obj, TorchError> {
        let items = self.tuple_items(pid, "persistent id")?;
        let bad = || self.err("persistent id is not ('storage', type, key, location, numel)");
        if items.len() != 5 {
            return Err(bad());
        }
        match &items[0] {
            Obj::Str(s) if &**s == "storage" => {}
            _ => return Err(bad()),
        }
        let dtype = match &items[1] {
            Obj::Global(m, n) if &**m == "torch" => DType::from_storage_name(n).ok_or_else(bad)?,
            _ => return Err(bad()),
        };
        let key = match &items[2] {
            Obj::Str(s) => s.clone(),
            _ => return Err(bad()),
        };
        let numel = u64::try_from(self.int_arg(&items[4], "storage size")?)
            .map_err(|_| self.err("negative storage size"))?;
        Ok(Obj::Storage(StorageRef { key, dtype, numel }))
    }

    fn call(&mut self, callable: &Obj, args: &Obj) -> Result<Obj, TorchError> {
        let Obj::Global(module, name) = callable else {
            return Err(self.err("call of something that is not an accepted global"));
        };
        let args = self.tuple_items(args, "call arguments")?;
        match (&**module, &**name) {
            ("collections", "OrderedDict") => {
                let o = self.node(Node::Dict(Vec::new()))?;
                match args.as_slice() {
                    [] => {}
                    [pairs] => {
                        let mut flat = Vec::new();
                        for p in self.tuple_items(pairs, "OrderedDict items")? {
                            let kv = self.tuple_items(&p, "OrderedDict item")?;
                            if kv.len() != 2 {
                                return Err(self.err("OrderedDict item is not a pair"));
                            }
                            flat.extend(kv);
                        }
                        self.extend_dict(o.clone(), flat)?;
                    }
                    _ => return Err(self.err("OrderedDict takes at most one argument")),
                }
                Ok(o)
            }
            ("torch", "Size") => match args.as_slice() {
                [dims] => {
                    let items = self.tuple_items(dims, "torch.Size")?;
                    self.tuple(items)
                }
                _ => Err(self.err("torch.Size takes one tuple")),
            },
            ("torch._utils", "_rebuild_parameter") => match args.first() {
                Some(t @ Obj::Node(i)) if matches!(self.nodes[*i], Node::Tensor(_)) => {
                    Ok(t.clone())
                }
                _ => Err(self.err("_rebuild_parameter without a tensor")),
            },
            ("torch._utils", "_rebuild_tensor_v2") => {
                if args.len() < 4 {
                    return Err(self.err("_rebuild_tensor_v2 needs storage, offset, size, stride"));
                }
                let Obj::Storage(storage) = &args[0] else {
                    return Err(self.err("_rebuild_tensor_v2: first argument is not a storage"));
                };
                let offset = self.int_arg(&args[1], "storage offset")?;
                let size = self.tuple_items(&args[2], "tensor size")?;
                let stride = self.tuple_items(&args[3], "tensor stride")?;
                let size: Vec<i64> = size
                    .iter()
                    .map(|o| self.int_arg(o, "tensor size"))
                    .collect::<Result<_, _>>()?;
                let stride: Vec<i64> = stride
                    .iter()
                    .map(|o| self.int_arg(o, "tensor stride"))
                    .collect::<Result<_, _>>()?;
                let t = self.rebuild_tensor(storage, offset, &size, &stride)?;
                self.node(Node::Tensor(t))
            }
            _ => Err(self.err(format!("`{module}.{name}` cannot be called"))),
        }
    }

    fn storage(&mut self, s: &StorageRef) -> Result<Rc<Vec<u8>>, TorchError> {
        if let Some(b) = self.storages.get(&*s.key) {
            return Ok(b.clone());
        }
        let path = self.archive.path.clone();
        let serr = |reason: String| TorchError::Storage {
            path: path.clone(),
            key: s.key.to_string(),
            reason,
        };
        let need = s
            .numel
            .checked_mul(s.dtype.size() as u64)
            .filter(|&b| b <= MAX_STORAGE_BYTES)
            .ok_or_else(|| TorchError::TooLarge {
                path: self.archive.path.clone(),
                what: format!("storage `{}`", s.key),
                size: s.numel.saturating_mul(s.dtype.size() as u64),
                limit: MAX_STORAGE_BYTES,
            })?;
        if self.storage_bytes + need > MAX_STORAGE_BYTES {
            return Err(TorchError::TooLarge {
                path: self.archive.path.clone(),
                what: "total storage".into(),
                size: self.storage_bytes + need,
                limit: MAX_STORAGE_BYTES,
            });
        }
        if s.key.contains('/') || s.key.contains('\\') {
            return Err(serr("key is not a plain name".into()));
        }
        let bytes = self
            .archive
            .read_entry(&format!("data/{}", s.key), need)?
            .ok_or_else(|| serr(format!("no data/{} entry in the archive", s.key)))?;
        if (bytes.len() as u64) != need {
            return Err(serr(format!(
                "{} bytes, expected {need} ({} {:?} elements)",
                bytes.len(),
                s.numel,
                s.dtype
            )));
        }
        self.storage_bytes += need;
        let b = Rc::new(bytes);
        self.storages.insert(s.key.to_string(), b.clone());
        Ok(b)
    }

    fn rebuild_tensor(
        &mut self,
        s: &StorageRef,
        offset: i64,
        size: &[i64],
        stride: &[i64],
    ) -> Result<Tensor, TorchError> {
        let path = self.archive.path.clone();
        let serr = |reason: String| TorchError::Storage {
            path: path.clone(),
            key: s.key.to_string(),
            reason,
        };
        if size.len() != stride.len() {
            return Err(serr(format!(
                "size {size:?} and stride {stride:?} differ in length"
            )));
        }
        if size.len() > MAX_DEPTH {
            return Err(serr(format!("{} dimensions", size.len())));
        }
        let offset = u64::try_from(offset).map_err(|_| serr("negative offset".into()))?;
        let mut shape = Vec::with_capacity(size.len());
        let mut numel: u64 = 1;
        for (&n, &st) in size.iter().zip(stride) {
            let n = u64::try_from(n).map_err(|_| serr(format!("negative size in {size:?}")))?;
            if st < 0 {
                return Err(serr(format!("negative stride in {stride:?}")));
            }
            numel = numel.saturating_mul(n);
            shape.push(n);
        }
        self.elements = self.elements.saturating_add(numel);
        if self.elements > MAX_TENSOR_ELEMENTS {
            return Err(TorchError::TooLarge {
                path: self.archive.path.clone(),
                what: format!("tensor elements (up to the tensor of shape {size:?})"),
                size: self.elements,
                limit: MAX_TENSOR_ELEMENTS,
            });
        }
        let bytes = self.storage(s)?;
        let shape: Vec<usize> = shape.into_iter().map(|n| n as usize).collect();
        let stride: Vec<u64> = stride.iter().map(|&st| st as u64).collect();
        // Every index is < storage numel: check the largest one.
        if numel > 0 {
            let last = shape
                .iter()
                .zip(&stride)
                .try_fold(offset, |acc, (&n, &st)| {
                    acc.checked_add((n as u64 - 1).checked_mul(st)?)
                });
            match last {
                Some(l) if l < s.numel => {}
                _ => {
                    return Err(serr(format!(
                        "offset {offset}, size {size:?}, stride {stride:?} reach past its {} elements",
                        s.numel
                    )));
                }
            }
        }
        let numel = numel as usize;
        let mut indices = Vec::with_capacity(numel);
        if numel > 0 {
            let mut idx = vec![0usize; shape.len()];
            for _ in 0..numel {
                let e: u64 = offset
                    + idx
                        .iter()
                        .zip(&stride)
                        .map(|(&i, &st)| i as u64 * st)
                        .sum::<u64>();
                indices.push(e as usize);
                for d in (0..shape.len()).rev() {
                    idx[d] += 1;
                    if idx[d] < shape[d] {
                        break;
                    }
                    idx[d] = 0;
                }
            }
        }
        let data = gather(&bytes, s.dtype, &indices);
        Ok(Tensor { shape, data })
    }

    /// Converts the result into a [`PtValue`], checking depth, key types and the budget (shared
    /// references are copied, so they count once per reference).
    fn to_value(&self, o: &Obj, depth: usize, budget: &mut Budget) -> Result<PtValue, TorchError> {
        let path = &self.archive.path;
        let err = |reason: String| TorchError::Pickle {
            path: path.clone(),
            offset: self.code.len(),
            reason,
        };
        if depth > MAX_DEPTH {
            return Err(err(format!(
                "nested deeper than {MAX_DEPTH} (or recursive)"
            )));
        }
        budget.spend(path, Spend::Values, 1)?;
        Ok(match o {
            Obj::None => PtValue::None,
            Obj::Bool(b) => PtValue::Bool(*b),
            Obj::Int(i) => PtValue::Int(*i),
            Obj::Float(f) => PtValue::Float(*f),
            Obj::Str(s) => {
                budget.spend(path, Spend::StringBytes, s.len() as u64)?;
                PtValue::Str(s.to_string())
            }
            Obj::Node(i) => match &self.nodes[*i] {
                Node::List(v) => PtValue::List(
                    v.iter()
                        .map(|x| self.to_value(x, depth + 1, budget))
                        .collect::<Result<_, _>>()?,
                ),
                Node::Tuple(v) => PtValue::Tuple(
                    v.iter()
                        .map(|x| self.to_value(x, depth + 1, budget))
                        .collect::<Result<_, _>>()?,
                ),
                Node::Dict(v) => {
                    let mut items = Vec::with_capacity(v.len());
                    for (k, val) in v {
                        let Obj::Str(k) = k else {
                            return Err(err("dict key is not a string".into()));
                        };
                        budget.spend(path, Spend::StringBytes, k.len() as u64)?;
                        items.push((k.to_string(), self.to_value(val, depth + 1, budget)?));
                    }
                    PtValue::Dict(items)
                }
                Node::Tensor(t) => {
                    budget.spend(path, Spend::Elements, t.len() as u64)?;
                    PtValue::Tensor(t.clone())
                }
            },
            Obj::Mark => return Err(err("mark left in the result".into())),
            Obj::Global(m, n) => return Err(err(format!("`{m}.{n}` left uncalled"))),
            Obj::Storage(s) => {
                return Err(err(format!("storage `{}` outside a tensor", s.key)));
            }
        })
    }
}

/// What the conversion of the pickled object may still produce.
struct Budget {
    values: u64,
    elements: u64,
    string_bytes: u64,
}

#[derive(Clone, Copy)]
enum Spend {
    Values,
    Elements,
    StringBytes,
}

impl Budget {
    fn spend(&mut self, path: &Path, what: Spend, n: u64) -> Result<(), TorchError> {
        let (left, limit, name) = match what {
            Spend::Values => (&mut self.values, MAX_VALUES as u64, "number of values"),
            Spend::Elements => (&mut self.elements, MAX_TENSOR_ELEMENTS, "tensor elements"),
            Spend::StringBytes => (&mut self.string_bytes, MAX_STRING_BYTES, "string bytes"),
        };
        *left = left.checked_sub(n).ok_or_else(|| TorchError::TooLarge {
            path: path.to_path_buf(),
            what: format!("{name} of the read object (shared references counted each time)"),
            size: limit - *left + n,
            limit,
        })?;
        Ok(())
    }
}

/// Elements at `indices` of little-endian storage bytes.
fn gather(bytes: &[u8], dtype: DType, indices: &[usize]) -> TensorData {
    fn arr<const N: usize>(b: &[u8], i: usize) -> [u8; N] {
        let mut a = [0u8; N];
        a.copy_from_slice(&b[i * N..(i + 1) * N]);
        a
    }
    match dtype {
        DType::F32 => TensorData::F32(
            indices
                .iter()
                .map(|&i| f32::from_le_bytes(arr(bytes, i)))
                .collect(),
        ),
        DType::F64 => TensorData::F64(
            indices
                .iter()
                .map(|&i| f64::from_le_bytes(arr(bytes, i)))
                .collect(),
        ),
        DType::I32 => TensorData::I32(
            indices
                .iter()
                .map(|&i| i32::from_le_bytes(arr(bytes, i)))
                .collect(),
        ),
        DType::I64 => TensorData::I64(
            indices
                .iter()
                .map(|&i| i64::from_le_bytes(arr(bytes, i)))
                .collect(),
        ),
        DType::U8 => TensorData::U8(indices.iter().map(|&i| bytes[i]).collect()),
    }
}

/// Writes `value` as a `.pt` file (zip format, little-endian, one storage per tensor),
/// atomically.
pub fn write_pt(path: &Path, value: &PtValue) -> Result<(), TorchError> {
    let bytes = to_pt_bytes(value, path)?;
    write_atomic(path, &bytes).map_err(|source| TorchError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// The bytes [`write_pt`] writes; `path` names the file in errors.
pub fn to_pt_bytes(value: &PtValue, path: &Path) -> Result<Vec<u8>, TorchError> {
    let unwritable = |reason: String| TorchError::Unwritable {
        path: path.to_path_buf(),
        reason,
    };
    let mut pickler = Pickler::default();
    pickler.out.extend_from_slice(&[0x80, 2]);
    pickler.value(value, 0).map_err(unwritable)?;
    pickler.out.push(b'.');

    let zip_err = |e: zip::result::ZipError| unwritable(format!("zip: {e}"));
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options =
        zip::write::FileOptions::default().compression_method(zip::CompressionMethod::Stored);
    let entry = |zip: &mut zip::ZipWriter<Cursor<Vec<u8>>>, name: &str, data: &[u8]| {
        // torch aligns entry data to 64 bytes (so storages can be memory-mapped).
        zip.start_file_aligned(format!("archive/{name}"), options, 64)
            .map_err(zip_err)?;
        zip.write_all(data)
            .map_err(|e| unwritable(format!("zip: {e}")))
    };
    entry(&mut zip, "data.pkl", &pickler.out)?;
    entry(&mut zip, "byteorder", b"little")?;
    for (i, s) in pickler.storages.iter().enumerate() {
        entry(&mut zip, &format!("data/{i}"), s)?;
    }
    entry(&mut zip, "version", b"3\n")?;
    Ok(zip.finish().map_err(zip_err)?.into_inner())
}

/// Protocol-2 pickling of [`PtValue`]s, without memo (every value is written in full).
#[derive(Default)]
struct Pickler {
    out: Vec<u8>,
    storages: Vec<Vec<u8>>,
}

impl Pickler {
    fn str(&mut self, s: &str) {
        self.out.push(b'X');
        self.out.extend_from_slice(&(s.len() as u32).to_le_bytes());
        self.out.extend_from_slice(s.as_bytes());
    }

    fn int(&mut self, i: i64) {
        if (0..256).contains(&i) {
            self.out.extend_from_slice(&[b'K', i as u8]);
        } else if (0..65536).contains(&i) {
            self.out.push(b'M');
            self.out.extend_from_slice(&(i as u16).to_le_bytes());
        } else if let Ok(v) = i32::try_from(i) {
            self.out.push(b'J');
            self.out.extend_from_slice(&v.to_le_bytes());
        } else {
            self.out.extend_from_slice(&[0x8a, 8]);
            self.out.extend_from_slice(&i.to_le_bytes());
        }
    }

    fn global(&mut self, module: &str, name: &str) {
        self.out.push(b'c');
        self.out.extend_from_slice(module.as_bytes());
        self.out.push(b'\n');
        self.out.extend_from_slice(name.as_bytes());
        self.out.push(b'\n');
    }

    fn int_tuple(&mut self, v: &[usize]) {
        self.out.push(b'(');
        for &x in v {
            self.int(x as i64);
        }
        self.out.push(b't');
    }

    fn value(&mut self, v: &PtValue, depth: usize) -> Result<(), String> {
        if depth > MAX_DEPTH {
            return Err(format!("nested deeper than {MAX_DEPTH}"));
        }
        match v {
            PtValue::None => self.out.push(b'N'),
            PtValue::Bool(b) => self.out.push(if *b { 0x88 } else { 0x89 }),
            PtValue::Int(i) => self.int(*i),
            PtValue::Float(f) => {
                self.out.push(b'G');
                self.out.extend_from_slice(&f.to_be_bytes());
            }
            PtValue::Str(s) => self.str(s),
            PtValue::List(items) => {
                self.out.push(b']');
                if !items.is_empty() {
                    self.out.push(b'(');
                    for x in items {
                        self.value(x, depth + 1)?;
                    }
                    self.out.push(b'e');
                }
            }
            PtValue::Tuple(items) => {
                self.out.push(b'(');
                for x in items {
                    self.value(x, depth + 1)?;
                }
                self.out.push(b't');
            }
            PtValue::Dict(items) => {
                self.out.push(b'}');
                if !items.is_empty() {
                    self.out.push(b'(');
                    for (k, x) in items {
                        self.str(k);
                        self.value(x, depth + 1)?;
                    }
                    self.out.push(b'u');
                }
            }
            PtValue::Tensor(t) => self.tensor(t)?,
        }
        Ok(())
    }

    fn tensor(&mut self, t: &Tensor) -> Result<(), String> {
        let numel = t
            .shape
            .iter()
            .try_fold(1usize, |a, &n| a.checked_mul(n))
            .ok_or("tensor shape overflows")?;
        if numel != t.len() {
            return Err(format!(
                "tensor of shape {:?} holds {} elements, not {numel}",
                t.shape,
                t.len()
            ));
        }
        let bytes: Vec<u8> = match &t.data {
            TensorData::F32(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            TensorData::F64(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            TensorData::I32(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            TensorData::I64(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            TensorData::U8(v) => v.clone(),
        };
        let key = self.storages.len();
        self.storages.push(bytes);
        // Row-major strides.
        let mut stride = vec![1usize; t.shape.len()];
        for d in (0..t.shape.len().saturating_sub(1)).rev() {
            stride[d] = stride[d + 1] * t.shape[d + 1];
        }
        self.global("torch._utils", "_rebuild_tensor_v2");
        self.out.push(b'(');
        // Persistent id ('storage', torch.XStorage, key, 'cpu', numel).
        self.out.push(b'(');
        self.str("storage");
        self.global("torch", t.dtype().storage_name());
        self.str(&key.to_string());
        self.str("cpu");
        self.int(numel as i64);
        self.out.push(b't');
        self.out.push(b'Q');
        self.int(0);
        self.int_tuple(&t.shape);
        self.int_tuple(&stride);
        self.out.push(0x89); // requires_grad
        self.global("collections", "OrderedDict");
        self.out.push(b')');
        self.out.push(b'R'); // backward hooks: OrderedDict()
        self.out.push(b't');
        self.out.push(b'R');
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(v: &PtValue) -> PtValue {
        let bytes = to_pt_bytes(v, Path::new("t.pt")).unwrap();
        parse_pt(&bytes, Path::new("t.pt")).unwrap()
    }

    #[test]
    fn scalars_and_containers_round_trip() {
        let v = PtValue::Dict(vec![
            ("none".into(), PtValue::None),
            ("t".into(), PtValue::Bool(true)),
            ("f".into(), PtValue::Bool(false)),
            ("small".into(), PtValue::Int(7)),
            ("mid".into(), PtValue::Int(4000)),
            ("neg".into(), PtValue::Int(-5)),
            ("big".into(), PtValue::Int(i64::MIN)),
            ("huge".into(), PtValue::Int(1 << 40)),
            ("x".into(), PtValue::Float(-0.1)),
            ("s".into(), PtValue::Str("héllo".into())),
            (
                "l".into(),
                PtValue::List(vec![PtValue::Int(1), PtValue::List(vec![])]),
            ),
            (
                "tup".into(),
                PtValue::Tuple(vec![PtValue::Int(1), PtValue::Str("a".into())]),
            ),
            ("empty".into(), PtValue::Dict(vec![])),
        ]);
        assert_eq!(round_trip(&v), v);
    }

    #[test]
    fn tensors_of_every_type_round_trip() {
        let v = PtValue::List(vec![
            PtValue::Tensor(Tensor::f32(vec![2, 3], vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.5])),
            PtValue::Tensor(Tensor::f64(vec![3], vec![0.1, -2.0, 1e300])),
            PtValue::Tensor(Tensor {
                shape: vec![2, 1, 2],
                data: TensorData::I32(vec![1, -2, 3, i32::MAX]),
            }),
            PtValue::Tensor(Tensor {
                shape: vec![],
                data: TensorData::I64(vec![i64::MIN]),
            }),
            PtValue::Tensor(Tensor {
                shape: vec![0, 4],
                data: TensorData::U8(vec![]),
            }),
        ]);
        assert_eq!(round_trip(&v), v);
    }

    #[test]
    fn a_tensor_whose_data_does_not_fill_its_shape_is_unwritable() {
        let v = PtValue::Tensor(Tensor::f64(vec![2, 2], vec![1.0]));
        assert!(matches!(
            to_pt_bytes(&v, Path::new("x.pt")),
            Err(TorchError::Unwritable { .. })
        ));
    }

    #[test]
    fn legacy_and_non_zip_files_are_named_as_such() {
        let mut legacy = LEGACY_MAGIC.to_vec();
        legacy.extend_from_slice(b".");
        let e = parse_pt(&legacy, Path::new("old.pt")).unwrap_err();
        assert!(matches!(e, TorchError::LegacyFormat { .. }), "{e}");
        assert!(e.to_string().contains("legacy"), "{e}");
        let e = parse_pt(b"hello", Path::new("x.pt")).unwrap_err();
        assert!(matches!(e, TorchError::NotTorch { .. }), "{e}");
    }
}
