// Backward rasterisation: one workgroup per tile, one thread per pixel, walking each pixel's run
// back to front from its last blended Gaussian, recovering the transmittance by division
// (T_before = T_after / (1 - alpha)). Per Gaussian it accumulates, over pixels, with `add_grad`
// (float atomics or a CAS loop, prepended): grads2d[9 g ..] = dL/d(mean x, mean y), dL/d(conic
// a, b, c), dL/d(r, g, b), dL/d(opacity).

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> proj: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> values: array<u32>;
@group(0) @binding(3) var<storage, read> ranges: array<u32>;
@group(0) @binding(4) var<storage, read> final_t: array<f32>;
@group(0) @binding(5) var<storage, read> n_contrib: array<u32>;
@group(0) @binding(6) var<storage, read> dl_dimage: array<f32>;

var<workgroup> b_xy_op: array<vec4<f32>, 256>;   // mean x, mean y, opacity, Gaussian id bits
var<workgroup> b_conic: array<vec4<f32>, 256>;
var<workgroup> b_rgb: array<vec4<f32>, 256>;
var<workgroup> max_last: atomic<u32>;
var<workgroup> shared_u: vec2<u32>;
var<workgroup> last_snap: u32;

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid3: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let p = params;
    let tile = wg.y * p.dims.z + wg.x;
    let px = wg.x * TILE + lid3.x;
    let py = wg.y * TILE + lid3.y;
    let inside = px < p.dims.x && py < p.dims.y;
    let pix = vec2<f32>(f32(px) + 0.5, f32(py) + 0.5);
    if lid == 0u {
        shared_u = vec2<u32>(ranges[2u * tile], ranges[2u * tile + 1u]);
        atomicStore(&max_last, 0u);
    }
    let range = workgroupUniformLoad(&shared_u);
    var t_final = 1.0;
    var last = 0u;
    var v_out = vec3<f32>(0.0);
    if inside {
        let o = py * p.dims.x + px;
        t_final = final_t[o];
        last = n_contrib[o];
        v_out = vec3<f32>(dl_dimage[3u * o], dl_dimage[3u * o + 1u], dl_dimage[3u * o + 2u]);
        atomicMax(&max_last, last);
    }
    workgroupBarrier();
    if lid == 0u {
        last_snap = atomicLoad(&max_last);
    }
    let tile_last = workgroupUniformLoad(&last_snap);
    let total = range.y - range.x;
    let v_bg = dot(p.bg.xyz, v_out);
    var t = t_final;
    var acc = vec3<f32>(0.0);
    let batches = (tile_last + 255u) / 256u;
    for (var bb = 0u; bb < batches; bb++) {
        let b = batches - 1u - bb;
        workgroupBarrier();
        let k = b * 256u + lid;
        if k < total {
            let g = values[range.x + k];
            let p0 = proj[3u * g];
            let p1 = proj[3u * g + 1u];
            b_xy_op[lid] = vec4<f32>(p0.xy, p1.w, bitcast<f32>(g));
            b_conic[lid] = vec4<f32>(p1.xyz, 0.0);
            b_rgb[lid] = proj[3u * g + 2u];
        }
        workgroupBarrier();
        let in_batch = min(256u, total - b * 256u);
        for (var jj = 0u; jj < in_batch; jj++) {
            let j = in_batch - 1u - jj;
            if b * 256u + j >= last {
                continue;
            }
            let xo = b_xy_op[j];
            let q = b_conic[j].xyz;
            let d = xo.xy - pix;
            let power = -0.5 * (q.x * d.x * d.x + q.z * d.y * d.y) - q.y * d.x * d.y;
            if power > 0.0 {
                continue;
            }
            let vis = exp(power);
            let raw = xo.z * vis;
            let alpha = min(ALPHA_MAX, raw);
            if alpha < ALPHA_MIN {
                continue;
            }
            let ra = 1.0 / (1.0 - alpha);
            t *= ra;
            let rgb = b_rgb[j].xyz;
            let fac = alpha * t;
            let g = bitcast<u32>(xo.w);
            let v_rgb = fac * v_out;
            add_grad(9u * g + 5u, v_rgb.x);
            add_grad(9u * g + 6u, v_rgb.y);
            add_grad(9u * g + 7u, v_rgb.z);
            let v_alpha = dot(rgb * t - acc * ra, v_out) - t_final * ra * v_bg;
            acc += rgb * fac;
            if raw <= ALPHA_MAX {
                let v_power = v_alpha * alpha;
                add_grad(9u * g, -v_power * (q.x * d.x + q.y * d.y));
                add_grad(9u * g + 1u, -v_power * (q.y * d.x + q.z * d.y));
                add_grad(9u * g + 2u, -0.5 * v_power * d.x * d.x);
                add_grad(9u * g + 3u, -v_power * d.x * d.y);
                add_grad(9u * g + 4u, -0.5 * v_power * d.y * d.y);
                add_grad(9u * g + 8u, v_alpha * vis);
            }
        }
    }
}
