// Encodes the samples of a chunk (src/nerf/gpu.rs; CPU twin `render::encode` via `Batch::new`):
// sample g = row0 + s lies on ray g / per_ray at distance t[g]; its position o + t d and its
// ray's unit direction d are written as [x, sin(2^k x), cos(2^k x)] per band (3 + 6 L floats).
// rays: 8 floats per ray (origin, near, direction, far). `RayParams` is prepended by gpu.rs.

@group(0) @binding(0) var<storage, read> rp: RayParams;
@group(0) @binding(1) var<storage, read> rays: array<f32>;
@group(0) @binding(2) var<storage, read> t: array<f32>;
@group(0) @binding(3) var<storage, read_write> pos: array<f32>;
@group(0) @binding(4) var<storage, read_write> dir: array<f32>;

fn write_encoding(x: vec3<f32>, bands: u32, base: u32, is_pos: bool) {
    var out = base;
    for (var c = 0u; c < 3u; c++) {
        if is_pos { pos[out] = x[c]; } else { dir[out] = x[c]; }
        out += 1u;
    }
    var f = 1.0;
    for (var k = 0u; k < bands; k++) {
        for (var c = 0u; c < 3u; c++) {
            let v = sin(f * x[c]);
            if is_pos { pos[out] = v; } else { dir[out] = v; }
            out += 1u;
        }
        for (var c = 0u; c < 3u; c++) {
            let v = cos(f * x[c]);
            if is_pos { pos[out] = v; } else { dir[out] = v; }
            out += 1u;
        }
        f *= 2.0;
    }
}

@compute @workgroup_size(256)
fn main(inv: Invocation) {
    let s = flat_index(inv);
    if s >= rp.n {
        return;
    }
    let g = rp.row0 + s;
    let r = g / rp.per_ray;
    let o = vec3<f32>(rays[r * 8u], rays[r * 8u + 1u], rays[r * 8u + 2u]);
    let d = vec3<f32>(rays[r * 8u + 4u], rays[r * 8u + 5u], rays[r * 8u + 6u]);
    let p = o + t[g] * d;
    write_encoding(p, rp.pos_bands, s * (3u + 6u * rp.pos_bands), true);
    write_encoding(d, rp.dir_bands, s * (3u + 6u * rp.dir_bands), false);
}
