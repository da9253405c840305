//! PyTorch `.pt`/`.pth` state dicts read by recon itself: the zip archive
//! `torch.save` writes, and the subset of pickle its `data.pkl` uses
//! (dicts, tuples, lists, scalars, globals, `_rebuild_tensor_v2` and the
//! storage persistent ids). Every size the file claims is checked before
//! anything of that size is allocated: strings against the bytes left, nesting
//! depth, shared-object copies, and each tensor against its zip entry.

use crate::{Error, Result};
use candle_core::{DType, Device, Tensor};
use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::rc::Rc;

/// Deepest nesting of pickle containers accepted (a state dict needs 4).
const MAX_DEPTH: usize = 64;
/// Largest `data.pkl` read (the pickle of the full TRELLIS checkpoints is < 1 MB).
const MAX_PICKLE_BYTES: u64 = 64 << 20;

/// One tensor of the state dict: where its bytes are and what they hold.
#[derive(Debug, Clone, PartialEq)]
pub struct PtTensorInfo {
    /// Element dtype.
    pub dtype: DType,
    /// Shape (row-major, contiguous).
    pub shape: Vec<usize>,
    /// Zip entry holding the storage (`<archive>/data/<key>`).
    pub entry: String,
    /// Offset into the storage, in elements.
    pub offset: usize,
}

/// An opened `.pt` file: the tensors of the selected state dict.
pub struct PtFile {
    /// The archive file.
    pub path: PathBuf,
    /// The selected state dict's tensors by name, as stored (no prefix stripped).
    pub tensors: BTreeMap<String, PtTensorInfo>,
}

#[derive(Clone, Debug)]
enum Obj {
    None,
    Bool,
    Int(i64),
    Float,
    Str(Rc<str>),
    Class(Rc<(String, String)>),
    Tuple(usize, Rc<Vec<Obj>>),
    List(usize, Rc<Vec<Obj>>),
    Dict(usize, Rc<Vec<(Obj, Obj)>>),
    Storage(Rc<(DType, String, usize)>),
    Tensor(Rc<PtTensorInfo>),
    /// The result of a call recon does not model (kept so the stack stays aligned).
    Opaque,
}

impl Obj {
    fn depth(&self) -> usize {
        match self {
            Obj::Tuple(d, _) | Obj::List(d, _) | Obj::Dict(d, _) => *d,
            _ => 0,
        }
    }
    fn kind(&self) -> &'static str {
        match self {
            Obj::None => "None",
            Obj::Bool => "bool",
            Obj::Int(_) => "int",
            Obj::Float => "float",
            Obj::Str(_) => "str",
            Obj::Class(_) => "global",
            Obj::Tuple(..) => "tuple",
            Obj::List(..) => "list",
            Obj::Dict(..) => "dict",
            Obj::Storage(_) => "storage",
            Obj::Tensor(_) => "tensor",
            Obj::Opaque => "object",
        }
    }
}

struct Unpickler<'a> {
    buf: &'a [u8],
    pos: usize,
    stack: Vec<Obj>,
    /// Stack positions of the open marks.
    marks: Vec<usize>,
    memo: HashMap<u32, Obj>,
    /// Elements copied when a shared (memoised) container is modified; bounded
    /// so a pickle cannot make the reader quadratic.
    copies_left: usize,
    file: &'a str,
}

