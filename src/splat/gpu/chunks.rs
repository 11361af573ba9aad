//! Whole-Gaussian chunks of the per-Gaussian buffers (parameters, gradients, Adam moments,
//! densification statistics).
//!
//! Each per-Gaussian buffer is one `wgpu::Buffer` (up to the adapter's `max_buffer_size`), but a
//! kernel binds it as sub-ranges of at most `per_chunk` Gaussians, each within the adapter's
//! `max_storage_buffer_binding_size`, and is dispatched once per chunk. The chunk size is planned
//! for the widest per-Gaussian buffer, the 48-float (192-byte) SH block, and is a multiple of
//! `min_storage_buffer_offset_alignment / 4` Gaussians so that every sub-range offset is aligned
//! whatever the buffer's floats per Gaussian. On a real GPU (≥ 2 GiB bindings) a model of up to
//! ≈ 11M Gaussians is one chunk, i.e. one dispatch as before; on lavapipe (128 MiB) a chunk is
//! 699,008 Gaussians.
//!
//! Buffers read at random by Gaussian id (the projected records and the screen-space gradients,
//! read and written by the rasteriser through the sorted intersections) are bound as up to
//! [`SLOTS`] sub-ranges ("slots") of whole Gaussians ([`SlotPlan`]); the shader picks the slot
//! from the id (`shaders/slots.wgsl`). The kernels that run per Gaussian (projection, emission,
//! projection backward) bind them in the chunks above. The intersection arrays are split into
//! bands of tile rows, each within one binding (`renderer.rs`). On lavapipe (128 MiB bindings)
//! that allows 4 × 2,796,160 Gaussians and any number of intersections as long as one row of
//! 16-pixel tiles holds at most 33.5M.

use std::num::NonZeroU64;

use crate::splat::gpu::buffers::{bind_entries, params_from};
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::model::SH_FLOATS;

/// Floats per Gaussian of the widest per-Gaussian buffer (the SH block, its gradient and moments).
pub const WIDEST_FLOATS: u64 = SH_FLOATS as u64;

/// The bytes one chunk or slot binding may hold ([`GpuContext::chunk_binding_bytes`]), the
/// alignment unit in Gaussians (whatever a buffer's floats per Gaussian, every offset a multiple
/// of it is aligned), and how many whole units of Gaussians of `bytes_each` fit one binding.
fn per_binding(ctx: &GpuContext, bytes_each: u64) -> (u64, u64, u64) {
    let cap = ctx.chunk_binding_bytes();
    let unit = (ctx.offset_alignment / 4).max(1);
    (cap, unit, (cap / bytes_each) / unit * unit)
}

/// How `count` Gaussians split into chunks of `per_chunk` (the last one possibly shorter).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ChunkPlan {
    /// Number of Gaussians.
    pub count: u32,
    /// Gaussians per chunk (a multiple of the alignment unit).
    pub per_chunk: u32,
}

/// One chunk: first Gaussian and number of Gaussians.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Chunk {
    pub base: u32,
    pub len: u32,
}

impl ChunkPlan {
    /// Plans chunks of `count` Gaussians under [`GpuContext::chunk_binding_bytes`].
    pub fn new(ctx: &GpuContext, count: u32) -> Result<Self, GpuError> {
        let (cap, unit, per) = per_binding(ctx, WIDEST_FLOATS * 4);
        if per == 0 {
            return Err(GpuError::BufferTooLarge {
                what: "one aligned chunk of per-Gaussian SH coefficients",
                bytes: unit * WIDEST_FLOATS * 4,
                limit: cap,
            });
        }
        Ok(ChunkPlan {
            count,
            per_chunk: u32::try_from(per).unwrap_or(u32::MAX),
        })
    }

    /// Number of chunks (0 for an empty model).
    pub fn len(&self) -> u32 {
        self.count.div_ceil(self.per_chunk)
    }

    /// Whether there is no chunk (an empty model).
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The chunks in order.
    pub fn chunks(&self) -> impl Iterator<Item = Chunk> + '_ {
        (0..self.len()).map(move |c| {
            let base = c * self.per_chunk;
            Chunk {
                base,
                len: self.per_chunk.min(self.count - base),
            }
        })
    }
}

