// Gradient accumulation with native float atomics (feature SHADER_FLOAT32_ATOMIC).
@group(0) @binding(7) var<storage, read_write> grads2d: array<atomic<f32>>;

fn add_grad(i: u32, v: f32) {
    atomicAdd(&grads2d[i], v);
}
