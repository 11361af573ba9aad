//! A NeRF baseline as the paper specifies it (its Section 3.7.1, after Mildenhall et al. 2020):
//! a coarse and a fine network ([`mlp`]: 8 ReLU layers × 256, the encoded position joining
//! again after the 4th layer; 10 frequency bands for the position, 4 for the direction), 64
//! stratified coarse samples and 128 fine samples per ray ([`render`]), the squared error of
//! both passes' colours, batches of 4096 rays drawn at random from every training pixel, and
//! Adam from 5e-4 decaying exponentially to 5e-5 over the run.
//!
//! This is the CPU implementation (the reference the GPU kernels are held to). Its budget is
//! the caller's: steps and rays per step, or a wall-clock limit over which the learning rate
//! decays instead (`sylva bench method`'s `nerf` arm gets the wall time of the 3DGS arms).
//! The paper trained 300,000 steps of 4096 rays (11–43 hours on its GPU).
//!
//! Scene frame: positions are taken relative to the sparse points' centroid and divided by
//! the radius that holds 95 % of them, so the encoding sees coordinates of order 1 whatever
//! the scene's size. Each view samples between a near and far bound from the sparse points in
//! front of it (0.9 × the 1st percentile of their depth, 1.2 × the 99th); rays that leave the
//! far bound composite onto black (Mildenhall's real scenes).
//!
//! Memory: the forward pass that feeds compositing keeps nothing; the backward pass runs the
//! network again, chunk by chunk ([`NerfConfig::chunk`] samples), keeping only one chunk's
//! activations per thread.

pub mod gpu;
pub mod mlp;
pub mod render;

use std::time::Instant;

use rayon::prelude::*;

use crate::progress::Progress;
use crate::rng::SplitMix64;
use crate::splat::camera::Camera;
use crate::splat::dataset::Dataset;
use crate::splat::eval::{EvalRegion, EvalReport, ViewMetrics};
use mlp::{Cache, Mlp, MlpShape};
use render::{
    Ray, composite, composite_backward, encode, encoded_len, merge_sorted, sample_pdf, stratified,
};

/// The NeRF's settings; [`Default`] is the paper's.
#[derive(Debug, Clone, PartialEq)]
pub struct NerfConfig {
    /// ReLU layers on the position: 8 (the paper).
    pub depth: usize,
    /// Units per layer: 256 (the paper).
    pub width: usize,
    /// The position joins again after this layer (0-based): 4 (the paper).
    pub skip: usize,
    /// Frequency bands of the position's encoding: 10 (the paper).
    pub pos_bands: usize,
    /// Frequency bands of the direction's encoding: 4 (the paper).
    pub dir_bands: usize,
    /// Coarse samples per ray: 64 (the paper).
    pub coarse: usize,
    /// Fine samples per ray, added to the coarse ones for the fine network: 128 (the paper).
    pub fine: usize,
    /// Rays per step: 4096 (the paper).
    pub rays: usize,
    /// Learning rate at the start and at the end of the run (exponential between): 5e-4 and
    /// 5e-5 (the paper).
    pub lr_start: f64,
    pub lr_end: f64,
    /// Steps: 300,000 (the paper); a run also stops at [`NerfConfig::seconds`].
    pub steps: u32,
    /// Wall-clock limit of training, seconds; the learning rate then decays over the time
    /// rather than the steps. None: no limit.
    pub seconds: Option<f64>,
    /// Samples per chunk of the network's passes: 8192 (bounds memory, not results).
    pub chunk: usize,
    pub seed: u64,
    /// GPU (default) or CPU.
    pub device: NerfDevice,
}

impl Default for NerfConfig {
    fn default() -> Self {
        NerfConfig {
            depth: 8,
            width: 256,
            skip: 4,
            pos_bands: 10,
            dir_bands: 4,
            coarse: 64,
            fine: 128,
            rays: 4096,
            lr_start: 5e-4,
            lr_end: 5e-5,
            steps: 300_000,
            seconds: None,
            chunk: 8192,
            seed: 0,
            device: NerfDevice::Gpu,
        }
    }
}

