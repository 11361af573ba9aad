// Bindings 0-7 of both rasterisers (the frame's parameters, then random access to the projected
// records), prepended by `raster_fwd.rs` and `raster_bwd.rs`: the records are bound as up to four sub-ranges ("slots") of whole Gaussians
// (`chunks.rs`, `SlotPlan`), Gaussian g lives in slot g / band.z at record g mod band.z, so one
// frame may hold more records than one storage binding. Also the band uniform: the rasterisers
// run once per band of whole tile rows, each with its own sorted intersection arrays. And what
// else both share: the staged batch of Gaussians and the pixels of a thread.

@group(0) @binding(0) var<storage, read> params: Params;
@group(0) @binding(1) var<storage, read> proj0: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> proj1: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> proj2: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> proj3: array<vec4<f32>>;
// First tile row of the band, one past its last, Gaussians per slot, intersections in the band.
@group(0) @binding(5) var<storage, read> band: vec4<u32>;
// The band's sorted intersections (Gaussian ids) and, per tile, its run in them.
@group(0) @binding(6) var<storage, read> values: array<u32>;
@group(0) @binding(7) var<storage, read> ranges: array<u32>;

// Record row k (0: mean, depth, radius; 1: conic, opacity; 2: rgb) of Gaussian g.
fn load_proj(g: u32, k: u32) -> vec4<f32> {
    let s = min(g / band.z, 3u);
    let o = 3u * (g - s * band.z) + k;
    var r: vec4<f32>;
    switch s {
        case 0u: { r = proj0[o]; }
        case 1u: { r = proj1[o]; }
        case 2u: { r = proj2[o]; }
        default: { r = proj3[o]; }
    }
    return r;
}

// Both rasterisers stage batches of BATCH Gaussians of a tile's sorted run in workgroup memory.
const BATCH: u32 = 256u;

var<workgroup> b_xy_op: array<vec4<f32>, BATCH>;   // mean x, mean y, opacity, `w` of `stage`
var<workgroup> b_conic: array<vec4<f32>, BATCH>;
var<workgroup> b_rgb: array<vec4<f32>, BATCH>;
var<workgroup> shared_u: vec2<u32>;

// Stages Gaussian g in batch entry s, `w` in the fourth lane of its position.
fn stage(s: u32, g: u32, w: f32) {
    let p0 = load_proj(g, 0u);
    let p1 = load_proj(g, 1u);
    b_xy_op[s] = vec4<f32>(p0.xy, p1.w, w);
    b_conic[s] = vec4<f32>(p1.xyz, 0.0);
    b_rgb[s] = load_proj(g, 2u);
}

// The run (first, one past last) in `values` of tile (wg.x, tile_y), read by thread `lid` 0 and
// shared with the workgroup: a barrier, so called from uniform control flow.
fn tile_run(wg: vec3<u32>, tile_y: u32, lid: u32) -> vec2<u32> {
    let tile = tile_y * params.dims.z + wg.x;
    if lid == 0u {
        shared_u = vec2<u32>(ranges[2u * tile], ranges[2u * tile + 1u]);
    }
    return workgroupUniformLoad(&shared_u);
}

// Pixel (x, y) of the k-th of the PIX pixels of thread `lid` in the tile (wg.x, tile_y).
fn pixel_of(wg: vec3<u32>, tile_y: u32, lid: u32, k: u32) -> vec2<u32> {
    let lp = lid * PIX + k;
    return vec2<u32>(wg.x * TILE + lp % TILE, tile_y * TILE + lp / TILE);
}
