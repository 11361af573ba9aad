use super::*;
use crate::splat::cpu::test_scenes::{random_scene, ring_dataset_sized};

/// A small network for the gradient checks: every kind of layer, the skip included.
fn small_shape() -> MlpShape {
    MlpShape {
        depth: 4,
        width: 8,
        skip: 1,
        pos_dim: encoded_len(2),
        dir_dim: encoded_len(1),
    }
}

fn inputs(n: usize, shape: MlpShape, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut rng = SplitMix64::new(seed);
    let mut pos = Vec::new();
    let mut dir = Vec::new();
    for _ in 0..n {
        let p = [0; 3].map(|_| (rng.uniform() * 2.0 - 1.0) as f32);
        let d = [0; 3].map(|_| (rng.uniform() * 2.0 - 1.0) as f32);
        encode(p, (shape.pos_dim - 3) / 6, &mut pos);
        encode(d, (shape.dir_dim - 3) / 6, &mut dir);
    }
    (pos, dir)
}

/// L = Σ a·σ_raw + Σ b·rgb for fixed random a, b, in f64.
fn weighted(out: &mlp::Output, a: &[f32], b: &[[f32; 3]]) -> f64 {
    let mut l = 0.0f64;
    for i in 0..a.len() {
        l += f64::from(a[i]) * f64::from(out.sigma_raw[i]);
        for (w, v) in b[i].iter().zip(&out.rgb[i]) {
            l += f64::from(*w) * f64::from(*v);
        }
    }
    l
}

#[test]
fn mlp_gradients_match_finite_differences_in_every_layer() {
    let shape = small_shape();
    let mut net = Mlp::new(shape, 7);
    let n = 6;
    let (pos, dir) = inputs(n, shape, 11);
    let mut rng = SplitMix64::new(3);
    let a: Vec<f32> = (0..n).map(|_| (rng.uniform() * 2.0 - 1.0) as f32).collect();
    let b: Vec<[f32; 3]> = (0..n)
        .map(|_| [0; 3].map(|_| (rng.uniform() * 2.0 - 1.0) as f32))
        .collect();
    let mut cache = Cache::default();
    net.forward(&pos, &dir, n, Some(&mut cache));
    let mut grad = vec![0.0f32; net.params.len()];
    net.backward(&cache, &a, &b, &mut grad);
    let eps = 1e-3f32;
    let mut checked = 0;
    for layer in net.layers.clone() {
        // Six parameters of each layer: weights from its start, middle and end, and biases.
        let picks = [
            layer.offset,
            layer.offset + layer.inputs * layer.outputs / 2,
            layer.bias_offset() - 1,
            layer.bias_offset(),
            layer.end() - 1,
            layer.offset + 1,
        ];
        for &p in &picks {
            let keep = net.params[p];
            net.params[p] = keep + eps;
            let up = weighted(&net.forward(&pos, &dir, n, None), &a, &b);
            net.params[p] = keep - eps;
            let down = weighted(&net.forward(&pos, &dir, n, None), &a, &b);
            net.params[p] = keep;
            let fd = (up - down) / (2.0 * f64::from(eps));
            let an = f64::from(grad[p]);
            assert!(
                (fd - an).abs() <= 2e-3 + 2e-2 * fd.abs(),
                "parameter {p} of layer {layer:?}: analytic {an}, finite difference {fd}"
            );
            checked += 1;
        }
    }
    assert_eq!(checked, 6 * (shape.depth + 4));
}

#[test]
fn the_paper_network_has_its_layers_and_parameter_count() {
    let cfg = NerfConfig::default();
    let net = Mlp::new(cfg.shape(), 1);
    assert_eq!(net.shape.pos_dim, 63);
    assert_eq!(net.shape.dir_dim, 27);
    let sizes: Vec<(usize, usize)> = net.layers.iter().map(|l| (l.inputs, l.outputs)).collect();
    assert_eq!(
        sizes,
        vec![
            (63, 256),
            (256, 256),
            (256, 256),
            (256, 256),
            (256, 256),
            (256 + 63, 256),
            (256, 256),
            (256, 256),
            (256, 1),
            (256, 256),
            (256 + 27, 128),
            (128, 3),
        ]
    );
    let count: usize = sizes.iter().map(|(i, o)| i * o + o).sum();
    assert_eq!(net.params.len(), count);
}

fn composite_loss(t: &[f32], s: &[f32], rgb: &[[f32; 3]], bg: [f32; 3], d: [f32; 3]) -> f64 {
    let c = composite(t, s, rgb, bg).colour;
    (0..3).map(|k| f64::from(c[k] * d[k])).sum()
}

