// The sum of `v` over the 256 invocations of a workgroup, by a fixed-order tree reduction in
// workgroup memory (the same bits on every run); every invocation gets it. Call it from
// uniform control flow (it holds barriers).

var<workgroup> sums: array<vec2<f32>, 256>;

fn workgroup_sum(lid: u32, v: vec2<f32>) -> vec2<f32> {
    sums[lid] = v;
    workgroupBarrier();
    for (var stride = 128u; stride > 0u; stride = stride >> 1u) {
        if (lid < stride) {
            sums[lid] += sums[lid + stride];
        }
        workgroupBarrier();
    }
    return sums[0];
}
