// Pass 2: vertical blur of the statistics, SSIM per pixel and channel, its partial derivatives
// with respect to the blurred maps (scaled by -LAMBDA / count), and per-workgroup partial sums
// of |x - y| and SSIM (`workgroup_sum`).

@compute @workgroup_size(16, 16)
fn main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let w = params.width;
    let h = params.height;
    var local = vec2<f32>(0.0);
    if (gid.x < w && gid.y < h) {
        var s: array<f32, 15>;
        for (var m = 0u; m < 15u; m++) {
            s[m] = 0.0;
        }
        for (var k = 0; k < 11; k++) {
            let yy = i32(gid.y) + k - HALF;
            if (yy < 0 || yy >= i32(h)) {
                continue;
            }
            let o = 15u * (u32(yy) * w + gid.x);
            let wk = WIN[k];
            for (var m = 0u; m < 15u; m++) {
                s[m] += wk * stats_h[o + m];
            }
        }
        let mx = load3(&s, 0u);
        let my = load3(&s, 3u);
        let exx = load3(&s, 6u);
        let eyy = load3(&s, 9u);
        let exy = load3(&s, 12u);
        let a1 = 2.0 * mx * my + C1;
        let a2 = 2.0 * (exy - mx * my) + C2;
        let b1 = mx * mx + my * my + C1;
        let b2 = (exx - mx * mx) + (eyy - my * my) + C2;
        let ssim = a1 * a2 / (b1 * b2);
        let d_mu = 2.0 * my * (a2 - a1) / (b1 * b2) - ssim * (2.0 * mx / b1 - 2.0 * mx / b2);
        let d_xx = -ssim / b2;
        let d_xy = 2.0 * a1 / (b1 * b2);
        let scale = -LAMBDA / value_count();
        let i = gid.y * w + gid.x;
        let all = array<vec3<f32>, 3>(d_mu * scale, d_xx * scale, d_xy * scale);
        for (var m = 0u; m < 3u; m++) {
            for (var c = 0u; c < 3u; c++) {
                dmaps[9u * i + 3u * m + c] = all[m][c];
            }
        }
        let diff = abs(load_rendered(i) - load_target(i));
        local = vec2<f32>(diff.x + diff.y + diff.z, ssim.x + ssim.y + ssim.z);
    }
    let total = workgroup_sum(lid, local);
    if (lid == 0u) {
        let g = wid.y * nwg.x + wid.x;
        partials[2u * g] = total.x;
        partials[2u * g + 1u] = total.y;
    }
}
