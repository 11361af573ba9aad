//! The NeRF on the GPU through wgpu (`shaders/nerf/*.wgsl`), held to the CPU code of this
//! module's parent by `tests/gpu/nerf.rs`: each network's forward and backward pass, and whole
//! training steps.
//!
//! One step is recorded into one command encoder and submitted without reading anything back:
//! the step's draws ([`StepDraw`]: rays, targets, coarse distances, fine numbers) are written
//! to the GPU; the coarse network runs over every coarse sample in chunks of
//! [`NerfConfig::chunk`] samples (`encode`, then `dense_fwd` per layer), `composite` gives the
//! coarse weights and gradients, `sample_fine` the fine distances, the fine network runs, its
//! `composite`; then each network runs again chunk by chunk keeping its activations, and
//! `dense_bwd_w` / `dense_bwd_x` carry the gradients back layer by layer into one flat gradient
//! per network; Adam (`shaders/adam.wgsl`, ε 1e-7) updates both. The squared errors stay on
//! the GPU until [`GpuNerf::last_loss`] asks for them.
//!
//! Memory: the whole batch's distances, densities, colours, weights and their gradients (about
//! 14 floats per fine sample: 44 MB for 4096 rays of 192), and one chunk's activations (about
//! 10 × 256 floats per sample: 84 MB for the 8192-sample default), besides the two networks'
//! parameters, gradients and Adam moments (4 × 2.4 MB each).

use crate::gpu::buffers::{params_from, pipeline, read_buffer, storage_zeroed};
use crate::gpu::context::{GpuContext, GpuError};
use crate::splat::gpu::adam::{adam_pipeline, encode_adam_flat};
use crate::splat::gpu::buffers::wgsl_struct;
use crate::splat::gpu::project::{dispatch, groups_for};

use super::mlp::{Layer, Mlp, MlpShape};
use super::{ADAM_EPSILON, Nerf, NerfConfig, StepDraw};

wgsl_struct! {
    /// The parameter buffer of the dense kernels.
    struct DenseParams {
        n: u32,
        in_a: u32,
        in_b: u32,
        outs: u32,
        w_off: u32,
        act: u32,
        accumulate: u32,
        _pad: u32,
    }
}

wgsl_struct! {
    /// The parameter buffer of the ray kernels.
    struct RayParams {
        n: u32,
        row0: u32,
        per_ray: u32,
        n_fine: u32,
        pos_bands: u32,
        dir_bands: u32,
        scale: f32,
        _pad: u32,
    }
}

/// Most samples per ray the compositing and sampling kernels hold (their private arrays).
pub const MAX_SAMPLES: usize = 256;

struct Kernels {
    dense_fwd: wgpu::ComputePipeline,
    dense_bwd_x: wgpu::ComputePipeline,
    dense_bwd_w: wgpu::ComputePipeline,
    encode: wgpu::ComputePipeline,
    composite: wgpu::ComputePipeline,
    sample_fine: wgpu::ComputePipeline,
    adam: wgpu::ComputePipeline,
}

impl Kernels {
    fn new(ctx: &GpuContext) -> Self {
        let dense = |name: &str, src: &str| {
            pipeline(
                ctx,
                name,
                &format!("{}\n{src}", DenseParams::wgsl()),
                "main",
            )
        };
        let ray = |name: &str, src: &str| {
            pipeline(ctx, name, &format!("{}\n{src}", RayParams::wgsl()), "main")
        };
        Kernels {
            dense_fwd: dense(
                "nerf dense_fwd",
                include_str!("../../shaders/nerf/dense_fwd.wgsl"),
            ),
            dense_bwd_x: dense(
                "nerf dense_bwd_x",
                include_str!("../../shaders/nerf/dense_bwd_x.wgsl"),
            ),
            dense_bwd_w: dense(
                "nerf dense_bwd_w",
                include_str!("../../shaders/nerf/dense_bwd_w.wgsl"),
            ),
            encode: ray(
                "nerf encode",
                include_str!("../../shaders/nerf/encode.wgsl"),
            ),
            composite: ray(
                "nerf composite",
                include_str!("../../shaders/nerf/composite.wgsl"),
            ),
            sample_fine: ray(
                "nerf sample_fine",
                include_str!("../../shaders/nerf/sample_fine.wgsl"),
            ),
            adam: adam_pipeline(ctx),
        }
    }
}

