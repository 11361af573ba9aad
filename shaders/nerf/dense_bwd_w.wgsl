// The parameter gradient of one dense layer (src/nerf/gpu.rs; CPU twin `Mlp::backward`):
// g[i][j] += sum_s x[s][i] dy[s][j] over the chunk's samples, for i < in (x the concatenation
// [xa, xb]) and i = in, the bias (x = 1); g sits at w_off in the flat gradient, laid out as the
// parameters. Tiles of 16 × 16, the samples staged 16 at a time.

@group(0) @binding(0) var<storage, read> dp: DenseParams;
@group(0) @binding(1) var<storage, read> xa: array<f32>;
@group(0) @binding(2) var<storage, read> xb: array<f32>;
@group(0) @binding(3) var<storage, read> dy: array<f32>;
@group(0) @binding(4) var<storage, read_write> grad: array<f32>;

var<workgroup> ta: array<array<f32, 16>, 16>;
var<workgroup> tb: array<array<f32, 16>, 16>;

fn x_at(s: u32, k: u32) -> f32 {
    let kin = dp.in_a + dp.in_b;
    if k == kin {
        return 1.0;
    }
    if k < dp.in_a {
        return xa[s * dp.in_a + k];
    }
    return xb[s * dp.in_b + (k - dp.in_a)];
}

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let row = wg.y * 16u + lid.y;
    let col = wg.x * 16u + lid.x;
    let rows = dp.in_a + dp.in_b + 1u;
    var acc = 0.0;
    for (var s0 = 0u; s0 < dp.n; s0 += 16u) {
        let sa = s0 + lid.x;
        var a = 0.0;
        if row < rows && sa < dp.n {
            a = x_at(sa, row);
        }
        ta[lid.y][lid.x] = a;
        let sb = s0 + lid.y;
        var b = 0.0;
        if sb < dp.n && col < dp.outs {
            b = dy[sb * dp.outs + col];
        }
        tb[lid.y][lid.x] = b;
        workgroupBarrier();
        for (var k = 0u; k < 16u; k++) {
            acc += ta[lid.y][k] * tb[k][lid.x];
        }
        workgroupBarrier();
    }
    if row < rows && col < dp.outs {
        let i = dp.w_off + row * dp.outs + col;
        grad[i] += acc;
    }
}
