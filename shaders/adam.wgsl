// Adam (torch form, as the reference 3DGS): one thread per float of one parameter buffer.
// m = b1 m + (1 - b1) g; v = b2 v + (1 - b2) g^2; p -= lr * (m / bc1) / (sqrt(v / bc2) + eps),
// bc = 1 - b^t. The first `n_first` floats of each stride use `lr_first`, the rest `lr_rest`
// (SH: DC vs higher bands). `AdamParams` is prepended by `adam.rs` (its `wgsl_struct!`).

@group(0) @binding(0) var<storage, read> ap: AdamParams;
@group(0) @binding(1) var<storage, read_write> param: array<f32>;
@group(0) @binding(2) var<storage, read> grad: array<f32>;
@group(0) @binding(3) var<storage, read_write> m1: array<f32>;
@group(0) @binding(4) var<storage, read_write> m2: array<f32>;

@compute @workgroup_size(256)
fn main(inv: Invocation) {
    let i = flat_index(inv);
    if i >= ap.n_floats {
        return;
    }
    let g = grad[i];
    let m = ap.beta1 * m1[i] + (1.0 - ap.beta1) * g;
    let v = ap.beta2 * m2[i] + (1.0 - ap.beta2) * g * g;
    m1[i] = m;
    m2[i] = v;
    let lr = select(ap.lr_rest, ap.lr_first, i % ap.stride < ap.n_first);
    param[i] -= lr * (m / ap.bc1) / (sqrt(v / ap.bc2) + ap.eps);
}
