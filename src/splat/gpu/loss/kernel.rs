//! Pipelines, scratch buffers and command encoding of the fused loss.

use crate::gpu::buffers::wgsl_struct;
use crate::splat::gpu::loss::{LossError, shader_header};
use std::sync::Mutex;
use wgpu::util::DeviceExt;

/// Size of the `loss_out` buffer, bytes: `[loss, l1, ssim, 0]` as f32.
pub const LOSS_OUT_BYTES: u64 = 16;

const COMMON: &str = include_str!("../../../../shaders/loss/common.wgsl");
/// The workgroup reduction of the passes that sum partials (`workgroup_sum`).
const SUM: &str = include_str!("../../../../shaders/loss/workgroup_sum.wgsl");
/// Each pass: label, snippet it needs besides [`COMMON`] (or none), body.
const PASSES: [(&str, &str, &str); 5] = [
    (
        "loss blur stats",
        "",
        include_str!("../../../../shaders/loss/blur_stats.wgsl"),
    ),
    (
        "loss ssim map",
        SUM,
        include_str!("../../../../shaders/loss/ssim_map.wgsl"),
    ),
    (
        "loss blur grad",
        "",
        include_str!("../../../../shaders/loss/blur_grad.wgsl"),
    ),
    (
        "loss grad",
        "",
        include_str!("../../../../shaders/loss/grad.wgsl"),
    ),
    (
        "loss finalize",
        SUM,
        include_str!("../../../../shaders/loss/finalize.wgsl"),
    ),
];
/// Workgroup edge of the per-pixel passes.
const TILE: u32 = 16;

wgsl_struct! {
    /// The parameter buffer of every pass (`common.wgsl`).
    struct Params {
        width: u32,
        height: u32,
        /// Number of (l1, ssim) partial-sum pairs written by the SSIM pass.
        n_partials: u32,
        _pad: u32,
    }
}

/// Intermediate buffers for one image size.
struct Scratch {
    size: (u32, u32),
    stats_h: wgpu::Buffer,
    dmaps: wgpu::Buffer,
    dmaps_h: wgpu::Buffer,
    partials: wgpu::Buffer,
}

/// The fused loss: create once per device, then [`LossKernel::encode`] once per training step.
pub struct LossKernel {
    pipelines: Vec<wgpu::ComputePipeline>,
    scratch: Mutex<Option<Scratch>>,
}

impl LossKernel {
    /// Compiles the five passes on `device`.
    pub fn new(device: &wgpu::Device) -> Self {
        let header = shader_header();
        let pipelines = PASSES
            .iter()
            .map(|(label, snippet, body)| {
                let source = format!("{header}\n{}\n{COMMON}\n{snippet}\n{body}", Params::wgsl());
                let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                    label: Some(label),
                    source: wgpu::ShaderSource::Wgsl(source.into()),
                });
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(label),
                    layout: None,
                    module: &module,
                    entry_point: Some("main"),
                    compilation_options: Default::default(),
                    cache: None,
                })
            })
            .collect();
        LossKernel {
            pipelines,
            scratch: Mutex::new(None),
        }
    }

    /// Records the loss of `rendered` (f32 RGB interleaved, `width·height·3`, STORAGE) against
    /// `target` (one RGBA8 `u32` per pixel, R in the low byte, STORAGE) into `encoder`: writes
    /// dL/drendered to `grad_out` (f32, `width·height·3`, STORAGE) and `[loss, l1, ssim, 0]`
    /// (f32) to the first [`LOSS_OUT_BYTES`] of `loss_out` (STORAGE; add COPY_SRC to read it).
    /// Scratch buffers are kept for the last image size.
    #[allow(clippy::too_many_arguments)]
    pub fn encode(
        &self,
        device: &wgpu::Device,
        encoder: &mut wgpu::CommandEncoder,
        rendered: &wgpu::Buffer,
        target: &wgpu::Buffer,
        grad_out: &wgpu::Buffer,
        loss_out: &wgpu::Buffer,
        width: u32,
        height: u32,
    ) -> Result<(), LossError> {
        if width == 0 || height == 0 {
            return Err(LossError::EmptyImage);
        }
        let pixels = u64::from(width) * u64::from(height);
        for (what, buf, needed) in [
            ("rendered", rendered, pixels * 12),
            ("target", target, pixels * 4),
            ("grad_out", grad_out, pixels * 12),
            ("loss_out", loss_out, LOSS_OUT_BYTES),
        ] {
            if buf.size() < needed {
                return Err(LossError::BufferTooSmall {
                    what,
                    needed,
                    got: buf.size(),
                });
            }
        }
        let limits = device.limits();
        let limit = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        if pixels * 60 > limit {
            return Err(LossError::ImageTooLarge {
                needed: pixels * 60,
                limit,
            });
        }
        let groups = (width.div_ceil(TILE), height.div_ceil(TILE));
        let n_partials = groups.0 * groups.1;
        let mut guard = self.scratch.lock().unwrap_or_else(|e| e.into_inner());
        if guard.as_ref().map(|s| s.size) != Some((width, height)) {
            *guard = Some(Scratch::new(device, pixels, n_partials, (width, height)));
        }
        let Some(scratch) = guard.as_ref() else {
            return Err(LossError::EmptyImage);
        };
        let params = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("loss params"),
            contents: bytemuck::bytes_of(&Params {
                width,
                height,
                n_partials,
                _pad: 0,
            }),
            usage: crate::gpu::buffers::STORAGE,
        });
        // Bindings of common.wgsl, in order.
        let all: [&wgpu::Buffer; 9] = [
            &params,
            rendered,
            target,
            &scratch.stats_h,
            &scratch.dmaps,
            &scratch.dmaps_h,
            &scratch.partials,
            grad_out,
            loss_out,
        ];
        let used: [&[u32]; 5] = [
            &[0, 1, 2, 3],
            &[0, 1, 2, 3, 4, 6],
            &[0, 4, 5],
            &[0, 1, 2, 5, 7],
            &[0, 6, 8],
        ];
        let dispatch = [groups, groups, groups, groups, (1, 1)];
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("loss"),
            timestamp_writes: None,
        });
        for ((pipeline, bindings), (gx, gy)) in self.pipelines.iter().zip(used).zip(dispatch) {
            let entries: Vec<wgpu::BindGroupEntry> = bindings
                .iter()
                .map(|&b| wgpu::BindGroupEntry {
                    binding: b,
                    resource: all[b as usize].as_entire_binding(),
                })
                .collect();
            let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("loss"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        Ok(())
    }
}

impl Scratch {
    fn new(device: &wgpu::Device, pixels: u64, n_partials: u32, size: (u32, u32)) -> Self {
        let storage = |label: &str, bytes: u64| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes.max(16),
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        };
        Scratch {
            size,
            stats_h: storage("loss stats_h", pixels * 15 * 4),
            dmaps: storage("loss dmaps", pixels * 9 * 4),
            dmaps_h: storage("loss dmaps_h", pixels * 9 * 4),
            partials: storage("loss partials", u64::from(n_partials) * 8),
        }
    }
}