impl<'a> Unpickler<'a> {
    fn err(&self, msg: impl std::fmt::Display) -> Error {
        Error::input(self.file, format!("data.pkl: {msg} (at byte {})", self.pos))
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len()).ok_or_else(|| {
            Error::too_large(
                self.file,
                format!("data.pkl operand at byte {}", self.pos),
                n as u128,
                (self.buf.len() - self.pos) as u128,
                "bytes",
                "more than the pickle has left",
            )
        })?;
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }
    fn le<const N: usize>(&mut self) -> Result<[u8; N]> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }
    fn line(&mut self) -> Result<String> {
        let rest = &self.buf[self.pos..];
        let n = rest.iter().position(|&b| b == b'\n').ok_or_else(|| self.err("GLOBAL name without a newline"))?;
        let s = String::from_utf8_lossy(&rest[..n]).into_owned();
        self.pos += n + 1;
        Ok(s)
    }
    fn string(&mut self, n: usize) -> Result<Obj> {
        let b = self.take(n)?;
        let s = std::str::from_utf8(b).map_err(|_| self.err("string is not UTF-8"))?;
        Ok(Obj::Str(s.into()))
    }
    fn push(&mut self, o: Obj) -> Result<()> {
        if o.depth() > MAX_DEPTH {
            return Err(self.err(format!("containers nested deeper than {MAX_DEPTH}")));
        }
        self.stack.push(o);
        Ok(())
    }
    fn pop(&mut self) -> Result<Obj> {
        if self.marks.last().is_some_and(|&m| m >= self.stack.len()) {
            return Err(self.err("pop across a mark"));
        }
        self.stack.pop().ok_or_else(|| self.err("stack underflow"))
    }
    fn pop_mark(&mut self) -> Result<Vec<Obj>> {
        let m = self.marks.pop().ok_or_else(|| self.err("no mark on the stack"))?;
        let items = self.stack.split_off(m);
        Ok(items)
    }
    fn charge(&mut self, n: usize) -> Result<()> {
        self.copies_left = self.copies_left.checked_sub(n).ok_or_else(|| self.err("too many copies of shared objects"))?;
        Ok(())
    }
    /// Mutable access to the container on top of the stack, copying it first
    /// when the memo shares it (pickle's memo holds a snapshot here).
    fn top_list(&mut self, extra: Vec<Obj>) -> Result<()> {
        let child = extra.iter().map(Obj::depth).max().unwrap_or(0);
        let n = match self.stack.last() {
            Some(Obj::List(_, v)) if Rc::strong_count(v) > 1 => v.len(),
            _ => 0,
        };
        self.charge(n)?;
        match self.stack.last_mut() {
            Some(Obj::List(d, v)) => {
                *d = (*d).max(child + 1);
                Rc::make_mut(v).extend(extra);
            }
            Some(o) => {
                let k = o.kind();
                return Err(self.err(format!("APPEND to a {k}")));
            }
            None => return Err(self.err("stack underflow")),
        }
        if self.stack.last().is_some_and(|o| o.depth() > MAX_DEPTH) {
            return Err(self.err(format!("containers nested deeper than {MAX_DEPTH}")));
        }
        Ok(())
    }
    fn top_dict(&mut self, items: Vec<Obj>) -> Result<()> {
        if !items.len().is_multiple_of(2) {
            return Err(self.err("SETITEMS with an odd number of objects"));
        }
        let child = items.iter().map(Obj::depth).max().unwrap_or(0);
        let n = match self.stack.last() {
            Some(Obj::Dict(_, v)) if Rc::strong_count(v) > 1 => v.len(),
            _ => 0,
        };
        self.charge(n)?;
        match self.stack.last_mut() {
            Some(Obj::Dict(d, v)) => {
                *d = (*d).max(child + 1);
                let v = Rc::make_mut(v);
                let mut it = items.into_iter();
                while let (Some(k), Some(x)) = (it.next(), it.next()) {
                    v.push((k, x));
                }
            }
            Some(Obj::Opaque) => {} // SETITEMS on an object recon does not model
            Some(o) => {
                let k = o.kind();
                return Err(self.err(format!("SETITEM on a {k}")));
            }
            None => return Err(self.err("stack underflow")),
        }
        if self.stack.last().is_some_and(|o| o.depth() > MAX_DEPTH) {
            return Err(self.err(format!("containers nested deeper than {MAX_DEPTH}")));
        }
        Ok(())
    }

    fn tuple(items: Vec<Obj>) -> Obj {
        let d = items.iter().map(Obj::depth).max().unwrap_or(0) + 1;
        Obj::Tuple(d, Rc::new(items))
    }

    fn persistent_load(&self, pid: Obj) -> Result<Obj> {
        // ('storage', torch.<T>Storage, key, location, numel)
        let Obj::Tuple(_, t) = pid else { return Err(self.err(format!("persistent id is a {}, expected a tuple", pid.kind()))) };
        match t.as_slice() {
            [Obj::Str(tag), Obj::Class(cls), key, _loc, Obj::Int(numel)] if &**tag == "storage" => {
                let dtype = match cls.1.as_str() {
                    "FloatStorage" => DType::F32,
                    "DoubleStorage" => DType::F64,
                    "HalfStorage" => DType::F16,
                    "BFloat16Storage" => DType::BF16,
                    "ByteStorage" => DType::U8,
                    "LongStorage" => DType::I64,
                    other => return Err(self.err(format!("unsupported storage type `{other}`"))),
                };
                let key = match key {
                    Obj::Str(s) => s.to_string(),
                    Obj::Int(i) => i.to_string(),
                    o => return Err(self.err(format!("storage key is a {}", o.kind()))),
                };
                let numel = usize::try_from(*numel).map_err(|_| self.err("negative storage size"))?;
                Ok(Obj::Storage(Rc::new((dtype, key, numel))))
            }
            _ => Err(self.err("persistent id is not ('storage', type, key, location, numel)")),
        }
    }

    fn ints(&self, o: &Obj, what: &str) -> Result<Vec<usize>> {
        let Obj::Tuple(_, t) = o else { return Err(self.err(format!("tensor {what} is a {}, expected a tuple", o.kind()))) };
        t.iter()
            .map(|x| match x {
                Obj::Int(i) => usize::try_from(*i).map_err(|_| self.err(format!("negative tensor {what}"))),
                o => Err(self.err(format!("tensor {what} holds a {}", o.kind()))),
            })
            .collect()
    }

    fn reduce(&mut self, callable: Obj, args: Obj) -> Result<Obj> {
        let Obj::Class(c) = &callable else { return Ok(Obj::Opaque) };
        let Obj::Tuple(_, a) = &args else { return Err(self.err(format!("REDUCE arguments are a {}", args.kind()))) };
        match (c.0.as_str(), c.1.as_str()) {
            ("collections", "OrderedDict") => Ok(Obj::Dict(1, Rc::new(Vec::new()))),
            ("torch._utils", "_rebuild_parameter") => a.first().cloned().ok_or_else(|| self.err("_rebuild_parameter without data")),
            ("torch._utils", "_rebuild_tensor_v2") | ("torch._utils", "_rebuild_tensor") => {
                let [storage, offset, size, stride, ..] = a.as_slice() else {
                    return Err(self.err(format!("_rebuild_tensor_v2 with {} arguments, expected at least 4", a.len())));
                };
                let Obj::Storage(st) = storage else { return Err(self.err("tensor without a storage")) };
                let Obj::Int(offset) = offset else { return Err(self.err("tensor offset is not an int")) };
                let offset = usize::try_from(*offset).map_err(|_| self.err("negative tensor offset"))?;
                let shape = self.ints(size, "size")?;
                let stride = self.ints(stride, "stride")?;
                if stride.len() != shape.len() {
                    return Err(self.err("tensor size and stride differ in length"));
                }
                // Row-major strides only: that is what torch.save writes for the
                // parameters of a module.
                let mut acc: u128 = 1;
                for (d, s) in shape.iter().zip(&stride).rev() {
                    if *d > 1 && *s as u128 != acc {
                        return Err(self.err(format!("non-contiguous tensor (size {shape:?}, stride {stride:?}) is not supported")));
                    }
                    acc = acc.saturating_mul(*d as u128);
                }
                let (dtype, key, _numel) = &**st;
                Ok(Obj::Tensor(Rc::new(PtTensorInfo { dtype: *dtype, shape, entry: key.clone(), offset })))
            }
            _ => Ok(Obj::Opaque),
        }
    }

    fn run(mut self) -> Result<Obj> {
        loop {
            let op = self.u8()?;
            match op {
                0x80 => {
                    self.u8()?; // PROTO
                }
                0x95 => {
                    self.take(8)?; // FRAME
                }
                b'c' => {
                    let (m, n) = (self.line()?, self.line()?);
                    self.push(Obj::Class(Rc::new((m, n))))?
                }
                0x93 => {
                    let n = self.pop()?;
                    let m = self.pop()?;
                    match (m, n) {
                        (Obj::Str(m), Obj::Str(n)) => self.push(Obj::Class(Rc::new((m.to_string(), n.to_string()))))?,
                        _ => return Err(self.err("STACK_GLOBAL needs two strings")),
                    }
                }
                b'K' => {
                    let v = self.u8()? as i64;
                    self.push(Obj::Int(v))?
                }
                b'M' => {
                    let v = u16::from_le_bytes(self.le()?) as i64;
                    self.push(Obj::Int(v))?
                }
                b'J' => {
                    let v = i32::from_le_bytes(self.le()?) as i64;
                    self.push(Obj::Int(v))?
                }
                0x8a => {
                    // LONG1: little-endian two's complement of n bytes.
                    let n = self.u8()? as usize;
                    if n > 8 {
                        return Err(self.err(format!("LONG1 of {n} bytes does not fit 64 bits")));
                    }
                    let b = self.take(n)?;
                    let mut a = [if b.last().is_some_and(|&x| x & 0x80 != 0) { 0xff } else { 0 }; 8];
                    a[..n].copy_from_slice(b);
                    self.push(Obj::Int(i64::from_le_bytes(a)))?
                }
                b'G' => {
                    self.take(8)?; // BINFLOAT: no float is needed from a state dict
                    self.push(Obj::Float)?
                }
                b'X' => {
                    let n = u32::from_le_bytes(self.le()?) as usize;
                    let s = self.string(n)?;
                    self.push(s)?
                }
                0x8c | b'U' => {
                    let n = self.u8()? as usize;
                    let s = self.string(n)?;
                    self.push(s)?
                }
                0x8d => {
                    let n = usize::try_from(u64::from_le_bytes(self.le()?)).unwrap_or(usize::MAX);
                    let s = self.string(n)?;
                    self.push(s)?
                }
                b'T' => {
                    let n = u32::from_le_bytes(self.le()?) as usize;
                    let s = self.string(n)?;
                    self.push(s)?
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let o = self.persistent_load(pid)?;
                    self.push(o)?
                }
                b'(' => self.marks.push(self.stack.len()),
                b't' => {
                    let items = self.pop_mark()?;
                    self.push(Self::tuple(items))?
                }
                b')' => self.push(Self::tuple(Vec::new()))?,
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    let mut items = Vec::with_capacity(n);
                    for _ in 0..n {
                        items.push(self.pop()?);
                    }
                    items.reverse();
                    self.push(Self::tuple(items))?
                }
                0x88 | 0x89 => self.push(Obj::Bool)?,
                b'N' => self.push(Obj::None)?,
                b']' => self.push(Obj::List(1, Rc::new(Vec::new())))?,
                b'l' => {
                    let items = self.pop_mark()?;
                    let d = items.iter().map(Obj::depth).max().unwrap_or(0) + 1;
                    self.push(Obj::List(d, Rc::new(items)))?
                }
                b'a' => {
                    let v = self.pop()?;
                    self.top_list(vec![v])?
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    self.top_list(items)?
                }
                b'}' => self.push(Obj::Dict(1, Rc::new(Vec::new())))?,
                b'd' => {
                    let items = self.pop_mark()?;
                    self.push(Obj::Dict(1, Rc::new(Vec::new())))?;
                    self.top_dict(items)?
                }
                b's' => {
                    let v = self.pop()?;
                    let k = self.pop()?;
                    self.top_dict(vec![k, v])?
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    self.top_dict(items)?
                }
                b'R' => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let o = self.reduce(callable, args)?;
                    self.push(o)?
                }
                0x81 => {
                    self.pop()?;
                    self.pop()?;
                    self.push(Obj::Opaque)?
                }
                b'b' => {
                    // BUILD: state applied to the object below; recon keeps the object.
                    self.pop()?;
                    if self.stack.is_empty() {
                        return Err(self.err("BUILD without an object"));
                    }
                }
                b'h' | b'j' => {
                    let k = if op == b'h' { self.u8()? as u32 } else { u32::from_le_bytes(self.le()?) };
                    let o = self.memo.get(&k).cloned().ok_or_else(|| self.err(format!("memo key {k} not set")))?;
                    self.push(o)?
                }
                b'q' | b'r' | 0x94 => {
                    let k = match op {
                        b'q' => self.u8()? as u32,
                        b'r' => u32::from_le_bytes(self.le()?),
                        _ => self.memo.len() as u32,
                    };
                    let top = self.stack.last().cloned().ok_or_else(|| self.err("memo put on an empty stack"))?;
                    self.memo.insert(k, top);
                }
                b'0' => {
                    self.pop()?;
                }
                b'.' => return self.pop(),
                other => return Err(self.err(format!("unsupported pickle opcode 0x{other:02x}"))),
            }
        }
    }
}

