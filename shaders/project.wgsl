// Projection (docs/splatting.md "Forward", steps 1-8): one thread per Gaussian of one chunk. Writes the
// screen-space record (3 vec4 per Gaussian) and the number of touched tiles (0 when culled). Every
// buffer but the uniforms is bound as the chunk's sub-range (index `c`; see `chunks.rs`).

@group(0) @binding(0) var<storage, read> params: Params;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> rotations: array<f32>;
@group(0) @binding(4) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(5) var<storage, read> sh: array<f32>;
// proj[3i] = (mean x, mean y, depth, bitcast radius), proj[3i+1] = (conic a, b, c, opacity),
// proj[3i+2] = (r, g, b, camera depth t.z) — the depth is the rasterisers' fourth channel.
@group(0) @binding(6) var<storage, read_write> proj: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> tile_counts: array<u32>;
// First Gaussian of the chunk, Gaussians in the chunk.
@group(0) @binding(8) var<storage, read> chunk: vec4<u32>;

fn cull(c: u32) {
    proj[3u * c] = vec4<f32>(0.0);
    proj[3u * c + 1u] = vec4<f32>(0.0);
    proj[3u * c + 2u] = vec4<f32>(0.0);
    tile_counts[c] = 0u;
}

@compute @workgroup_size(256)
fn main(inv: Invocation) {
    let c = flat_index(inv);
    if c >= chunk.y {
        return;
    }
    let p = params;
    let mu = vec3<f32>(means[3u * c], means[3u * c + 1u], means[3u * c + 2u]);
    let w = cam_rot(p);
    let t = w * mu + p.trans.xyz;
    if t.z < NEAR {
        cull(c);
        return;
    }
    let q = vec4<f32>(rotations[4u * c], rotations[4u * c + 1u], rotations[4u * c + 2u],
        rotations[4u * c + 3u]);
    let rq = quat_to_mat(q / length(q));
    let s = exp(vec3<f32>(log_scales[3u * c], log_scales[3u * c + 1u], log_scales[3u * c + 2u]));
    let m = mat3x3<f32>(rq[0] * s.x, rq[1] * s.y, rq[2] * s.z);
    let sigma_c = w * (m * transpose(m)) * transpose(w);
    let fx = p.focal.x;
    let fy = p.focal.y;
    let tx = clamp(t.x / t.z, -p.lim.x, p.lim.x) * t.z;
    let ty = clamp(t.y / t.z, -p.lim.y, p.lim.y) * t.z;
    let j0 = vec3<f32>(fx / t.z, 0.0, -fx * tx / (t.z * t.z));
    let j1 = vec3<f32>(0.0, fy / t.z, -fy * ty / (t.z * t.z));
    let c00 = dot(j0, sigma_c * j0);
    let c01 = dot(j0, sigma_c * j1);
    let c11 = dot(j1, sigma_c * j1);
    let s00 = c00 + LOW_PASS;
    let s01 = c01;
    let s11 = c11 + LOW_PASS;
    let det = s00 * s11 - s01 * s01;
    if !(det > 0.0) {
        cull(c);
        return;
    }
    let conic = vec3<f32>(s11 / det, -s01 / det, s00 / det);
    let mid = 0.5 * (s00 + s11);
    let lambda = mid + sqrt(max(0.1, mid * mid - det));
    let r = ceil(3.0 * sqrt(lambda));
    let mean2d = vec2<f32>(fx * t.x / t.z + p.focal.z, fy * t.y / t.z + p.focal.w);
    let size = p.lim.zw;
    if mean2d.x + r < 0.0 || mean2d.x - r >= size.x || mean2d.y + r < 0.0
        || mean2d.y - r >= size.y {
        cull(c);
        return;
    }
    // Colour from SH at the active degree.
    let d = normalize(mu - p.campos.xyz);
    let y = sh_basis(d, p.counts.y);
    var rgb = vec3<f32>(0.5);
    let nk = (p.counts.y + 1u) * (p.counts.y + 1u);
    for (var k = 0u; k < nk; k++) {
        let b = 48u * c + 3u * k;
        rgb += y[k] * vec3<f32>(sh[b], sh[b + 1u], sh[b + 2u]);
    }
    rgb = max(rgb, vec3<f32>(0.0));
    var opacity = 1.0 / (1.0 + exp(-opacity_logits[c]));
    if p.counts.w != 0u {
        // The 2-D Mip filter: the blended opacity is sigmoid(logit) * rho.
        opacity *= compensation(c00, c01, c11, det);
    }
    proj[3u * c] = vec4<f32>(mean2d, t.z, bitcast<f32>(u32(r)));
    proj[3u * c + 1u] = vec4<f32>(conic, opacity);
    proj[3u * c + 2u] = vec4<f32>(rgb, t.z);
    let rect = tile_rect(mean2d, r, p.dims.zw);
    tile_counts[c] = (rect.z - rect.x + 1u) * (rect.w - rect.y + 1u);
}
