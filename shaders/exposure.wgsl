// Per-image exposure compensation (docs/splatting.md "Exposure"): out = A rgb + b with the
// image's [A | b] (row-major 3x4, 12 floats per image), its backward, and the sum of
// dL/d[A | b] over the pixels. CPU twin: src/splat/cpu/exposure.rs.
//
// No atomics and no subgroup operations: each workgroup of 256 threads sums its pixels' terms
// in workgroup memory in a fixed tree order, then one workgroup sums those partials, so the
// result is the same on every adapter and every run.
//
// The parameter buffer `Params` is prepended by `exposure.rs` (its `wgsl_struct!`).

@group(0) @binding(0) var<storage, read> params: Params;
// The render, RGB f32 interleaved, row-major.
@group(0) @binding(1) var<storage, read> rendered: array<f32>;
// The photo, one RGBA8 per pixel, R in the low byte.
@group(0) @binding(2) var<storage, read> target_rgba: array<u32>;
// [A | b] of every image.
@group(0) @binding(3) var<storage, read> exposure: array<f32>;
// apply: the exposed render, RGB f32 interleaved.
@group(0) @binding(4) var<storage, read_write> exposed: array<f32>;
// backward: dL/d(exposed render), RGB f32 interleaved.
@group(0) @binding(5) var<storage, read> dl_dout: array<f32>;
// backward: dL/d(render) = A^T dL/dout, RGB f32 interleaved (what the raster backward reads).
@group(0) @binding(6) var<storage, read_write> dl_drgb: array<f32>;
// backward: 12 floats per workgroup, dL/d[A | b] of its pixels.
@group(0) @binding(7) var<storage, read_write> partials: array<f32>;
// reduce: dL/d[A | b] of every image (zero but for `index`).
@group(0) @binding(8) var<storage, read_write> grads: array<f32>;

// Three rows of (dL/da_r0, dL/da_r1, dL/da_r2, dL/db_r) per thread: 12 KiB.
var<workgroup> red: array<vec4<f32>, 768>;

fn masked(i: u32) -> bool {
    return params.left_half != 0u && (i % params.width) >= params.width / 2u;
}

fn load_rgb(i: u32) -> vec3<f32> {
    return vec3<f32>(rendered[3u * i], rendered[3u * i + 1u], rendered[3u * i + 2u]);
}

// Row r of [A | b] of the current image.
fn row(r: u32) -> vec4<f32> {
    let o = 12u * params.index + 4u * r;
    return vec4<f32>(exposure[o], exposure[o + 1u], exposure[o + 2u], exposure[o + 3u]);
}

// Sums red[base + 0..256] into red[base] for the three rows (all threads must call it).
fn tree_sum(lid: u32) {
    workgroupBarrier();
    for (var stride = 128u; stride > 0u; stride = stride >> 1u) {
        if (lid < stride) {
            red[lid] += red[lid + stride];
            red[256u + lid] += red[256u + lid + stride];
            red[512u + lid] += red[512u + lid + stride];
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn apply(inv: Invocation) {
    let i = flat_index(inv);
    if (i >= params.width * params.height) {
        return;
    }
    var out: vec3<f32>;
    if (masked(i)) {
        out = unpack4x8unorm(target_rgba[i]).xyz;
    } else {
        let c = vec4<f32>(load_rgb(i), 1.0);
        out = vec3<f32>(dot(row(0u), c), dot(row(1u), c), dot(row(2u), c));
    }
    exposed[3u * i] = out.x;
    exposed[3u * i + 1u] = out.y;
    exposed[3u * i + 2u] = out.z;
}

@compute @workgroup_size(256)
fn backward(inv: Invocation) {
    let g_id = flat_group(inv);
    let i = flat_index(inv);
    let lid = inv.lid;
    var rows = array<vec4<f32>, 3>(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
    if (i < params.width * params.height) {
        var d = vec3<f32>(0.0);
        if (!masked(i)) {
            let g = vec3<f32>(dl_dout[3u * i], dl_dout[3u * i + 1u], dl_dout[3u * i + 2u]);
            let c = vec4<f32>(load_rgb(i), 1.0);
            let r0 = row(0u);
            let r1 = row(1u);
            let r2 = row(2u);
            d = g.x * r0.xyz + g.y * r1.xyz + g.z * r2.xyz;
            rows[0] = g.x * c;
            rows[1] = g.y * c;
            rows[2] = g.z * c;
        }
        dl_drgb[3u * i] = d.x;
        dl_drgb[3u * i + 1u] = d.y;
        dl_drgb[3u * i + 2u] = d.z;
    }
    red[lid] = rows[0];
    red[256u + lid] = rows[1];
    red[512u + lid] = rows[2];
    tree_sum(lid);
    if (lid == 0u && g_id < params.n_partials) {
        for (var r = 0u; r < 3u; r++) {
            let v = red[256u * r];
            partials[12u * g_id + 4u * r] = v.x;
            partials[12u * g_id + 4u * r + 1u] = v.y;
            partials[12u * g_id + 4u * r + 2u] = v.z;
            partials[12u * g_id + 4u * r + 3u] = v.w;
        }
    }
}

// One workgroup: sums the partials (fixed order), then writes the gradient of every image,
// zero but for the current one (so that Adam can run over all of them, as torch does).
@compute @workgroup_size(256)
fn reduce(@builtin(local_invocation_index) lid: u32) {
    var rows = array<vec4<f32>, 3>(vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0));
    for (var g = lid; g < params.n_partials; g += 256u) {
        for (var r = 0u; r < 3u; r++) {
            let o = 12u * g + 4u * r;
            rows[r] += vec4<f32>(partials[o], partials[o + 1u], partials[o + 2u], partials[o + 3u]);
        }
    }
    red[lid] = rows[0];
    red[256u + lid] = rows[1];
    red[512u + lid] = rows[2];
    tree_sum(lid);
    let total = 12u * params.n_images;
    for (var k = lid; k < total; k += 256u) {
        var v = 0.0;
        if (k / 12u == params.index) {
            let j = k % 12u;
            v = red[256u * (j / 4u)][j % 4u];
        }
        grads[k] = v;
    }
}
