//! The INRIA 3DGS PLY layout: binary little-endian, one `vertex` element with float properties
//! `x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3`, as written by the
//! reference trainer (`GaussianModel.save_ply`) and read by every splat viewer.
//!
//! Differences from our model layout (docs/splatting.md), converted here:
//! - `f_rest` is channel-major (all R rest coefficients, then G, then B), ours is
//!   coefficient-major (`sh[k * 3 + c]`);
//! - opacity is stored as the logit, scales as logs, rotation as (w, x, y, z) — as ours.
//!
//! The normals are written as zeros. The trunk probability is not part of the layout; it can be
//! appended as an extra `trunk_prob` property, which the reader picks up when present.

use std::io::{self, Read, Write};

use crate::splat::model::{Gaussians, MAX_SH_DEGREE, SH_COEFFS};

/// Rest (non-DC) SH coefficients per channel at degree 3.
const REST_PER_CHANNEL: usize = SH_COEFFS - 1;
/// Largest header accepted by the reader, bytes (a real header is about 1.5 KiB).
const MAX_HEADER: usize = 64 * 1024;

/// Property names of the INRIA layout, in file order; `trunk_prob` appended when asked.
pub fn ply_property_names(with_trunk_prob: bool) -> Vec<String> {
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    names.extend((0..3).map(|i| format!("f_dc_{i}")));
    names.extend((0..3 * REST_PER_CHANNEL).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    if with_trunk_prob {
        names.push("trunk_prob".into());
    }
    names
}

/// Writes `g` in the exact INRIA layout (all 45 `f_rest` whatever the active SH degree).
pub fn write_ply<W: Write>(out: W, g: &Gaussians) -> io::Result<()> {
    write_ply_with(out, g, false)
}

/// Writes `g` in the INRIA layout, with an extra trailing `trunk_prob` float property when
/// `with_trunk_prob` is set (viewers ignore unknown properties).
pub fn write_ply_with<W: Write>(out: W, g: &Gaussians, with_trunk_prob: bool) -> io::Result<()> {
    let mut out = io::BufWriter::new(out);
    let names = ply_property_names(with_trunk_prob);
    writeln!(
        out,
        "ply\nformat binary_little_endian 1.0\nelement vertex {}",
        g.len()
    )?;
    for n in &names {
        writeln!(out, "property float {n}")?;
    }
    writeln!(out, "end_header")?;
    let mut row = Vec::with_capacity(names.len());
    for i in 0..g.len() {
        row.clear();
        row.extend_from_slice(&g.means[i]);
        row.extend_from_slice(&[0.0; 3]);
        row.extend_from_slice(&g.sh[i][0..3]);
        for c in 0..3 {
            row.extend((1..SH_COEFFS).map(|k| g.sh[i][k * 3 + c]));
        }
        row.push(g.opacity_logits[i]);
        row.extend_from_slice(&g.log_scales[i]);
        row.extend_from_slice(&g.rotations[i]);
        if with_trunk_prob {
            row.push(g.trunk_prob.get(i).copied().unwrap_or(0.0));
        }
        for v in &row {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    out.flush()
}

/// Why a PLY file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    #[error("reading the PLY failed: {0}")]
    Io(#[from] io::Error),
    #[error("not a PLY file (no `ply` magic line)")]
    NotPly,
    #[error("PLY header has no `end_header` within {MAX_HEADER} bytes")]
    UnterminatedHeader,
    #[error("PLY format {0:?} is not supported; export as binary_little_endian 1.0")]
    UnsupportedFormat(String),
    #[error("PLY header line {line:?} is not understood: {why}")]
    BadHeader { line: String, why: &'static str },
    #[error("PLY has no `vertex` element")]
    NoVertexElement,
    #[error("PLY vertex element lacks property {0:?}; is this a 3DGS (INRIA layout) file?")]
    MissingProperty(String),
    #[error("PLY has {0} f_rest properties; expected 0, 9, 24 or 45 (SH degree 0–3)")]
    BadShRestCount(usize),
    #[error("PLY is truncated: {vertices} vertices need {needed} bytes of data, found {found}")]
    Truncated {
        vertices: usize,
        needed: usize,
        found: usize,
    },
}

fn type_size(t: &str) -> Option<usize> {
    Some(match t {
        "char" | "uchar" | "int8" | "uint8" => 1,
        "short" | "ushort" | "int16" | "uint16" => 2,
        "int" | "uint" | "int32" | "uint32" | "float" | "float32" => 4,
        "double" | "float64" => 8,
        _ => return None,
    })
}

/// Reads a PLY written in the INRIA layout (any property order; `float` or `double` values;
/// `f_rest` of any SH degree; optional `trunk_prob`). The active SH degree is the file's.
pub fn read_ply<R: Read>(mut input: R) -> Result<Gaussians, PlyError> {
    let mut bytes = Vec::new();
    input.read_to_end(&mut bytes)?;
    let end = find_end_header(&bytes)?;
    let header = String::from_utf8_lossy(&bytes[..end]);
    let mut lines = header.lines().map(|l| l.trim_end_matches('\r').trim());
    if lines.next() != Some("ply") {
        return Err(PlyError::NotPly);
    }
    let bad = |line: &str, why| PlyError::BadHeader {
        line: line.to_string(),
        why,
    };
    // (name, type) of the vertex properties; vertex count; bytes of elements before `vertex`.
    let (mut props, mut count, mut in_vertex, mut seen_vertex) = (Vec::new(), None, false, false);
    for line in lines {
        let f: Vec<&str> = line.split_whitespace().collect();
        match f.as_slice() {
            ["format", fmt, ..] if *fmt != "binary_little_endian" => {
                return Err(PlyError::UnsupportedFormat(fmt.to_string()));
            }
            ["format", ..] | ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, n] => {
                if seen_vertex {
                    break; // later elements are not needed
                }
                if *name != "vertex" {
                    return Err(bad(line, "elements before `vertex` are not supported"));
                }
                count = Some(
                    n.parse::<usize>()
                        .map_err(|_| bad(line, "vertex count is not a number"))?,
                );
                (in_vertex, seen_vertex) = (true, true);
            }
            ["property", "list", ..] => return Err(bad(line, "list properties are not supported")),
            ["property", ty, name] if in_vertex => {
                let size = type_size(ty).ok_or_else(|| bad(line, "unknown property type"))?;
                props.push((name.to_string(), ty.to_string(), size));
            }
            ["end_header"] => break,
            _ => return Err(bad(line, "unexpected line")),
        }
    }
    let n = count.ok_or(PlyError::NoVertexElement)?;
    let stride: usize = props.iter().map(|p| p.2).sum();
    let data = &bytes[end..];
    let needed = n.saturating_mul(stride);
    if data.len() < needed {
        return Err(PlyError::Truncated {
            vertices: n,
            needed,
            found: data.len(),
        });
    }
    let offset = |name: &str| -> Result<(usize, &str), PlyError> {
        let mut off = 0;
        for (pn, ty, size) in &props {
            if pn == name {
                return Ok((off, ty.as_str()));
            }
            off += size;
        }
        Err(PlyError::MissingProperty(name.to_string()))
    };
    let n_rest = props.iter().filter(|p| p.0.starts_with("f_rest_")).count();
    let degree = (0..=MAX_SH_DEGREE).find(|&d| ((d + 1) * (d + 1) - 1) as usize * 3 == n_rest);
    let degree = degree.ok_or(PlyError::BadShRestCount(n_rest))?;
    let rest_per = n_rest / 3;
    let col = |name: &str| -> Result<Vec<f32>, PlyError> {
        let (off, ty) = offset(name)?;
        Ok((0..n)
            .map(|i| read_value(&data[i * stride + off..], ty))
            .collect())
    };
    let cols = |names: &[String]| names.iter().map(|s| col(s)).collect::<Result<Vec<_>, _>>();
    let names = |pre: &str, k: usize| (0..k).map(|i| format!("{pre}{i}")).collect::<Vec<_>>();
    let xyz = cols(&["x", "y", "z"].map(String::from))?;
    let dc = cols(&names("f_dc_", 3))?;
    let rest = cols(&names("f_rest_", n_rest))?;
    let opacity = col("opacity")?;
    let scale = cols(&names("scale_", 3))?;
    let rot = cols(&names("rot_", 4))?;
    let trunk = col("trunk_prob").ok();
    let mut g = Gaussians {
        sh_degree: degree,
        ..Default::default()
    };
    for i in 0..n {
        let mut sh = [0.0; crate::splat::model::SH_FLOATS];
        for c in 0..3 {
            sh[c] = dc[c][i];
            for k in 1..=rest_per {
                sh[k * 3 + c] = rest[c * rest_per + k - 1][i];
            }
        }
        g.means.push([xyz[0][i], xyz[1][i], xyz[2][i]]);
        g.log_scales.push([scale[0][i], scale[1][i], scale[2][i]]);
        g.rotations
            .push([rot[0][i], rot[1][i], rot[2][i], rot[3][i]]);
        g.opacity_logits.push(opacity[i]);
        g.sh.push(sh);
        g.trunk_prob.push(trunk.as_ref().map_or(0.0, |t| t[i]));
    }
    Ok(g)
}

/// Byte offset just past the `end_header` line.
fn find_end_header(bytes: &[u8]) -> Result<usize, PlyError> {
    if !bytes.starts_with(b"ply") {
        return Err(PlyError::NotPly);
    }
    let marker = b"end_header";
    let limit = bytes.len().min(MAX_HEADER);
    let at = bytes[..limit]
        .windows(marker.len())
        .position(|w| w == marker)
        .ok_or(PlyError::UnterminatedHeader)?;
    let nl = bytes[at..]
        .iter()
        .position(|&b| b == b'\n')
        .ok_or(PlyError::UnterminatedHeader)?;
    Ok(at + nl + 1)
}

fn read_value(b: &[u8], ty: &str) -> f32 {
    let a = |k: usize| -> [u8; 8] { std::array::from_fn(|i| if i < k { b[i] } else { 0 }) };
    match ty {
        "double" | "float64" => f64::from_le_bytes(a(8)) as f32,
        "char" | "int8" => b[0] as i8 as f32,
        "uchar" | "uint8" => b[0] as f32,
        "short" | "int16" => i16::from_le_bytes([b[0], b[1]]) as f32,
        "ushort" | "uint16" => u16::from_le_bytes([b[0], b[1]]) as f32,
        "int" | "int32" => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
        "uint" | "uint32" => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
        _ => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
    }
}

#[cfg(test)]
#[path = "export_tests.rs"]
mod tests;