/// One network on the GPU: parameters, gradient and Adam's moments.
struct GpuNet {
    shape: MlpShape,
    layers: Vec<Layer>,
    n: u32,
    params: wgpu::Buffer,
    grad: wgpu::Buffer,
    m: wgpu::Buffer,
    v: wgpu::Buffer,
}

impl GpuNet {
    fn upload(ctx: &GpuContext, net: &Mlp) -> Result<Self, GpuError> {
        let bytes = (net.params.len() * 4) as u64;
        let params = crate::gpu::buffers::storage_from(ctx, "nerf params", &net.params)?;
        Ok(GpuNet {
            shape: net.shape,
            layers: net.layers.clone(),
            n: net.params.len() as u32,
            params,
            grad: storage_zeroed(ctx, "nerf grad", bytes)?,
            m: storage_zeroed(ctx, "nerf adam m", bytes)?,
            v: storage_zeroed(ctx, "nerf adam v", bytes)?,
        })
    }
}

/// One chunk's buffers: encodings, activations and their gradients.
struct ChunkBuffers {
    pos: wgpu::Buffer,
    dir: wgpu::Buffer,
    /// Outputs of the trunk layers, then density, feature, view and colour.
    act: Vec<wgpu::Buffer>,
    /// Gradients: two of a layer's width (ping-pong), the view's, the feature's, the colour's
    /// and the density's.
    dh: [wgpu::Buffer; 2],
    d_view: wgpu::Buffer,
    d_feature: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
    d_sigma: wgpu::Buffer,
}

/// The whole batch's per-sample and per-ray buffers of one pass (coarse or fine).
struct PassBuffers {
    per_ray: u32,
    t: wgpu::Buffer,
    sigma: wgpu::Buffer,
    rgb: wgpu::Buffer,
    weights: wgpu::Buffer,
    d_sigma: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
    sq_err: wgpu::Buffer,
    colour: wgpu::Buffer,
}

/// The NeRF on the GPU (see the module doc).
pub struct GpuNerf<'a> {
    ctx: &'a GpuContext,
    cfg: NerfConfig,
    kernels: Kernels,
    nets: [GpuNet; 2],
    chunk: ChunkBuffers,
    /// Rays of the batch: 8 floats each (origin, near, direction, far); targets: 4 each.
    rays: wgpu::Buffer,
    targets: wgpu::Buffer,
    u: wgpu::Buffer,
    passes: [PassBuffers; 2],
    /// A 16-byte buffer bound where a kernel's second input is empty.
    empty: wgpu::Buffer,
    /// Adam steps taken.
    pub step: u32,
    /// Rays of the last batch recorded.
    last_rays: u32,
}

fn zeroed(ctx: &GpuContext, label: &'static str, floats: usize) -> Result<wgpu::Buffer, GpuError> {
    storage_zeroed(ctx, label, (floats.max(4) * 4) as u64)
}

