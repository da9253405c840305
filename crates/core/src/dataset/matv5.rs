//! Minimal reader for MATLAB level-5 MAT files (`*-meta.mat` of YCB-Video).
//!
//! Format (MathWorks "MAT-File Format", level 5): a 128-byte header (text,
//! subsystem offset, version, a 2-byte endian indicator `IM`/`MI`), then a
//! sequence of data elements. Each element has an 8-byte tag
//! `(type: u32, nbytes: u32)`; when the upper 16 bits of the first word are
//! non-zero the element is "small": `nbytes` is the upper half, the type the
//! lower half, and the data sits in the tag's second word. Elements inside
//! a matrix are padded to 8 bytes. `miCOMPRESSED` (15) holds a zlib stream
//! that decompresses to one further element (decoded with `flate2`).
//! A numeric `miMATRIX` (14) holds array flags (class in the low byte),
//! dimensions (int32), a name (int8) and the real part, stored in any numeric
//! type (MATLAB saves doubles as uint8 when the values allow); data is
//! column-major.
//!
//! Only what YCB-Video needs is read: numeric real arrays (double, single,
//! all integer classes) are converted to `f64`; complex, char, cell,
//! struct, object and sparse variables are skipped, not errors.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use crate::{Error, Result};

/// A numeric MATLAB array: `dims` as stored (column-major), values as f64.
#[derive(Debug, Clone, PartialEq)]
pub struct MatArray {
    /// Dimensions as stored (column-major).
    pub dims: Vec<usize>,
    /// Values, column-major, converted to f64.
    pub data: Vec<f64>,
}

impl MatArray {
    /// Element at a multi-index (column-major: the first index varies fastest).
    pub fn at(&self, idx: &[usize]) -> Option<f64> {
        if idx.len() > self.dims.len() && idx[self.dims.len()..].iter().any(|&i| i != 0) {
            return None;
        }
        let mut off = 0usize;
        let mut stride = 1usize;
        for (k, &d) in self.dims.iter().enumerate() {
            let i = idx.get(k).copied().unwrap_or(0);
            if i >= d {
                return None;
            }
            // i < d, and the product of the dims before it is at most data.len()
            // unless a later dim is 0: checked, as dims come from the file.
            off = off.checked_add(i.checked_mul(stride)?)?;
            stride = stride.checked_mul(d)?;
        }
        self.data.get(off).copied()
    }

    /// Number of values.
    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// Whether the array holds no values.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// A 2-D array as rows (`[r][c]`), or `None` if not 2-D.
    pub fn rows(&self) -> Option<Vec<Vec<f64>>> {
        if self.dims.len() != 2 {
            return None;
        }
        let (r, c) = (self.dims[0], self.dims[1]);
        // Dims come from the file: a zero-sized side must not make `r` empty rows.
        if r.checked_mul(c) != Some(self.data.len()) || self.data.is_empty() {
            return None;
        }
        Some((0..r).map(|i| (0..c).map(|j| self.data[i + r * j]).collect()).collect())
    }
}

/// The numeric variables of a MAT file, by name.
#[derive(Debug, Clone, Default)]
pub struct MatFile {
    /// Variables by name.
    pub vars: BTreeMap<String, MatArray>,
}

const MI_INT8: u32 = 1;
const MI_UINT8: u32 = 2;
const MI_INT16: u32 = 3;
const MI_UINT16: u32 = 4;
const MI_INT32: u32 = 5;
const MI_UINT32: u32 = 6;
const MI_SINGLE: u32 = 7;
const MI_DOUBLE: u32 = 9;
const MI_INT64: u32 = 12;
const MI_UINT64: u32 = 13;
const MI_MATRIX: u32 = 14;
const MI_COMPRESSED: u32 = 15;

// Array classes that hold plain numbers (mxDOUBLE_CLASS .. mxUINT64_CLASS).
const NUMERIC_CLASSES: std::ops::RangeInclusive<u8> = 6..=15;
const FLAG_COMPLEX: u32 = 0x0800;

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
    big_endian: bool,
    file: &'a str,
}

