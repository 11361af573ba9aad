// Forward rasterisation: one workgroup per 16x16 tile, one thread per pixel. Batches of 256
// Gaussians of the tile's depth-sorted run are staged in workgroup memory and blended front to
// back (SPLATTING.md "Per pixel"); the workgroup stops once every pixel is saturated.

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> proj: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> values: array<u32>;
@group(0) @binding(3) var<storage, read> ranges: array<u32>;
@group(0) @binding(4) var<storage, read_write> image: array<f32>;
@group(0) @binding(5) var<storage, read_write> final_t: array<f32>;
// Per pixel: 1 + position (within the tile's run) of the last Gaussian blended, 0 if none.
@group(0) @binding(6) var<storage, read_write> n_contrib: array<u32>;

var<workgroup> b_xy_op: array<vec4<f32>, 256>;   // mean x, mean y, opacity, unused
var<workgroup> b_conic: array<vec4<f32>, 256>;
var<workgroup> b_rgb: array<vec4<f32>, 256>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> shared_u: vec2<u32>;
var<workgroup> done_snap: u32;

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
        atomicStore(&done_count, 0u);
    }
    let range = workgroupUniformLoad(&shared_u);
    var done = !inside;
    if done {
        atomicAdd(&done_count, 1u);
    }
    var t = 1.0;
    var c = vec3<f32>(0.0);
    var last = 0u;
    let total = range.y - range.x;
    let batches = (total + 255u) / 256u;
    for (var b = 0u; b < batches; b++) {
        workgroupBarrier();
        if lid == 0u {
            done_snap = atomicLoad(&done_count);
        }
        if workgroupUniformLoad(&done_snap) >= 256u {
            break;
        }
        let k = range.x + b * 256u + lid;
        if k < range.y {
            let g = values[k];
            let p0 = proj[3u * g];
            let p1 = proj[3u * g + 1u];
            b_xy_op[lid] = vec4<f32>(p0.xy, p1.w, 0.0);
            b_conic[lid] = vec4<f32>(p1.xyz, 0.0);
            b_rgb[lid] = proj[3u * g + 2u];
        }
        workgroupBarrier();
        let in_batch = min(256u, total - b * 256u);
        for (var j = 0u; j < in_batch && !done; j++) {
            let xo = b_xy_op[j];
            let q = b_conic[j].xyz;
            let d = xo.xy - pix;
            let power = -0.5 * (q.x * d.x * d.x + q.z * d.y * d.y) - q.y * d.x * d.y;
            if power > 0.0 {
                continue;
            }
            let alpha = min(ALPHA_MAX, xo.z * exp(power));
            if alpha < ALPHA_MIN {
                continue;
            }
            let t_next = t * (1.0 - alpha);
            if t_next < T_MIN {
                done = true;
                atomicAdd(&done_count, 1u);
                break;
            }
            c += t * alpha * b_rgb[j].xyz;
            t = t_next;
            last = b * 256u + j + 1u;
        }
    }
    if inside {
        let o = py * p.dims.x + px;
        let col = c + t * p.bg.xyz;
        image[3u * o] = col.x;
        image[3u * o + 1u] = col.y;
        image[3u * o + 2u] = col.z;
        final_t[o] = t;
        n_contrib[o] = last;
    }
}
