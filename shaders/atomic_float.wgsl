// Gradient accumulation with native float atomics (feature SHADER_FLOAT32_ATOMIC). A template:
// `raster_bwd.rs` emits one copy per screen-gradient slot, substituting the slot number for SLOT
// and its binding for BINDING.
@group(0) @binding(BINDING) var<storage, read_write> grads2d_SLOT: array<atomic<f32>>;

fn add_SLOT(i: u32, v: f32) {
    atomicAdd(&grads2d_SLOT[i], v);
}