impl<'a> Reader<'a> {
    fn err(&self, msg: impl Into<String>) -> Error {
        Error::input(self.file, format!("MAT v5: {} (at byte {})", msg.into(), self.pos))
    }

    fn u32_at(&self, p: usize) -> Result<u32> {
        let b: [u8; 4] = self.buf.get(p..p + 4).ok_or_else(|| self.err("truncated"))?.try_into().unwrap();
        Ok(if self.big_endian { u32::from_be_bytes(b) } else { u32::from_le_bytes(b) })
    }

    /// Next element: (type, payload). Advances past padding when `padded`.
    fn next(&mut self, padded: bool) -> Result<Option<(u32, &'a [u8])>> {
        if self.pos >= self.buf.len() {
            return Ok(None);
        }
        let w0 = self.u32_at(self.pos)?;
        let (ty, n, start, total) = if w0 >> 16 != 0 {
            // Small data element: 4-byte tag + up to 4 bytes of data.
            let (ty, n) = (w0 & 0xffff, (w0 >> 16) as usize);
            if n > 4 {
                return Err(self.err(format!("small element claims {n} bytes")));
            }
            (ty, n, self.pos + 4, 8)
        } else {
            let n = self.u32_at(self.pos + 4)? as usize;
            let total = if padded { 8 + n.div_ceil(8) * 8 } else { 8 + n };
            (w0, n, self.pos + 8, total)
        };
        let data = self.buf.get(start..start + n).ok_or_else(|| self.err(format!("element of {n} bytes runs past the end")))?;
        self.pos = (self.pos + total).min(self.buf.len());
        Ok(Some((ty, data)))
    }
}

fn decode_numeric(ty: u32, data: &[u8], big_endian: bool, file: &str) -> Result<Vec<f64>> {
    macro_rules! conv {
        ($t:ty, $n:expr) => {
            data.chunks_exact($n)
                .map(|c| {
                    let a: [u8; $n] = c.try_into().unwrap();
                    (if big_endian { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) }) as f64
                })
                .collect()
        };
    }
    Ok(match ty {
        MI_INT8 => data.iter().map(|&b| b as i8 as f64).collect(),
        MI_UINT8 => data.iter().map(|&b| b as f64).collect(),
        MI_INT16 => conv!(i16, 2),
        MI_UINT16 => conv!(u16, 2),
        MI_INT32 => conv!(i32, 4),
        MI_UINT32 => conv!(u32, 4),
        MI_SINGLE => conv!(f32, 4),
        MI_DOUBLE => conv!(f64, 8),
        MI_INT64 => conv!(i64, 8),
        MI_UINT64 => conv!(u64, 8),
        t => return Err(Error::input(file, format!("MAT v5: data type {t} is not numeric"))),
    })
}

/// Parse one `miMATRIX` payload; `None` for variables we do not decode.
fn parse_matrix(payload: &[u8], big_endian: bool, file: &str) -> Result<Option<(String, MatArray)>> {
    let mut r = Reader { buf: payload, pos: 0, big_endian, file };
    let (_, flags) = r.next(true)?.ok_or_else(|| r.err("matrix without array flags"))?;
    if flags.len() < 4 {
        return Err(r.err("short array flags"));
    }
    let f0 = {
        let a: [u8; 4] = flags[..4].try_into().unwrap();
        if big_endian {
            u32::from_be_bytes(a)
        } else {
            u32::from_le_bytes(a)
        }
    };
    let class = (f0 & 0xff) as u8;
    let (dty, dims_raw) = r.next(true)?.ok_or_else(|| r.err("matrix without dimensions"))?;
    let dims: Vec<usize> = decode_numeric(dty, dims_raw, big_endian, file)?.iter().map(|&d| d.max(0.0) as usize).collect();
    let (_, name_raw) = r.next(true)?.ok_or_else(|| r.err("matrix without a name"))?;
    let name = String::from_utf8_lossy(name_raw).into_owned();
    if !NUMERIC_CLASSES.contains(&class) || f0 & FLAG_COMPLEX != 0 {
        return Ok(None);
    }
    // The values must be in the data element, so the claimed count is checked
    // against it (and never multiplied out with overflow).
    let n = crate::util::checked_product(dims.iter().map(|&d| d as u128)).unwrap_or(u128::MAX);
    let data = match r.next(true)? {
        Some((ty, raw)) => decode_numeric(ty, raw, big_endian, file)?,
        None if n == 0 => Vec::new(),
        None => return Err(r.err(format!("variable `{name}` has no data"))),
    };
    if data.len() as u128 != n {
        return Err(Error::input(file, format!("MAT v5: variable `{name}` has {} values for dims {dims:?}", data.len())));
    }
    Ok(Some((name, MatArray { dims, data })))
}

