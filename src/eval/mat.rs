//! Minimal MATLAB MAT-file (level 5) reader: top-level numeric arrays (double, single,
//! (u)int8/16/32/64, char as code units), including `miCOMPRESSED` (zlib) elements.
//! Cell, struct, object and sparse arrays are skipped; complex arrays keep the real part.
//! Big- and little-endian files are handled.

use crate::{Error, Result};
use std::collections::HashMap;
use std::io::Read;
use std::path::Path;

/// A numeric array, values converted to `f64`, stored in MATLAB's **column-major** order.
#[derive(Debug, Clone, PartialEq)]
pub struct MatArray {
    pub dims: Vec<usize>,
    pub data: Vec<f64>,
}

impl MatArray {
    /// Element at a full multi-index (column-major: the first index varies fastest).
    pub fn get(&self, idx: &[usize]) -> Option<f64> {
        if idx.len() != self.dims.len() {
            return None;
        }
        let mut off = 0;
        let mut stride = 1;
        for (&i, &d) in idx.iter().zip(&self.dims) {
            if i >= d {
                return None;
            }
            off += i * stride;
            stride *= d;
        }
        self.data.get(off).copied()
    }

    /// A 2-D array as row-major rows (`dims = [rows, cols]`; trailing singleton dims allowed).
    pub fn rows(&self) -> Option<Vec<Vec<f64>>> {
        if self.dims.len() < 2 || self.dims[2..].iter().any(|&d| d != 1) {
            return None;
        }
        let (r, c) = (self.dims[0], self.dims[1]);
        Some((0..r).map(|i| (0..c).map(|j| self.data[i + j * r]).collect()).collect())
    }
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
const MI_UTF8: u32 = 16;
const MI_UTF16: u32 = 17;
const MI_UTF32: u32 = 18;

/// Reads every supported top-level variable of a MAT v5 file, keyed by name.
pub fn read_mat(path: &Path) -> Result<HashMap<String, MatArray>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    parse_mat(&bytes, &path.display().to_string())
}

/// Parses MAT v5 bytes; `file` names the source in errors.
pub fn parse_mat(bytes: &[u8], file: &str) -> Result<HashMap<String, MatArray>> {
    let err = |m: String| Error::input(file, m);
    if bytes.len() < 128 {
        return Err(err("too short for a MAT v5 header (128 bytes)".into()));
    }
    let le = match &bytes[126..128] {
        b"IM" => true,
        b"MI" => false,
        _ => return Err(err("not a MAT v5 file (no endian indicator `IM`/`MI`; v7.3/HDF5 and v4 files are unsupported)".into())),
    };
    let mut out = HashMap::new();
    parse_elements(&bytes[128..], le, file, &mut out, 0)?;
    Ok(out)
}

struct Cur<'a> {
    b: &'a [u8],
    pos: usize,
    le: bool,
}

impl<'a> Cur<'a> {
    fn u32(&self, at: usize) -> Option<u32> {
        let a: [u8; 4] = self.b.get(at..at + 4)?.try_into().ok()?;
        Some(if self.le { u32::from_le_bytes(a) } else { u32::from_be_bytes(a) })
    }
    /// Next data element: (type, payload). Handles the small (packed 4-byte) format.
    fn element(&mut self) -> Option<std::result::Result<(u32, &'a [u8]), String>> {
        let b: &'a [u8] = self.b;
        if self.pos + 8 > b.len() {
            return None;
        }
        let w0 = self.u32(self.pos)?;
        if w0 >> 16 != 0 {
            // Small data element: 2-byte size, 2-byte type, data in the next 4 bytes.
            let (ty, n) = (w0 & 0xffff, (w0 >> 16) as usize);
            if n > 4 {
                return Some(Err(format!("small data element claims {n} bytes")));
            }
            let d = &b[self.pos + 4..self.pos + 4 + n];
            self.pos += 8;
            return Some(Ok((ty, d)));
        }
        let n = self.u32(self.pos + 4)? as usize;
        let start = self.pos + 8;
        let Some(d) = b.get(start..start.checked_add(n)?) else {
            return Some(Err(format!("element of type {w0} claims {n} bytes but only {} remain", b.len() - start)));
        };
        // Compressed elements are not padded; everything else pads to 8 bytes.
        self.pos = if w0 == MI_COMPRESSED { start + n } else { start + n.div_ceil(8) * 8 };
        Some(Ok((w0, d)))
    }
}

