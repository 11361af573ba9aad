// Pass 5: one workgroup sums the per-workgroup partials (fixed order) and writes
// loss_out = (loss, l1, ssim, 0).

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) lid: u32) {
    var acc = vec2<f32>(0.0);
    for (var g = lid; g < params.n_partials; g += 256u) {
        acc += vec2<f32>(partials[2u * g], partials[2u * g + 1u]);
    }
    let total = workgroup_sum(lid, acc);
    if (lid == 0u) {
        let l1 = total.x / value_count();
        let ssim = total.y / value_count();
        loss_out[0] = (1.0 - LAMBDA) * l1 + LAMBDA * (1.0 - ssim);
        loss_out[1] = l1;
        loss_out[2] = ssim;
        loss_out[3] = 0.0;
    }
}