fn parse_elements(buf: &[u8], big_endian: bool, file: &str, out: &mut MatFile, depth: usize) -> Result<()> {
    if depth > 4 {
        return Err(Error::input(file, "MAT v5: nested compressed elements"));
    }
    let mut r = Reader { buf, pos: 0, big_endian, file };
    // Top-level elements after a compressed one are not padded (the
    // compressed byte count is exact); uncompressed ones are 8-aligned.
    loop {
        let pos = r.pos;
        let w0 = if pos + 4 <= buf.len() { r.u32_at(pos)? } else { break };
        let padded = w0 != MI_COMPRESSED;
        let Some((ty, data)) = r.next(padded)? else { break };
        match ty {
            MI_COMPRESSED => {
                // Read one byte past the bound to tell "exactly at" from "over" (a zlib bomb).
                let cap = crate::util::MAX_MAT_INFLATED;
                let mut dec = Vec::new();
                flate2::read::ZlibDecoder::new(data)
                    .take(cap + 1)
                    .read_to_end(&mut dec)
                    .map_err(|e| Error::input(file, format!("MAT v5: bad zlib stream at byte {pos}: {e}")))?;
                if dec.len() as u64 > cap {
                    return Err(Error::too_large(
                        file,
                        format!("compressed element at byte {pos}"),
                        dec.len() as u128,
                        cap as u128,
                        "bytes inflated",
                        "MAT v5 zlib streams are bounded",
                    ));
                }
                parse_elements(&dec, big_endian, file, out, depth + 1)?;
            }
            MI_MATRIX => {
                if let Some((name, arr)) = parse_matrix(data, big_endian, file)? {
                    out.vars.insert(name, arr);
                }
            }
            _ => {} // other top-level elements carry no variables we need
        }
    }
    Ok(())
}

impl MatFile {
    /// Reads and parses a MAT v5 file.
    pub fn open(path: &Path) -> Result<Self> {
        let buf = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        Self::parse(&buf, &path.display().to_string())
    }

    /// Parse the bytes of a level-5 MAT file; `file` names it in errors.
    pub fn parse(buf: &[u8], file: &str) -> Result<Self> {
        if buf.len() < 128 || !buf[..116].starts_with(b"MATLAB 5.0 MAT-file") {
            return Err(Error::input(file, "not a MATLAB 5.0 MAT-file (header text missing); v7.3 (HDF5) files are not supported"));
        }
        let big_endian = match &buf[126..128] {
            b"IM" => false,
            b"MI" => true,
            e => return Err(Error::input(file, format!("MAT v5: bad endian indicator {e:?}"))),
        };
        let mut out = MatFile::default();
        parse_elements(&buf[128..], big_endian, file, &mut out, 0)?;
        Ok(out)
    }

    /// The variable named `name`.
    pub fn get(&self, name: &str) -> Option<&MatArray> {
        self.vars.get(name)
    }

