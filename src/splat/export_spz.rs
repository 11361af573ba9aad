//! Niantic's SPZ format, version 2 (public description: github.com/nianticlabs/spz, README
//! "File Format"): a gzip stream holding a 16-byte little-endian header then one array per
//! attribute (structure of arrays), in this order:
//!
//! | array | bytes per Gaussian | encoding (our model → byte) |
//! |---|---|---|
//! | positions | 9 | x, y, z as 24-bit signed fixed point with `fractional_bits` fraction bits |
//! | alphas | 1 | round(sigmoid(opacity logit) · 255) |
//! | colours | 3 | round((dc · 0.15 + 0.5) · 255), the format's `COLOR_SCALE` 0.15 |
//! | scales | 3 | round((log-scale + 10) · 16): log-scales −10 … 5.94, step 1/16 |
//! | rotations | 3 | normalised quaternion with w ≥ 0; x, y, z as round(v · 127.5 + 127.5); w derived |
//! | SH | 3 · ((d+1)² − 1) | round(c · 128) + 128, to buckets of 8 (degree 1, 5 bits) or 16 (degrees 2–3, 4 bits) |
//!
//! Header: magic `0x5053474e` ("NGSP"), version 2, Gaussian count (u32), SH degree (u8),
//! fractional bits (u8), flags (u8; 0x1 = trained with anti-aliasing, never set here: this
//! trainer is not Mip-Splatting), reserved 0. The SH arrays are coefficient-major with the colour
//! channel innermost, as our model stores them, without the DC term (which is in the colours).
//!
//! Fractional bits: 12 (the reference writer's default, 0.24 mm steps, ±2048 m) unless a
//! coordinate needs fewer to fit 24 bits. Coordinates are written as they are (the model's
//! local metric frame, z up), i.e. the format's `UNSPECIFIED` coordinate system: no axis flip.

use std::io::{self, Read, Write};

use flate2::Compression;
use flate2::read::GzDecoder;
use flate2::write::GzEncoder;

use crate::splat::model::{Gaussians, SH_FLOATS, sigmoid};

/// "NGSP", little-endian.
pub const SPZ_MAGIC: u32 = 0x5053_474e;
/// The version this module writes and reads.
pub const SPZ_VERSION: u32 = 2;
/// Scale of the DC colour term (the format's `COLOR_SCALE`).
pub const COLOR_SCALE: f32 = 0.15;
/// Fractional bits of positions unless a coordinate is too large (reference default).
pub const DEFAULT_FRACTIONAL_BITS: u8 = 12;
/// SH quantisation buckets: 5 bits for degree 1, 4 bits above (reference defaults).
const SH1_BUCKET: i32 = 1 << (8 - 5);
const SH_REST_BUCKET: i32 = 1 << (8 - 4);
/// Largest magnitude of a 24-bit signed integer.
const I24_MAX: i32 = (1 << 23) - 1;
/// Largest Gaussian count a reader accepts (guards the allocation against a corrupt header).
const MAX_POINTS: u32 = 1 << 28;

/// Errors of [`read_spz`].
#[derive(Debug, thiserror::Error)]
pub enum SpzError {
    #[error("reading the SPZ failed: {0}")]
    Io(#[from] io::Error),
    #[error("not an SPZ file: {0}")]
    Format(String),
}

fn to_u8(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// SH coefficients per channel above the DC term at `degree`.
fn sh_dim(degree: u32) -> usize {
    ((degree + 1) * (degree + 1) - 1) as usize
}

/// Fraction bits so that every coordinate fits 24 bits (at most the default 12).
fn fractional_bits(g: &Gaussians) -> io::Result<u8> {
    let max = g
        .means
        .iter()
        .flatten()
        .fold(0.0f64, |m, v| m.max((*v as f64).abs()));
    if !max.is_finite() || max > I24_MAX as f64 {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("a Gaussian position of {max} m does not fit SPZ's 24-bit fixed point"),
        ));
    }
    let mut bits = DEFAULT_FRACTIONAL_BITS;
    while bits > 0 && (max * f64::from(1u32 << bits)).round() > I24_MAX as f64 {
        bits -= 1;
    }
    Ok(bits)
}

fn quantise_sh(c: f32, bucket: i32) -> u8 {
    let q = (c * 128.0).round() as i32 + 128;
    let q = (q + bucket / 2) / bucket * bucket;
    q.clamp(0, 255) as u8
}