fn parse_elements(b: &[u8], le: bool, file: &str, out: &mut HashMap<String, MatArray>, depth: usize) -> Result<()> {
    let err = |m: String| Error::input(file, m);
    let mut cur = Cur { b, pos: 0, le };
    while let Some(el) = cur.element() {
        let (ty, data) = el.map_err(err)?;
        match ty {
            MI_COMPRESSED => {
                if depth > 2 {
                    return Err(err("nested miCOMPRESSED elements".into()));
                }
                let mut dec = Vec::new();
                flate2::read::ZlibDecoder::new(data).read_to_end(&mut dec).map_err(|e| err(format!("miCOMPRESSED element: zlib: {e}")))?;
                parse_elements(&dec, le, file, out, depth + 1)?;
            }
            MI_MATRIX => {
                if let Some((name, arr)) = parse_matrix(data, le).map_err(|m| err(m))? {
                    out.insert(name, arr);
                }
            }
            _ => {} // stray top-level elements carry no variable
        }
    }
    Ok(())
}

/// Returns `None` for classes this reader skips.
fn parse_matrix(b: &[u8], le: bool) -> std::result::Result<Option<(String, MatArray)>, String> {
    let mut cur = Cur { b, pos: 0, le };
    let mut next = |what: &str| cur.element().unwrap_or_else(|| Err(format!("miMATRIX: missing {what}")));
    let (_, flags) = next("array flags")?;
    let w0 = {
        let a: [u8; 4] = flags.get(..4).ok_or("miMATRIX: short array flags")?.try_into().map_err(|_| "flags")?;
        if le { u32::from_le_bytes(a) } else { u32::from_be_bytes(a) }
    };
    let class = w0 & 0xff;
    let (dty, dims_b) = next("dimensions")?;
    let dims: Vec<usize> = numeric(dty, dims_b, le).ok_or("miMATRIX: bad dimensions type")?.iter().map(|&d| d.max(0.0) as usize).collect();
    let (_, name_b) = next("name")?;
    let name = String::from_utf8_lossy(name_b).trim_end_matches('\0').to_string();
    // 4 = char, 6..=15 numeric; 1 cell, 2 struct, 3 object, 5 sparse are skipped.
    if !(class == 4 || (6..=15).contains(&class)) {
        return Ok(None);
    }
    let (rty, real) = next(&format!("real part of `{name}`"))?;
    let data = numeric(rty, real, le).ok_or_else(|| format!("variable `{name}`: unsupported data type {rty}"))?;
    let n: usize = dims.iter().product();
    if data.len() != n {
        return Err(format!("variable `{name}`: {} values for dims {dims:?}", data.len()));
    }
    Ok(Some((name, MatArray { dims, data })))
}