impl NerfConfig {
    fn shape(&self) -> MlpShape {
        MlpShape {
            depth: self.depth,
            width: self.width,
            skip: self.skip,
            pos_dim: encoded_len(self.pos_bands),
            dir_dim: encoded_len(self.dir_bands),
        }
    }

    /// Refuses settings the network or sampler cannot run with.
    pub fn validate(&self) -> Result<(), NerfError> {
        let bad = |m: &str| Err(NerfError::Invalid(m.to_string()));
        if self.depth < 2 || self.skip + 1 >= self.depth {
            return bad("the skip must join before the last layer (skip + 1 < depth, depth ≥ 2)");
        }
        if self.width < 2 || self.coarse < 3 || self.rays == 0 || self.chunk == 0 {
            return bad("width ≥ 2, coarse samples ≥ 3, rays and chunk ≥ 1");
        }
        if !(self.lr_start > 0.0 && self.lr_end > 0.0) {
            return bad("learning rates must be > 0");
        }
        Ok(())
    }
}

/// Why a NeRF could not be trained or rendered.
#[derive(Debug, thiserror::Error)]
pub enum NerfError {
    #[error("{0}")]
    Invalid(String),
    #[error("cancelled")]
    Cancelled,
    #[error(transparent)]
    Gpu(#[from] crate::gpu::context::GpuError),
}

/// Where a NeRF trains and renders.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum NerfDevice {
    /// The GPU through wgpu ([`gpu`]), the kernels this module's CPU code is the twin of.
    #[default]
    Gpu,
    /// The CPU (`matrixmultiply`, every core).
    Cpu,
}

/// The normalised scene frame (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneFrame {
    pub centre: [f32; 3],
    /// Normalised units per metre.
    pub scale: f32,
}

impl SceneFrame {
    /// From the sparse points: centroid and the 95th percentile of their distance from it.
    pub fn of_points(points: &[[f32; 3]]) -> Self {
        if points.is_empty() {
            return SceneFrame {
                centre: [0.0; 3],
                scale: 1.0,
            };
        }
        let n = points.len() as f64;
        let mut c = [0.0f64; 3];
        for p in points {
            for k in 0..3 {
                c[k] += f64::from(p[k]) / n;
            }
        }
        let centre = c.map(|v| v as f32);
        let mut d: Vec<f32> = points.iter().map(|p| dist(*p, centre)).collect();
        let r = percentile(&mut d, 0.95).max(1e-3);
        SceneFrame {
            centre,
            scale: 1.0 / r,
        }
    }

