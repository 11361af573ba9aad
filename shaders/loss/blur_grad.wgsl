// Pass 3: horizontal blur of the 9 derivative maps (the window is symmetric, so the adjoint of
// the zero-padded "same" convolution is the same convolution).

@compute @workgroup_size(16, 16)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    if (gid.x >= w || gid.y >= params.height) {
        return;
    }
    var s: array<f32, 9>;
    for (var m = 0u; m < 9u; m++) {
        s[m] = 0.0;
    }
    for (var k = 0; k < 11; k++) {
        let xx = i32(gid.x) + k - HALF;
        if (xx < 0 || xx >= i32(w)) {
            continue;
        }
        let o = 9u * (gid.y * w + u32(xx));
        let wk = WIN[k];
        for (var m = 0u; m < 9u; m++) {
            s[m] += wk * dmaps[o + m];
        }
    }
    let o = 9u * (gid.y * w + gid.x);
    for (var m = 0u; m < 9u; m++) {
        dmaps_h[o + m] = s[m];
    }
}
