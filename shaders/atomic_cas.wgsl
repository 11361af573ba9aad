// Gradient accumulation without float atomics: compare-and-swap on the f32 bit pattern.
@group(0) @binding(7) var<storage, read_write> grads2d: array<atomic<u32>>;

fn add_grad(i: u32, v: f32) {
    var old = atomicLoad(&grads2d[i]);
    loop {
        let r = atomicCompareExchangeWeak(&grads2d[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}
