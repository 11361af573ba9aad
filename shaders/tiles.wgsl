// Tile bookkeeping, in bands of whole tile rows (`renderer.rs`: a frame whose intersections
// exceed one storage binding is split into bands, each with its own intersection arrays).
// `emit`: one thread per Gaussian of one chunk writes a (band-local tile id, depth bits, Gaussian
// id) triple per touched tile of the band at its scanned offset (Gaussian order, so ties in depth
// keep the index order after the stable sort). `ranges`: one thread per sorted intersection of a
// band marks where each tile's run starts and ends. `row_counts`: intersections per tile row (to
// plan the bands). `band_counts`: per Gaussian, the tiles it touches within the band.
// Per-Gaussian buffers (proj, offsets, counts) are bound as the chunk's sub-range (index `c`).

@group(0) @binding(0) var<storage, read> params: Params;
@group(0) @binding(1) var<storage, read> proj: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> offsets: array<u32>;
@group(0) @binding(3) var<storage, read_write> keys_hi: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_lo: array<u32>;
@group(0) @binding(5) var<storage, read_write> values: array<u32>;
// ranges[2 t] = first intersection of tile t (in its band's arrays), ranges[2 t + 1] = one past
// its last.
@group(0) @binding(6) var<storage, read_write> ranges: array<u32>;
// First Gaussian of the chunk, Gaussians in the chunk.
@group(0) @binding(7) var<storage, read> chunk: vec4<u32>;
// First tile row of the band, one past its last, Gaussians per proj slot (unused here),
// intersections in the band.
@group(0) @binding(8) var<storage, read> band: vec4<u32>;
@group(0) @binding(9) var<storage, read_write> rows: array<atomic<u32>>;
@group(0) @binding(10) var<storage, read_write> counts: array<u32>;

// Tile rectangle of chunk Gaussian `c` (x0, y0, x1, y1 inclusive); `ok` false when culled (a
// visible Gaussian has a radius of at least 2 px, `project.wgsl`).
struct Rect {
    r: vec4<u32>,
    ok: bool,
}

fn rect_of(c: u32) -> Rect {
    let p0 = proj[3u * c];
    let radius = bitcast<u32>(p0.w);
    if radius == 0u {
        return Rect(vec4<u32>(0u), false);
    }
    return Rect(tile_rect(p0.xy, f32(radius), params.dims.zw), true);
}

// The tile rectangle of chunk Gaussian `c` clipped to the band's rows (inclusive, as
// `rect_of`); `ok` false when culled or when it touches no row of the band.
fn band_rect(c: u32) -> Rect {
    let rc = rect_of(c);
    let y0 = max(rc.r.y, band.x);
    let y1 = min(rc.r.w + 1u, band.y);
    return Rect(vec4<u32>(rc.r.x, y0, rc.r.z, y1 - 1u), rc.ok && y0 < y1);
}

@compute @workgroup_size(256)
fn emit(inv: Invocation) {
    let c = flat_index(inv);
    if c >= chunk.y {
        return;
    }
    let rc = band_rect(c);
    if !rc.ok {
        return;
    }
    let i = chunk.x + c;
    // Depth > NEAR > 0, so its IEEE bits order like the value.
    let depth_bits = bitcast<u32>(proj[3u * c].z);
    var k = offsets[c];
    for (var ty = rc.r.y; ty <= rc.r.w; ty++) {
        for (var tx = rc.r.x; tx <= rc.r.z; tx++) {
            keys_hi[k] = (ty - band.x) * params.dims.z + tx;
            keys_lo[k] = depth_bits;
            values[k] = i;
            k++;
        }
    }
}

@compute @workgroup_size(256)
fn ranges_main(inv: Invocation) {
    let k = flat_index(inv);
    let n = band.w;
    if k >= n {
        return;
    }
    let local = keys_hi[k];
    let tile = band.x * params.dims.z + local;
    if k == 0u || keys_hi[k - 1u] != local {
        ranges[2u * tile] = k;
    }
    if k + 1u == n || keys_hi[k + 1u] != local {
        ranges[2u * tile + 1u] = k + 1u;
    }
}

@compute @workgroup_size(256)
fn row_counts(inv: Invocation) {
    let c = flat_index(inv);
    if c >= chunk.y {
        return;
    }
    let rc = rect_of(c);
    if !rc.ok {
        return;
    }
    let width = rc.r.z - rc.r.x + 1u;
    for (var ty = rc.r.y; ty <= rc.r.w; ty++) {
        atomicAdd(&rows[ty], width);
    }
}

@compute @workgroup_size(256)
fn band_counts(inv: Invocation) {
    let c = flat_index(inv);
    if c >= chunk.y {
        return;
    }
    let rc = band_rect(c);
    var n = 0u;
    if rc.ok {
        n = (rc.r.z - rc.r.x + 1u) * (rc.r.w - rc.r.y + 1u);
    }
    counts[c] = n;
}