    fn to_frame(self, p: [f32; 3]) -> [f32; 3] {
        [0, 1, 2].map(|k| (p[k] - self.centre[k]) * self.scale)
    }
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn percentile(v: &mut [f32], q: f64) -> f32 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f32::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// Near and far bounds of a camera, metres, from the sparse points in front of it (see the
/// module doc); the whole cloud's extent when none is.
pub fn view_bounds(camera: &Camera, points: &[[f32; 3]]) -> (f32, f32) {
    let mut depths: Vec<f32> = points
        .iter()
        .map(|p| camera.to_camera(*p)[2])
        .filter(|z| *z > 1e-3)
        .collect();
    if depths.is_empty() {
        let frame = SceneFrame::of_points(points);
        let r = 1.0 / frame.scale;
        let d = dist(camera.centre(), frame.centre);
        return ((d - 2.0 * r).max(0.01), d + 2.0 * r);
    }
    let near = 0.9 * percentile(&mut depths, 0.01);
    let far = 1.2 * percentile(&mut depths, 0.99);
    (near.max(1e-3), far.max(near * 1.01 + 1e-3))
}

/// The ray through pixel (x, y)'s centre, in the normalised frame.
pub fn pixel_ray(camera: &Camera, x: f32, y: f32, bounds: (f32, f32), frame: &SceneFrame) -> Ray {
    let d_cam = [
        (x - camera.cx) / camera.fx,
        (y - camera.cy) / camera.fy,
        1.0,
    ];
    let r = &camera.r;
    // World direction Rᵀ d, then unit length; depth z along the axis is t_world · dir_z.
    let d = [0, 1, 2].map(|k| r[0][k] * d_cam[0] + r[1][k] * d_cam[1] + r[2][k] * d_cam[2]);
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let dir = d.map(|v| v / len);
    // The bounds are depths along the optical axis; along this ray they are `len` times longer.
    Ray {
        origin: frame.to_frame(camera.centre()),
        dir,
        near: bounds.0 * len * frame.scale,
        far: bounds.1 * len * frame.scale,
    }
}

/// A trained NeRF.
#[derive(Debug, Clone)]
pub struct Nerf {
    pub cfg: NerfConfig,
    pub coarse: Mlp,
    pub fine: Mlp,
    pub frame: SceneFrame,
}

/// Adam's state over one network's flat parameters: `splat::gpu::adam`'s (β1 0.9, β2 0.999,
/// the bias corrections in f64) with ε [`ADAM_EPSILON`].
struct Adam {
    m: Vec<f32>,
    v: Vec<f32>,
    t: u32,
}

/// Adam's ε: 1e-7 (Mildenhall's TensorFlow default).
pub const ADAM_EPSILON: f32 = 1e-7;

impl Adam {
    fn new(n: usize) -> Self {
        Adam {
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }

    fn step(&mut self, params: &mut [f32], grad: &[f32], lr: f64) {
        self.t += 1;
        let lr = lr as f32;
        crate::splat::gpu::adam::adam_cpu(
            params,
            grad,
            &mut self.m,
            &mut self.v,
            1,
            1,
            lr,
            lr,
            self.t,
            ADAM_EPSILON,
        );
    }
}

/// Adam over both networks of a NeRF (the CPU path's optimiser, and the GPU's twin).
pub struct CpuAdam {
    coarse: Adam,
    fine: Adam,
}

impl CpuAdam {
    /// Zero moments for `nerf`'s networks.
    pub fn new(nerf: &Nerf) -> Self {
        CpuAdam {
            coarse: Adam::new(nerf.coarse.params.len()),
            fine: Adam::new(nerf.fine.params.len()),
        }
    }

    /// One step of both networks from their gradients at learning rate `lr`.
    pub fn step(&mut self, nerf: &mut Nerf, coarse: &[f32], fine: &[f32], lr: f64) {
        self.coarse.step(&mut nerf.coarse.params, coarse, lr);
        self.fine.step(&mut nerf.fine.params, fine, lr);
    }
}

/// The random draws of one training step, shared by the CPU and GPU paths: the rays and
/// their target colours, each ray's coarse distances (stratified, jittered) and its fine
/// numbers `u` (ascending, `fine` per ray).
#[derive(Debug, Clone)]
pub struct StepDraw {
    pub rays: Vec<Ray>,
    pub targets: Vec<[f32; 3]>,
    pub coarse_t: Vec<f32>,
    pub u: Vec<f32>,
}

/// The fixed draws of rendering: the coarse bins' middles and evenly spaced `u`.
pub fn fixed_draw(rays: &[Ray], cfg: &NerfConfig) -> StepDraw {
    let mut coarse_t = Vec::with_capacity(rays.len() * cfg.coarse);
    for r in rays {
        coarse_t.extend(stratified(r, cfg.coarse, || 0.5));
    }
    let u1: Vec<f32> = (0..cfg.fine)
        .map(|k| (k as f32 + 0.5) / cfg.fine as f32)
        .collect();
    StepDraw {
        rays: rays.to_vec(),
        targets: vec![[0.0; 3]; rays.len()],
        coarse_t,
        u: u1.repeat(rays.len()),
    }
}

/// Training pixels, decoded once, with their view's camera and bounds.
/// A training view's camera, near and far bounds (m) and pixels.
type TrainingView = (Camera, (f32, f32), Vec<[f32; 3]>);

/// Every training pixel with its view (see [`TrainingPixels::draw`]).
pub struct TrainingPixels {
    views: Vec<TrainingView>,
    total: u64,
}

impl TrainingPixels {
    pub fn new(data: &Dataset) -> Result<Self, NerfError> {
        let mut views = Vec::new();
        for v in &data.train {
            let img = v
                .image
                .image()
                .map_err(|e| NerfError::Invalid(format!("{}: {e}", v.name)))?;
            views.push((
                v.camera,
                view_bounds(&v.camera, &data.points),
                img.to_rgb_f32(),
            ));
        }
        let total = views
            .iter()
            .map(|(c, _, _)| u64::from(c.width) * u64::from(c.height))
            .sum();
        if total == 0 {
            return Err(NerfError::Invalid("no training pixels".into()));
        }
        Ok(TrainingPixels { views, total })
    }

