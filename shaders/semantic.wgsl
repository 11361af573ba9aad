// The semantic geometric term L_geo (docs/method.md Stage 4), three passes per step:
//   query  — per Gaussian: nearest trunk anchor, mean distance to the K nearest trunk anchors,
//            nearest leaf anchor (uniform grids, exact ring search), the weight w = alpha P q and
//            the targets; writes 2 vec4 per Gaussian: (a_nn.xyz, s_target), (w, 0, 0, 0),
//            w = 0 outside the candidate set S;
//   reduce — one workgroup sums w and w * term: W and L_geo = sum(w term) / W;
// Each pass is the text before the first `#ifdef` plus its blocks `#ifdef NAME` … `#endif`
// (GRID then QUERY, or GRID then BIND; src/splat/gpu/semantic.rs splits the file; WGSL itself
// has no preprocessor).
//   apply  — adds gamma * w / W * (2 (mu - a) / N_pos^2, 2 (s - s_target)) to the gradients;
// and Sylva's binding (src/splat/bind.rs), one pass after Adam:
//   bind   — per bound Gaussian (P >= bind_min_prob): nearest trunk anchor a with normal n; the
//            offset (mu - a).n clamped to +-band, the local z axis turned onto +-n, the z
//            log-scale capped.
// GRID holds the anchors and their ring search, shared by QUERY and BIND.
// The CPU twins are src/splat/semantic.rs (geo_targets, geo_loss_and_grad) and
// src/splat/bind.rs (project). The parameter buffer `GeoParams` is prepended by semantic.rs (its
// `wgsl_struct!`).

const MAX_K: u32 = 16u;

@group(0) @binding(0) var<storage, read> gp: GeoParams;

#ifdef GRID
// Cell starts of the trunk grid, then of the leaf grid (each with its closing entry).
@group(0) @binding(4) var<storage, read> starts: array<u32>;
// Trunk anchors sorted by cell, then leaf anchors sorted by cell (xyz, unused w).
@group(0) @binding(5) var<storage, read> anchors: array<vec4<f32>>;

var<private> best_d2: array<f32, 16>;
var<private> best_id: array<u32, 16>;
var<private> n_best: u32;

fn insert(d2: f32, id: u32, k: u32) {
    if n_best == k && d2 >= best_d2[k - 1u] {
        return;
    }
    var j = min(n_best, k - 1u);
    if n_best < k {
        n_best += 1u;
    }
    loop {
        if j == 0u || best_d2[j - 1u] <= d2 {
            break;
        }
        best_d2[j] = best_d2[j - 1u];
        best_id[j] = best_id[j - 1u];
        j -= 1u;
    }
    best_d2[j] = d2;
    best_id[j] = id;
}

fn cell_of(p: vec3<f32>, origin: vec3<f32>, cell: f32, dims: vec3<u32>) -> vec3<i32> {
    // Clamped in floating point first: far-off (or non-finite) means land in a border cell.
    let c = clamp(floor((p - origin) / cell), vec3<f32>(0.0), vec3<f32>(dims - vec3<u32>(1u)));
    return vec3<i32>(c);
}

// Scans the cells at Chebyshev distance exactly r from c, keeping the k nearest anchors.
fn scan_shell(p: vec3<f32>, c: vec3<i32>, r: i32, dims: vec3<u32>, cell_base: u32,
              point_base: u32, k: u32) {
    let d = vec3<i32>(dims);
    for (var dz = -r; dz <= r; dz += 1) {
        let z = c.z + dz;
        if z < 0 || z >= d.z { continue; }
        for (var dy = -r; dy <= r; dy += 1) {
            let y = c.y + dy;
            if y < 0 || y >= d.y { continue; }
            let face = abs(dz) == r || abs(dy) == r;
            var dx = -r;
            loop {
                if dx > r { break; }
                let x = c.x + dx;
                if x >= 0 && x < d.x {
                    let ci = cell_base + u32((z * d.y + y) * d.x + x);
                    let a = starts[ci];
                    let b = starts[ci + 1u];
                    for (var j = a; j < b; j += 1u) {
                        let q = anchors[point_base + j].xyz - p;
                        insert(dot(q, q), j, k);
                    }
                }
                if face || r == 0 { dx += 1; } else { dx += 2 * r; }
            }
        }
    }
}

// Rings beyond which the whole grid has been seen.
fn max_ring(c: vec3<i32>, dims: vec3<u32>) -> i32 {
    let d = vec3<i32>(dims) - vec3<i32>(1);
    let m = max(c, d - c);
    return max(m.x, max(m.y, m.z));
}

