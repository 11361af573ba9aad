// Projection backward: one thread per Gaussian. Recomputes the forward projection, then chains
// the screen-space gradients of the raster backward (grads2d, 10 per Gaussian) to the
// parameters: conic -> 2-D covariance -> (J, camera covariance) -> (t, scale, rotation through
// the quaternion normalisation); mean2d -> t -> mu; rgb -> SH coefficients and mu through the
// view direction; opacity -> logit and, with the 2-D Mip filter (params.counts.w), through the
// compensation rho to the 2-D covariance. Also accumulates the densification statistic.

@group(0) @binding(0) var<storage, read> params: Params;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> rotations: array<f32>;
@group(0) @binding(4) var<storage, read> sh: array<f32>;
@group(0) @binding(5) var<storage, read> proj: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> grads2d: array<f32>;
@group(0) @binding(7) var<storage, read_write> g_means: array<f32>;
@group(0) @binding(8) var<storage, read_write> g_log_scales: array<f32>;
@group(0) @binding(9) var<storage, read_write> g_rotations: array<f32>;
@group(0) @binding(10) var<storage, read_write> g_opacity: array<f32>;
@group(0) @binding(11) var<storage, read_write> g_sh: array<f32>;
// densify[3 i] += |dL/dm| scaled to NDC, densify[3 i + 1] += 1 per view where visible,
// densify[3 i + 2] = the largest screen radius (pixels) over those views.
@group(0) @binding(12) var<storage, read_write> densify: array<f32>;
// First Gaussian of the chunk, Gaussians in the chunk: every other buffer (parameters, proj,
// grads2d, gradients, densify) is bound as the chunk's sub-range (index `c`).
@group(0) @binding(13) var<storage, read> chunk: vec4<u32>;
@group(0) @binding(14) var<storage, read> opacity_logits: array<f32>;

// d Y_k / d(x, y, z) for k = 1..15, treating the components as independent.
fn sh_basis_grad(d: vec3<f32>, k: u32) -> vec3<f32> {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    switch k {
        case 1u: { return vec3<f32>(0.0, -SH_C1, 0.0); }
        case 2u: { return vec3<f32>(0.0, 0.0, SH_C1); }
        case 3u: { return vec3<f32>(-SH_C1, 0.0, 0.0); }
        case 4u: { return SH_C2[0] * vec3<f32>(y, x, 0.0); }
        case 5u: { return SH_C2[1] * vec3<f32>(0.0, z, y); }
        case 6u: { return SH_C2[2] * vec3<f32>(-2.0 * x, -2.0 * y, 4.0 * z); }
        case 7u: { return SH_C2[3] * vec3<f32>(z, 0.0, x); }
        case 8u: { return SH_C2[4] * vec3<f32>(2.0 * x, -2.0 * y, 0.0); }
        case 9u: { return SH_C3[0] * vec3<f32>(6.0 * x * y, 3.0 * x * x - 3.0 * y * y, 0.0); }
        case 10u: { return SH_C3[1] * vec3<f32>(y * z, x * z, x * y); }
        case 11u: {
            return SH_C3[2] * vec3<f32>(-2.0 * x * y, 4.0 * z * z - x * x - 3.0 * y * y,
                8.0 * y * z);
        }
        case 12u: {
            return SH_C3[3] * vec3<f32>(-6.0 * x * z, -6.0 * y * z,
                6.0 * z * z - 3.0 * x * x - 3.0 * y * y);
        }
        case 13u: {
            return SH_C3[4] * vec3<f32>(4.0 * z * z - 3.0 * x * x - y * y, -2.0 * x * y,
                8.0 * x * z);
        }
        case 14u: { return SH_C3[5] * vec3<f32>(2.0 * x * z, -2.0 * y * z, x * x - y * y); }
        case 15u: { return SH_C3[6] * vec3<f32>(3.0 * x * x - 3.0 * y * y, -6.0 * x * y, 0.0); }
        default: { return vec3<f32>(0.0); }
    }
}

fn outer(a: vec3<f32>, b: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(a * b.x, a * b.y, a * b.z);
}