fn numeric(ty: u32, b: &[u8], le: bool) -> Option<Vec<f64>> {
    macro_rules! conv {
        ($t:ty, $n:expr) => {
            b.chunks_exact($n)
                .map(|c| {
                    let a: [u8; $n] = c.try_into().unwrap_or([0; $n]);
                    (if le { <$t>::from_le_bytes(a) } else { <$t>::from_be_bytes(a) }) as f64
                })
                .collect()
        };
    }
    Some(match ty {
        MI_INT8 => b.iter().map(|&x| x as i8 as f64).collect(),
        MI_UINT8 | MI_UTF8 => b.iter().map(|&x| x as f64).collect(),
        MI_INT16 => conv!(i16, 2),
        MI_UINT16 | MI_UTF16 => conv!(u16, 2),
        MI_INT32 => conv!(i32, 4),
        MI_UINT32 | MI_UTF32 => conv!(u32, 4),
        MI_SINGLE => conv!(f32, 4),
        MI_DOUBLE => conv!(f64, 8),
        MI_INT64 => conv!(i64, 8),
        MI_UINT64 => conv!(u64, 8),
        _ => return None,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::io::Write;

    fn el(ty: u32, data: &[u8]) -> Vec<u8> {
        let mut v = ty.to_le_bytes().to_vec();
        v.extend_from_slice(&(data.len() as u32).to_le_bytes());
        v.extend_from_slice(data);
        while v.len() % 8 != 0 {
            v.push(0);
        }
        v
    }

    /// A miMATRIX element (little-endian) of class `class` with real data of MAT type `dty`.
    pub(crate) fn matrix(name: &str, class: u32, dims: &[i32], dty: u32, data: &[u8]) -> Vec<u8> {
        let mut body = el(MI_UINT32, &[class.to_le_bytes(), 0u32.to_le_bytes()].concat());
        body.extend(el(MI_INT32, &dims.iter().flat_map(|d| d.to_le_bytes()).collect::<Vec<_>>()));
        if name.len() <= 4 {
            // Exercise the small-element format for short names.
            let mut s = (MI_INT8 | ((name.len() as u32) << 16)).to_le_bytes().to_vec();
            let mut n = name.as_bytes().to_vec();
            n.resize(4, 0);
            s.extend(n);
            body.extend(s);
        } else {
            body.extend(el(MI_INT8, name.as_bytes()));
        }
        body.extend(el(dty, data));
        el(MI_MATRIX, &body)
    }

    pub(crate) fn header() -> Vec<u8> {
        let mut h = b"MATLAB 5.0 MAT-file, written by recon tests".to_vec();
        h.resize(116, b' ');
        h.extend([0u8; 8]);
        h.extend(0x0100u16.to_le_bytes());
        h.extend(b"IM");
        h
    }

    pub(crate) fn compress(el: &[u8]) -> Vec<u8> {
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        z.write_all(el).unwrap();
        let c = z.finish().unwrap();
        let mut v = MI_COMPRESSED.to_le_bytes().to_vec();
        v.extend((c.len() as u32).to_le_bytes());
        v.extend(c);
        v
    }

    #[test]
    fn reads_plain_and_compressed_arrays() {
        let mut f = header();
        // 2x3 double, column-major [[1,2,3],[4,5,6]].
        let d: Vec<u8> = [1.0f64, 4.0, 2.0, 5.0, 3.0, 6.0].iter().flat_map(|x| x.to_le_bytes()).collect();
        f.extend(matrix("pose", 6, &[2, 3], MI_DOUBLE, &d));
        // A double-class array stored as uint8 (MATLAB's compact storage), compressed.
        f.extend(compress(&matrix("cls_indexes", 6, &[3, 1], MI_UINT8, &[1, 14, 21])));
        // Single-precision, compressed.
        let s: Vec<u8> = [0.5f32, -2.0].iter().flat_map(|x| x.to_le_bytes()).collect();
        f.extend(compress(&matrix("sgl", 7, &[1, 2], MI_SINGLE, &s)));
        // A struct is skipped without error.
        f.extend(el(MI_MATRIX, &[el(MI_UINT32, &[2u32.to_le_bytes(), 0u32.to_le_bytes()].concat()), el(MI_INT32, &[1i32.to_le_bytes(), 1i32.to_le_bytes()].concat()), el(MI_INT8, b"st")].concat()));
        let m = parse_mat(&f, "t.mat").unwrap();
        assert_eq!(m.len(), 3);
        assert_eq!(m["pose"].rows().unwrap(), vec![vec![1.0, 2.0, 3.0], vec![4.0, 5.0, 6.0]]);
        assert_eq!(m["pose"].get(&[1, 2]), Some(6.0));
        assert_eq!(m["cls_indexes"].data, vec![1.0, 14.0, 21.0]);
        assert_eq!(m["sgl"], MatArray { dims: vec![1, 2], data: vec![0.5, -2.0] });
        // Truncation is an error naming the file.
        let e = parse_mat(&f[..200], "t.mat").unwrap_err().to_string();
        assert!(e.starts_with("t.mat"), "{e}");
        assert!(parse_mat(&f[..100], "t.mat").is_err());
    }
}
