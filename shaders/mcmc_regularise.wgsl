// Regularisers: dL/dlogit += lambda_o / N * o (1 - o); dL/dlog_s += lambda_s / (3 N) * exp(log_s)
// (not for the background dome). Runs after the backward passes, before Adam.

@group(0) @binding(0) var<uniform> mp: McmcParams;
@group(0) @binding(1) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(2) var<storage, read> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> flags: array<u32>;
@group(0) @binding(4) var<storage, read_write> grad_opacity: array<f32>;
@group(0) @binding(5) var<storage, read_write> grad_log_scales: array<f32>;
// First Gaussian of the chunk, Gaussians in the chunk.
@group(0) @binding(6) var<uniform> chunk: vec4<u32>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let c = gid(wg, nwg, lid);
    if c >= chunk.y {
        return;
    }
    let o = sigmoid1(opacity_logits[c]);
    grad_opacity[c] += mp.opacity_coef * o * (1.0 - o);
    if (flags[c] & FLAG_BACKGROUND) == 0u {
        for (var k = 0u; k < 3u; k++) {
            grad_log_scales[3u * c + k] += mp.scale_coef * exp(log_scales[3u * c + k]);
        }
    }
}