fn sigmoid(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-x));
}

#endif

#ifdef QUERY
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(3) var<storage, read> trunk_prob: array<f32>;
@group(0) @binding(6) var<storage, read_write> geo: array<vec4<f32>>;

@compute @workgroup_size(256)
fn query(inv: Invocation) {
    let i = flat_index(inv);
    if i >= gp.n {
        return;
    }
    geo[2u * i] = vec4<f32>(0.0);
    geo[2u * i + 1u] = vec4<f32>(0.0);
    let alpha = sigmoid(opacity_logits[i]);
    let ap = alpha * trunk_prob[i];
    // w = alpha P q <= alpha P: nothing to search for when that is below the threshold.
    if ap < gp.threshold {
        return;
    }
    let p = vec3<f32>(means[3u * i], means[3u * i + 1u], means[3u * i + 2u]);

    // K nearest trunk anchors.
    n_best = 0u;
    let k = gp.k;
    let ct = cell_of(p, gp.t_origin, gp.t_cell, gp.t_dims);
    let rt = max_ring(ct, gp.t_dims);
    for (var r = 0; r <= rt; r += 1) {
        scan_shell(p, ct, r, gp.t_dims, 0u, 0u, k);
        // Anchors not yet seen lie at least r cells away.
        let reach = f32(r) * gp.t_cell;
        if n_best == k && best_d2[k - 1u] <= reach * reach {
            break;
        }
    }
    if n_best == 0u {
        return;
    }
    let d_t = sqrt(best_d2[0]);
    let a_nn = anchors[best_id[0]].xyz;
    var dsum = 0.0;
    for (var j = 0u; j < n_best; j += 1u) {
        dsum += sqrt(best_d2[j]);
    }
    let dbar = dsum / f32(n_best);

    // Nearest leaf anchor, searched only as far as it can still change q.
    var q = 1.0;
    if gp.n_leaf > 0u {
        n_best = 0u;
        let cl = cell_of(p, gp.l_origin, gp.l_cell, gp.l_dims);
        let rl = max_ring(cl, gp.l_dims);
        let trunk_base = gp.leaf_cell_base;
        // Leaf points follow the trunk points; their index in `anchors` is offset by the count
        // of trunk points, which is the trunk grid's closing cell start.
        let point_base = starts[trunk_base - 1u];
        for (var r = 0; r <= rl; r += 1) {
            scan_shell(p, cl, r, gp.l_dims, trunk_base, point_base, 1u);
            let reach = f32(r) * gp.l_cell;
            if n_best == 1u && best_d2[0] <= reach * reach {
                break;
            }
            if reach >= d_t + gp.leaf_cutoff {
                break;
            }
        }
        if n_best == 1u {
            q = sigmoid((sqrt(best_d2[0]) - d_t) / gp.temperature);
        }
    }
    let w = ap * q;
    if w < gp.threshold {
        return;
    }
    let s_t = log(gp.beta * dbar + gp.eps);
    geo[2u * i] = vec4<f32>(a_nn, s_t);
    geo[2u * i + 1u] = vec4<f32>(w, 0.0, 0.0, 0.0);
}
#endif

#ifdef REDUCE
@group(0) @binding(1) var<storage, read> log_scales: array<f32>;
@group(0) @binding(2) var<storage, read> geo: array<vec4<f32>>;
// (W, sum of w * term, L_geo, unused)
@group(0) @binding(3) var<storage, read_write> sums: array<f32>;
@group(0) @binding(4) var<storage, read> means: array<f32>;
// The loss read-back buffer of the photometric loss: L_geo goes to its fourth float.
@group(0) @binding(5) var<storage, read_write> loss_out: array<f32>;

var<workgroup> part_w: array<f32, 256>;
var<workgroup> part_t: array<f32, 256>;

@compute @workgroup_size(256)
fn reduce(@builtin(local_invocation_index) lid: u32) {
    var sw = 0.0;
    var st = 0.0;
    for (var i = lid; i < gp.n; i += 256u) {
        let w = geo[2u * i + 1u].x;
        if w > 0.0 {
            let t = geo[2u * i];
            let dm = vec3<f32>(means[3u * i], means[3u * i + 1u], means[3u * i + 2u]) - t.xyz;
            let ds = vec3<f32>(log_scales[3u * i], log_scales[3u * i + 1u],
                               log_scales[3u * i + 2u]) - vec3<f32>(t.w);
            sw += w;
            st += w * (dot(dm, dm) * gp.inv_npos2 + dot(ds, ds));
        }
    }
    part_w[lid] = sw;
    part_t[lid] = st;
    workgroupBarrier();
    for (var s = 128u; s > 0u; s >>= 1u) {
        if lid < s {
            part_w[lid] += part_w[lid + s];
            part_t[lid] += part_t[lid + s];
        }
        workgroupBarrier();
    }
    if lid == 0u {
        let total = part_w[0];
        let l = select(0.0, part_t[0] / total, total > 0.0);
        sums[0] = total;
        sums[1] = part_t[0];
        sums[2] = l;
        sums[3] = 0.0;
        loss_out[3] = l;
    }
}
#endif