impl<'a> GpuNerf<'a> {
    /// Uploads `nerf`'s networks; buffers for batches of `cfg.rays` rays.
    pub fn upload(ctx: &'a GpuContext, nerf: &Nerf) -> Result<Self, GpuError> {
        let cfg = nerf.cfg.clone();
        if cfg.coarse + cfg.fine > MAX_SAMPLES {
            return Err(GpuError::Invalid(format!(
                "{} + {} samples per ray; the GPU kernels hold at most {MAX_SAMPLES}",
                cfg.coarse, cfg.fine
            )));
        }
        let s = nerf.coarse.shape;
        let c = cfg.chunk;
        let mut act = Vec::new();
        for _ in 0..s.depth {
            act.push(zeroed(ctx, "nerf act", c * s.width)?);
        }
        act.push(zeroed(ctx, "nerf sigma", c)?);
        act.push(zeroed(ctx, "nerf feature", c * s.width)?);
        act.push(zeroed(ctx, "nerf view", c * (s.width / 2))?);
        act.push(zeroed(ctx, "nerf rgb", c * 3)?);
        let chunk = ChunkBuffers {
            pos: zeroed(ctx, "nerf pos", c * s.pos_dim)?,
            dir: zeroed(ctx, "nerf dir", c * s.dir_dim)?,
            act,
            dh: [
                zeroed(ctx, "nerf dh", c * s.width)?,
                zeroed(ctx, "nerf dh", c * s.width)?,
            ],
            d_view: zeroed(ctx, "nerf d_view", c * (s.width / 2))?,
            d_feature: zeroed(ctx, "nerf d_feature", c * s.width)?,
            d_rgb: zeroed(ctx, "nerf d_rgb", c * 3)?,
            d_sigma: zeroed(ctx, "nerf d_sigma", c)?,
        };
        let r = cfg.rays;
        let pass = |per_ray: usize| -> Result<PassBuffers, GpuError> {
            let n = r * per_ray;
            Ok(PassBuffers {
                per_ray: per_ray as u32,
                t: zeroed(ctx, "nerf t", n)?,
                sigma: zeroed(ctx, "nerf sigma all", n)?,
                rgb: zeroed(ctx, "nerf rgb all", n * 3)?,
                weights: zeroed(ctx, "nerf weights", n)?,
                d_sigma: zeroed(ctx, "nerf d_sigma all", n)?,
                d_rgb: zeroed(ctx, "nerf d_rgb all", n * 3)?,
                sq_err: zeroed(ctx, "nerf sq_err", r)?,
                colour: zeroed(ctx, "nerf colour", r * 4)?,
            })
        };
        Ok(GpuNerf {
            ctx,
            kernels: Kernels::new(ctx),
            nets: [
                GpuNet::upload(ctx, &nerf.coarse)?,
                GpuNet::upload(ctx, &nerf.fine)?,
            ],
            chunk,
            rays: zeroed(ctx, "nerf rays", r * 8)?,
            targets: zeroed(ctx, "nerf targets", r * 4)?,
            u: zeroed(ctx, "nerf u", r * cfg.fine)?,
            passes: [pass(cfg.coarse)?, pass(cfg.coarse + cfg.fine)?],
            empty: zeroed(ctx, "nerf empty", 4)?,
            cfg,
            step: 0,
            last_rays: 0,
        })
    }