/// The tensors of a `data.pkl`; `key` selects a wrapped state dict.
fn state_dict(pkl: &[u8], key: Option<&str>, file: &str) -> Result<BTreeMap<String, PtTensorInfo>> {
    let u = Unpickler {
        buf: pkl,
        pos: 0,
        stack: Vec::new(),
        marks: Vec::new(),
        memo: HashMap::new(),
        copies_left: 16 * pkl.len() + 4096,
        file,
    };
    let top = u.run()?;
    let mut dict = top;
    if let Some(k) = key {
        let Obj::Dict(_, items) = &dict else { return Err(Error::input(file, format!("top level is a {}, not a dict", dict.kind()))) };
        let found = items.iter().find(|(n, _)| matches!(n, Obj::Str(s) if &**s == k)).map(|(_, v)| v.clone());
        dict = found.ok_or_else(|| Error::input(file, format!("no key `{k}` at the top level")))?;
    }
    let Obj::Dict(_, items) = &dict else { return Ok(BTreeMap::new()) };
    let mut out = BTreeMap::new();
    for (k, v) in items.iter() {
        if let (Obj::Str(name), Obj::Tensor(t)) = (k, v) {
            out.insert(name.to_string(), (**t).clone());
        }
    }
    Ok(out)
}

fn zip_err(file: &str, e: impl std::fmt::Display) -> Error {
    Error::input(file, format!("not a readable torch zip archive: {e}"))
}

