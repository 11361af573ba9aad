// Shared declarations of the fused loss kernels (Sylva gpuloss). The host prepends the
// constants WIN (11-tap Gaussian window, sigma 1.5, sum 1), HALF = 5, LAMBDA, C1, C2, and the
// parameter buffer `Params` (its `wgsl_struct!` in kernel.rs).
// Each pass uses a subset of these bindings; unused ones are left out of its layout.

@group(0) @binding(0) var<storage, read> params: Params;
// Rendered image, RGB f32 interleaved, row-major.
@group(0) @binding(1) var<storage, read> rendered: array<f32>;
// Target image, one RGBA8 per pixel, R in the low byte.
@group(0) @binding(2) var<storage, read> target_rgba: array<u32>;
// Horizontal blur of (x, y, x², y², xy) per channel: 15 floats per pixel.
@group(0) @binding(3) var<storage, read_write> stats_h: array<f32>;
// dL/d(mu_x, E[x²], E[xy]) per channel: 9 floats per pixel.
@group(0) @binding(4) var<storage, read_write> dmaps: array<f32>;
// Horizontal blur of dmaps: 9 floats per pixel.
@group(0) @binding(5) var<storage, read_write> dmaps_h: array<f32>;
// Per-workgroup (sum |x - y|, sum SSIM) pairs.
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;
// dL/drendered, RGB f32 interleaved.
@group(0) @binding(7) var<storage, read_write> grad_out: array<f32>;
// (loss, l1, ssim, 0).
@group(0) @binding(8) var<storage, read_write> loss_out: array<f32>;

fn load_rendered(i: u32) -> vec3<f32> {
    return vec3<f32>(rendered[3u * i], rendered[3u * i + 1u], rendered[3u * i + 2u]);
}

fn load_target(i: u32) -> vec3<f32> {
    return unpack4x8unorm(target_rgba[i]).xyz;
}

fn load3(buf_value: ptr<function, array<f32, 15>>, o: u32) -> vec3<f32> {
    return vec3<f32>((*buf_value)[o], (*buf_value)[o + 1u], (*buf_value)[o + 2u]);
}

// Number of averaged values: pixels × 3 channels.
fn value_count() -> f32 {
    return 3.0 * f32(params.width) * f32(params.height);
}
