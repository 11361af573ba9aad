// Gradient accumulation without float atomics: compare-and-swap on the f32 bit pattern. A
// template: `raster_bwd.rs` emits one copy per screen-gradient slot, substituting the slot number
// for SLOT and its binding for BINDING.
@group(0) @binding(BINDING) var<storage, read_write> grads2d_SLOT: array<atomic<u32>>;

fn add_SLOT(i: u32, v: f32) {
    var old = atomicLoad(&grads2d_SLOT[i]);
    loop {
        let r = atomicCompareExchangeWeak(&grads2d_SLOT[i], old,
            bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}
