// Pass 1: horizontal blur of x, y, x², y², xy (zero padding).

@compute @workgroup_size(16, 16)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    if (gid.x >= w || gid.y >= params.height) {
        return;
    }
    var mx = vec3<f32>(0.0);
    var my = vec3<f32>(0.0);
    var exx = vec3<f32>(0.0);
    var eyy = vec3<f32>(0.0);
    var exy = vec3<f32>(0.0);
    for (var k = 0; k < 11; k++) {
        let xx = i32(gid.x) + k - HALF;
        if (xx < 0 || xx >= i32(w)) {
            continue;
        }
        let i = gid.y * w + u32(xx);
        let x = load_rendered(i);
        let y = load_target(i);
        let wk = WIN[k];
        mx += wk * x;
        my += wk * y;
        exx += wk * x * x;
        eyy += wk * y * y;
        exy += wk * x * y;
    }
    let o = 15u * (gid.y * w + gid.x);
    let all = array<vec3<f32>, 5>(mx, my, exx, eyy, exy);
    for (var m = 0u; m < 5u; m++) {
        for (var c = 0u; c < 3u; c++) {
            stats_h[o + 3u * m + c] = all[m][c];
        }
    }
}
