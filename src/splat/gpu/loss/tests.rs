//! GPU loss and gradient against the f64 CPU reference (`splat_cpu`). Needs a Vulkan adapter
//! (lavapipe is fine: `WGPU_BACKEND=vulkan XDG_RUNTIME_DIR=/tmp`); without one the tests print a
//! skip reason and return.

use crate::splat::gpu::loss::{LOSS_OUT_BYTES, LossError, LossKernel, SSIM_LAMBDA, ssim_window};
use rand::rngs::ChaCha8Rng;
use rand::{RngExt, SeedableRng};
use wgpu::util::DeviceExt;

fn device() -> Option<(wgpu::Device, wgpu::Queue)> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter =
        match pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions::default()))
        {
            Ok(a) => a,
            Err(e) => {
                crate::testing::skip("gpu", &format!("GPU loss test: no adapter ({e})"));
                return None;
            }
        };
    match pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor::default())) {
        Ok(dq) => Some(dq),
        Err(e) => {
            crate::testing::skip("gpu", &format!("GPU loss test: no device ({e})"));
            None
        }
    }
}

struct Images {
    rendered: Vec<f32>,
    target: Vec<u32>,
}

fn random_images(width: usize, height: usize, seed: u64) -> Images {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = width * height;
    let rendered = (0..n * 3)
        .map(|i| {
            let x = ((i / 3) % width) as f32;
            (0.5 + 0.3 * (0.4 * x + (i % 3) as f32).sin() + rng.random_range(-0.2f32..0.2))
                .clamp(0.0, 1.0)
        })
        .collect();
    let target = (0..n)
        .map(|_| u32::from_le_bytes([0, 1, 2, 3].map(|_| rng.random::<u8>())))
        .collect();
    Images { rendered, target }
}

fn read_f32(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    src: &wgpu::Buffer,
    bytes: u64,
) -> Vec<f32> {
    let staging = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: bytes,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut enc = device.create_command_encoder(&Default::default());
    enc.copy_buffer_to_buffer(src, 0, &staging, 0, bytes);
    queue.submit([enc.finish()]);
    staging
        .slice(..)
        .map_async(wgpu::MapMode::Read, |r| r.expect("map"));
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .expect("poll");
    let view = staging.slice(..).get_mapped_range().expect("mapped range");
    bytemuck::cast_slice(&view).to_vec()
}

/// Runs the kernel; returns (loss_out, grad).
fn run_gpu(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    kernel: &LossKernel,
    img: &Images,
    w: u32,
    h: u32,
) -> (Vec<f32>, Vec<f32>) {
    let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
    let init = |contents: &[u8]| {
        device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: None,
            contents,
            usage: storage,
        })
    };
    let rendered = init(bytemuck::cast_slice(&img.rendered));
    let target = init(bytemuck::cast_slice(&img.target));
    let grad_bytes = u64::from(w * h * 12);
    let grad = device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: grad_bytes,
        usage: storage,
        mapped_at_creation: false,
    });
    let loss = device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: LOSS_OUT_BYTES,
        usage: storage,
        mapped_at_creation: false,
    });
    let mut enc = device.create_command_encoder(&Default::default());
    kernel
        .encode(device, &mut enc, &rendered, &target, &grad, &loss, w, h)
        .expect("encode");
    queue.submit([enc.finish()]);
    (
        read_f32(device, queue, &loss, LOSS_OUT_BYTES),
        read_f32(device, queue, &grad, grad_bytes),
    )
}

fn compare_with_cpu(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    kernel: &LossKernel,
    w: u32,
    h: u32,
    seed: u64,
) {
    let img = random_images(w as usize, h as usize, seed);
    let (loss, grad) = run_gpu(device, queue, kernel, &img, w, h);
    let x: Vec<[f64; 3]> = img
        .rendered
        .chunks(3)
        .map(|p| [0, 1, 2].map(|c| f64::from(p[c])))
        .collect();
    let y: Vec<[f64; 3]> = img
        .target
        .iter()
        .map(|&t| [0, 1, 2].map(|c| f64::from(t.to_le_bytes()[c]) / 255.0))
        .collect();
    let (value, cpu_grad) = crate::splat::cpu::loss_and_grad_f64(&x, &y, w, h).expect("cpu loss");
    let rel = |a: f32, b: f64| (f64::from(a) - b).abs() / b.abs();
    assert!(
        rel(loss[0], value.loss) < 1e-4,
        "loss {} vs {}",
        loss[0],
        value.loss
    );
    assert!(
        rel(loss[1], value.l1) < 1e-4,
        "l1 {} vs {}",
        loss[1],
        value.l1
    );
    assert!(
        rel(loss[2], value.ssim) < 1e-4,
        "ssim {} vs {}",
        loss[2],
        value.ssim
    );
    let scale = cpu_grad
        .iter()
        .flatten()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let mut worst = 0.0f64;
    for (p, g) in cpu_grad.iter().enumerate() {
        for c in 0..3 {
            worst = worst.max((f64::from(grad[3 * p + c]) - g[c]).abs());
        }
    }
    eprintln!(
        "{w}x{h}: loss {} vs {}, max |grad err| {worst:e} (max |grad| {scale:e})",
        loss[0], value.loss
    );
    assert!(
        worst < 1e-5 && worst < 1e-4 * scale,
        "gradient error {worst:e} (scale {scale:e})"
    );
}

#[test]
fn gpu_loss_and_gradient_match_cpu_reference() {
    let Some((device, queue)) = device() else {
        return;
    };
    let kernel = LossKernel::new(&device);
    compare_with_cpu(&device, &queue, &kernel, 40, 30, 1);
    // A different size on the same kernel (scratch reallocation), smaller than the window.
    compare_with_cpu(&device, &queue, &kernel, 9, 7, 2);
    compare_with_cpu(&device, &queue, &kernel, 40, 30, 3);
}

#[test]
fn constants_agree_with_cpu_reference() {
    let cpu = crate::splat::cpu::loss::ssim_window();
    for (g, c) in ssim_window().iter().zip(cpu) {
        assert!((f64::from(*g) - c).abs() < 1e-7);
    }
    let cpu_lambda = crate::splat::cpu::loss::SSIM_LAMBDA as f32;
    assert_eq!(SSIM_LAMBDA, cpu_lambda);
}

#[test]
fn bad_sizes_are_errors() {
    let Some((device, _queue)) = device() else {
        return;
    };
    let kernel = LossKernel::new(&device);
    let buf = |size| {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: None,
            size,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        })
    };
    let (small, ok) = (buf(16), buf(4096));
    let mut enc = device.create_command_encoder(&Default::default());
    assert_eq!(
        kernel.encode(&device, &mut enc, &ok, &ok, &ok, &ok, 0, 5),
        Err(LossError::EmptyImage)
    );
    let err = kernel.encode(&device, &mut enc, &small, &ok, &ok, &ok, 10, 10);
    assert_eq!(
        err,
        Err(LossError::BufferTooSmall {
            what: "rendered",
            needed: 1200,
            got: 16
        })
    );
}
