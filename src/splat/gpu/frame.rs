//! One rendered view on the GPU: every buffer the forward pass wrote that the backward pass or a
//! loss kernel needs.

use crate::splat::gpu::buffers::read_buffer;
use crate::splat::gpu::chunks::SlotPlan;
use crate::splat::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::params::RenderParams;

/// A band of whole tile rows with its own sorted intersection arrays (each within one storage
/// binding): one band per frame unless the frame's intersections exceed one binding.
pub struct Band {
    /// First tile row.
    pub row0: u32,
    /// Tile rows.
    pub rows: u32,
    /// Intersections of the band's tiles.
    pub count: u32,
    /// Sorted intersections: band-local tile id (row − `row0`) · tiles_x + column, depth bits,
    /// Gaussian id.
    pub keys_hi: wgpu::Buffer,
    pub keys_lo: wgpu::Buffer,
    pub values: wgpu::Buffer,
    /// `vec4<u32>(row0, row0 + rows, Gaussians per slot, count)`, `band` in the shaders.
    pub params: wgpu::Buffer,
}

/// Buffers of one forward render (kept for its backward pass).
pub struct Frame {
    /// The uniform parameters (with the intersection count filled in).
    pub params: RenderParams,
    pub params_buf: wgpu::Buffer,
    /// Per Gaussian, 3 × vec4: (mean2d px, depth m, radius px as u32 bits), (conic a, b, c,
    /// opacity), (r, g, b, camera depth m). All zero for culled Gaussians. Bound in chunks and
    /// `slots`.
    pub proj: wgpu::Buffer,
    /// How the rasterisers bind `proj` and the screen-space gradients (random access by id).
    pub slots: SlotPlan,
    /// Bound in place of projected-record slots past the model (16 bytes, never read).
    pub dummy: wgpu::Buffer,
    /// Exclusive prefix sum of the touched-tile counts, `count + 1` entries (last = total).
    pub offsets: wgpu::Buffer,
    /// The bands of tile rows, top to bottom, covering every row.
    pub bands: Vec<Band>,
    /// Per tile: first and one-past-last intersection in its band's arrays.
    pub ranges: wgpu::Buffer,
    /// The rendered image incl. background: `w·h·3` f32, interleaved RGB, row-major.
    pub image: wgpu::Buffer,
    /// Final transmittance per pixel, `w·h` f32.
    pub final_t: wgpu::Buffer,
    /// Per pixel: 1 + position of the last blended Gaussian in its tile's run (0 if none).
    /// Not the number blended: skipped Gaussians before it are counted too.
    pub n_contrib: wgpu::Buffer,
    /// Expected depth per pixel, Σ T α z (metres; the background adds nothing), `w·h` f32.
    pub depth: wgpu::Buffer,
    /// dL/d(`depth`) per pixel, `w·h` f32: zero when rendered; a depth loss writes it before
    /// the backward pass, which reads it.
    pub depth_grad: wgpu::Buffer,
    /// Number of Gaussians rendered.
    pub count: u32,
    /// Number of (Gaussian, tile) intersections.
    pub intersections: u32,
}

impl Frame {
    /// Image width and height, pixels.
    pub fn size(&self) -> (u32, u32) {
        (self.params.dims[0], self.params.dims[1])
    }

    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        let (w, h) = self.size();
        w as usize * h as usize
    }

    /// Reads the image back (blocking), row-major RGB.
    pub fn read_image(&self, ctx: &GpuContext) -> Result<Vec<[f32; 3]>, GpuError> {
        read_buffer(ctx, &self.image, self.pixels())
    }

    /// Reads the expected depth back (blocking), metres per pixel.
    pub fn read_depth(&self, ctx: &GpuContext) -> Result<Vec<f32>, GpuError> {
        read_buffer(ctx, &self.depth, self.pixels())
    }

    /// Reads the final transmittance back (blocking).
    pub fn read_final_t(&self, ctx: &GpuContext) -> Result<Vec<f32>, GpuError> {
        read_buffer(ctx, &self.final_t, self.pixels())
    }

    /// Reads the per-Gaussian screen records back (blocking): 3 × [f32; 4] per Gaussian.
    pub fn read_projected(&self, ctx: &GpuContext) -> Result<Vec<[[f32; 4]; 3]>, GpuError> {
        read_buffer(ctx, &self.proj, self.count as usize)
    }
}
