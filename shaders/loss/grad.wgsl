// Pass 4: vertical blur of the derivative maps and the gradient
// dL/dx = G*dmu + 2 x G*dxx + y G*dxy + (1 - LAMBDA) sign(x - y) / count.

@compute @workgroup_size(16, 16)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    if (gid.x >= w || gid.y >= h) {
        return;
    }
    var s: array<f32, 9>;
    for (var m = 0u; m < 9u; m++) {
        s[m] = 0.0;
    }
    for (var k = 0; k < 11; k++) {
        let yy = i32(gid.y) + k - HALF;
        if (yy < 0 || yy >= i32(h)) {
            continue;
        }
        let o = 9u * (u32(yy) * w + gid.x);
        let wk = WIN[k];
        for (var m = 0u; m < 9u; m++) {
            s[m] += wk * dmaps_h[o + m];
        }
    }
    let i = gid.y * w + gid.x;
    let x = load_rendered(i);
    let y = load_target(i);
    let g_mu = vec3<f32>(s[0], s[1], s[2]);
    let g_xx = vec3<f32>(s[3], s[4], s[5]);
    let g_xy = vec3<f32>(s[6], s[7], s[8]);
    let g = g_mu + 2.0 * x * g_xx + y * g_xy + (1.0 - LAMBDA) * sign(x - y) / value_count();
    grad_out[3u * i] = g.x;
    grad_out[3u * i + 1u] = g.y;
    grad_out[3u * i + 2u] = g.z;
}