    /// `cfg.rays` pixels drawn uniformly from every training pixel, with their draws.
    pub fn draw(&self, cfg: &NerfConfig, frame: &SceneFrame, rng: &mut SplitMix64) -> StepDraw {
        let mut d = StepDraw {
            rays: Vec::with_capacity(cfg.rays),
            targets: Vec::with_capacity(cfg.rays),
            coarse_t: Vec::with_capacity(cfg.rays * cfg.coarse),
            u: Vec::with_capacity(cfg.rays * cfg.fine),
        };
        for _ in 0..cfg.rays {
            let mut k = rng.below(self.total);
            let mut vi = 0;
            loop {
                let c = &self.views[vi].0;
                let n = u64::from(c.width) * u64::from(c.height);
                if k < n {
                    break;
                }
                k -= n;
                vi += 1;
            }
            let (cam, bounds, img) = &self.views[vi];
            let (x, y) = (
                (k % u64::from(cam.width)) as f32,
                (k / u64::from(cam.width)) as f32,
            );
            let ray = pixel_ray(cam, x + 0.5, y + 0.5, *bounds, frame);
            d.coarse_t
                .extend(stratified(&ray, cfg.coarse, || rng.uniform() as f32));
            let mut u: Vec<f32> = (0..cfg.fine).map(|_| rng.uniform() as f32).collect();
            u.sort_by(f32::total_cmp);
            d.u.extend(u);
            d.rays.push(ray);
            d.targets.push(img[k as usize]);
        }
        d
    }
}

/// The samples of a batch of rays, encoded for one network.
struct Batch {
    pos: Vec<f32>,
    dir: Vec<f32>,
    /// Distances per ray (each `per_ray` long).
    t: Vec<f32>,
    per_ray: usize,
}

impl Batch {
    fn new(rays: &[Ray], t: Vec<f32>, per_ray: usize, cfg: &NerfConfig) -> Self {
        let n = rays.len() * per_ray;
        let mut pos = Vec::with_capacity(n * encoded_len(cfg.pos_bands));
        let mut dir = Vec::with_capacity(n * encoded_len(cfg.dir_bands));
        let mut d_enc = Vec::with_capacity(encoded_len(cfg.dir_bands));
        for (r, ts) in rays.iter().zip(t.chunks_exact(per_ray)) {
            d_enc.clear();
            encode(r.dir, cfg.dir_bands, &mut d_enc);
            for &ti in ts {
                encode(r.at(ti), cfg.pos_bands, &mut pos);
                dir.extend_from_slice(&d_enc);
            }
        }
        Batch {
            pos,
            dir,
            t,
            per_ray,
        }
    }

    fn len(&self) -> usize {
        self.t.len()
    }
}

impl Nerf {
    /// A fresh NeRF for `points` (the sparse model, metres).
    pub fn new(cfg: &NerfConfig, points: &[[f32; 3]]) -> Result<Self, NerfError> {
        cfg.validate()?;
        let shape = cfg.shape();
        Ok(Nerf {
            cfg: cfg.clone(),
            coarse: Mlp::new(shape, cfg.seed ^ 0xC0A2),
            fine: Mlp::new(shape, cfg.seed ^ 0xF1E),
            frame: SceneFrame::of_points(points),
        })
    }

    /// Runs `net` on every sample of `b` in chunks (in parallel); no cache.
    fn run(&self, net: &Mlp, b: &Batch) -> mlp::Output {
        let (pd, dd) = (net.shape.pos_dim, net.shape.dir_dim);
        let chunk = self.cfg.chunk;
        let parts: Vec<mlp::Output> = (0..b.len().div_ceil(chunk))
            .into_par_iter()
            .map(|k| {
                let (s, e) = (k * chunk, ((k + 1) * chunk).min(b.len()));
                net.forward(&b.pos[s * pd..e * pd], &b.dir[s * dd..e * dd], e - s, None)
            })
            .collect();
        let mut out = mlp::Output::default();
        for p in parts {
            out.sigma_raw.extend(p.sigma_raw);
            out.rgb.extend(p.rgb);
        }
        out
    }