type Archive = zip::ZipArchive<std::io::BufReader<std::fs::File>>;

fn open_archive(path: &Path) -> Result<Archive> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    zip::ZipArchive::new(std::io::BufReader::new(f)).map_err(|e| zip_err(&path.display().to_string(), e))
}

/// Bytes a zip entry can honestly deliver: its declared size, but no more than
/// its compressed bytes allow.
fn entry_capacity<R: Read>(e: &zip::read::ZipFile<'_, R>) -> u64 {
    let bound = match e.compression() {
        zip::CompressionMethod::Stored => e.compressed_size(),
        _ => e.compressed_size().saturating_mul(crate::util::MAX_DEFLATE_RATIO),
    };
    e.size().min(bound)
}

impl PtFile {
    /// Open a `.pt` archive and read its state dict (`key` as in [`super::Checkpoint::open`]).
    pub fn open(path: &Path, key: Option<&str>) -> Result<Self> {
        let file = path.display().to_string();
        let mut zip = open_archive(path)?;
        let names: Vec<String> = zip.file_names().filter_map(|n| n.ok().map(|n| n.into_owned())).collect();
        let pkl_name = names
            .iter()
            .find(|n| n.ends_with("data.pkl"))
            .cloned()
            .ok_or_else(|| Error::input(&file, "torch archive has no `data.pkl`"))?;
        let prefix = pkl_name.strip_suffix("data.pkl").unwrap_or("").to_string();
        let mut pkl = Vec::new();
        {
            let e = zip.by_name(&pkl_name).map_err(|e| zip_err(&file, e))?;
            let cap = entry_capacity(&e).min(MAX_PICKLE_BYTES);
            if e.size() > MAX_PICKLE_BYTES {
                return Err(Error::too_large(&file, &pkl_name, e.size() as u128, MAX_PICKLE_BYTES as u128, "bytes", "pickle size bound"));
            }
            e.take(cap).read_to_end(&mut pkl).map_err(|e| zip_err(&file, e))?;
        }
        let mut tensors = state_dict(&pkl, key, &file)?;
        // Each tensor must fit its storage entry before anything is read.
        for (name, t) in tensors.iter_mut() {
            t.entry = format!("{prefix}data/{}", t.entry);
            let e = zip
                .by_name(&t.entry)
                .map_err(|_| Error::input(&file, format!("tensor `{name}`: storage entry `{}` missing from the archive", t.entry)))?;
            let have = entry_capacity(&e) as u128;
            let elems = crate::util::checked_product(t.shape.iter().map(|&d| d as u128)).unwrap_or(u128::MAX);
            let need = elems.saturating_add(t.offset as u128).saturating_mul(t.dtype.size_in_bytes() as u128);
            if need > have {
                return Err(Error::too_large(
                    &file,
                    format!("tensor `{name}` shape {:?}", t.shape),
                    need,
                    have,
                    "bytes",
                    format!("its storage entry `{}` holds {have} bytes", t.entry),
                ));
            }
        }
        Ok(PtFile { path: path.to_path_buf(), tensors })
    }

