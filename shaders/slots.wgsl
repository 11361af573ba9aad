// Random access of both rasterisers to the projected records, prepended by `raster_fwd.rs` and
// `raster_bwd.rs`: the records are bound as up to four sub-ranges ("slots") of whole Gaussians
// (`chunks.rs`, `SlotPlan`), Gaussian g lives in slot g / band.z at record g mod band.z, so one
// frame may hold more records than one storage binding. Also the band uniform: the rasterisers
// run once per band of whole tile rows, each with its own sorted intersection arrays.

@group(0) @binding(1) var<storage, read> proj0: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> proj1: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> proj2: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> proj3: array<vec4<f32>>;
// First tile row of the band, one past its last, Gaussians per slot, intersections in the band.
@group(0) @binding(5) var<uniform> band: vec4<u32>;

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
