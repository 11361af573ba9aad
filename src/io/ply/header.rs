//! PLY header parsing and the size check of binary bodies.

use std::io::{BufRead, Read};
use std::path::Path;

use glam::DVec3;

use super::PlyEncoding;
use crate::io::IoError;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    pub(super) fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    /// Decodes one value from exactly `size()` bytes.
    pub(super) fn decode(self, b: &[u8], big: bool) -> f64 {
        let mut a = [0u8; 8];
        let n = self.size();
        a[..n].copy_from_slice(&b[..n]);
        if big {
            a[..n].reverse();
        }
        match self {
            Scalar::I8 => f64::from(a[0] as i8),
            Scalar::U8 => f64::from(a[0]),
            Scalar::I16 => f64::from(i16::from_le_bytes([a[0], a[1]])),
            Scalar::U16 => f64::from(u16::from_le_bytes([a[0], a[1]])),
            Scalar::I32 => f64::from(i32::from_le_bytes([a[0], a[1], a[2], a[3]])),
            Scalar::U32 => f64::from(u32::from_le_bytes([a[0], a[1], a[2], a[3]])),
            Scalar::F32 => f64::from(f32::from_le_bytes([a[0], a[1], a[2], a[3]])),
            Scalar::F64 => f64::from_le_bytes(a),
        }
    }
}

#[derive(Debug, Clone)]
pub(super) struct Property {
    pub(super) name: String,
    pub(super) ty: Scalar,
    /// `Some(count type)` for a list property whose items have type `ty`.
    pub(super) list: Option<Scalar>,
    pub(super) text: String,
}

#[derive(Debug, Clone)]
pub(super) struct Element {
    pub(super) name: String,
    pub(super) count: u64,
    pub(super) props: Vec<Property>,
}

impl Element {
    /// Bytes per row when no property is a list.
    pub(super) fn fixed_row(&self) -> Option<u64> {
        self.props
            .iter()
            .map(|p| p.list.is_none().then_some(p.ty.size() as u64))
            .sum()
    }
    /// Smallest possible row (lists empty).
    pub(super) fn min_row(&self) -> u64 {
        self.props
            .iter()
            .map(|p| p.list.unwrap_or(p.ty).size() as u64)
            .sum()
    }
}

pub(super) struct Header {
    pub(super) encoding: PlyEncoding,
    pub(super) elements: Vec<Element>,
    pub(super) offset: Option<DVec3>,
    pub(super) header_bytes: u64,
    pub(super) header_lines: u64,
}

pub(super) fn parse_header(path: &Path, r: &mut impl BufRead) -> Result<Header, IoError> {
    let bad =
        |line: u64, what: &str| IoError::format(path, format!("PLY header line {line}: {what}"));
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut offset = None;
    let (mut bytes, mut lines) = (0u64, 0u64);
    let mut buf = Vec::new();
    loop {
        buf.clear();
        let n = r
            .by_ref()
            .take(4096)
            .read_until(b'\n', &mut buf)
            .map_err(|e| IoError::read(path, e, "PLY header"))?;
        if n == 0 {
            return Err(IoError::format(path, "PLY header has no end_header line"));
        }
        bytes += n as u64;
        lines += 1;
        if lines > 10_000 || !buf.ends_with(b"\n") {
            return Err(bad(lines, "line too long or header too large"));
        }
        let text = std::str::from_utf8(&buf).map_err(|_| bad(lines, "not UTF-8"))?;
        let words: Vec<&str> = text.split_whitespace().collect();
        match words.as_slice() {
            ["ply"] if lines == 1 => {}
            _ if lines == 1 => return Err(bad(1, "missing 'ply' magic")),
            ["format", f, _] => {
                encoding = Some(match *f {
                    "ascii" => PlyEncoding::Ascii,
                    "binary_little_endian" => PlyEncoding::BinaryLittleEndian,
                    "binary_big_endian" => PlyEncoding::BinaryBigEndian,
                    _ => return Err(bad(lines, "unknown format")),
                })
            }
            ["comment", "sylva_offset", x, y, z] => {
                let v: Vec<f64> = [x, y, z].iter().filter_map(|s| s.parse().ok()).collect();
                match v.as_slice() {
                    [x, y, z] if x.is_finite() && y.is_finite() && z.is_finite() => {
                        offset = Some(DVec3::new(*x, *y, *z))
                    }
                    _ => return Err(bad(lines, "bad sylva_offset comment")),
                }
            }
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, count] => elements.push(Element {
                name: name.to_string(),
                count: count.parse().map_err(|_| bad(lines, "bad element count"))?,
                props: Vec::new(),
            }),
            ["property", rest @ ..] => {
                let el = elements
                    .last_mut()
                    .ok_or_else(|| bad(lines, "property before any element"))?;
                let ty =
                    |s: &str| Scalar::parse(s).ok_or_else(|| bad(lines, "unknown property type"));
                let (ty, list, name) = match rest {
                    ["list", c, t, name] => (ty(t)?, Some(ty(c)?), name),
                    [t, name] => (ty(t)?, None, name),
                    _ => return Err(bad(lines, "malformed property")),
                };
                el.props.push(Property {
                    name: name.to_string(),
                    ty,
                    list,
                    text: rest.join(" "),
                });
            }
            ["end_header"] => break,
            _ => return Err(bad(lines, "unrecognised header line")),
        }
    }
    let encoding =
        encoding.ok_or_else(|| IoError::format(path, "PLY header has no format line"))?;
    let vertex = elements
        .iter()
        .find(|e| e.name == "vertex")
        .ok_or_else(|| IoError::format(path, "PLY has no vertex element"))?;
    for axis in ["x", "y", "z"] {
        if !vertex
            .props
            .iter()
            .any(|p| p.name == axis && p.list.is_none())
        {
            return Err(IoError::format(
                path,
                format!("PLY vertex element has no scalar '{axis}'"),
            ));
        }
    }
    Ok(Header {
        encoding,
        elements,
        offset,
        header_bytes: bytes,
        header_lines: lines,
    })
}

/// For binary files: the body must be as large as the header implies (exactly, when no
/// element has list properties, give or take less than one vertex row of trailing bytes).
pub(super) fn check_size(path: &Path, h: &Header, len: u64) -> Result<(), IoError> {
    if h.encoding == PlyEncoding::Ascii {
        return Ok(());
    }
    let overflow = || IoError::format(path, "PLY element sizes overflow");
    let mut need = h.header_bytes;
    let mut exact = true;
    for e in &h.elements {
        exact &= e.fixed_row().is_some();
        let row = e.fixed_row().unwrap_or_else(|| e.min_row());
        need = e
            .count
            .checked_mul(row)
            .and_then(|b| b.checked_add(need))
            .ok_or_else(overflow)?;
    }
    let vcount = h
        .elements
        .iter()
        .find(|e| e.name == "vertex")
        .map_or(0, |e| e.count);
    if len < need {
        return Err(IoError::format(
            path,
            format!(
                "header declares {vcount} vertices needing at least {need} bytes but the file holds {len}"
            ),
        ));
    }
    let vrow = h
        .elements
        .iter()
        .find(|e| e.name == "vertex")
        .and_then(Element::fixed_row);
    if let (true, Some(vrow)) = (exact, vrow)
        && len - need >= vrow.max(1)
    {
        return Err(IoError::format(
            path,
            format!(
                "header declares {vcount} vertices ({need} bytes) but the file holds {len} bytes"
            ),
        ));
    }
    Ok(())
}
