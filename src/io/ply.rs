//! PLY point clouds: ascii, binary_little_endian and binary_big_endian.
//!
//! The `vertex` element must have scalar `x`, `y`, `z` (any numeric type; metres). Optional
//! `red`/`green`/`blue` (uchar, or ushort scaled down by 257 when above 255) and
//! `intensity`/`scalar_intensity` (any numeric type, rounded and clamped to 0..=65535) are
//! kept; other properties (including list properties) and other elements (faces, ...) are
//! skipped. A `comment sylva_offset X Y Z` header line gives the local origin of the file:
//! vertex coordinates are then relative to it, so a write/read round trip keeps the offset.
//! ASCII files are read one element row per line.

mod header;

use std::fs::File;
use std::io::{BufRead, BufWriter, Read, Write};
use std::path::Path;

use glam::DVec3;
use serde::Serialize;

use super::pointcloud::{CloudBuilder, CloudFormat, PointCloud, colors_to_u8};
use super::{IoError, PROGRESS_STEP, check_cancel, file_len, open_buffered};
use crate::progress::Progress;
use header::{Element, Header, Scalar, check_size, parse_header};

/// A named per-point `f32` field written (and read back) as a PLY vertex property.
#[derive(Debug, Clone, PartialEq)]
pub struct ScalarField {
    pub name: String,
    pub values: Vec<f32>,
}

/// Encoding of a PLY body.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PlyEncoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

/// Header facts of a PLY file.
#[derive(Debug, Clone, Serialize)]
pub struct PlyInfo {
    pub encoding: PlyEncoding,
    /// Declared number of vertices.
    pub vertex_count: u64,
    /// Vertex properties as "type name" (lists as "list count_type item_type name").
    pub properties: Vec<String>,
    /// Every element as (name, declared count), in file order.
    pub elements: Vec<(String, u64)>,
    pub has_color: bool,
    /// The local origin from a `comment sylva_offset X Y Z` line (metres).
    pub sylva_offset: Option<[f64; 3]>,
}

/// Reads only the PLY header and checks it against the file size.
pub fn inspect_ply(path: &Path) -> Result<PlyInfo, IoError> {
    let len = file_len(path)?;
    let mut r = open_buffered(path)?;
    let h = parse_header(path, &mut r)?;
    check_size(path, &h, len)?;
    if h.encoding == PlyEncoding::Ascii {
        check_ascii_rows(path, &h, &mut r)?;
    }
    let vertex = h.elements.iter().find(|e| e.name == "vertex");
    let has = |n: &str| vertex.is_some_and(|v| v.props.iter().any(|p| p.name == n));
    Ok(PlyInfo {
        encoding: h.encoding,
        vertex_count: vertex.map_or(0, |v| v.count),
        properties: vertex.map_or_else(Vec::new, |v| {
            v.props.iter().map(|p| p.text.clone()).collect()
        }),
        elements: h
            .elements
            .iter()
            .map(|e| (e.name.clone(), e.count))
            .collect(),
        has_color: has("red") && has("green") && has("blue"),
        sylva_offset: h.offset.map(|o| o.to_array()),
    })
}

/// An ASCII body has one row per element instance: counts the non-blank rows after the header
/// (a streaming pass, about as fast as the disk) and refuses a file with fewer than declared.
fn check_ascii_rows(path: &Path, h: &Header, r: &mut impl std::io::BufRead) -> Result<(), IoError> {
    let declared: u64 = h.elements.iter().map(|e| e.count).sum();
    let mut rows = 0u64;
    let mut line = Vec::new();
    loop {
        line.clear();
        let n = r
            .read_until(b'\n', &mut line)
            .map_err(|e| IoError::io(path, e))?;
        if n == 0 || rows >= declared {
            break;
        }
        if line.iter().any(|b| !b.is_ascii_whitespace()) {
            rows += 1;
        }
    }
    if rows < declared {
        let vcount = h
            .elements
            .iter()
            .find(|e| e.name == "vertex")
            .map_or(0, |e| e.count);
        return Err(IoError::format(
            path,
            format!(
                "header declares {vcount} vertices ({declared} rows in all) but the file holds {rows} rows"
            ),
        ));
    }
    Ok(())
}

/// Reads a PLY point cloud (see the module documentation).
pub fn read_ply(path: &Path, progress: &dyn Progress) -> Result<PointCloud, IoError> {
    read_ply_impl(path, false, progress).map(|(c, _)| c)
}

/// Reads a PLY point cloud and every other scalar vertex property as an `f32` field.
pub fn read_ply_with_fields(
    path: &Path,
    progress: &dyn Progress,
) -> Result<(PointCloud, Vec<ScalarField>), IoError> {
    read_ply_impl(path, true, progress)
}

#[derive(Clone, Copy, PartialEq)]
enum Role {
    Axis(usize),
    Color(usize),
    Intensity,
    Extra(usize),
    Skip,
}

