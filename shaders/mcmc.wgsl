// The MCMC strategy's per-step terms (src/splat/mcmc.rs; Kheradmand et al. 2024), one thread
// per Gaussian of one chunk, two entry points over one set of bindings: `regularise` and
// `noise`. The parameter buffer `McmcParams` is prepended by src/splat/gpu/mcmc.rs (its `wgsl_struct!`).
// CPU twins: mcmc::regularise_grads, mcmc::add_noise, mcmc::normal3.

@group(0) @binding(0) var<storage, read> mp: McmcParams;
// First Gaussian of the chunk, Gaussians in the chunk.
@group(0) @binding(1) var<storage, read> chunk: vec4<u32>;
@group(0) @binding(2) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(3) var<storage, read> log_scales: array<f32>;
@group(0) @binding(4) var<storage, read> flags: array<u32>;
// regularise only.
@group(0) @binding(5) var<storage, read_write> grad_opacity: array<f32>;
@group(0) @binding(6) var<storage, read_write> grad_log_scales: array<f32>;
// noise only.
@group(0) @binding(7) var<storage, read_write> means: array<f32>;
@group(0) @binding(8) var<storage, read> rotations: array<f32>;

const FLAG_BOUND: u32 = 1u;
const FLAG_BACKGROUND: u32 = 2u;

fn sigmoid1(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-x));
}

// PCG "RXS-M-XS" output hash of one word (Jarzynski & Olano 2020).
fn pcg_hash(v: u32) -> u32 {
    let s = v * 747796405u + 2891336453u;
    let w = ((s >> ((s >> 28u) + 4u)) ^ s) * 277803737u;
    return (w >> 22u) ^ w;
}

fn unit_of(h: u32) -> f32 {
    return (f32(h >> 8u) + 0.5) * (1.0 / 16777216.0);
}

// Regularisers: dL/dlogit += lambda_o / N * o (1 - o); dL/dlog_s += lambda_s / (3 N) * exp(log_s)
// (not for the background dome). Runs after the backward passes, before Adam.
@compute @workgroup_size(256)
fn regularise(inv: Invocation) {
    let c = flat_index(inv);
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

// Position noise after the optimiser step: mu += lr * noise_lr * gate(o) * Sigma eps, with
// Sigma = R S^2 R^T, gate(o) = sigmoid(100 (1 - o - 0.995)) and eps ~ N(0, I) hashed from
// (seed, step, index). Bound trunk surfels get none.
@compute @workgroup_size(256)
fn noise(inv: Invocation) {
    let c = flat_index(inv);
    if c >= chunk.y {
        return;
    }
    if (flags[c] & FLAG_BOUND) != 0u {
        return;
    }
    let index = chunk.x + c;
    let key = pcg_hash(mp.seed ^ pcg_hash(mp.step));
    var h = pcg_hash(key ^ (index * 0x9E3779B9u));
    var u: array<f32, 4>;
    for (var k = 0u; k < 4u; k++) {
        h = pcg_hash(h);
        u[k] = unit_of(h);
    }
    let r0 = sqrt(-2.0 * log(u[0]));
    let r1 = sqrt(-2.0 * log(u[2]));
    let tau = 6.283185307179586;
    let e = vec3<f32>(r0 * cos(tau * u[1]), r0 * sin(tau * u[1]), r1 * cos(tau * u[3]));
    let o = sigmoid1(opacity_logits[c]);
    let gate = 1.0 / (1.0 + exp(-100.0 * ((1.0 - o) - 0.995)));
    // Rows of R from the normalised quaternion (w, x, y, z), as strategy::quat_to_matrix.
    var q = vec4<f32>(rotations[4u * c], rotations[4u * c + 1u], rotations[4u * c + 2u],
        rotations[4u * c + 3u]);
    q = q / max(length(q), 1e-12);
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let r_0 = vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y));
    let r_1 = vec3<f32>(2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x));
    let r_2 = vec3<f32>(2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y));
    let s2 = exp(2.0 * vec3<f32>(log_scales[3u * c], log_scales[3u * c + 1u],
        log_scales[3u * c + 2u]));
    // R^T e, scaled by S^2, then R.
    let rt = r_0 * e.x + r_1 * e.y + r_2 * e.z;
    let scaled_e = s2 * rt;
    let d = vec3<f32>(dot(r_0, scaled_e), dot(r_1, scaled_e), dot(r_2, scaled_e));
    let k = mp.scaler * gate;
    means[3u * c] += k * d.x;
    means[3u * c + 1u] += k * d.y;
    means[3u * c + 2u] += k * d.z;
}
