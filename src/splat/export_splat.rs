//! The antimatter15 `.splat` format (the WebGL viewer's `convert.py`): 32 bytes per Gaussian,
//! no header, little-endian:
//!
//! | bytes | content |
//! |---|---|
//! | 0..12 | position, f32 × 3, metres |
//! | 12..24 | linear scale exp(s), f32 × 3, metres |
//! | 24..28 | RGBA u8: colour 0.5 + C0 · dc clamped to [0, 1], alpha sigmoid(opacity logit) |
//! | 28..32 | rotation u8 × 4: normalised (w, x, y, z) mapped q · 128 + 128, clamped |
//!
//! Splats are sorted by descending exp(s0 + s1 + s2) · opacity, as `convert.py`, so that viewers
//! streaming the file show the largest, most opaque first. View-dependent colour is lost.

use std::io::{self, Write};

use crate::splat::model::{Gaussians, SH_C0, sigmoid};

/// Bytes per splat.
pub const SPLAT_RECORD_BYTES: usize = 32;

/// One decoded `.splat` record.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatRecord {
    /// Centre, metres.
    pub position: [f32; 3],
    /// Axis standard deviations, metres.
    pub scale: [f32; 3],
    /// Colour and opacity, 0–255.
    pub rgba: [u8; 4],
    /// Quaternion (w, x, y, z) encoded as q · 128 + 128.
    pub rotation: [u8; 4],
}

impl SplatRecord {
    /// The rotation decoded back to [-1, 1] components (w, x, y, z).
    pub fn quaternion(&self) -> [f32; 4] {
        self.rotation.map(|v| (v as f32 - 128.0) / 128.0)
    }
}

fn to_u8(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// The `.splat` record of Gaussian `i`.
fn record(g: &Gaussians, i: usize) -> SplatRecord {
    let dc = &g.sh[i];
    let q = g.rotations[i];
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let q = if n > 0.0 && n.is_finite() {
        q.map(|v| v / n)
    } else {
        [1.0, 0.0, 0.0, 0.0]
    };
    SplatRecord {
        position: g.means[i],
        scale: g.log_scales[i].map(f32::exp),
        rgba: [
            to_u8((0.5 + SH_C0 * dc[0]).clamp(0.0, 1.0) * 255.0),
            to_u8((0.5 + SH_C0 * dc[1]).clamp(0.0, 1.0) * 255.0),
            to_u8((0.5 + SH_C0 * dc[2]).clamp(0.0, 1.0) * 255.0),
            to_u8(sigmoid(g.opacity_logits[i]) * 255.0),
        ],
        rotation: q.map(|v| to_u8(v * 128.0 + 128.0)),
    }
}

/// Writes `g` as `.splat` records, largest and most opaque first.
pub fn write_splat<W: Write>(out: W, g: &Gaussians) -> io::Result<()> {
    let mut out = io::BufWriter::new(out);
    let key = |i: usize| {
        let s = g.log_scales[i];
        -((s[0] + s[1] + s[2]).exp() * sigmoid(g.opacity_logits[i]))
    };
    let mut order: Vec<usize> = (0..g.len()).collect();
    order.sort_by(|&a, &b| key(a).total_cmp(&key(b)));
    for i in order {
        let r = record(g, i);
        for v in r.position.iter().chain(&r.scale) {
            out.write_all(&v.to_le_bytes())?;
        }
        out.write_all(&r.rgba)?;
        out.write_all(&r.rotation)?;
    }
    out.flush()
}

/// Why a `.splat` buffer could not be decoded.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SplatError {
    #[error("a .splat file is a whole number of 32-byte records; {0} bytes is not")]
    Truncated(usize),
}

/// Decodes a `.splat` buffer.
pub fn read_splat(bytes: &[u8]) -> Result<Vec<SplatRecord>, SplatError> {
    if !bytes.len().is_multiple_of(SPLAT_RECORD_BYTES) {
        return Err(SplatError::Truncated(bytes.len()));
    }
    let f = |b: &[u8], k: usize| {
        f32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]])
    };
    Ok(bytes
        .chunks_exact(SPLAT_RECORD_BYTES)
        .map(|b| SplatRecord {
            position: [f(b, 0), f(b, 1), f(b, 2)],
            scale: [f(b, 3), f(b, 4), f(b, 5)],
            rgba: [b[24], b[25], b[26], b[27]],
            rotation: [b[28], b[29], b[30], b[31]],
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::model::Gaussian;

    #[test]
    fn splat_records_read_back_sorted_by_size_times_opacity() {
        let mut g = Gaussians::default();
        g.push(Gaussian::isotropic(
            [1.0, 2.0, 3.0],
            0.01,
            [1.0, 0.0, 0.5],
            0.5,
        ));
        let mut big = Gaussian::isotropic([4.0, 5.0, 6.0], 0.1, [0.2, 0.4, 0.6], 0.9);
        big.rotation = [2.0, 0.0, 0.0, 2.0]; // unnormalised: 45° about z after normalising
        g.push(big);
        let mut bytes = Vec::new();
        write_splat(&mut bytes, &g).expect("write to memory");
        assert_eq!(bytes.len(), 2 * SPLAT_RECORD_BYTES);
        let r = read_splat(&bytes).expect("whole records");
        assert_eq!(r[0].position, [4.0, 5.0, 6.0], "largest first");
        assert!((r[0].scale[0] - 0.1).abs() < 1e-6);
        assert_eq!(r[0].rgba, [51, 102, 153, 230]);
        assert_eq!(r[0].rotation, [219, 128, 128, 219]);
        let q = r[0].quaternion();
        assert!((q[0] - std::f32::consts::FRAC_1_SQRT_2).abs() < 0.01);
        assert_eq!(r[1].rgba, [255, 0, 128, 128]);
        assert_eq!(r[1].rotation, [255, 128, 128, 128], "w = 1 clamps to 255");
        assert_eq!(read_splat(&bytes[..40]), Err(SplatError::Truncated(40)));
    }
}
