//! A training photo in host memory: decoded (packed RGBA8, 4 bytes a pixel) or, when the
//! decoded photos of a run would take more host memory than it allows, compressed losslessly
//! and decoded each time it is used (uploaded to the GPU's photo cache, measured, sampled).
//!
//! The compression is PNG through the `image` crate, the codec Sylva already links, at its
//! fast setting (fdeflate) with the `Sub` filter. Measured on one core (2026-11-28, the
//! photos undecoded by `image` and re-encoded by this module):
//!
//! | photos | size of RGBA8 | encode | decode |
//! |---|---|---|---|
//! | generated `paper` plot, 1920×1080 | 42–52 % | 10–11 ms | 11–17 ms |
//! | real UAV (Brighton), 4000×2250 | 69 % | 63 ms | 68 ms |
//! | real phone (nerfpl_tree), 600×800 | 73 % | 3 ms | 3 ms |
//!
//! The adaptive and Paeth filters gained 1–4 points of size for 1.5× the decoding time, the
//! default deflate level 2 points for 40× the encoding time. A decode is one photo's upload,
//! against a step of tens of milliseconds at 1920×1080 on a GPU, and the trainer names the
//! next step's photo ahead ([`crate::splat::backend::Backend::prefetch`]), so the decode runs
//! while the GPU works. Lossless, so training sees exactly the pixels it would see decoded.

use std::borrow::Cow;

use image::ImageEncoder;

use super::packed_image::PackedImage;

/// Decoded photos may take this much host memory before a run keeps them compressed, MiB:
/// 4096 (Sylva's choice: a third of the 12 GB a stage may hold on a 24 GB machine; the
/// generated `stand` plot's 100 photos at 640×360 take 88 MiB, the paper's 857 at 1920×1080
/// 6.8 GiB).
pub const DEFAULT_HOST_PHOTO_MB: u64 = 4096;

/// A photo could not be compressed or decoded again.
#[derive(Debug, thiserror::Error)]
pub enum PhotoError {
    #[error("photo {width}×{height}: {what}: {source}")]
    Codec {
        width: u32,
        height: u32,
        what: &'static str,
        #[source]
        source: image::ImageError,
    },
    #[error("photo {width}×{height}: its compressed copy decodes to {got_w}×{got_h}")]
    Size {
        width: u32,
        height: u32,
        got_w: u32,
        got_h: u32,
    },
}

/// See the module documentation. `width` and `height` are the photo's size in pixels, whether
/// it is held decoded or compressed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Photo {
    pub width: u32,
    pub height: u32,
    store: Store,
}

#[derive(Debug, Clone, PartialEq, Eq)]
enum Store {
    Decoded(PackedImage),
    /// A PNG of the RGBA8 pixels.
    Png(Vec<u8>),
}

impl From<PackedImage> for Photo {
    fn from(image: PackedImage) -> Self {
        Photo {
            width: image.width,
            height: image.height,
            store: Store::Decoded(image),
        }
    }
}

impl Photo {
    /// The photo compressed (a no-op when it already is).
    pub fn compressed(self) -> Result<Photo, PhotoError> {
        let Store::Decoded(image) = &self.store else {
            return Ok(self);
        };
        let bytes: Vec<u8> = image
            .pixels
            .iter()
            .flat_map(|&p| super::packed_image::unpack(p))
            .collect();
        let mut png = Vec::new();
        image::codecs::png::PngEncoder::new_with_quality(
            &mut png,
            image::codecs::png::CompressionType::Fast,
            image::codecs::png::FilterType::Sub,
        )
        .write_image(
            &bytes,
            self.width,
            self.height,
            image::ExtendedColorType::Rgba8,
        )
        .map_err(|source| self.error("cannot compress", source))?;
        png.shrink_to_fit();
        Ok(Photo {
            width: self.width,
            height: self.height,
            store: Store::Png(png),
        })
    }

    /// True when the photo is held compressed.
    pub fn is_compressed(&self) -> bool {
        matches!(self.store, Store::Png(_))
    }

    /// Host memory the photo takes, bytes (its pixels or its PNG).
    pub fn host_bytes(&self) -> usize {
        match &self.store {
            Store::Decoded(image) => image.pixels.len() * 4,
            Store::Png(png) => png.len(),
        }
    }

    /// The decoded photo: borrowed when held decoded, decoded now when compressed.
    pub fn image(&self) -> Result<Cow<'_, PackedImage>, PhotoError> {
        match &self.store {
            Store::Decoded(image) => Ok(Cow::Borrowed(image)),
            Store::Png(png) => {
                let decoded = image::load_from_memory_with_format(png, image::ImageFormat::Png)
                    .map_err(|source| self.error("cannot decode its compressed copy", source))?
                    .into_rgba8();
                let (got_w, got_h) = decoded.dimensions();
                PackedImage::from_rgba8(got_w, got_h, decoded.as_raw())
                    .filter(|p| (p.width, p.height) == (self.width, self.height))
                    .map(Cow::Owned)
                    .ok_or(PhotoError::Size {
                        width: self.width,
                        height: self.height,
                        got_w,
                        got_h,
                    })
            }
        }
    }

    fn error(&self, what: &'static str, source: image::ImageError) -> PhotoError {
        PhotoError::Codec {
            width: self.width,
            height: self.height,
            what,
            source,
        }
    }
}

/// Whether decoded photos of `total_pixels` pixels in all exceed `limit_mb` MiB (4 bytes a
/// pixel), so that a run keeps them compressed.
pub fn keep_compressed(total_pixels: u64, limit_mb: u64) -> bool {
    total_pixels.saturating_mul(4) > limit_mb.saturating_mul(1 << 20)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::packed_image::pack;

    fn noisy(w: u32, h: u32) -> PackedImage {
        let mut img = PackedImage::filled(w, h, [0; 4]);
        let mut s = 12345u64;
        for (i, p) in img.pixels.iter_mut().enumerate() {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let r = (s >> 33) as u8;
            // A gradient with noise, and a transparent corner as undistortion leaves.
            let a = if i % w as usize == 0 { 0 } else { 255 };
            *p = pack([r, (i % 251) as u8, (i / w as usize) as u8, a]);
        }
        img
    }

    #[test]
    fn a_compressed_photo_decodes_to_the_same_pixels_in_less_memory() {
        let img = noisy(97, 61);
        let photo = Photo::from(img.clone());
        assert!(!photo.is_compressed());
        assert_eq!(photo.host_bytes(), 97 * 61 * 4);
        let small = photo.clone().compressed().expect("compress");
        assert!(small.is_compressed());
        assert_eq!((small.width, small.height), (97, 61));
        assert!(
            small.host_bytes() < photo.host_bytes(),
            "{}",
            small.host_bytes()
        );
        assert_eq!(small.image().expect("decode").as_ref(), &img);
        assert_eq!(photo.image().expect("borrow").as_ref(), &img);
        // Compressing again changes nothing.
        assert_eq!(small.clone().compressed().expect("again"), small);
    }

    #[test]
    fn photos_are_compressed_past_the_host_limit() {
        // The paper's 857 photos at 1920×1080 are 6.6 GiB decoded.
        let paper = 857 * 1920 * 1080;
        assert!(keep_compressed(paper, DEFAULT_HOST_PHOTO_MB));
        assert!(!keep_compressed(paper, 8192));
        // `stand`: 100 photos at 640×360.
        assert!(!keep_compressed(100 * 640 * 360, DEFAULT_HOST_PHOTO_MB));
        assert!(keep_compressed(1, 0));
    }
}