    /// The gradient of `net`'s parameters for per-sample derivatives (recomputing the forward
    /// pass chunk by chunk, with one cache per thread).
    fn gradient(&self, net: &Mlp, b: &Batch, d_sigma: &[f32], d_rgb: &[[f32; 3]]) -> Vec<f32> {
        let (pd, dd) = (net.shape.pos_dim, net.shape.dir_dim);
        let chunk = self.cfg.chunk;
        let np = net.params.len();
        (0..b.len().div_ceil(chunk))
            .into_par_iter()
            .fold(
                || (vec![0.0f32; np], Cache::default()),
                |(mut g, mut cache), k| {
                    let (s, e) = (k * chunk, ((k + 1) * chunk).min(b.len()));
                    net.forward(
                        &b.pos[s * pd..e * pd],
                        &b.dir[s * dd..e * dd],
                        e - s,
                        Some(&mut cache),
                    );
                    net.backward(&cache, &d_sigma[s..e], &d_rgb[s..e], &mut g);
                    (g, cache)
                },
            )
            .map(|(g, _)| g)
            .reduce(
                || vec![0.0f32; np],
                |mut a, b| {
                    for (x, y) in a.iter_mut().zip(&b) {
                        *x += y;
                    }
                    a
                },
            )
    }

    /// Coarse pass, fine distances, fine pass for `draw`'s rays: (coarse batch and output,
    /// fine batch and output).
    fn passes(&self, draw: &StepDraw) -> ((Batch, mlp::Output), (Batch, mlp::Output)) {
        let cfg = &self.cfg;
        let rays = &draw.rays;
        let cb = Batch::new(rays, draw.coarse_t.clone(), cfg.coarse, cfg);
        let co = self.run(&self.coarse, &cb);
        let per_fine = cfg.coarse + cfg.fine;
        let mut tf = Vec::with_capacity(rays.len() * per_fine);
        for (i, ts) in cb.t.chunks_exact(cfg.coarse).enumerate() {
            let s = i * cfg.coarse..(i + 1) * cfg.coarse;
            let comp = composite(ts, &co.sigma_raw[s.clone()], &co.rgb[s], [0.0; 3]);
            let u = &draw.u[i * cfg.fine..(i + 1) * cfg.fine];
            tf.extend(merge_sorted(ts, &sample_pdf(ts, &comp.weights, u)));
        }
        let fb = Batch::new(rays, tf, per_fine, cfg);
        let fo = self.run(&self.fine, &fb);
        ((cb, co), (fb, fo))
    }

    /// One training step's losses (mean squared error of the coarse and of the fine colours)
    /// and both networks' gradients (of their sum), for `draw`.
    pub fn step_gradients(&self, draw: &StepDraw) -> (f64, f64, Vec<f32>, Vec<f32>) {
        let (rays, targets) = (&draw.rays, &draw.targets);
        let ((cb, co), (fb, fo)) = self.passes(draw);
        let scale = 2.0 / (3.0 * rays.len() as f32);
        let mut loss = [0.0f64; 2];
        let mut grads = Vec::new();
        for (k, (b, o)) in [(&cb, &co), (&fb, &fo)].into_iter().enumerate() {
            let per = b.per_ray;
            let mut d_sigma = vec![0.0f32; b.len()];
            let mut d_rgb = vec![[0.0f32; 3]; b.len()];
            for (i, target) in targets.iter().enumerate() {
                let s = i * per..(i + 1) * per;
                let ts = &b.t[s.clone()];
                let comp = composite(ts, &o.sigma_raw[s.clone()], &o.rgb[s.clone()], [0.0; 3]);
                let err = [0, 1, 2].map(|c| comp.colour[c] - target[c]);
                loss[k] += err.iter().map(|e| f64::from(e * e)).sum::<f64>();
                let (ds, dr) = composite_backward(
                    ts,
                    &o.sigma_raw[s.clone()],
                    &o.rgb[s.clone()],
                    [0.0; 3],
                    err.map(|e| e * scale),
                );
                d_sigma[s.clone()].copy_from_slice(&ds);
                d_rgb[s].copy_from_slice(&dr);
            }
            let net = if k == 0 { &self.coarse } else { &self.fine };
            grads.push(self.gradient(net, b, &d_sigma, &d_rgb));
        }
        let n = 3.0 * rays.len() as f64;
        let fine = grads.pop().unwrap_or_default();
        let coarse = grads.pop().unwrap_or_default();
        (loss[0] / n, loss[1] / n, coarse, fine)
    }

