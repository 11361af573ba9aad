// Alpha compositing of each ray onto black and the squared error's gradient (src/nerf/gpu.rs;
// CPU twins `render::composite` and `render::composite_backward`): ray r of n has per_ray
// samples at distances t (ascending) with raw densities sig and colours rgb (after the
// sigmoid). With dL/dC = scale (C - target), writes each sample's weight, dL/d raw density
// (0 where raw <= 0) and dL/d colour before the sigmoid (dL/dc c (1 - c)), and the ray's
// squared error |C - target|^2 and its colour. At most 256 samples per ray (gpu.rs checks).

@group(0) @binding(0) var<storage, read> rp: RayParams;
@group(0) @binding(1) var<storage, read> t: array<f32>;
@group(0) @binding(2) var<storage, read> sig: array<f32>;
@group(0) @binding(3) var<storage, read> rgb: array<f32>;
@group(0) @binding(4) var<storage, read> target_rgb: array<f32>;
@group(0) @binding(5) var<storage, read_write> weights: array<f32>;
@group(0) @binding(6) var<storage, read_write> dsig: array<f32>;
@group(0) @binding(7) var<storage, read_write> drgb: array<f32>;
@group(0) @binding(8) var<storage, read_write> sq_err: array<f32>;
@group(0) @binding(9) var<storage, read_write> colour_out: array<f32>;

const LAST_DELTA: f32 = 1e10;

fn colour_at(i: u32) -> vec3<f32> {
    return vec3<f32>(rgb[i * 3u], rgb[i * 3u + 1u], rgb[i * 3u + 2u]);
}

@compute @workgroup_size(256)
fn main(inv: Invocation) {
    let r = flat_index(inv);
    if r >= rp.n {
        return;
    }
    let base = r * rp.per_ray;
    var trans: array<f32, 256>;
    var alpha: array<f32, 256>;
    var colour = vec3<f32>(0.0);
    var tr = 1.0;
    for (var i = 0u; i < rp.per_ray; i++) {
        var d = LAST_DELTA;
        if i + 1u < rp.per_ray {
            d = t[base + i + 1u] - t[base + i];
        }
        let a = 1.0 - exp(-max(sig[base + i], 0.0) * d);
        trans[i] = tr;
        alpha[i] = a;
        let w = tr * a;
        colour += w * colour_at(base + i);
        weights[base + i] = w;
        tr *= 1.0 - a;
    }
    colour_out[r * 4u] = colour.x;
    colour_out[r * 4u + 1u] = colour.y;
    colour_out[r * 4u + 2u] = colour.z;
    colour_out[r * 4u + 3u] = 1.0;
    let tgt = vec3<f32>(target_rgb[r * 4u], target_rgb[r * 4u + 1u], target_rgb[r * 4u + 2u]);
    let err = colour - tgt;
    sq_err[r] = dot(err, err);
    let dc = err * rp.scale;
    // The light behind sample i: nothing behind the last (black), then back to front.
    var behind = 0.0;
    for (var k = 0u; k < rp.per_ray; k++) {
        let i = rp.per_ray - 1u - k;
        var d = LAST_DELTA;
        if i + 1u < rp.per_ray {
            d = t[base + i + 1u] - t[base + i];
        }
        let c = colour_at(base + i);
        let w = trans[i] * alpha[i];
        var ds = 0.0;
        if sig[base + i] > 0.0 {
            ds = d * (trans[i] * (1.0 - alpha[i]) * dot(c, dc) - behind);
        }
        dsig[base + i] = ds;
        let g = dc * w * c * (vec3<f32>(1.0) - c);
        drgb[(base + i) * 3u] = g.x;
        drgb[(base + i) * 3u + 1u] = g.y;
        drgb[(base + i) * 3u + 2u] = g.z;
        behind += w * dot(c, dc);
    }
}