    /// Read one tensor (its size was checked at open against the entry).
    pub fn load(&self, name: &str) -> Result<Option<Tensor>> {
        let Some(t) = self.tensors.get(name) else { return Ok(None) };
        let file = self.path.display().to_string();
        let mut zip = open_archive(&self.path)?;
        let e = zip.by_name(&t.entry).map_err(|e| zip_err(&file, e))?;
        let es = t.dtype.size_in_bytes();
        let n: usize = t.shape.iter().product();
        let mut buf = Vec::with_capacity(n * es);
        e.take(((t.offset + n) * es) as u64).read_to_end(&mut buf).map_err(|e| zip_err(&file, e))?;
        let bytes = buf
            .get(t.offset * es..)
            .filter(|b| b.len() == n * es)
            .ok_or_else(|| Error::input(&file, format!("tensor `{name}`: storage entry `{}` is shorter than its header says", t.entry)))?;
        Ok(Some(Tensor::from_raw_buffer(bytes, t.dtype, &t.shape, &Device::Cpu)?))
    }
}

/// True when the torch archive at `path` holds a record named `name`.
pub fn has_record(path: &Path, name: &str) -> Result<bool> {
    let z = open_archive(path)?;
    let found = z.file_names().any(|n| n.is_ok_and(|n| n == name));
    Ok(found)
}

