//! The training photos on the GPU (with their LiDAR depth maps when the depth loss has them):
//! each uploaded on first use and kept, or, when the memory plan says so
//! ([`crate::splat::plan`]), held in a fixed number of slots. A photo that is not on the GPU
//! takes the slot used longest ago, whose buffers are written in place, so a cache allocates
//! nothing after it fills. The host keeps every photo (`Dataset`), decoded or compressed
//! ([`crate::splat::photo`]); the trainer names the next step's photo while the current step
//! runs ([`crate::splat::backend::Backend::prefetch`]), so its decoding and upload happen
//! while the GPU works and are queued before the next step is recorded.

use std::collections::HashMap;

use crate::gpu::buffers::storage_from;
use crate::gpu::context::{GpuContext, GpuError};
use crate::splat::cameras::View;

/// One photo on the GPU.
pub struct Resident {
    /// Packed RGBA8, one word per pixel.
    pub photo: wgpu::Buffer,
    /// The view's LiDAR depth map and its count of pixels with a return.
    pub depth: Option<(wgpu::Buffer, usize)>,
    /// When it was last used (the cache's clock).
    used: u64,
}

/// See the module documentation.
#[derive(Default)]
pub struct PhotoCache {
    /// Photos held at once; `None`: all.
    slots: Option<usize>,
    entries: HashMap<String, Resident>,
    clock: u64,
    /// Photos written to the GPU, and requests met by a photo already there.
    pub uploads: u64,
    pub hits: u64,
}

/// Writes `data` into `buf` when it is large enough, or makes a new buffer.
fn write_or_make<T: bytemuck::Pod>(
    ctx: &GpuContext,
    label: &'static str,
    buf: Option<wgpu::Buffer>,
    data: &[T],
) -> Result<wgpu::Buffer, GpuError> {
    let bytes: &[u8] = bytemuck::cast_slice(data);
    match buf {
        Some(b) if !bytes.is_empty() && b.size() >= bytes.len() as u64 => {
            ctx.queue.write_buffer(&b, 0, bytes);
            Ok(b)
        }
        _ => storage_from(ctx, label, data),
    }
}

impl PhotoCache {
    /// Holds at most `slots` photos from now on (`None`: all; at least 1), dropping those
    /// used longest ago.
    pub fn set_slots(&mut self, slots: Option<usize>) {
        self.slots = slots.map(|s| s.max(1));
        if let Some(s) = self.slots {
            while self.entries.len() > s {
                if let Some(name) = self.oldest(None) {
                    self.entries.remove(&name);
                }
            }
        }
    }

    /// The photo used longest ago, other than `keep`.
    fn oldest(&self, keep: Option<&str>) -> Option<String> {
        self.entries
            .iter()
            .filter(|(n, _)| Some(n.as_str()) != keep)
            .min_by_key(|(_, r)| r.used)
            .map(|(n, _)| n.clone())
    }

    /// Puts `view`'s photo (and `depth`, its depth map with its count of returns) on the GPU
    /// unless it is there; in a full cache it takes the slot of the photo used longest ago
    /// other than `keep`.
    pub fn ensure(
        &mut self,
        ctx: &GpuContext,
        view: &View,
        depth: Option<(&[f32], usize)>,
        keep: Option<&str>,
    ) -> Result<(), GpuError> {
        self.clock += 1;
        if let Some(r) = self.entries.get_mut(&view.name) {
            r.used = self.clock;
            if r.depth.is_none()
                && let Some((map, valid)) = depth
            {
                r.depth = Some((storage_from(ctx, "LiDAR depth", map)?, valid));
            }
            self.hits += 1;
            return Ok(());
        }
        let victim = match self.slots {
            Some(s) if self.entries.len() >= s => self
                .oldest(keep)
                .and_then(|name| self.entries.remove(&name)),
            _ => None,
        };
        let (old_photo, old_depth) = match victim {
            Some(r) => (Some(r.photo), r.depth.map(|(b, _)| b)),
            None => (None, None),
        };
        // A photo held compressed on the host is decoded here, once per upload.
        let pixels = view
            .image
            .image()
            .map_err(|e| GpuError::Invalid(format!("{}: {e}", view.name)))?;
        let photo = write_or_make(ctx, "target image", old_photo, &pixels.pixels)?;
        let depth = match depth {
            Some((map, valid)) => Some((write_or_make(ctx, "LiDAR depth", old_depth, map)?, valid)),
            None => None,
        };
        self.uploads += 1;
        self.entries.insert(
            view.name.clone(),
            Resident {
                photo,
                depth,
                used: self.clock,
            },
        );
        Ok(())
    }

    /// The photo of `name` when it is on the GPU.
    pub fn get(&self, name: &str) -> Option<&Resident> {
        self.entries.get(name)
    }

    /// Forgets the depth maps (the depth targets changed).
    pub fn clear_depth(&mut self) {
        for r in self.entries.values_mut() {
            r.depth = None;
        }
    }
}
