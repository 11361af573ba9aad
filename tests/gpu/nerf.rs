//! The NeRF's GPU kernels (`shaders/nerf/*.wgsl`) against their CPU twins (src/nerf): each
//! network's forward and backward pass, and whole training steps (encoding, compositing, fine
//! sampling, both networks and Adam) from the same draws.

use crate::common;

use sylva::nerf::gpu::GpuNerf;
use sylva::nerf::mlp::Cache;
use sylva::nerf::render::{encode, encoded_len};
use sylva::nerf::{Nerf, NerfConfig, NerfDevice, SceneFrame, StepDraw};
use sylva::rng::SplitMix64;

/// A small NeRF whose sizes are not multiples of the kernels' 16-wide tiles, with the skip.
fn small_config() -> NerfConfig {
    NerfConfig {
        depth: 4,
        width: 40,
        skip: 1,
        pos_bands: 3,
        dir_bands: 2,
        coarse: 12,
        fine: 20,
        rays: 48,
        chunk: 200,
        seed: 9,
        device: NerfDevice::Gpu,
        ..NerfConfig::default()
    }
}

fn close(name: &str, gpu: &[f32], cpu: &[f32], tol: f32) {
    assert_eq!(gpu.len(), cpu.len(), "{name}: lengths");
    let scale = cpu.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
    for (i, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(
            (g - c).abs() <= tol * scale,
            "{name}[{i}]: GPU {g}, CPU {c} (largest |CPU| {scale})"
        );
    }
}

fn encodings(n: usize, cfg: &NerfConfig, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut rng = SplitMix64::new(seed);
    let (mut pos, mut dir) = (Vec::new(), Vec::new());
    for _ in 0..n {
        let p = [0; 3].map(|_| (rng.uniform() * 2.0 - 1.0) as f32);
        let d = [0; 3].map(|_| (rng.uniform() * 2.0 - 1.0) as f32);
        encode(p, cfg.pos_bands, &mut pos);
        encode(d, cfg.dir_bands, &mut dir);
    }
    (pos, dir)
}

#[test]
fn nerf_network_forward_and_backward_match_the_cpu() {
    let Some(ctx) = common::context() else { return };
    let cfg = small_config();
    let nerf = Nerf::new(&cfg, &[[0.0; 3], [1.0, 1.0, 1.0]]).expect("nerf");
    let gpu = GpuNerf::upload(&ctx, &nerf).expect("upload");
    let n = 150;
    let (pos, dir) = encodings(n, &cfg, 4);
    assert_eq!(pos.len(), n * encoded_len(cfg.pos_bands));
    for (k, net) in [&nerf.coarse, &nerf.fine].into_iter().enumerate() {
        let (sigma, rgb) = gpu.forward_net(k, &pos, &dir, n).expect("forward");
        let mut cache = Cache::default();
        let out = net.forward(&pos, &dir, n, Some(&mut cache));
        close("sigma", &sigma, &out.sigma_raw, 1e-4);
        let cpu_rgb: Vec<f32> = out.rgb.iter().flatten().copied().collect();
        close("rgb", &rgb, &cpu_rgb, 1e-4);
        // Backward from random derivatives: the GPU takes them before the sigmoid.
        let mut rng = SplitMix64::new(17 + k as u64);
        let d_sigma: Vec<f32> = (0..n).map(|_| (rng.uniform() - 0.5) as f32).collect();
        let d_rgb: Vec<[f32; 3]> = (0..n)
            .map(|_| [0; 3].map(|_| (rng.uniform() - 0.5) as f32))
            .collect();
        let d_raw: Vec<f32> = d_rgb
            .iter()
            .zip(&out.rgb)
            .flat_map(|(d, c)| [0, 1, 2].map(|i| d[i] * c[i] * (1.0 - c[i])))
            .collect();
        let g = gpu
            .gradient_net(k, &pos, &dir, n, &d_sigma, &d_raw)
            .expect("gradient");
        let mut cg = vec![0.0f32; net.params.len()];
        net.backward(&cache, &d_sigma, &d_rgb, &mut cg);
        // Layer by layer, so a failure names the layer.
        for (l, layer) in net.layers.iter().enumerate() {
            close(
                &format!("network {k} layer {l} gradient"),
                &g[layer.offset..layer.end()],
                &cg[layer.offset..layer.end()],
                2e-3,
            );
        }
    }
}

