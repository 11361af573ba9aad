// One dense layer of the NeRF MLP (src/nerf/gpu.rs; CPU twin `Mlp::forward` in src/nerf/mlp.rs):
// y[s][j] = act(sum_k x[s][k] w[k][j] + b[j]) for the samples s of a chunk, where x is the
// concatenation [xa[s], xb[s]] (xb empty when in_b = 0) and w, b sit in the network's flat
// parameters at w_off (row-major in × out, the bias after it). act: 0 none, 1 ReLU, 2 sigmoid.
// Tiles of 16 × 16 outputs per workgroup, the inner dimension staged 16 at a time in
// workgroup memory. `DenseParams` is prepended by gpu.rs.

@group(0) @binding(0) var<storage, read> dp: DenseParams;
@group(0) @binding(1) var<storage, read> net: array<f32>;
@group(0) @binding(2) var<storage, read> xa: array<f32>;
@group(0) @binding(3) var<storage, read> xb: array<f32>;
@group(0) @binding(4) var<storage, read_write> y: array<f32>;

var<workgroup> ta: array<array<f32, 16>, 16>;
var<workgroup> tb: array<array<f32, 16>, 16>;

fn x_at(s: u32, k: u32) -> f32 {
    if k < dp.in_a {
        return xa[s * dp.in_a + k];
    }
    return xb[s * dp.in_b + (k - dp.in_a)];
}

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let row = wg.y * 16u + lid.y;
    let col = wg.x * 16u + lid.x;
    let kin = dp.in_a + dp.in_b;
    var acc = 0.0;
    for (var k0 = 0u; k0 < kin; k0 += 16u) {
        let ka = k0 + lid.x;
        var a = 0.0;
        if row < dp.n && ka < kin {
            a = x_at(row, ka);
        }
        ta[lid.y][lid.x] = a;
        let kb = k0 + lid.y;
        var b = 0.0;
        if kb < kin && col < dp.outs {
            b = net[dp.w_off + kb * dp.outs + col];
        }
        tb[lid.y][lid.x] = b;
        workgroupBarrier();
        for (var k = 0u; k < 16u; k++) {
            acc += ta[lid.y][k] * tb[k][lid.x];
        }
        workgroupBarrier();
    }
    if row < dp.n && col < dp.outs {
        var v = acc + net[dp.w_off + kin * dp.outs + col];
        if dp.act == 1u {
            v = max(v, 0.0);
        } else if dp.act == 2u {
            v = 1.0 / (1.0 + exp(-v));
        }
        y[row * dp.outs + col] = v;
    }
}
