//! The LiDAR depth loss kernel (`depth_loss.wgsl`) against its CPU twin
//! (`depth::loss_and_grad`), on a rendered frame's expected depth.

use crate::common;

use sylva::splat::depth;
use sylva::splat::gpu::buffers::{read_buffer, storage_from};
use sylva::splat::gpu::depth::DepthLoss;
use sylva::splat::gpu::{GpuSplats, Renderer};

#[test]
fn gpu_depth_loss_matches_cpu_twin() {
    let Some(ctx) = common::context() else { return };
    let model = common::scene(12, 300, 0, 1.2);
    let (w, h) = (61u32, 37u32);
    let cam = common::camera(w, h, 0.8 * w as f32);
    let renderer = Renderer::new(&ctx);
    let splats = GpuSplats::upload(&ctx, &model).expect("upload");
    let frame = renderer
        .render(&ctx, &splats, &cam, [0.0; 3])
        .expect("render");
    let rendered = frame.read_depth(&ctx).expect("depth");
    // A LiDAR map near the rendered depth, with holes, and some pixels exactly equal.
    let lidar: Vec<f32> = rendered
        .iter()
        .enumerate()
        .map(|(p, &d)| match p % 5 {
            0 => 0.0,
            1 => d,
            k => 3.0 + 0.3 * k as f32 + 0.1 * (p as f32 * 0.13).sin(),
        })
        .collect();
    let weight = 0.3;
    let valid = depth::valid_count(&lidar);
    let map = storage_from(&ctx, "lidar", &lidar).expect("buffer");
    let kernel = DepthLoss::new(&ctx);
    let mut enc = ctx.device.create_command_encoder(&Default::default());
    kernel
        .encode(&ctx, &mut enc, &frame, &map, weight, valid)
        .expect("encode");
    ctx.queue.submit([enc.finish()]);
    let got: Vec<f32> = read_buffer(&ctx, &frame.depth_grad, (w * h) as usize).expect("read");
    let (_, want) = depth::loss_and_grad(&rendered, &lidar, weight);
    let nonzero = want.iter().filter(|g| **g != 0.0).count();
    assert!(
        nonzero > (w * h / 3) as usize,
        "only {nonzero} pixels with a gradient"
    );
    for (p, (a, b)) in got.iter().zip(&want).enumerate() {
        assert!(
            (a - b).abs() <= 1e-6 * b.abs() + 1e-12,
            "pixel {p}: gpu {a} cpu {b}"
        );
    }
}