#[test]
fn nerf_training_steps_on_the_gpu_match_the_cpu() {
    let Some(ctx) = common::context() else { return };
    let cfg = small_config();
    let points: Vec<[f32; 3]> = (0..50)
        .map(|i| {
            let a = i as f32 * 0.7;
            [a.sin() * 1.5, a.cos() * 1.5, (i % 5) as f32 * 0.2]
        })
        .collect();
    let mut cpu = Nerf::new(&cfg, &points).expect("nerf");
    let mut gpu = GpuNerf::upload(&ctx, &cpu).expect("upload");
    let frame = SceneFrame::of_points(&points);
    let cam = sylva::splat::camera::Camera::look_at(
        [0.5, -5.0, 1.0],
        [0.0, 0.0, 0.3],
        [0.0, 0.0, 1.0],
        16,
        12,
        14.0,
    );
    let bounds = sylva::nerf::view_bounds(&cam, &points);
    let mut rng = SplitMix64::new(23);
    let mut adam_state: Option<sylva::nerf::CpuAdam> = None;
    for step in 1..=3u32 {
        // Rays through random pixels, random targets, jittered coarse bins, sorted u.
        let mut draw = StepDraw {
            rays: Vec::new(),
            targets: Vec::new(),
            coarse_t: Vec::new(),
            u: Vec::new(),
        };
        for _ in 0..cfg.rays {
            let (x, y) = (rng.uniform() as f32 * 16.0, rng.uniform() as f32 * 12.0);
            let ray = sylva::nerf::pixel_ray(&cam, x, y, bounds, &frame);
            draw.coarse_t
                .extend(sylva::nerf::render::stratified(&ray, cfg.coarse, || {
                    rng.uniform() as f32
                }));
            let mut u: Vec<f32> = (0..cfg.fine).map(|_| rng.uniform() as f32).collect();
            u.sort_by(f32::total_cmp);
            draw.u.extend(u);
            draw.targets.push([0; 3].map(|_| rng.uniform() as f32));
            draw.rays.push(ray);
        }
        let (lc, lf, gc, gf) = cpu.step_gradients(&draw);
        let lr = 5e-4;
        let state = adam_state.get_or_insert_with(|| sylva::nerf::CpuAdam::new(&cpu));
        state.step(&mut cpu, &gc, &gf, lr);
        gpu.step(&draw, lr).expect("step");
        let (gl_c, gl_f) = gpu.last_loss().expect("loss");
        assert!(
            (gl_c - lc).abs() <= 1e-3 * lc.max(1e-3) && (gl_f - lf).abs() <= 1e-3 * lf.max(1e-3),
            "step {step}: losses GPU {gl_c} / {gl_f}, CPU {lc} / {lf}"
        );
        let (pc, pf) = gpu.download().expect("download");
        // Adam moves each parameter by about ±lr whatever its gradient's size, so a gradient
        // near 0 (|g| ~ ε) may move differently on the two: 99 % of parameters within lr / 10.
        for (name, g, c) in [
            ("coarse", &pc, &cpu.coarse.params),
            ("fine", &pf, &cpu.fine.params),
        ] {
            let near = g
                .iter()
                .zip(c.iter())
                .filter(|(a, b)| (*a - *b).abs() <= 0.1 * lr as f32)
                .count();
            assert!(
                near as f64 >= 0.99 * g.len() as f64,
                "step {step}, {name}: {near} of {} parameters within lr/10",
                g.len()
            );
        }
    }
    // Rendering: the fine colours of fixed draws.
    let rays: Vec<_> = (0..cfg.rays)
        .map(|i| {
            sylva::nerf::pixel_ray(
                &cam,
                (i % 16) as f32 + 0.5,
                (i / 16) as f32 + 0.5,
                bounds,
                &frame,
            )
        })
        .collect();
    let draw = sylva::nerf::fixed_draw(&rays, &cfg);
    let colours = gpu.colours(&draw).expect("colours");
    let cpu_render = cpu.render_rays(&rays);
    let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    close("render", &flat(&colours), &flat(&cpu_render), 1e-3);
}

#[test]
fn nerf_trains_and_evaluates_on_the_gpu() {
    let Some(_ctx) = common::context() else {
        return;
    };
    let truth = crate::test_scenes::random_scene(5, 24, 0);
    let mut data = crate::test_scenes::ring_dataset_sized(&truth, 16, (24, 18), 22.0);
    data.points = truth.means.clone();
    let cfg = NerfConfig {
        steps: 60,
        lr_start: 2e-3,
        lr_end: 2e-4,
        ..small_config()
    };
    let start = Nerf::new(&cfg, &data.points).expect("nerf");
    let out = sylva::nerf::train(&data, &cfg, &sylva::progress::NoProgress).expect("trains");
    assert_eq!(out.steps, 60);
    assert!(out.last_loss.is_finite(), "{}", out.last_loss);
    assert_ne!(
        out.nerf.fine.params, start.fine.params,
        "the GPU's parameters came back"
    );
    let (eval, base) = sylva::nerf::evaluate(&out.nerf, &data).expect("evaluates");
    assert!(
        eval.psnr > base,
        "held out {} dB against the mean colour's {base} dB",
        eval.psnr
    );
}