#ifdef APPLY
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> geo: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> sums: array<f32>;
@group(0) @binding(5) var<storage, read_write> grad_means: array<f32>;
@group(0) @binding(6) var<storage, read_write> grad_log_scales: array<f32>;

@compute @workgroup_size(256)
fn apply(inv: Invocation) {
    let i = flat_index(inv);
    if i >= gp.n {
        return;
    }
    let w = geo[2u * i + 1u].x;
    let total = sums[0];
    if w <= 0.0 || total <= 0.0 {
        return;
    }
    let g = gp.gamma * w / total;
    let t = geo[2u * i];
    for (var a = 0u; a < 3u; a += 1u) {
        grad_means[3u * i + a] += g * 2.0 * (means[3u * i + a] - t[a]) * gp.inv_npos2;
        grad_log_scales[3u * i + a] += g * 2.0 * (log_scales[3u * i + a] - t.w);
    }
}
#endif

#ifdef BIND
@group(0) @binding(1) var<storage, read_write> means: array<f32>;
@group(0) @binding(2) var<storage, read_write> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> trunk_prob: array<f32>;
@group(0) @binding(6) var<storage, read_write> rotations: array<vec4<f32>>;
// Unit normal of each trunk anchor, in the trunk grid's order (zero where unknown).
@group(0) @binding(7) var<storage, read> normals: array<vec4<f32>>;

fn hamilton(a: vec4<f32>, b: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(
        a.x * b.x - a.y * b.y - a.z * b.z - a.w * b.w,
        a.x * b.y + a.y * b.x + a.z * b.w - a.w * b.z,
        a.x * b.z - a.y * b.w + a.z * b.x + a.w * b.y,
        a.x * b.w + a.y * b.z - a.z * b.y + a.w * b.x);
}

@compute @workgroup_size(256)
fn bind(inv: Invocation) {
    let i = flat_index(inv);
    if i >= gp.n || trunk_prob[i] < gp.bind_min_prob {
        return;
    }
    let p = vec3<f32>(means[3u * i], means[3u * i + 1u], means[3u * i + 2u]);
    n_best = 0u;
    let ct = cell_of(p, gp.t_origin, gp.t_cell, gp.t_dims);
    let rt = max_ring(ct, gp.t_dims);
    for (var r = 0; r <= rt; r += 1) {
        scan_shell(p, ct, r, gp.t_dims, 0u, 0u, 1u);
        let reach = f32(r) * gp.t_cell;
        if n_best == 1u && best_d2[0] <= reach * reach {
            break;
        }
    }
    if n_best == 0u {
        return;
    }
    let n = normals[best_id[0]].xyz;
    if dot(n, n) < 0.25 {
        return;
    }
    let a = anchors[best_id[0]].xyz;
    let o = dot(p - a, n);
    let q_mu = p - (o - clamp(o, -gp.bind_band, gp.bind_band)) * n;
    means[3u * i] = q_mu.x;
    means[3u * i + 1u] = q_mu.y;
    means[3u * i + 2u] = q_mu.z;
    // Local z axis of the normalised rotation (w, x, y, z), turned onto +-n by the shortest arc.
    var q = rotations[i];
    let l = length(q);
    q = select(vec4<f32>(1.0, 0.0, 0.0, 0.0), q / l, l > 1e-12);
    let u = vec3<f32>(2.0 * (q.y * q.w + q.x * q.z),
                      2.0 * (q.z * q.w - q.x * q.y),
                      1.0 - 2.0 * (q.y * q.y + q.z * q.z));
    let v = select(-n, n, dot(u, n) >= 0.0);
    let ax = cross(u, v);
    let r = normalize(vec4<f32>(1.0 + dot(u, v), ax));
    rotations[i] = hamilton(r, q);
    log_scales[3u * i + 2u] = min(log_scales[3u * i + 2u], gp.bind_log_scale);
}
#endif