/// Writes `g` as SPZ version 2 (gzip at the default level).
pub fn write_spz<W: Write>(out: W, g: &Gaussians) -> io::Result<()> {
    if !g.is_consistent() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "the model's parameter vectors differ in length",
        ));
    }
    let n = u32::try_from(g.len())
        .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "too many Gaussians"))?;
    let degree = g.sh_degree.min(3);
    let dim = sh_dim(degree);
    let bits = fractional_bits(g)?;
    let scale = f64::from(1u32 << bits);
    let len = g.len();
    let mut body = Vec::with_capacity(16 + len * (19 + 3 * dim));
    body.extend_from_slice(&SPZ_MAGIC.to_le_bytes());
    body.extend_from_slice(&SPZ_VERSION.to_le_bytes());
    body.extend_from_slice(&n.to_le_bytes());
    body.extend_from_slice(&[degree as u8, bits, 0, 0]);
    for m in &g.means {
        for &v in m {
            let fixed = ((v as f64) * scale)
                .round()
                .clamp(-(I24_MAX as f64), I24_MAX as f64);
            body.extend_from_slice(&(fixed as i32).to_le_bytes()[..3]);
        }
    }
    body.extend(g.opacity_logits.iter().map(|&o| to_u8(sigmoid(o) * 255.0)));
    for sh in &g.sh {
        body.extend((0..3).map(|c| to_u8((sh[c] * COLOR_SCALE + 0.5) * 255.0)));
    }
    for s in &g.log_scales {
        body.extend(s.iter().map(|&v| to_u8((v + 10.0) * 16.0)));
    }
    for q in &g.rotations {
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        let mut q = if norm > 0.0 && norm.is_finite() {
            q.map(|v| v / norm)
        } else {
            [1.0, 0.0, 0.0, 0.0]
        };
        if q[0] < 0.0 {
            q = q.map(|v| -v);
        }
        body.extend(q[1..].iter().map(|&v| to_u8(v * 127.5 + 127.5)));
    }
    for sh in &g.sh {
        for k in 0..dim {
            let bucket = if k < 3 { SH1_BUCKET } else { SH_REST_BUCKET };
            body.extend((0..3).map(|c| quantise_sh(sh[3 + 3 * k + c], bucket)));
        }
    }
    let mut gz = GzEncoder::new(out, Compression::default());
    gz.write_all(&body)?;
    gz.finish()?.flush()
}

/// Reads an SPZ version-2 file back into a model (`trunk_prob` 0). Alphas of 0 or 255 decode to
/// opacities of 0.5/255 and 1 − 0.5/255 so that the logits stay finite.
pub fn read_spz<R: Read>(input: R) -> Result<Gaussians, SpzError> {
    let mut bytes = Vec::new();
    GzDecoder::new(input).read_to_end(&mut bytes)?;
    let bad = |why: String| SpzError::Format(why);
    if bytes.len() < 16 {
        return Err(bad(format!(
            "{} bytes, shorter than the header",
            bytes.len()
        )));
    }
    let word = |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
    if word(0) != SPZ_MAGIC {
        return Err(bad(format!("magic {:#010x}", word(0))));
    }
    if word(4) != SPZ_VERSION {
        return Err(bad(format!(
            "version {} (this reader reads version {SPZ_VERSION})",
            word(4)
        )));
    }
    let n32 = word(8);
    let (degree, bits) = (u32::from(bytes[12]), bytes[13]);
    if n32 > MAX_POINTS || degree > 3 || bits > 23 {
        return Err(bad(format!(
            "header: {n32} Gaussians, SH degree {degree}, {bits} fractional bits"
        )));
    }
    let n = n32 as usize;
    let dim = sh_dim(degree);
    let want = 16 + n * (9 + 1 + 3 + 3 + 3 + 3 * dim);
    if bytes.len() != want {
        return Err(bad(format!(
            "{} bytes for {n} Gaussians at SH degree {degree}, {want} expected",
            bytes.len()
        )));
    }
    let mut at = 16;
    let mut take = |k: usize| {
        let s = &bytes[at..at + k];
        at += k;
        s
    };
    let scale = 1.0 / f64::from(1u32 << bits);
    let means: Vec<[f32; 3]> = take(9 * n)
        .chunks_exact(9)
        .map(|p| {
            std::array::from_fn(|a| {
                let b = &p[3 * a..3 * a + 3];
                // Sign-extend the 24-bit little-endian integer.
                let v = i32::from_le_bytes([b[0], b[1], b[2], 0]) << 8 >> 8;
                (v as f64 * scale) as f32
            })
        })
        .collect();
    let opacity_logits: Vec<f32> = take(n)
        .iter()
        .map(|&a| {
            let p = (a as f32 / 255.0).clamp(0.5 / 255.0, 1.0 - 0.5 / 255.0);
            (p / (1.0 - p)).ln()
        })
        .collect();
    let colours = take(3 * n).to_vec();
    let log_scales: Vec<[f32; 3]> = take(3 * n)
        .chunks_exact(3)
        .map(|s| std::array::from_fn(|a| s[a] as f32 / 16.0 - 10.0))
        .collect();
    let rotations: Vec<[f32; 4]> = take(3 * n)
        .chunks_exact(3)
        .map(|r| {
            let [x, y, z] = [0, 1, 2].map(|a| r[a] as f32 / 127.5 - 1.0);
            let w = (1.0 - (x * x + y * y + z * z)).max(0.0).sqrt();
            [w, x, y, z]
        })
        .collect();
    let rest = take(3 * dim * n);
    let sh: Vec<[f32; SH_FLOATS]> = (0..n)
        .map(|i| {
            let mut s = [0.0f32; SH_FLOATS];
            for c in 0..3 {
                s[c] = (colours[3 * i + c] as f32 / 255.0 - 0.5) / COLOR_SCALE;
            }
            for (k, &b) in rest[3 * dim * i..3 * dim * (i + 1)].iter().enumerate() {
                s[3 + k] = (b as f32 - 128.0) / 128.0;
            }
            s
        })
        .collect();
    Ok(Gaussians {
        means,
        log_scales,
        rotations,
        opacity_logits,
        sh,
        trunk_prob: vec![0.0; n],
        sh_degree: degree,
    })
}

#[cfg(test)]
#[path = "export_spz_tests.rs"]
mod tests;
