// Tile bookkeeping. `emit`: one thread per Gaussian writes a (tile id, depth bits, Gaussian id)
// triple per touched tile at its scanned offset (Gaussian order, so ties in depth keep the index
// order after the stable sort). `ranges`: one thread per sorted intersection marks where each
// tile's run starts and ends.

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> proj: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> offsets: array<u32>;
@group(0) @binding(3) var<storage, read_write> keys_hi: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_lo: array<u32>;
@group(0) @binding(5) var<storage, read_write> values: array<u32>;
// ranges[2 t] = first intersection of tile t, ranges[2 t + 1] = one past its last.
@group(0) @binding(6) var<storage, read_write> ranges: array<u32>;

@compute @workgroup_size(256)
fn emit(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
        @builtin(local_invocation_index) lid: u32) {
    let i = linear_id(wg, nwg, lid);
    if i >= params.counts.x {
        return;
    }
    let count = offsets[i + 1u] - offsets[i];
    if count == 0u {
        return;
    }
    let p0 = proj[3u * i];
    let r = f32(bitcast<u32>(p0.w));
    let rect = tile_rect(p0.xy, r, params.dims.zw);
    // Depth > NEAR > 0, so its IEEE bits order like the value.
    let depth_bits = bitcast<u32>(p0.z);
    var k = offsets[i];
    for (var ty = rect.y; ty <= rect.w; ty++) {
        for (var tx = rect.x; tx <= rect.z; tx++) {
            keys_hi[k] = ty * params.dims.z + tx;
            keys_lo[k] = depth_bits;
            values[k] = i;
            k++;
        }
    }
}

@compute @workgroup_size(256)
fn ranges_main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>,
               @builtin(local_invocation_index) lid: u32) {
    let k = linear_id(wg, nwg, lid);
    let n = params.counts.z;
    if k >= n {
        return;
    }
    let tile = keys_hi[k];
    if k == 0u || keys_hi[k - 1u] != tile {
        ranges[2u * tile] = k;
    }
    if k + 1u == n || keys_hi[k + 1u] != tile {
        ranges[2u * tile + 1u] = k + 1u;
    }
}
