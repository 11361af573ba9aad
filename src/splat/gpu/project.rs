//! Projection and tile bookkeeping kernels: `project.wgsl` (per-Gaussian screen record and
//! touched-tile count) and `tiles.wgsl` (emit one sort key per touched tile; per-tile ranges;
//! intersections per tile row and per band).

use crate::splat::gpu::buffers::{bind, grid, pipeline};
use crate::splat::gpu::context::GpuContext;

const COMMON: &str = include_str!("../../../shaders/common.wgsl");

/// `common.wgsl` followed by `body`.
pub fn with_common(body: &str) -> String {
    format!("{COMMON}\n{body}")
}

/// Workgroups (folded onto x, y) for one thread per item, 256 threads per workgroup.
pub fn groups_for(items: u32) -> (u32, u32) {
    grid(items.div_ceil(256))
}

/// Records one compute pass of `pipeline` over `groups` with `buffers` bound in order.
pub fn dispatch(
    ctx: &GpuContext,
    enc: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::ComputePipeline,
    buffers: &[&wgpu::Buffer],
    groups: (u32, u32),
) {
    let bg = bind(ctx, pipeline, buffers);
    dispatch_group(enc, pipeline, &bg, groups);
}

/// Records one compute pass of `pipeline` over `groups` with bind group `bg`.
pub fn dispatch_group(
    enc: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::ComputePipeline,
    bg: &wgpu::BindGroup,
    groups: (u32, u32),
) {
    let mut pass = enc.begin_compute_pass(&Default::default());
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bg, &[]);
    pass.dispatch_workgroups(groups.0, groups.1, 1);
}

/// Projection, emit and range pipelines.
pub struct ProjectKernels {
    /// Per Gaussian: `proj` record (3 vec4) and touched-tile count.
    pub project: wgpu::ComputePipeline,
    /// Per Gaussian: one (tile, depth, id) triple per touched tile.
    pub emit: wgpu::ComputePipeline,
    /// Per sorted intersection: tile run boundaries.
    pub ranges: wgpu::ComputePipeline,
    /// Per Gaussian: add its intersections to each touched tile row.
    pub row_counts: wgpu::ComputePipeline,
    /// Per Gaussian: its intersections within one band of tile rows.
    pub band_counts: wgpu::ComputePipeline,
}

impl ProjectKernels {
    /// Compiles the kernels.
    pub fn new(ctx: &GpuContext) -> Self {
        let project = with_common(include_str!("../../../shaders/project.wgsl"));
        let tiles = with_common(include_str!("../../../shaders/tiles.wgsl"));
        ProjectKernels {
            project: pipeline(ctx, "project", &project, "main"),
            emit: pipeline(ctx, "emit", &tiles, "emit"),
            ranges: pipeline(ctx, "ranges", &tiles, "ranges_main"),
            row_counts: pipeline(ctx, "row counts", &tiles, "row_counts"),
            band_counts: pipeline(ctx, "band counts", &tiles, "band_counts"),
        }
    }
}