fn read_ply_impl(
    path: &Path,
    want_extra: bool,
    progress: &dyn Progress,
) -> Result<(PointCloud, Vec<ScalarField>), IoError> {
    let len = file_len(path)?;
    let mut r = open_buffered(path)?;
    let h = parse_header(path, &mut r)?;
    check_size(path, &h, len)?;
    let big = h.encoding == PlyEncoding::BinaryBigEndian;
    let mut line_no = h.header_lines;
    let mut line = String::new();
    for el in &h.elements {
        if el.name != "vertex" {
            skip_element(path, &h, el, &mut r, &mut line_no, &mut line)?;
            continue;
        }
        let has = |n: &str| el.props.iter().any(|p| p.name == n && p.list.is_none());
        let with_color = has("red") && has("green") && has("blue");
        let mut extra: Vec<ScalarField> = Vec::new();
        let roles: Vec<Role> = el
            .props
            .iter()
            .map(|p| match (p.list, p.name.as_str()) {
                (Some(_), _) => Role::Skip,
                (None, "x") => Role::Axis(0),
                (None, "y") => Role::Axis(1),
                (None, "z") => Role::Axis(2),
                (None, "red") if with_color => Role::Color(0),
                (None, "green") if with_color => Role::Color(1),
                (None, "blue") if with_color => Role::Color(2),
                (None, "intensity" | "scalar_intensity") => Role::Intensity,
                (None, name) if want_extra => {
                    extra.push(ScalarField {
                        name: name.to_string(),
                        values: Vec::new(),
                    });
                    Role::Extra(extra.len() - 1)
                }
                _ => Role::Skip,
            })
            .collect();
        let has_intensity = roles.contains(&Role::Intensity);
        // ASCII counts are unchecked: preallocate no more than the file could hold (6 bytes
        // per vertex at least).
        let cap_points = el.count.min(len / 6);
        let mut cloud = match h.offset {
            Some(o) => CloudBuilder::with_offset(path, o, cap_points),
            None => CloudBuilder::new(path, None, cap_points),
        };
        let cap = cap_points.min(1 << 24) as usize;
        let mut colors: Vec<[u16; 3]> = Vec::with_capacity(if with_color { cap } else { 0 });
        let mut intensity: Vec<u16> = Vec::with_capacity(if has_intensity { cap } else { 0 });
        let mut values = vec![0f64; el.props.len()];
        let mut raw = Vec::new();
        for i in 0..el.count {
            if i % PROGRESS_STEP as u64 == 0 {
                check_cancel(progress)?;
                progress.set(i as f64 / el.count as f64);
            }
            if h.encoding == PlyEncoding::Ascii {
                let toks = next_line(path, &mut r, &mut line_no, &mut line)?;
                let mut t = toks.split_whitespace();
                for (k, p) in el.props.iter().enumerate() {
                    let mut num = || -> Result<f64, IoError> {
                        t.next().and_then(|s| s.parse::<f64>().ok()).ok_or_else(|| {
                            IoError::format(
                                path,
                                format!("line {line_no}: vertex {i} is malformed"),
                            )
                        })
                    };
                    if p.list.is_some() {
                        let n = num()? as u64;
                        for _ in 0..n {
                            num()?;
                        }
                    } else {
                        values[k] = num()?;
                    }
                }
            } else {
                for (k, p) in el.props.iter().enumerate() {
                    if let Some(ct) = p.list {
                        let n = read_value(path, &mut r, ct, big, &mut raw)? as u64;
                        skip_bytes(path, &mut r, n * p.ty.size() as u64)?;
                    } else {
                        values[k] = read_value(path, &mut r, p.ty, big, &mut raw)?;
                    }
                }
            }
            let (mut xyz, mut rgb, mut inten) = ([0f64; 3], [0u16; 3], 0u16);
            for (k, role) in roles.iter().enumerate() {
                match *role {
                    Role::Axis(a) => xyz[a] = values[k],
                    Role::Color(c) => rgb[c] = values[k].round().clamp(0.0, 65535.0) as u16,
                    Role::Intensity => inten = values[k].round().clamp(0.0, 65535.0) as u16,
                    Role::Extra(f) => extra[f].values.push(values[k] as f32),
                    Role::Skip => {}
                }
            }
            if h.offset.is_some() {
                cloud.push_local(DVec3::from_array(xyz).as_vec3())?;
            } else {
                cloud.push(DVec3::from_array(xyz))?;
            }
            if with_color {
                colors.push(rgb);
            }
            if has_intensity {
                intensity.push(inten);
            }
        }
        progress.set(1.0);
        let (offset, positions) = cloud.finish();
        let cloud = PointCloud {
            offset,
            positions,
            colors: with_color.then(|| colors_to_u8(&colors)),
            intensity: has_intensity.then_some(intensity),
            format: CloudFormat::Ply,
        };
        return Ok((cloud, extra));
    }
    Err(IoError::format(path, "PLY has no vertex element"))
}