@compute @workgroup_size(256)
fn main(inv: Invocation) {
    let c = flat_index(inv);
    if c >= chunk.y {
        return;
    }
    let p = params;
    let radius = bitcast<u32>(proj[3u * c].w);
    for (var k = 0u; k < 48u; k++) {
        g_sh[48u * c + k] = 0.0;
    }
    if radius == 0u {
        for (var k = 0u; k < 3u; k++) {
            g_means[3u * c + k] = 0.0;
            g_log_scales[3u * c + k] = 0.0;
        }
        for (var k = 0u; k < 4u; k++) {
            g_rotations[4u * c + k] = 0.0;
        }
        g_opacity[c] = 0.0;
        return;
    }
    let v_m = vec2<f32>(grads2d[10u * c], grads2d[10u * c + 1u]);
    let v_conic = vec3<f32>(grads2d[10u * c + 2u], grads2d[10u * c + 3u], grads2d[10u * c + 4u]);
    let v_rgb_in = vec3<f32>(grads2d[10u * c + 5u], grads2d[10u * c + 6u], grads2d[10u * c + 7u]);
    let v_opacity = grads2d[10u * c + 8u];
    let v_depth = grads2d[10u * c + 9u];

    // Densification statistic (reference: NDC gradient = pixel gradient x (w/2, h/2)).
    densify[3u * c] += length(v_m * 0.5 * p.lim.zw);
    densify[3u * c + 1u] += 1.0;
    densify[3u * c + 2u] = max(densify[3u * c + 2u], f32(radius));

    // Recompute the forward quantities.
    let mu = vec3<f32>(means[3u * c], means[3u * c + 1u], means[3u * c + 2u]);
    let w = cam_rot(p);
    let t = w * mu + p.trans.xyz;
    let q_raw = vec4<f32>(rotations[4u * c], rotations[4u * c + 1u], rotations[4u * c + 2u],
        rotations[4u * c + 3u]);
    let q_len = length(q_raw);
    let qn = q_raw / q_len;
    let rq = quat_to_mat(qn);
    let s = exp(vec3<f32>(log_scales[3u * c], log_scales[3u * c + 1u], log_scales[3u * c + 2u]));
    let m = mat3x3<f32>(rq[0] * s.x, rq[1] * s.y, rq[2] * s.z);
    let sigma_c = w * (m * transpose(m)) * transpose(w);
    let fx = p.focal.x;
    let fy = p.focal.y;
    let rz = 1.0 / t.z;
    let rz2 = rz * rz;
    let ux = t.x * rz;
    let uy = t.y * rz;
    let tx = clamp(ux, -p.lim.x, p.lim.x) * t.z;
    let ty = clamp(uy, -p.lim.y, p.lim.y) * t.z;
    let j0 = vec3<f32>(fx * rz, 0.0, -fx * tx * rz2);
    let j1 = vec3<f32>(0.0, fy * rz, -fy * ty * rz2);
    let c00 = dot(j0, sigma_c * j0);
    let c01 = dot(j0, sigma_c * j1);
    let c11 = dot(j1, sigma_c * j1);
    let s00 = c00 + LOW_PASS;
    let s01 = c01;
    let s11 = c11 + LOW_PASS;
    let det = s00 * s11 - s01 * s01;
    let qa = s11 / det;
    let qb = -s01 / det;
    let qc = s00 / det;

    // Opacity: the blended opacity is o * rho (rho = 1 without the 2-D Mip filter), o the
    // sigmoid of the logit.
    let o = 1.0 / (1.0 + exp(-opacity_logits[c]));
    var rho = 1.0;
    if p.counts.w != 0u {
        rho = compensation(c00, c01, c11, det);
    }
    g_opacity[c] = v_opacity * rho * o * (1.0 - o);

    // Conic -> 2-D covariance: dL/dSigma2D = -Q V Q, V the symmetric gradient of Q
    // (b appears twice in Q, so V's off-diagonal is v_b / 2).
    let qm = mat2x2<f32>(vec2<f32>(qa, qb), vec2<f32>(qb, qc));
    let vm = mat2x2<f32>(vec2<f32>(v_conic.x, 0.5 * v_conic.y), vec2<f32>(0.5 * v_conic.y, v_conic.z));
    let gs = (qm * vm * qm) * -1.0;
    var g00 = gs[0][0];
    var g01 = 0.5 * (gs[0][1] + gs[1][0]);
    var g11 = gs[1][1];
    // 2-D Mip filter: d rho / d Sigma2D = ((1 - rho^2) Q - LOW_PASS det(Q) I) / (2 rho), zero
    // where rho is clamped at 0 (CPU twin: `compensation_grad`); dL/d rho = v_opacity * o.
    if p.counts.w != 0u && rho > 0.0 {
        let k = v_opacity * o * 0.5 / rho;
        let one = 1.0 - rho * rho;
        let det_q = qa * qc - qb * qb;
        g00 += k * (one * qa - LOW_PASS * det_q);
        g01 += k * one * qb;
        g11 += k * (one * qc - LOW_PASS * det_q);
    }

    // Sigma2D = J Sigma_c J^T: dL/dSigma_c = J^T G J; dL/dJ rows = 2 G J Sigma_c.
    let v_sigma_c = g00 * outer(j0, j0) + g01 * (outer(j0, j1) + outer(j1, j0)) + g11 * outer(j1, j1);
    let sj0 = sigma_c * j0;
    let sj1 = sigma_c * j1;
    let v_j0 = 2.0 * (g00 * sj0 + g01 * sj1);
    let v_j1 = 2.0 * (g01 * sj0 + g11 * sj1);

    // J -> t (the clamped tx, ty are constants; docs/splatting.md step 3) and mean2d -> t.
    let rz3 = rz2 * rz;
    var v_t = vec3<f32>(0.0);
    if ux >= -p.lim.x && ux <= p.lim.x {
        v_t.x += -fx * rz2 * v_j0.z;
    }
    if uy >= -p.lim.y && uy <= p.lim.y {
        v_t.y += -fy * rz2 * v_j1.z;
    }
    v_t.z += -fx * rz2 * v_j0.x + 2.0 * fx * tx * rz3 * v_j0.z - fy * rz2 * v_j1.y
        + 2.0 * fy * ty * rz3 * v_j1.z;
    v_t += vec3<f32>(fx * rz * v_m.x, fy * rz * v_m.y,
        -fx * t.x * rz2 * v_m.x - fy * t.y * rz2 * v_m.y + v_depth);
    var v_mu = transpose(w) * v_t;

    // Sigma_c = W Sigma W^T; Sigma = M M^T with M = Rq S.
    let v_sigma = transpose(w) * v_sigma_c * w;
    let v_mm = 2.0 * v_sigma * m;
    let v_s = vec3<f32>(dot(rq[0], v_mm[0]), dot(rq[1], v_mm[1]), dot(rq[2], v_mm[2])) * s;
    let v_rq = mat3x3<f32>(v_mm[0] * s.x, v_mm[1] * s.y, v_mm[2] * s.z);
    // Rotation matrix -> normalised quaternion; G(r, c) = v_rq[c][r].
    let qw = qn.x;
    let qx = qn.y;
    let qy = qn.z;
    let qz = qn.w;
    let g01r = v_rq[1][0];
    let g02r = v_rq[2][0];
    let g10r = v_rq[0][1];
    let g12r = v_rq[2][1];
    let g20r = v_rq[0][2];
    let g21r = v_rq[1][2];
    let g00r = v_rq[0][0];
    let g11r = v_rq[1][1];
    let g22r = v_rq[2][2];
    let v_qn = 2.0 * vec4<f32>(
        -qz * g01r + qy * g02r + qz * g10r - qx * g12r - qy * g20r + qx * g21r,
        qy * g01r + qz * g02r + qy * g10r - 2.0 * qx * g11r - qw * g12r + qz * g20r + qw * g21r
            - 2.0 * qx * g22r,
        -2.0 * qy * g00r + qx * g01r + qw * g02r + qx * g10r + qz * g12r - qw * g20r + qz * g21r
            - 2.0 * qy * g22r,
        -2.0 * qz * g00r - qw * g01r + qx * g02r + qw * g10r - 2.0 * qz * g11r + qy * g12r
            + qx * g20r + qy * g21r,
    );
    let v_q = (v_qn - qn * dot(qn, v_qn)) / q_len;

    // Colour: clamp mask, SH coefficients, and the view direction back to mu.
    let dir_raw = mu - p.campos.xyz;
    let dir_len = length(dir_raw);
    let dir = dir_raw / dir_len;
    let deg = p.counts.y;
    let nk = (deg + 1u) * (deg + 1u);
    let y = sh_basis(dir, deg);
    var raw = vec3<f32>(0.5);
    for (var k = 0u; k < nk; k++) {
        let b = 48u * c + 3u * k;
        raw += y[k] * vec3<f32>(sh[b], sh[b + 1u], sh[b + 2u]);
    }
    // The gradient passes at the clamp itself (as the CPU twin): a colour at exactly 0 can rise.
    let v_rgb = select(vec3<f32>(0.0), v_rgb_in, raw >= vec3<f32>(0.0));
    var v_dir = vec3<f32>(0.0);
    for (var k = 0u; k < nk; k++) {
        let b = 48u * c + 3u * k;
        g_sh[b] = y[k] * v_rgb.x;
        g_sh[b + 1u] = y[k] * v_rgb.y;
        g_sh[b + 2u] = y[k] * v_rgb.z;
        if k > 0u {
            let coef = vec3<f32>(sh[b], sh[b + 1u], sh[b + 2u]);
            v_dir += dot(coef, v_rgb) * sh_basis_grad(dir, k);
        }
    }
    v_mu += (v_dir - dir * dot(dir, v_dir)) / dir_len;

    for (var k = 0u; k < 3u; k++) {
        g_means[3u * c + k] = v_mu[k];
        g_log_scales[3u * c + k] = v_s[k];
    }
    for (var k = 0u; k < 4u; k++) {
        g_rotations[4u * c + k] = v_q[k];
    }
}
