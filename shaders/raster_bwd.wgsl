// Backward rasterisation: one workgroup per tile; each thread owns PIX consecutive pixels of one
// tile row (PIX and THREADS = 256 / PIX are prepended by `raster_bwd.rs`), walking their runs back
// to front from the last blended Gaussian, recovering the transmittance by division
// (T_before = T_after / (1 - alpha)). Per Gaussian, a thread first sums its own pixels'
// contributions in registers, then adds the sum to the Gaussian's screen-space gradient with
// `add_grad` (float atomics or a CAS loop, prepended): grads2d[10 g ..] = dL/d(mean x, mean y),
// dL/d(conic a, b, c), dL/d(r, g, b), dL/d(opacity), dL/d(depth z). The depth is a fourth channel
// (record lane 2.w, background 0) whose per-pixel gradient comes from `depth_grad` (zero unless
// a depth loss wrote it). PIX = 1 is the classic one-pixel-per-thread
// kernel; a larger PIX divides the global atomics by up to PIX, which pays on CPU adapters
// (lavapipe) where an atomic float add is a locked compare-and-swap loop. No subgroup operations.

// Bindings 0-7 (parameters, projected record slots, band, the band's sorted intersections):
// `slots.wgsl`; 11-14: the screen-space gradient slots, same split as the records
// (`atomic_*.wgsl`, one copy per slot). One dispatch per band of tile rows.
@group(0) @binding(8) var<storage, read> final_t: array<f32>;
@group(0) @binding(9) var<storage, read> n_contrib: array<u32>;
@group(0) @binding(10) var<storage, read> dl_dimage: array<f32>;
// dL/d(expected depth) per pixel (binding after the four gradient slots 11-14).
@group(0) @binding(15) var<storage, read> depth_grad: array<f32>;

// Adds v to screen-space gradient k (0..9) of Gaussian g, in g's slot.
fn add_grad(g: u32, k: u32, v: f32) {
    let s = min(g / band.z, 3u);
    let i = 10u * (g - s * band.z) + k;
    switch s {
        case 0u: { add_0(i, v); }
        case 1u: { add_1(i, v); }
        case 2u: { add_2(i, v); }
        default: { add_3(i, v); }
    }
}

// The staged batch (`slots.wgsl`) holds each Gaussian's id bits in its fourth position lane.
var<workgroup> max_last: atomic<u32>;
var<workgroup> last_snap: u32;

@compute @workgroup_size(THREADS)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let p = params;
    let tile_y = wg.y + band.x;
    if lid == 0u {
        atomicStore(&max_last, 0u);
    }
    let range = tile_run(wg, tile_y, lid);
    var pix: array<vec2<f32>, PIX>;
    var t_final: array<f32, PIX>;
    var last: array<u32, PIX>;
    var v_out: array<vec4<f32>, PIX>;
    var v_bg: array<f32, PIX>;
    var t: array<f32, PIX>;
    var acc: array<vec4<f32>, PIX>;
    var my_last = 0u;
    for (var k = 0u; k < PIX; k++) {
        let q = pixel_of(wg, tile_y, lid, k);
        let px = q.x;
        let py = q.y;
        pix[k] = vec2<f32>(f32(px) + 0.5, f32(py) + 0.5);
        t_final[k] = 1.0;
        last[k] = 0u;
        v_out[k] = vec4<f32>(0.0);
        if px < p.dims.x && py < p.dims.y {
            let o = py * p.dims.x + px;
            t_final[k] = final_t[o];
            last[k] = n_contrib[o];
            v_out[k] = vec4<f32>(dl_dimage[3u * o], dl_dimage[3u * o + 1u],
                dl_dimage[3u * o + 2u], depth_grad[o]);
        }
        my_last = max(my_last, last[k]);
        v_bg[k] = dot(p.bg.xyz, v_out[k].xyz);
        t[k] = t_final[k];
        acc[k] = vec4<f32>(0.0);
    }
    atomicMax(&max_last, my_last);
    workgroupBarrier();
    if lid == 0u {
        last_snap = atomicLoad(&max_last);
    }
    let tile_last = workgroupUniformLoad(&last_snap);
    let total = range.y - range.x;
    let batches = (tile_last + BATCH - 1u) / BATCH;
    for (var bb = 0u; bb < batches; bb++) {
        let b = batches - 1u - bb;
        workgroupBarrier();
        for (var s = lid; s < BATCH; s += THREADS) {
            let k = b * BATCH + s;
            if k < total {
                let g = values[range.x + k];
                stage(s, g, bitcast<f32>(g));
            }
        }
        workgroupBarrier();
        let in_batch = min(BATCH, total - b * BATCH);
        for (var jj = 0u; jj < in_batch; jj++) {
            let j = in_batch - 1u - jj;
            let idx = b * BATCH + j;
            if idx >= my_last {
                continue;
            }
            let xo = b_xy_op[j];
            let q = b_conic[j].xyz;
            let rgb = b_rgb[j];
            var g_rgb = vec4<f32>(0.0);
            var g_mean = vec2<f32>(0.0);
            var g_conic = vec3<f32>(0.0);
            var g_opacity = 0.0;
            var hit = false;
            var hit_geo = false;
            for (var k = 0u; k < PIX; k++) {
                if idx >= last[k] {
                    continue;
                }
                let d = xo.xy - pix[k];
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
                t[k] *= ra;
                let fac = alpha * t[k];
                g_rgb += fac * v_out[k];
                let v_alpha = dot(rgb * t[k] - acc[k] * ra, v_out[k]) - t_final[k] * ra * v_bg[k];
                acc[k] += rgb * fac;
                hit = true;
                if raw <= ALPHA_MAX {
                    let v_power = v_alpha * alpha;
                    g_mean += -v_power * vec2<f32>(q.x * d.x + q.y * d.y, q.y * d.x + q.z * d.y);
                    g_conic += v_power * vec3<f32>(-0.5 * d.x * d.x, -d.x * d.y, -0.5 * d.y * d.y);
                    g_opacity += v_alpha * vis;
                    hit_geo = true;
                }
            }
            if hit {
                let g = bitcast<u32>(xo.w);
                add_grad(g, 5u, g_rgb.x);
                add_grad(g, 6u, g_rgb.y);
                add_grad(g, 7u, g_rgb.z);
                add_grad(g, 9u, g_rgb.w);
                if hit_geo {
                    add_grad(g, 0u, g_mean.x);
                    add_grad(g, 1u, g_mean.y);
                    add_grad(g, 2u, g_conic.x);
                    add_grad(g, 3u, g_conic.y);
                    add_grad(g, 4u, g_conic.z);
                    add_grad(g, 8u, g_opacity);
                }
            }
        }
    }
}