fn next_line<'a>(
    path: &Path,
    r: &mut impl BufRead,
    line_no: &mut u64,
    line: &'a mut String,
) -> Result<&'a str, IoError> {
    loop {
        line.clear();
        let n = r
            .read_line(line)
            .map_err(|e| IoError::read(path, e, "PLY body"))?;
        *line_no += 1;
        if n == 0 {
            return Err(IoError::format(
                path,
                format!("file ends at line {line_no}, before all declared rows"),
            ));
        }
        if !line.trim().is_empty() {
            return Ok(line.as_str());
        }
    }
}

fn read_value(
    path: &Path,
    r: &mut impl Read,
    ty: Scalar,
    big: bool,
    raw: &mut Vec<u8>,
) -> Result<f64, IoError> {
    raw.resize(ty.size(), 0);
    r.read_exact(raw)
        .map_err(|e| IoError::read(path, e, "PLY body"))?;
    Ok(ty.decode(raw, big))
}

fn skip_bytes(path: &Path, r: &mut impl Read, n: u64) -> Result<(), IoError> {
    let got = std::io::copy(&mut r.take(n), &mut std::io::sink())
        .map_err(|e| IoError::read(path, e, "PLY body"))?;
    if got != n {
        return Err(IoError::format(path, "file is truncated (PLY body)"));
    }
    Ok(())
}

fn skip_element(
    path: &Path,
    h: &Header,
    el: &Element,
    r: &mut impl BufRead,
    line_no: &mut u64,
    line: &mut String,
) -> Result<(), IoError> {
    let big = h.encoding == PlyEncoding::BinaryBigEndian;
    if h.encoding == PlyEncoding::Ascii {
        for _ in 0..el.count {
            next_line(path, r, line_no, line)?;
        }
    } else if let Some(row) = el.fixed_row() {
        let n = el
            .count
            .checked_mul(row)
            .ok_or_else(|| IoError::format(path, "element too large"))?;
        skip_bytes(path, r, n)?;
    } else {
        let mut raw = Vec::new();
        for _ in 0..el.count {
            for p in &el.props {
                let n = match p.list {
                    Some(ct) => read_value(path, r, ct, big, &mut raw)? as u64 * p.ty.size() as u64,
                    None => p.ty.size() as u64,
                };
                skip_bytes(path, r, n)?;
            }
        }
    }
    Ok(())
}

const RESERVED: [&str; 7] = ["x", "y", "z", "red", "green", "blue", "intensity"];

/// Writes a binary little-endian PLY: float x, y, z relative to `cloud.offset` (recorded in a
/// `comment sylva_offset X Y Z` line), uchar red/green/blue when the cloud has colour, ushort
/// intensity when it has intensity, then one float property per `extra` field.
pub fn write_ply(path: &Path, cloud: &PointCloud, extra: &[ScalarField]) -> Result<(), IoError> {
    for (i, f) in extra.iter().enumerate() {
        let valid = !f.name.is_empty()
            && f.name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !valid
            || RESERVED.contains(&f.name.as_str())
            || extra[..i].iter().any(|g| g.name == f.name)
        {
            return Err(IoError::format(
                path,
                format!("invalid scalar field name '{}'", f.name),
            ));
        }
        if f.values.len() != cloud.len() {
            return Err(IoError::format(
                path,
                format!(
                    "scalar field '{}' has {} values for {} points",
                    f.name,
                    f.values.len(),
                    cloud.len()
                ),
            ));
        }
    }
    let colors = cloud.colors.as_ref().filter(|c| c.len() == cloud.len());
    let intensity = cloud.intensity.as_ref().filter(|c| c.len() == cloud.len());
    let mut head = String::from("ply\nformat binary_little_endian 1.0\ncomment written by sylva\n");
    let o = cloud.offset;
    head += &format!("comment sylva_offset {} {} {}\n", o.x, o.y, o.z);
    head += &format!("element vertex {}\n", cloud.len());
    head += "property float x\nproperty float y\nproperty float z\n";
    if colors.is_some() {
        head += "property uchar red\nproperty uchar green\nproperty uchar blue\n";
    }
    if intensity.is_some() {
        head += "property ushort intensity\n";
    }
    for f in extra {
        head += &format!("property float {}\n", f.name);
    }
    head += "end_header\n";
    let io = |e| IoError::io(path, e);
    let mut w = BufWriter::new(File::create(path).map_err(io)?);
    w.write_all(head.as_bytes()).map_err(io)?;
    let mut row = Vec::with_capacity(64);
    for (i, p) in cloud.positions.iter().enumerate() {
        row.clear();
        for v in p.to_array() {
            row.extend_from_slice(&v.to_le_bytes());
        }
        if let Some(c) = colors {
            row.extend_from_slice(&c[i]);
        }
        if let Some(t) = intensity {
            row.extend_from_slice(&t[i].to_le_bytes());
        }
        for f in extra {
            row.extend_from_slice(&f.values[i].to_le_bytes());
        }
        w.write_all(&row).map_err(io)?;
    }
    w.flush().map_err(io)
}

#[cfg(test)]
mod tests;