impl Chunk {
    /// The sub-range of `buffer` (`floats` f32 per Gaussian) holding this chunk.
    pub fn range<'a>(&self, buffer: &'a wgpu::Buffer, floats: u32) -> wgpu::BufferBinding<'a> {
        let per = floats as u64 * 4;
        wgpu::BufferBinding {
            buffer,
            offset: self.base as u64 * per,
            size: NonZeroU64::new(self.len as u64 * per),
        }
    }

    /// A parameter buffer `vec4<u32>(base, len, 0, 0)` that chunked kernels read as `chunk`.
    pub fn params(&self, ctx: &GpuContext) -> wgpu::Buffer {
        params_from(ctx, "chunk", &[self.base, self.len, 0, 0])
    }
}

/// Binds `bindings` in order to binding 0.. of a fresh bind group for `pipeline`'s group 0.
pub fn bind_ranges(
    ctx: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    bindings: &[wgpu::BufferBinding],
) -> wgpu::BindGroup {
    let indexed: Vec<(u32, wgpu::BufferBinding)> = bindings
        .iter()
        .enumerate()
        .map(|(i, b)| (i as u32, b.clone()))
        .collect();
    bind_entries(ctx, pipeline, &indexed)
}

/// Storage bindings through which the rasterisers reach the projected records, and as many for
/// the screen-space gradients (`shaders/slots.wgsl`): with the 9 other buffers of the backward
/// raster (with the depth gradient) that is 14 storage bindings per stage, within the 16 this
/// crate asks for.
pub const SLOTS: u32 = 4;

/// Bytes per Gaussian of the widest slotted buffer: the projected record, 3 × `vec4<f32>`.
pub const SLOT_BYTES: u64 = 48;

/// How `count` Gaussians split into at most [`SLOTS`] slots of `per_slot` for random access.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SlotPlan {
    /// Number of Gaussians.
    pub count: u32,
    /// Gaussians per slot (a multiple of the alignment unit, at least 1).
    pub per_slot: u32,
}

impl SlotPlan {
    /// Plans slots of `count` Gaussians under [`GpuContext::chunk_binding_bytes`]; fails with
    /// [`GpuError::BufferTooLarge`] when [`SLOTS`] bindings cannot hold the projected records.
    pub fn new(ctx: &GpuContext, count: u32) -> Result<Self, GpuError> {
        let (_, _, per) = per_binding(ctx, SLOT_BYTES);
        if per == 0 || count as u64 > per * SLOTS as u64 {
            return Err(GpuError::BufferTooLarge {
                what: "projected Gaussians (48 bytes each, read at random through 4 bindings)",
                bytes: count as u64 * SLOT_BYTES,
                limit: per * SLOTS as u64 * SLOT_BYTES,
            });
        }
        Ok(SlotPlan {
            count,
            per_slot: u32::try_from(per).unwrap_or(u32::MAX),
        })
    }

    /// Slots in use (0 for an empty model).
    pub fn used(&self) -> u32 {
        self.count.div_ceil(self.per_slot)
    }

    /// The [`SLOTS`] sub-ranges of `buffer` (`floats` f32 per Gaussian) in slot order; a slot
    /// past the model binds `dummy` (any small storage buffer, never read or written).
    pub fn bindings<'a>(
        &self,
        buffer: &'a wgpu::Buffer,
        floats: u32,
        dummy: &'a wgpu::Buffer,
    ) -> Vec<wgpu::BufferBinding<'a>> {
        (0..SLOTS)
            .map(|s| {
                let base = s as u64 * self.per_slot as u64;
                if base >= self.count as u64 {
                    return dummy.as_entire_buffer_binding();
                }
                let chunk = Chunk {
                    base: base as u32,
                    len: (self.count as u64 - base).min(self.per_slot as u64) as u32,
                };
                chunk.range(buffer, floats)
            })
            .collect()
    }
}