    /// Renders a view with the fine network (fixed samples), RGB in [0, 1].
    pub fn render(&self, camera: &Camera, bounds: (f32, f32)) -> Vec<[f32; 3]> {
        self.render_rays(&self.camera_rays(camera, bounds))
    }

    /// The rays through every pixel's centre of `camera`, row by row.
    pub fn camera_rays(&self, camera: &Camera, bounds: (f32, f32)) -> Vec<Ray> {
        (0..camera.height)
            .flat_map(|y| (0..camera.width).map(move |x| (x, y)))
            .map(|(x, y)| pixel_ray(camera, x as f32 + 0.5, y as f32 + 0.5, bounds, &self.frame))
            .collect()
    }

    /// The fine colours of `rays` with the fixed draws of rendering ([`fixed_draw`]).
    pub fn render_rays(&self, rays: &[Ray]) -> Vec<[f32; 3]> {
        let mut out = Vec::with_capacity(rays.len());
        let batch = (self.cfg.chunk / (self.cfg.coarse + self.cfg.fine)).max(1) * 4;
        for rs in rays.chunks(batch) {
            let (_, (fb, fo)) = self.passes(&fixed_draw(rs, &self.cfg));
            let per = fb.per_ray;
            for i in 0..rs.len() {
                let s = i * per..(i + 1) * per;
                out.push(
                    composite(
                        &fb.t[s.clone()],
                        &fo.sigma_raw[s.clone()],
                        &fo.rgb[s],
                        [0.0; 3],
                    )
                    .colour,
                );
            }
        }
        out
    }
}

/// What a training run did.
#[derive(Debug, Clone)]
pub struct NerfOutcome {
    pub nerf: Nerf,
    pub steps: u32,
    pub rays_per_step: usize,
    pub train_seconds: f64,
    /// Mean squared error of the fine colours over the last step's rays.
    pub last_loss: f64,
}

/// Trains a NeRF on `data`'s training views (see the module doc).
pub fn train(
    data: &Dataset,
    cfg: &NerfConfig,
    progress: &dyn Progress,
) -> Result<NerfOutcome, NerfError> {
    let mut nerf = Nerf::new(cfg, &data.points)?;
    let pixels = TrainingPixels::new(data)?;
    let mut rng = SplitMix64::new(cfg.seed ^ 0x4E_E2F);
    let start = Instant::now();
    let ctx = match cfg.device {
        NerfDevice::Gpu => Some(crate::gpu::context::GpuContext::new()?),
        NerfDevice::Cpu => None,
    };
    // The CPU steps with its own Adam; the GPU keeps everything on the device and is read
    // back only every 100 steps (the loss) and at the end (the parameters).
    let mut runner = match &ctx {
        Some(c) => Runner::Gpu(Box::new(gpu::GpuNerf::upload(c, &nerf)?)),
        None => Runner::Cpu(CpuAdam::new(&nerf)),
    };
    let mut step = 0u32;
    let mut last_loss = f64::NAN;
    while step < cfg.steps {
        let Some(frac) = schedule(cfg, step, start.elapsed().as_secs_f64()) else {
            break;
        };
        if progress.is_cancelled() {
            return Err(NerfError::Cancelled);
        }
        let draw = pixels.draw(cfg, &nerf.frame, &mut rng);
        let lr = cfg.lr_start * (cfg.lr_end / cfg.lr_start).powf(frac);
        step += 1;
        let loss = match &mut runner {
            Runner::Cpu(adam) => {
                let (_, fine, gc, gf) = nerf.step_gradients(&draw);
                adam.step(&mut nerf, &gc, &gf, lr);
                Some(fine)
            }
            Runner::Gpu(g) => {
                g.step(&draw, lr)?;
                if step == 1 || step.is_multiple_of(100) {
                    Some(g.last_loss()?.1)
                } else {
                    None
                }
            }
        };
        if let Some(l) = loss {
            last_loss = l;
            log_step(progress, step, l, lr, start);
        }
        progress.set(frac.clamp(0.0, 1.0));
    }
    if let Runner::Gpu(g) = &runner {
        if step > 0 {
            last_loss = g.last_loss()?.1;
        }
        let (c, f) = g.download()?;
        nerf.coarse.params = c;
        nerf.fine.params = f;
    }
    Ok(NerfOutcome {
        nerf,
        steps: step,
        rays_per_step: cfg.rays,
        train_seconds: start.elapsed().as_secs_f64(),
        last_loss,
    })
}

/// Where a training run steps.
enum Runner<'a> {
    Cpu(CpuAdam),
    Gpu(Box<gpu::GpuNerf<'a>>),
}

/// The fraction of the run done before `step` after `elapsed` seconds (of the time limit when
/// there is one, else of the steps); None once the time limit is reached, or when another
/// step as long as the mean so far would end past it (so a run ends within its limit, the
/// first step aside).
pub fn schedule(cfg: &NerfConfig, step: u32, elapsed: f64) -> Option<f64> {
    match cfg.seconds {
        Some(s) if step > 0 && elapsed * (1.0 + 1.0 / f64::from(step)) > s => None,
        Some(s) => Some((elapsed / s).min(1.0)),
        None => Some(f64::from(step) / f64::from(cfg.steps.max(1))),
    }
}

/// Logs the 1st and every 10th step.
fn log_step(progress: &dyn Progress, step: u32, fine_loss: f64, lr: f64, start: Instant) {
    if step.is_multiple_of(10) || step == 1 {
        progress.log(&format!(
            "nerf step {step}: fine MSE {fine_loss:.4} ({:.1} dB), lr {lr:.2e}, {:.1} s",
            -10.0 * fine_loss.max(1e-10).log10(),
            start.elapsed().as_secs_f64()
        ));
    }
}

/// Renders and measures every held-out view (full images), beside the mean training colour's
/// PSNR on the same views.
pub fn evaluate(nerf: &Nerf, data: &Dataset) -> Result<(EvalReport, f32), NerfError> {
    let ctx = match nerf.cfg.device {
        NerfDevice::Gpu => Some(crate::gpu::context::GpuContext::new()?),
        NerfDevice::Cpu => None,
    };
    let mut gpu = match &ctx {
        Some(c) => Some(gpu::GpuNerf::upload(c, nerf)?),
        None => None,
    };
    let mean =
        crate::splat::trainer::mean_colour(data).map_err(|e| NerfError::Invalid(e.to_string()))?;
    let mut views = Vec::new();
    let mut baseline = Vec::new();
    for v in &data.test {
        let truth = v
            .image
            .image()
            .map_err(|e| NerfError::Invalid(format!("{}: {e}", v.name)))?;
        let bounds = view_bounds(&v.camera, &data.points);
        let img = match gpu.as_mut() {
            Some(g) => render_gpu(g, nerf, &v.camera, bounds)?,
            None => nerf.render(&v.camera, bounds),
        };
        let m = |img: &[[f32; 3]]| {
            ViewMetrics::measure(&v.name, img, &truth, EvalRegion::Full)
                .map_err(|e| NerfError::Invalid(e.to_string()))
        };
        views.push(m(&img)?);
        baseline.push(m(&vec![mean; img.len()])?.psnr);
    }
    let base = baseline.iter().sum::<f32>() / baseline.len().max(1) as f32;
    Ok((EvalReport::from_views(views), base))
}

/// Renders a view on the GPU, a batch of rays at a time.
fn render_gpu(
    g: &mut gpu::GpuNerf<'_>,
    nerf: &Nerf,
    camera: &Camera,
    bounds: (f32, f32),
) -> Result<Vec<[f32; 3]>, NerfError> {
    let rays = nerf.camera_rays(camera, bounds);
    let mut out = Vec::with_capacity(rays.len());
    for rs in rays.chunks(nerf.cfg.rays) {
        out.extend(g.colours(&fixed_draw(rs, &nerf.cfg))?);
    }
    Ok(out)
}

#[cfg(test)]
mod tests;