    /// The networks' parameters (coarse, fine), read back.
    pub fn download(&self) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        Ok((
            read_buffer(self.ctx, &self.nets[0].params, self.nets[0].n as usize)?,
            read_buffer(self.ctx, &self.nets[1].params, self.nets[1].n as usize)?,
        ))
    }

    /// The parameter buffer of a dense kernel on `layer` over `n` samples: inputs `in_a` from
    /// the first source and `in_b` from the second, activation (or mask) `act`.
    fn dense_params(
        &self,
        l: Layer,
        n: usize,
        in_a: usize,
        in_b: usize,
        act: u32,
        accumulate: bool,
    ) -> wgpu::Buffer {
        let p = DenseParams {
            n: n as u32,
            in_a: in_a as u32,
            in_b: in_b as u32,
            outs: l.outputs as u32,
            w_off: l.offset as u32,
            act,
            accumulate: u32::from(accumulate),
            _pad: 0,
        };
        params_from(self.ctx, "nerf dense", &p)
    }

    #[allow(clippy::too_many_arguments)]
    fn dense(
        &self,
        enc: &mut wgpu::CommandEncoder,
        net: usize,
        layer: usize,
        n: usize,
        [xa, xb]: [&wgpu::Buffer; 2],
        in_b: usize,
        act: u32,
        y: &wgpu::Buffer,
    ) {
        let l = self.nets[net].layers[layer];
        let pb = self.dense_params(l, n, l.inputs - in_b, in_b, act, false);
        let groups = (l.outputs.div_ceil(16) as u32, n.div_ceil(16) as u32);
        dispatch(
            self.ctx,
            enc,
            &self.kernels.dense_fwd,
            &[&pb, &self.nets[net].params, xa, xb, y],
            groups,
        );
    }

    /// dW += xᵀ dy for `layer` over `n` samples.
    #[allow(clippy::too_many_arguments)]
    fn dense_w(
        &self,
        enc: &mut wgpu::CommandEncoder,
        net: usize,
        layer: usize,
        n: usize,
        [xa, xb]: [&wgpu::Buffer; 2],
        in_b: usize,
        dy: &wgpu::Buffer,
    ) {
        let l = self.nets[net].layers[layer];
        let pb = self.dense_params(l, n, l.inputs - in_b, in_b, 0, false);
        let groups = (
            l.outputs.div_ceil(16) as u32,
            (l.inputs + 1).div_ceil(16) as u32,
        );
        dispatch(
            self.ctx,
            enc,
            &self.kernels.dense_bwd_w,
            &[&pb, xa, xb, dy, &self.nets[net].grad],
            groups,
        );
    }

    /// dx (first `in_a` inputs) = dy Wᵀ, masked by `prev` > 0, added to dx when `accumulate`.
    #[allow(clippy::too_many_arguments)]
    fn dense_x(
        &self,
        enc: &mut wgpu::CommandEncoder,
        net: usize,
        layer: usize,
        n: usize,
        in_a: usize,
        dy: &wgpu::Buffer,
        prev: Option<&wgpu::Buffer>,
        accumulate: bool,
        dx: &wgpu::Buffer,
    ) {
        let l = self.nets[net].layers[layer];
        let pb = self.dense_params(l, n, in_a, 0, u32::from(prev.is_some()), accumulate);
        let groups = (in_a.div_ceil(16) as u32, n.div_ceil(16) as u32);
        dispatch(
            self.ctx,
            enc,
            &self.kernels.dense_bwd_x,
            &[
                &pb,
                &self.nets[net].params,
                dy,
                prev.unwrap_or(&self.empty),
                dx,
            ],
            groups,
        );
    }

    fn ray_params(&self, n: usize, row0: usize, per_ray: u32, scale: f32) -> wgpu::Buffer {
        let p = RayParams {
            n: n as u32,
            row0: row0 as u32,
            per_ray,
            n_fine: self.cfg.fine as u32,
            pos_bands: self.cfg.pos_bands as u32,
            dir_bands: self.cfg.dir_bands as u32,
            scale,
            _pad: 0,
        };
        params_from(self.ctx, "nerf rays", &p)
    }

    /// The forward pass of network `net` over samples `row0..row0 + n` of `pass`, its
    /// activations left in the chunk buffers.
    fn forward_chunk(
        &self,
        enc: &mut wgpu::CommandEncoder,
        net: usize,
        pass: usize,
        row0: usize,
        n: usize,
    ) {
        let c = &self.chunk;
        let pb = &self.passes[pass];
        let rp = self.ray_params(n, row0, pb.per_ray, 0.0);
        dispatch(
            self.ctx,
            enc,
            &self.kernels.encode,
            &[&rp, &self.rays, &pb.t, &c.pos, &c.dir],
            groups_for(n as u32),
        );
        self.forward_encoded(enc, net, n);
    }

    /// The layers of network `net` on the chunk's encodings.
    fn forward_encoded(&self, enc: &mut wgpu::CommandEncoder, net: usize, n: usize) {
        let s = self.nets[net].shape;
        let c = &self.chunk;
        for l in 0..s.depth {
            let (xa, xb, in_b) = if l == 0 {
                (&c.pos, &self.empty, 0)
            } else if l == s.skip + 1 {
                (&c.act[l - 1], &c.pos, s.pos_dim)
            } else {
                (&c.act[l - 1], &self.empty, 0)
            };
            self.dense(enc, net, l, n, [xa, xb], in_b, 1, &c.act[l]);
        }
        let h = &c.act[s.depth - 1];
        self.dense(
            enc,
            net,
            s.depth,
            n,
            [h, &self.empty],
            0,
            0,
            &c.act[s.depth],
        );
        self.dense(
            enc,
            net,
            s.depth + 1,
            n,
            [h, &self.empty],
            0,
            0,
            &c.act[s.depth + 1],
        );
        self.dense(
            enc,
            net,
            s.depth + 2,
            n,
            [&c.act[s.depth + 1], &c.dir],
            s.dir_dim,
            1,
            &c.act[s.depth + 2],
        );
        self.dense(
            enc,
            net,
            s.depth + 3,
            n,
            [&c.act[s.depth + 2], &self.empty],
            0,
            2,
            &c.act[s.depth + 3],
        );
    }

    /// The backward pass of network `net` on the chunk (after its forward pass), from the
    /// chunk's `d_sigma` (raw density) and `d_rgb` (colour before the sigmoid).
    fn backward_chunk(&self, enc: &mut wgpu::CommandEncoder, net: usize, n: usize) {
        let s = self.nets[net].shape;
        let c = &self.chunk;
        let (d, e) = (&self.empty, s.depth);
        // Colour layer.
        self.dense_w(enc, net, e + 3, n, [&c.act[e + 2], d], 0, &c.d_rgb);
        self.dense_x(
            enc,
            net,
            e + 3,
            n,
            s.width / 2,
            &c.d_rgb,
            Some(&c.act[e + 2]),
            false,
            &c.d_view,
        );
        // View layer: its input is [feature, γ(d)]; the feature is linear (no mask).
        self.dense_w(
            enc,
            net,
            e + 2,
            n,
            [&c.act[e + 1], &c.dir],
            s.dir_dim,
            &c.d_view,
        );
        self.dense_x(
            enc,
            net,
            e + 2,
            n,
            s.width,
            &c.d_view,
            None,
            false,
            &c.d_feature,
        );
        // Feature and density layers, both on the last trunk output.
        let h = &c.act[e - 1];
        self.dense_w(enc, net, e + 1, n, [h, d], 0, &c.d_feature);
        self.dense_x(
            enc,
            net,
            e + 1,
            n,
            s.width,
            &c.d_feature,
            Some(h),
            false,
            &c.dh[0],
        );
        self.dense_w(enc, net, e, n, [h, d], 0, &c.d_sigma);
        self.dense_x(enc, net, e, n, s.width, &c.d_sigma, Some(h), true, &c.dh[0]);
        // Trunk, last to first; dh[k % 2] holds the gradient of layer l's output.
        let mut k = 0;
        for l in (0..e).rev() {
            let (xa, xb, in_b) = if l == 0 {
                (&c.pos, d, 0)
            } else if l == s.skip + 1 {
                (&c.act[l - 1], &c.pos, s.pos_dim)
            } else {
                (&c.act[l - 1], d, 0)
            };
            self.dense_w(enc, net, l, n, [xa, xb], in_b, &c.dh[k]);
            if l > 0 {
                self.dense_x(
                    enc,
                    net,
                    l,
                    n,
                    s.width,
                    &c.dh[k],
                    Some(&c.act[l - 1]),
                    false,
                    &c.dh[1 - k],
                );
                k = 1 - k;
            }
        }
    }

    fn copy_floats(
        enc: &mut wgpu::CommandEncoder,
        from: &wgpu::Buffer,
        from_float: usize,
        to: &wgpu::Buffer,
        to_float: usize,
        floats: usize,
    ) {
        enc.copy_buffer_to_buffer(
            from,
            (from_float * 4) as u64,
            to,
            (to_float * 4) as u64,
            (floats * 4) as u64,
        );
    }

    /// Network `net` over every sample of `pass` (chunk by chunk): densities and colours.
    fn forward_pass(&self, enc: &mut wgpu::CommandEncoder, net: usize, pass: usize, rays: usize) {
        let total = rays * self.passes[pass].per_ray as usize;
        let mut row0 = 0;
        while row0 < total {
            let n = self.cfg.chunk.min(total - row0);
            self.forward_chunk(enc, net, pass, row0, n);
            let e = self.nets[net].shape.depth;
            let pb = &self.passes[pass];
            Self::copy_floats(enc, &self.chunk.act[e], 0, &pb.sigma, row0, n);
            Self::copy_floats(enc, &self.chunk.act[e + 3], 0, &pb.rgb, row0 * 3, n * 3);
            row0 += n;
        }
    }

    /// The gradient of network `net` over every sample of `pass`, added to its gradient.
    fn backward_pass(&self, enc: &mut wgpu::CommandEncoder, net: usize, pass: usize, rays: usize) {
        let total = rays * self.passes[pass].per_ray as usize;
        let mut row0 = 0;
        while row0 < total {
            let n = self.cfg.chunk.min(total - row0);
            self.forward_chunk(enc, net, pass, row0, n);
            let pb = &self.passes[pass];
            Self::copy_floats(enc, &pb.d_sigma, row0, &self.chunk.d_sigma, 0, n);
            Self::copy_floats(enc, &pb.d_rgb, row0 * 3, &self.chunk.d_rgb, 0, n * 3);
            self.backward_chunk(enc, net, n);
            row0 += n;
        }
    }

    fn composite(&self, enc: &mut wgpu::CommandEncoder, pass: usize, rays: usize) {
        let pb = &self.passes[pass];
        let scale = 2.0 / (3.0 * rays as f32);
        let rp = self.ray_params(rays, 0, pb.per_ray, scale);
        dispatch(
            self.ctx,
            enc,
            &self.kernels.composite,
            &[
                &rp,
                &pb.t,
                &pb.sigma,
                &pb.rgb,
                &self.targets,
                &pb.weights,
                &pb.d_sigma,
                &pb.d_rgb,
                &pb.sq_err,
                &pb.colour,
            ],
            groups_for(rays as u32),
        );
    }

    /// Writes `draw` and records both passes' forward work and compositing.
    fn record_passes(
        &mut self,
        enc: &mut wgpu::CommandEncoder,
        draw: &StepDraw,
    ) -> Result<usize, GpuError> {
        let r = draw.rays.len();
        if r == 0 || r > self.cfg.rays {
            return Err(GpuError::Invalid(format!(
                "{r} rays; this NeRF's buffers hold 1 to {}",
                self.cfg.rays
            )));
        }
        let rays: Vec<f32> = draw
            .rays
            .iter()
            .flat_map(|y| {
                [
                    y.origin[0],
                    y.origin[1],
                    y.origin[2],
                    y.near,
                    y.dir[0],
                    y.dir[1],
                    y.dir[2],
                    y.far,
                ]
            })
            .collect();
        let targets: Vec<f32> = draw
            .targets
            .iter()
            .flat_map(|c| [c[0], c[1], c[2], 0.0])
            .collect();
        let q = &self.ctx.queue;
        q.write_buffer(&self.rays, 0, bytemuck::cast_slice(&rays));
        q.write_buffer(&self.targets, 0, bytemuck::cast_slice(&targets));
        q.write_buffer(&self.passes[0].t, 0, bytemuck::cast_slice(&draw.coarse_t));
        q.write_buffer(&self.u, 0, bytemuck::cast_slice(&draw.u));
        self.forward_pass(enc, 0, 0, r);
        self.composite(enc, 0, r);
        let rp = self.ray_params(r, 0, self.passes[0].per_ray, 0.0);
        dispatch(
            self.ctx,
            enc,
            &self.kernels.sample_fine,
            &[
                &rp,
                &self.passes[0].t,
                &self.passes[0].weights,
                &self.u,
                &self.passes[1].t,
            ],
            groups_for(r as u32),
        );
        self.forward_pass(enc, 1, 1, r);
        self.composite(enc, 1, r);
        self.last_rays = r as u32;
        Ok(r)
    }

    /// One training step on `draw` at learning rate `lr`, submitted without a read-back.
    pub fn step(&mut self, draw: &StepDraw, lr: f64) -> Result<(), GpuError> {
        let mut enc = self.ctx.device.create_command_encoder(&Default::default());
        let r = self.record_passes(&mut enc, draw)?;
        for net in 0..2 {
            enc.clear_buffer(&self.nets[net].grad, 0, None);
            self.backward_pass(&mut enc, net, net, r);
        }
        self.step += 1;
        for net in &self.nets {
            encode_adam_flat(
                self.ctx,
                &mut enc,
                &self.kernels.adam,
                [&net.params, &net.grad, &net.m, &net.v],
                net.n,
                lr as f32,
                self.step,
                ADAM_EPSILON,
            );
        }
        self.ctx.queue.submit([enc.finish()]);
        Ok(())
    }

    /// Mean squared error of the last step's coarse and fine colours (reads back).
    pub fn last_loss(&self) -> Result<(f64, f64), GpuError> {
        let r = self.last_rays as usize;
        let mut out = [0.0f64; 2];
        for (k, pb) in self.passes.iter().enumerate() {
            let e: Vec<f32> = read_buffer(self.ctx, &pb.sq_err, r)?;
            out[k] = e.iter().map(|v| f64::from(*v)).sum::<f64>() / (3 * r.max(1)) as f64;
        }
        Ok((out[0], out[1]))
    }

    /// The fine colours of `draw`'s rays (rendering: no gradient is used).
    pub fn colours(&mut self, draw: &StepDraw) -> Result<Vec<[f32; 3]>, GpuError> {
        let mut enc = self.ctx.device.create_command_encoder(&Default::default());
        let r = self.record_passes(&mut enc, draw)?;
        self.ctx.queue.submit([enc.finish()]);
        let c: Vec<f32> = read_buffer(self.ctx, &self.passes[1].colour, r * 4)?;
        Ok(c.chunks_exact(4).map(|p| [p[0], p[1], p[2]]).collect())
    }

    /// Network `net` (0 coarse, 1 fine) on given encodings, `n` ≤ chunk samples: raw
    /// densities and colours (for the twin tests).
    pub fn forward_net(
        &self,
        net: usize,
        pos: &[f32],
        dir: &[f32],
        n: usize,
    ) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        self.check_chunk(n)?;
        let q = &self.ctx.queue;
        q.write_buffer(&self.chunk.pos, 0, bytemuck::cast_slice(pos));
        q.write_buffer(&self.chunk.dir, 0, bytemuck::cast_slice(dir));
        let mut enc = self.ctx.device.create_command_encoder(&Default::default());
        self.forward_encoded(&mut enc, net, n);
        self.ctx.queue.submit([enc.finish()]);
        let e = self.nets[net].shape.depth;
        Ok((
            read_buffer(self.ctx, &self.chunk.act[e], n)?,
            read_buffer(self.ctx, &self.chunk.act[e + 3], n * 3)?,
        ))
    }

    /// The gradient of network `net`'s parameters for per-sample derivatives by the raw
    /// density and by the colour before its sigmoid (for the twin tests).
    pub fn gradient_net(
        &self,
        net: usize,
        pos: &[f32],
        dir: &[f32],
        n: usize,
        d_sigma: &[f32],
        d_rgb_raw: &[f32],
    ) -> Result<Vec<f32>, GpuError> {
        self.check_chunk(n)?;
        let q = &self.ctx.queue;
        q.write_buffer(&self.chunk.pos, 0, bytemuck::cast_slice(pos));
        q.write_buffer(&self.chunk.dir, 0, bytemuck::cast_slice(dir));
        q.write_buffer(&self.chunk.d_sigma, 0, bytemuck::cast_slice(d_sigma));
        q.write_buffer(&self.chunk.d_rgb, 0, bytemuck::cast_slice(d_rgb_raw));
        let mut enc = self.ctx.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&self.nets[net].grad, 0, None);
        self.forward_encoded(&mut enc, net, n);
        self.backward_chunk(&mut enc, net, n);
        self.ctx.queue.submit([enc.finish()]);
        read_buffer(self.ctx, &self.nets[net].grad, self.nets[net].n as usize)
    }

    fn check_chunk(&self, n: usize) -> Result<(), GpuError> {
        if n == 0 || n > self.cfg.chunk {
            return Err(GpuError::Invalid(format!(
                "{n} samples; a chunk holds 1 to {}",
                self.cfg.chunk
            )));
        }
        Ok(())
    }
}
