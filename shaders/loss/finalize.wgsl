// Pass 5: one workgroup sums the per-workgroup partials (fixed order) and writes
// loss_out = (loss, l1, ssim, 0).

var<workgroup> sums: array<vec2<f32>, 256>;

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) lid: u32) {
    var acc = vec2<f32>(0.0);
    for (var g = lid; g < params.n_partials; g += 256u) {
        acc += vec2<f32>(partials[2u * g], partials[2u * g + 1u]);
    }
    sums[lid] = acc;
    workgroupBarrier();
    for (var stride = 128u; stride > 0u; stride = stride >> 1u) {
        if (lid < stride) {
            sums[lid] += sums[lid + stride];
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        let l1 = sums[0].x / value_count();
        let ssim = sums[0].y / value_count();
        loss_out[0] = (1.0 - LAMBDA) * l1 + LAMBDA * (1.0 - ssim);
        loss_out[1] = l1;
        loss_out[2] = ssim;
        loss_out[3] = 0.0;
    }
}
