//! Training images in memory: 8-bit RGBA packed into one `u32` per pixel, with the two
//! resampling operations the loader needs (bilinear lookup, area-averaging downscale).
//!
//! Packing is little-endian: R in the low byte, then G, B, A (so `bytemuck`-style casts of
//! `[u8; 4]` RGBA pixels and this layout agree on little-endian machines). Pixel (i, j) has its
//! centre at (i + 0.5, j + 0.5), the COLMAP convention of docs/splatting.md.

/// An RGBA8 image, row-major, one packed `u32` per pixel (R in the low byte).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PackedImage {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// `width * height` packed pixels, row-major.
    pub pixels: Vec<u32>,
}

/// Packs RGBA bytes into one `u32`, R in the low byte.
pub fn pack(rgba: [u8; 4]) -> u32 {
    u32::from_le_bytes(rgba)
}

/// Unpacks a `u32` into RGBA bytes.
pub fn unpack(p: u32) -> [u8; 4] {
    p.to_le_bytes()
}

impl PackedImage {
    /// A `width × height` image filled with `rgba`.
    pub fn filled(width: u32, height: u32, rgba: [u8; 4]) -> Self {
        PackedImage {
            width,
            height,
            pixels: vec![pack(rgba); width as usize * height as usize],
        }
    }

    /// From tightly packed RGBA bytes (4 per pixel); `None` when the length does not match.
    pub fn from_rgba8(width: u32, height: u32, bytes: &[u8]) -> Option<Self> {
        if bytes.len() != width as usize * height as usize * 4 {
            return None;
        }
        let pixels = bytes
            .chunks_exact(4)
            .map(|c| pack([c[0], c[1], c[2], c[3]]))
            .collect();
        Some(PackedImage {
            width,
            height,
            pixels,
        })
    }

    /// RGBA of pixel (column `x`, row `y`); panics outside the image.
    pub fn get(&self, x: u32, y: u32) -> [u8; 4] {
        unpack(self.pixels[y as usize * self.width as usize + x as usize])
    }

    /// Linear RGB in [0, 1] per pixel (alpha dropped), the rasteriser's image layout.
    pub fn to_rgb_f32(&self) -> Vec<[f32; 3]> {
        self.pixels
            .iter()
            .map(|&p| {
                let c = unpack(p);
                [
                    c[0] as f32 / 255.0,
                    c[1] as f32 / 255.0,
                    c[2] as f32 / 255.0,
                ]
            })
            .collect()
    }

    /// Bilinear sample at continuous pixel coordinates (`x`, `y`), pixel centres at i + 0.5,
    /// clamped to the edge within the image rectangle [0, width] × [0, height]; `None` outside.
    pub fn sample_bilinear(&self, x: f64, y: f64) -> Option<[f32; 4]> {
        let (w, h) = (self.width as f64, self.height as f64);
        if !(0.0..=w).contains(&x) || !(0.0..=h).contains(&y) || self.pixels.is_empty() {
            return None;
        }
        let fx = (x - 0.5).clamp(0.0, w - 1.0);
        let fy = (y - 0.5).clamp(0.0, h - 1.0);
        let (x0, y0) = (fx.floor() as u32, fy.floor() as u32);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (tx, ty) = ((fx - x0 as f64) as f32, (fy - y0 as f64) as f32);
        let (a, b, c, d) = (
            self.get(x0, y0),
            self.get(x1, y0),
            self.get(x0, y1),
            self.get(x1, y1),
        );
        Some(std::array::from_fn(|k| {
            let top = a[k] as f32 * (1.0 - tx) + b[k] as f32 * tx;
            let bottom = c[k] as f32 * (1.0 - tx) + d[k] as f32 * tx;
            top * (1.0 - ty) + bottom * ty
        }))
    }

    /// This image resized to `width × height` by area averaging: each output pixel is the mean
    /// of the input area it covers, fractional pixels weighted by their covered share.
    pub fn resize_area(&self, width: u32, height: u32) -> PackedImage {
        let (w_in, h_in) = (self.width as usize, self.height as usize);
        let (w_out, h_out) = (width.max(1) as usize, height.max(1) as usize);
        let wx = area_weights(w_in, w_out);
        let wy = area_weights(h_in, h_out);
        // Horizontal pass into f32 rows, then vertical pass.
        let mut rows = vec![[0f32; 4]; w_out * h_in];
        for y in 0..h_in {
            for (ox, taps) in wx.iter().enumerate() {
                let acc = &mut rows[y * w_out + ox];
                for &(ix, wgt) in taps {
                    let c = unpack(self.pixels[y * w_in + ix]);
                    for k in 0..4 {
                        acc[k] += c[k] as f32 * wgt;
                    }
                }
            }
        }
        let mut pixels = vec![0u32; w_out * h_out];
        for (oy, taps) in wy.iter().enumerate() {
            for ox in 0..w_out {
                let mut acc = [0f32; 4];
                for &(iy, wgt) in taps {
                    let r = rows[iy * w_out + ox];
                    for k in 0..4 {
                        acc[k] += r[k] * wgt;
                    }
                }
                pixels[oy * w_out + ox] = pack(acc.map(|v| v.round().clamp(0.0, 255.0) as u8));
            }
        }
        PackedImage {
            width: w_out as u32,
            height: h_out as u32,
            pixels,
        }
    }
}

/// For each output index, the input indices it covers with weights summing to 1.
fn area_weights(n_in: usize, n_out: usize) -> Vec<Vec<(usize, f32)>> {
    let ratio = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|o| {
            let (lo, hi) = (o as f64 * ratio, (o + 1) as f64 * ratio);
            let last = (hi.ceil() as usize).min(n_in);
            (lo.floor() as usize..last)
                .filter_map(|i| {
                    let cover = (hi.min(i as f64 + 1.0) - lo.max(i as f64)).max(0.0);
                    (cover > 0.0).then_some((i, (cover / ratio) as f32))
                })
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packing_puts_red_in_the_low_byte() {
        assert_eq!(pack([1, 2, 3, 4]), 0x0403_0201);
        assert_eq!(unpack(0x0403_0201), [1, 2, 3, 4]);
    }

    #[test]
    fn area_downscale_averages_blocks_and_keeps_the_mean() {
        // 4×2 image of columns 0, 100, 200, 40 → 2×1: (0+100)/2, (200+40)/2.
        let bytes: Vec<u8> = (0..2)
            .flat_map(|_| [0u8, 100, 200, 40])
            .flat_map(|v| [v, v, v, 255])
            .collect();
        let img = PackedImage::from_rgba8(4, 2, &bytes).expect("size matches");
        let small = img.resize_area(2, 1);
        assert_eq!(small.get(0, 0), [50, 50, 50, 255]);
        assert_eq!(small.get(1, 0), [120, 120, 120, 255]);
        // Fractional factor 3 → 2: weights 2/3, 1/3 | 1/3, 2/3.
        let third = img.resize_area(3, 2).resize_area(2, 2);
        assert_eq!(third.width, 2);
    }

    #[test]
    fn bilinear_sample_interpolates_between_pixel_centres() {
        let img = PackedImage::from_rgba8(2, 1, &[0, 0, 0, 255, 200, 100, 50, 255]).expect("size");
        let mid = img.sample_bilinear(1.0, 0.5).expect("inside");
        assert_eq!(mid, [100.0, 50.0, 25.0, 255.0]);
        assert_eq!(img.sample_bilinear(0.2, 0.5).expect("inside")[0], 0.0);
        assert!(img.sample_bilinear(2.5, 0.5).is_none());
    }
}