/// Write `tensors` as a torch state dict (`{name: tensor}`) in the zip
/// archive `torch.save` writes: pickle protocol 2 in `archive/data.pkl`, one
/// uncompressed storage per tensor under `archive/data/`. `torch.load` and
/// [`PtFile`] read it. f32, f16 and bf16 tensors.
pub fn write_pt(tensors: &BTreeMap<String, Tensor>, path: &Path) -> Result<()> {
    write_pt_with_records(tensors, &[], path)
}

/// [`write_pt`] with extra archive records (`name`, bytes), which `torch.load`
/// does not read.
pub fn write_pt_with_records(tensors: &BTreeMap<String, Tensor>, extra: &[(&str, &[u8])], path: &Path) -> Result<()> {
    use std::io::Write;
    fn unicode(out: &mut Vec<u8>, s: &str) {
        out.push(b'X');
        out.extend_from_slice(&(s.len() as u32).to_le_bytes());
        out.extend_from_slice(s.as_bytes());
    }
    fn int(out: &mut Vec<u8>, v: usize) -> Result<()> {
        let v = i32::try_from(v).map_err(|_| Error::msg(format!("write_pt: {v} does not fit a pickle int")))?;
        out.push(b'J');
        out.extend_from_slice(&v.to_le_bytes());
        Ok(())
    }
    // PROTO 2, EMPTY_DICT, MARK … SETITEMS, STOP.
    let mut pkl = vec![0x80, 2, b'}', b'('];
    let mut storages = Vec::new();
    for (i, (name, t)) in tensors.iter().enumerate() {
        let t = t.contiguous()?;
        let flat = t.flatten_all()?;
        let (class, bytes): (&str, Vec<u8>) = match t.dtype() {
            DType::F32 => ("FloatStorage", flat.to_vec1::<f32>()?.iter().flat_map(|v| v.to_le_bytes()).collect()),
            DType::F16 => ("HalfStorage", flat.to_vec1::<half::f16>()?.iter().flat_map(|v| v.to_le_bytes()).collect()),
            DType::BF16 => ("BFloat16Storage", flat.to_vec1::<half::bf16>()?.iter().flat_map(|v| v.to_le_bytes()).collect()),
            other => return Err(Error::msg(format!("write_pt: tensor `{name}` is {other:?}; f32, f16 or bf16 only"))),
        };
        let key = i.to_string();
        unicode(&mut pkl, name);
        // _rebuild_tensor_v2(storage, offset, size, stride, requires_grad, OrderedDict())
        pkl.extend_from_slice(b"ctorch._utils\n_rebuild_tensor_v2\n(");
        // The storage's persistent id: ('storage', torch.<T>Storage, key, 'cpu', numel).
        pkl.push(b'(');
        unicode(&mut pkl, "storage");
        pkl.extend_from_slice(format!("ctorch\n{class}\n").as_bytes());
        unicode(&mut pkl, &key);
        unicode(&mut pkl, "cpu");
        int(&mut pkl, t.elem_count())?;
        pkl.extend_from_slice(b"tQ");
        int(&mut pkl, 0)?;
        let dims = t.dims().to_vec();
        let mut strides = vec![1usize; dims.len()];
        for d in (0..dims.len().saturating_sub(1)).rev() {
            strides[d] = strides[d + 1] * dims[d + 1];
        }
        for list in [&dims, &strides] {
            pkl.push(b'(');
            for &v in list.iter() {
                int(&mut pkl, v)?;
            }
            pkl.push(b't');
        }
        pkl.extend_from_slice(b"\x89ccollections\nOrderedDict\n)RtR");
        storages.push((key, bytes));
    }
    pkl.extend_from_slice(b"u.");
    let file = path.display().to_string();
    let zerr = |e: &dyn std::fmt::Display| Error::msg(format!("{file}: writing the torch archive: {e}"));
    let f = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    let mut z = zip::ZipWriter::new(f);
    let o = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    let mut entry = |name: &str, bytes: &[u8]| -> Result<()> {
        z.start_file(name, o).map_err(|e| zerr(&e))?;
        z.write_all(bytes).map_err(|e| zerr(&e))
    };
    entry("archive/data.pkl", &pkl)?;
    entry("archive/byteorder", b"little")?;
    for (key, bytes) in &storages {
        entry(&format!("archive/data/{key}"), bytes)?;
    }
    entry("archive/version", b"3\n")?;
    for (name, bytes) in extra {
        entry(name, bytes)?;
    }
    z.finish().map_err(|e| zerr(&e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unpickle(b: &[u8]) -> Result<Obj> {
        Unpickler { buf: b, pos: 0, stack: vec![], marks: vec![], memo: HashMap::new(), copies_left: 16 * b.len() + 4096, file: "t" }.run()
    }

    #[test]
    fn hostile_pickles_are_errors() {
        // A 4 GB string claim in a 10-byte pickle.
        assert!(matches!(unpickle(b"X\xff\xff\xff\xff.").unwrap_err(), Error::TooLarge(_)));
        // LONG1 wider than 64 bits.
        assert!(unpickle(b"\x8a\x20").is_err());
        // Deep nesting: 1000 nested lists.
        let mut deep = vec![b']'; 1000];
        deep.extend(std::iter::repeat_n(b'a', 999));
        deep.push(b'.');
        assert!(unpickle(&deep).unwrap_err().to_string().contains("nested deeper"));
        // Growing a memoised list one element per 7 bytes would copy it each
        // time (quadratic work): the copies are bounded.
        let mut grow = b"]q\x00".to_vec();
        for _ in 0..2000 {
            grow.extend_from_slice(b"h\x00K\x01aq\x000");
        }
        grow.extend_from_slice(b"h\x00.");
        assert!(unpickle(&grow).unwrap_err().to_string().contains("copies"));
        // The same list grown without the memo is linear and reads.
        let mut lin = b"]".to_vec();
        for _ in 0..2000 {
            lin.extend_from_slice(b"K\x01a");
        }
        lin.push(b'.');
        assert!(matches!(unpickle(&lin).unwrap(), Obj::List(1, v) if v.len() == 2000));
        // Stack underflow, pop across a mark, unknown opcode.
        for bad in [&b"a."[..], b"(0.", b"\xff", b""] {
            assert!(unpickle(bad).is_err(), "{bad:?}");
        }
    }

    /// What write_pt writes, PtFile reads back: names, dtypes, shapes, values.
    #[test]
    fn write_pt_round_trips() -> Result<()> {
        let dir = crate::util::testing::tmp("write-pt");
        let p = dir.join("w.pt");
        let a = Tensor::arange(0f32, 6.0, &Device::Cpu)?.reshape((2, 3))?;
        let b = Tensor::new(&[0.5f32, -1.5], &Device::Cpu)?.to_dtype(DType::F16)?;
        let c = Tensor::new(2.0f32, &Device::Cpu)?.to_dtype(DType::BF16)?;
        let t: BTreeMap<String, Tensor> = [("blocks.0.w".to_string(), a.clone()), ("b".into(), b), ("c".into(), c)].into_iter().collect();
        write_pt(&t, &p)?;
        let f = PtFile::open(&p, None)?;
        assert_eq!(f.tensors.keys().cloned().collect::<Vec<_>>(), vec!["b", "blocks.0.w", "c"]);
        assert_eq!((f.tensors["b"].dtype, f.tensors["c"].dtype), (DType::F16, DType::BF16));
        let got = f.load("blocks.0.w")?.expect("tensor");
        assert_eq!(got.to_vec2::<f32>()?, a.to_vec2::<f32>()?);
        assert_eq!(f.load("b")?.expect("b").to_dtype(DType::F32)?.to_vec1::<f32>()?, vec![0.5, -1.5]);
        assert_eq!(f.load("c")?.expect("c").dims(), &[] as &[usize]);
        let _ = std::fs::remove_dir_all(&dir);
        Ok(())
    }

    #[test]
    fn long1_is_twos_complement() {
        assert!(matches!(unpickle(b"\x8a\x01\xff.").unwrap(), Obj::Int(-1)));
        assert!(matches!(unpickle(b"\x8a\x02\x00\x01.").unwrap(), Obj::Int(256)));
    }
}
