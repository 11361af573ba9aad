// Pass 2: per 16×16 tile, for each channel: stage the channel's three derivative maps with a
// 5-pixel halo in workgroup memory (zero outside the image), blur them horizontally for the
// tile's 26 rows, then vertically per pixel (the window is symmetric, so the adjoint of the
// zero-padded "same" convolution is itself), and write the gradient
// dL/dx = G*dmu + 2 x G*dxx + y G*dxy + (1 - LAMBDA) sign(x - y) / count.

const TW: u32 = 16u;     // tile edge
const HW: u32 = 26u;     // tile edge + 2 HALF
const HROWS: u32 = 416u; // HW rows × TW columns of horizontal sums per map

var<workgroup> sd: array<f32, 2028>; // 3 maps × HW × HW
var<workgroup> hd: array<f32, 1248>; // 3 maps × HROWS

@compute @workgroup_size(16, 16)
fn main(
    @builtin(local_invocation_id) lid3: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
) {
    let w = params.width;
    let h = params.height;
    let ox = i32(wid.x * TW) - HALF;
    let oy = i32(wid.y * TW) - HALF;
    let px = wid.x * TW + lid3.x;
    let py = wid.y * TW + lid3.y;
    let inside = px < w && py < h;
    let i = py * w + px;
    for (var ch = 0u; ch < 3u; ch++) {
        for (var j = lid; j < HW * HW; j += 256u) {
            let gx = ox + i32(j % HW);
            let gy = oy + i32(j / HW);
            var d = vec3<f32>(0.0);
            if (gx >= 0 && gx < i32(w) && gy >= 0 && gy < i32(h)) {
                let o = 9u * (u32(gy) * w + u32(gx)) + ch;
                d = vec3<f32>(dmaps[o], dmaps[o + 3u], dmaps[o + 6u]);
            }
            sd[j] = d.x;
            sd[HW * HW + j] = d.y;
            sd[2u * HW * HW + j] = d.z;
        }
        workgroupBarrier();
        for (var j = lid; j < HROWS; j += 256u) {
            let base = (j / TW) * HW + j % TW;
            var s = vec3<f32>(0.0);
            for (var k = 0u; k < 11u; k++) {
                let wk = WIN[k];
                s.x += wk * sd[base + k];
                s.y += wk * sd[HW * HW + base + k];
                s.z += wk * sd[2u * HW * HW + base + k];
            }
            hd[j] = s.x;
            hd[HROWS + j] = s.y;
            hd[2u * HROWS + j] = s.z;
        }
        workgroupBarrier();
        var g = vec3<f32>(0.0);
        for (var k = 0u; k < 11u; k++) {
            let a = (lid3.y + k) * TW + lid3.x;
            let wk = WIN[k];
            g.x += wk * hd[a];
            g.y += wk * hd[HROWS + a];
            g.z += wk * hd[2u * HROWS + a];
        }
        if (inside) {
            let x = rendered[3u * i + ch];
            let y = unpack4x8unorm(target_rgba[i])[ch];
            grad_out[3u * i + ch] = g.x + 2.0 * x * g.y + y * g.z
                + (1.0 - LAMBDA) * sign(x - y) / value_count();
        }
        workgroupBarrier();
    }
}
