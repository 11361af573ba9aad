// Forward rasterisation: one workgroup per 16x16 tile; each thread owns PIX consecutive pixels of
// one tile row (PIX and THREADS = 256 / PIX are prepended by `raster_fwd.rs`; see
// `raster_bwd.wgsl`). Batches of 256 Gaussians of the tile's depth-sorted run are staged in
// workgroup memory and blended front to back (docs/splatting.md "Per pixel"); a thread reads each
// staged Gaussian once for all its pixels, and the workgroup stops once every pixel is saturated.

// Bindings 0-7 (parameters, projected record slots, band, the band's sorted intersections):
// `slots.wgsl`. One dispatch per band of tile rows.
@group(0) @binding(8) var<storage, read_write> image: array<f32>;
@group(0) @binding(9) var<storage, read_write> final_t: array<f32>;
// Per pixel: 1 + position (within the tile's run) of the last Gaussian blended, 0 if none.
@group(0) @binding(10) var<storage, read_write> n_contrib: array<u32>;
// Per pixel: expected depth sum T alpha z (the fourth channel, background 0), metres.
@group(0) @binding(11) var<storage, read_write> depth: array<f32>;

var<workgroup> done_count: atomic<u32>;
var<workgroup> done_snap: u32;

@compute @workgroup_size(THREADS)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let p = params;
    let tile_y = wg.y + band.x;
    if lid == 0u {
        atomicStore(&done_count, 0u);
    }
    let range = tile_run(wg, tile_y, lid);
    var pix: array<vec2<f32>, PIX>;
    var done: array<bool, PIX>;
    var t: array<f32, PIX>;
    var c: array<vec4<f32>, PIX>;
    var last: array<u32, PIX>;
    var live = 0u;
    for (var k = 0u; k < PIX; k++) {
        let q = pixel_of(wg, tile_y, lid, k);
        let px = q.x;
        let py = q.y;
        pix[k] = vec2<f32>(f32(px) + 0.5, f32(py) + 0.5);
        done[k] = !(px < p.dims.x && py < p.dims.y);
        t[k] = 1.0;
        c[k] = vec4<f32>(0.0);
        last[k] = 0u;
        if !done[k] {
            live++;
        }
    }
    if live < PIX {
        atomicAdd(&done_count, PIX - live);
    }
    let total = range.y - range.x;
    let batches = (total + BATCH - 1u) / BATCH;
    for (var b = 0u; b < batches; b++) {
        workgroupBarrier();
        if lid == 0u {
            done_snap = atomicLoad(&done_count);
        }
        if workgroupUniformLoad(&done_snap) >= 256u {
            break;
        }
        for (var s = lid; s < BATCH; s += THREADS) {
            let k = range.x + b * BATCH + s;
            if k < range.y {
                stage(s, values[k], 0.0);
            }
        }
        workgroupBarrier();
        let in_batch = min(BATCH, total - b * BATCH);
        for (var j = 0u; j < in_batch && live > 0u; j++) {
            let xo = b_xy_op[j];
            let q = b_conic[j].xyz;
            for (var k = 0u; k < PIX; k++) {
                if done[k] {
                    continue;
                }
                let d = xo.xy - pix[k];
                let power = -0.5 * (q.x * d.x * d.x + q.z * d.y * d.y) - q.y * d.x * d.y;
                if power > 0.0 {
                    continue;
                }
                let alpha = min(ALPHA_MAX, xo.z * exp(power));
                if alpha < ALPHA_MIN {
                    continue;
                }
                let t_next = t[k] * (1.0 - alpha);
                if t_next < T_MIN {
                    done[k] = true;
                    live--;
                    atomicAdd(&done_count, 1u);
                    continue;
                }
                c[k] += t[k] * alpha * b_rgb[j];
                t[k] = t_next;
                last[k] = b * BATCH + j + 1u;
            }
        }
    }
    for (var k = 0u; k < PIX; k++) {
        let q = pixel_of(wg, tile_y, lid, k);
        let px = q.x;
        let py = q.y;
        if px < p.dims.x && py < p.dims.y {
            let o = py * p.dims.x + px;
            let col = c[k].xyz + t[k] * p.bg.xyz;
            image[3u * o] = col.x;
            image[3u * o + 1u] = col.y;
            image[3u * o + 2u] = col.z;
            final_t[o] = t[k];
            n_contrib[o] = last[k];
            depth[o] = c[k].w;
        }
    }
}
