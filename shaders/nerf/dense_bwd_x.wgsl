// The input gradient of one dense layer (src/nerf/gpu.rs; CPU twin `Mlp::backward`):
// dx[s][i] = sum_j dy[s][j] w[i][j] for the first in_a inputs (the part of a concatenated input
// that came from the layer before), times (prev[s][i] > 0) when mask = 1 (that layer's ReLU),
// added to dx when accumulate = 1 (two layers reading the same input). Tiles of 16 × 16.

@group(0) @binding(0) var<storage, read> dp: DenseParams;
@group(0) @binding(1) var<storage, read> net: array<f32>;
@group(0) @binding(2) var<storage, read> dy: array<f32>;
@group(0) @binding(3) var<storage, read> prev: array<f32>;
@group(0) @binding(4) var<storage, read_write> dx: array<f32>;

var<workgroup> ta: array<array<f32, 16>, 16>;
var<workgroup> tb: array<array<f32, 16>, 16>;

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let row = wg.y * 16u + lid.y;
    let col = wg.x * 16u + lid.x;
    var acc = 0.0;
    for (var k0 = 0u; k0 < dp.outs; k0 += 16u) {
        let ka = k0 + lid.x;
        var a = 0.0;
        if row < dp.n && ka < dp.outs {
            a = dy[row * dp.outs + ka];
        }
        ta[lid.y][lid.x] = a;
        let kb = k0 + lid.y;
        var b = 0.0;
        if kb < dp.outs && col < dp.in_a {
            b = net[dp.w_off + col * dp.outs + kb];
        }
        tb[lid.y][lid.x] = b;
        workgroupBarrier();
        for (var k = 0u; k < 16u; k++) {
            acc += ta[lid.y][k] * tb[k][lid.x];
        }
        workgroupBarrier();
    }
    if row < dp.n && col < dp.in_a {
        let i = row * dp.in_a + col;
        if dp.act == 1u && prev[i] <= 0.0 {
            acc = 0.0;
        }
        if dp.accumulate == 1u {
            acc += dx[i];
        }
        dx[i] = acc;
    }
}