    /// A variable that must exist; the error names the file and lists what it holds.
    pub fn require(&self, name: &str, file: &str) -> Result<&MatArray> {
        self.get(name).ok_or_else(|| {
            let have: Vec<&str> = self.vars.keys().map(|s| s.as_str()).collect();
            Error::input(file, format!("MAT file has no numeric variable `{name}` (it has {have:?})"))
        })
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Writes a little-endian MAT v5 file holding the given double matrices,
    /// optionally zlib-compressed, so the reader is tested without fixtures.
    pub(crate) fn write_mat(vars: &[(&str, Vec<usize>, Vec<f64>)], compress: bool, as_uint8: bool) -> Vec<u8> {
        fn elem(ty: u32, data: &[u8], out: &mut Vec<u8>) {
            out.extend(ty.to_le_bytes());
            out.extend((data.len() as u32).to_le_bytes());
            out.extend(data);
            while !out.len().is_multiple_of(8) {
                out.push(0);
            }
        }
        let mut buf = Vec::new();
        let mut hdr = b"MATLAB 5.0 MAT-file, written by recon tests".to_vec();
        hdr.resize(116, b' ');
        buf.extend(hdr);
        buf.extend([0u8; 8]);
        buf.extend(0x0100u16.to_le_bytes());
        buf.extend(b"IM");
        for (name, dims, data) in vars {
            let mut m = Vec::new();
            elem(MI_UINT32, &[6u32.to_le_bytes(), 0u32.to_le_bytes()].concat(), &mut m);
            let d: Vec<u8> = dims.iter().flat_map(|&d| (d as i32).to_le_bytes()).collect();
            elem(MI_INT32, &d, &mut m);
            elem(MI_INT8, name.as_bytes(), &mut m);
            if as_uint8 {
                let v: Vec<u8> = data.iter().map(|&x| x as u8).collect();
                elem(MI_UINT8, &v, &mut m);
            } else {
                let v: Vec<u8> = data.iter().flat_map(|x| x.to_le_bytes()).collect();
                elem(MI_DOUBLE, &v, &mut m);
            }
            let mut whole = Vec::new();
            elem(MI_MATRIX, &m, &mut whole);
            if compress {
                use std::io::Write;
                let mut enc = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
                enc.write_all(&whole).unwrap();
                let z = enc.finish().unwrap();
                buf.extend(MI_COMPRESSED.to_le_bytes());
                buf.extend((z.len() as u32).to_le_bytes());
                buf.extend(z);
            } else {
                buf.extend(whole);
            }
        }
        buf
    }

    #[test]
    fn reads_plain_and_compressed_doubles() {
        let k = vec![1066.778, 0.0, 0.0, 0.0, 1067.487, 0.0, 312.9869, 241.3109, 1.0]; // column-major
        for (compress, as_u8) in [(false, false), (true, false)] {
            let bytes =
                write_mat(&[("intrinsic_matrix", vec![3, 3], k.clone()), ("factor_depth", vec![1, 1], vec![10000.0])], compress, as_u8);
            let m = MatFile::parse(&bytes, "t.mat").unwrap();
            let a = m.require("intrinsic_matrix", "t.mat").unwrap();
            assert_eq!(a.dims, vec![3, 3]);
            assert_eq!(a.rows().unwrap()[0], vec![1066.778, 0.0, 312.9869]);
            assert_eq!(a.at(&[1, 2]), Some(241.3109));
            assert_eq!(m.get("factor_depth").unwrap().data, vec![10000.0]);
            assert!(m.require("poses", "t.mat").is_err());
        }
        // Doubles stored as uint8 (MATLAB's compact storage), compressed.
        let bytes = write_mat(&[("cls_indexes", vec![3, 1], vec![8.0, 14.0, 21.0])], true, true);
        let m = MatFile::parse(&bytes, "t.mat").unwrap();
        assert_eq!(m.get("cls_indexes").unwrap().data, vec![8.0, 14.0, 21.0]);
    }

    #[test]
    fn rejects_garbage() {
        assert!(MatFile::parse(b"hello", "x").is_err());
        let mut bytes = write_mat(&[("a", vec![2, 2], vec![1.0; 4])], true, false);
        let n = bytes.len();
        bytes.truncate(n - 10); // cut the zlib stream
        assert!(MatFile::parse(&bytes, "x").is_err());
    }

    #[test]
    fn three_d_indexing() {
        // 3×4×2 column-major: value = i + 10 j + 100 k.
        let mut data = Vec::new();
        for k in 0..2 {
            for j in 0..4 {
                for i in 0..3 {
                    data.push((i + 10 * j + 100 * k) as f64);
                }
            }
        }
        let a = MatArray { dims: vec![3, 4, 2], data };
        assert_eq!(a.at(&[2, 3, 1]), Some(132.0));
        assert_eq!(a.at(&[3, 0, 0]), None);
    }
}