#[test]
fn compositing_gradients_match_finite_differences() {
    let mut rng = SplitMix64::new(21);
    let n = 9;
    let mut t: Vec<f32> = (0..n).map(|_| 1.0 + 3.0 * rng.uniform() as f32).collect();
    t.sort_by(f32::total_cmp);
    // Raw densities on both sides of 0 (the ReLU), none within reach of the kink.
    let mut s: Vec<f32> = (0..n).map(|_| (rng.uniform() * 3.0 - 0.8) as f32).collect();
    for v in &mut s {
        if v.abs() < 0.05 {
            *v = 0.3;
        }
    }
    let rgb: Vec<[f32; 3]> = (0..n)
        .map(|_| [0; 3].map(|_| rng.uniform() as f32))
        .collect();
    let bg = [0.2, 0.5, 0.9];
    let d = [0.7, -1.1, 0.4];
    let (ds, dr) = composite_backward(&t, &s, &rgb, bg, d);
    let eps = 1e-3f32;
    for i in 0..n {
        let mut sp = s.clone();
        sp[i] += eps;
        let mut sm = s.clone();
        sm[i] -= eps;
        let fd = (composite_loss(&t, &sp, &rgb, bg, d) - composite_loss(&t, &sm, &rgb, bg, d))
            / (2.0 * f64::from(eps));
        assert!(
            (fd - f64::from(ds[i])).abs() <= 1e-3 + 1e-2 * fd.abs(),
            "σ {i}: analytic {}, finite difference {fd}",
            ds[i]
        );
        for c in 0..3 {
            let mut rp = rgb.clone();
            rp[i][c] += eps;
            let mut rm = rgb.clone();
            rm[i][c] -= eps;
            let fd = (composite_loss(&t, &s, &rp, bg, d) - composite_loss(&t, &s, &rm, bg, d))
                / (2.0 * f64::from(eps));
            assert!((fd - f64::from(dr[i][c])).abs() <= 1e-4 + 1e-2 * fd.abs());
        }
    }
    // The background shows through exactly where nothing is dense.
    let clear = composite(&t, &vec![-1.0; n], &rgb, bg);
    assert_eq!(clear.colour, bg);
    assert!(clear.weights.iter().all(|w| *w == 0.0));
}

#[test]
fn fine_samples_follow_the_coarse_weights() {
    let t: Vec<f32> = (0..64).map(|i| 2.0 + i as f32 * 0.1).collect();
    // All the weight in the bins around t = 4.0.
    let w: Vec<f32> = t
        .iter()
        .map(|x| if (x - 4.0).abs() < 0.15 { 1.0 } else { 0.0 })
        .collect();
    let u: Vec<f32> = (0..128).map(|k| (k as f32 + 0.5) / 128.0).collect();
    let f = sample_pdf(&t, &w, &u);
    assert_eq!(f.len(), 128);
    assert!(
        f.windows(2).all(|p| p[0] <= p[1]),
        "ascending u, ascending samples"
    );
    let near = f.iter().filter(|x| (**x - 4.0).abs() < 0.25).count();
    assert!(near > 110, "{near} of 128 fine samples near the weight");
    assert!(f.iter().all(|x| *x >= t[0] && *x <= t[63]));
    // Flat weights: samples spread evenly.
    let flat = sample_pdf(&t, &[1.0; 64], &u);
    let mid = flat.iter().filter(|x| **x < 5.15).count();
    assert!((54..=74).contains(&mid), "{mid} of 128 in the first half");
}

#[test]
fn a_pixel_ray_passes_through_what_the_camera_sees_there() {
    let cam = Camera::look_at(
        [1.0, -4.0, 0.5],
        [0.2, 0.3, 0.1],
        [0.0, 0.0, 1.0],
        40,
        30,
        36.0,
    );
    let frame = SceneFrame {
        centre: [0.5, 0.5, 0.0],
        scale: 0.5,
    };
    let p = [0.3f32, 0.6, -0.2];
    let c = cam.to_camera(p);
    let (x, y) = (cam.fx * c[0] / c[2] + cam.cx, cam.fy * c[1] / c[2] + cam.cy);
    let ray = pixel_ray(&cam, x, y, (c[2], c[2] * 2.0), &frame);
    // The near bound is p's depth: the ray's start is p, in the normalised frame.
    let q = ray.at(ray.near);
    let want = frame.to_frame(p);
    for k in 0..3 {
        assert!((q[k] - want[k]).abs() < 1e-4, "{q:?} vs {want:?}");
    }
}

#[test]
fn nerf_learns_a_small_scene_and_beats_the_mean_colour_held_out() {
    let truth = random_scene(5, 24, 0);
    let mut data = ring_dataset_sized(&truth, 16, (24, 18), 22.0);
    data.points = truth.means.clone();
    let cfg = NerfConfig {
        depth: 4,
        width: 32,
        skip: 1,
        pos_bands: 6,
        dir_bands: 2,
        coarse: 16,
        fine: 16,
        rays: 128,
        steps: 300,
        // A small network at a short budget learns faster at 4× the paper's rates.
        lr_start: 2e-3,
        lr_end: 2e-4,
        chunk: 4096,
        seed: 2,
        device: NerfDevice::Cpu,
        ..NerfConfig::default()
    };
    let out = train(&data, &cfg, &crate::progress::NoProgress).expect("trains");
    assert_eq!(out.steps, 300);
    let (eval, base) = evaluate(&out.nerf, &data).expect("evaluates");
    eprintln!(
        "held out {:.2} dB (mean colour {base:.2} dB) after {} steps in {:.1} s",
        eval.psnr, out.steps, out.train_seconds
    );
    assert!(
        eval.psnr > base + 3.0,
        "held-out PSNR {} dB against the mean colour's {base} dB",
        eval.psnr
    );
    // Cancelling stops a run.
    struct Cancelled;
    impl crate::progress::Progress for Cancelled {
        fn set(&self, _: f64) {}
        fn is_cancelled(&self) -> bool {
            true
        }
    }
    assert!(matches!(
        train(&data, &cfg, &Cancelled),
        Err(NerfError::Cancelled)
    ));
    let bad = NerfConfig {
        skip: 7,
        ..NerfConfig::default()
    };
    assert!(matches!(Nerf::new(&bad, &[]), Err(NerfError::Invalid(_))));
}
