// The fine samples of each ray (src/nerf/gpu.rs; CPU twins `render::sample_pdf` and
// `render::merge_sorted`): from ray r's per_ray coarse distances tc and weights wc, the PDF over
// the bins between the coarse midpoints (weights 1..per_ray-1, + 1e-5), inverted at the ray's
// n_fine ascending numbers u; the fine and coarse distances merged in ascending order into
// tf (per_ray + n_fine per ray). At most 256 coarse samples per ray.

@group(0) @binding(0) var<storage, read> rp: RayParams;
@group(0) @binding(1) var<storage, read> tc: array<f32>;
@group(0) @binding(2) var<storage, read> wc: array<f32>;
@group(0) @binding(3) var<storage, read> u: array<f32>;
@group(0) @binding(4) var<storage, read_write> tf: array<f32>;

const PDF_EPS: f32 = 1e-5;

@compute @workgroup_size(256)
fn main(inv: Invocation) {
    let r = flat_index(inv);
    if r >= rp.n {
        return;
    }
    let nc = rp.per_ray;
    let nf = rp.n_fine;
    let base = r * nc;
    let out = r * (nc + nf);
    var bins: array<f32, 256>;
    var cdf: array<f32, 256>;
    for (var i = 0u; i + 1u < nc; i++) {
        bins[i] = 0.5 * (tc[base + i] + tc[base + i + 1u]);
    }
    var total = 0.0;
    for (var i = 1u; i + 1u < nc; i++) {
        total += wc[base + i] + PDF_EPS;
    }
    cdf[0] = 0.0;
    var acc = 0.0;
    for (var i = 1u; i + 1u < nc; i++) {
        acc += (wc[base + i] + PDF_EPS) / total;
        cdf[i] = min(acc, 1.0);
    }
    let ncdf = nc - 1u;
    // Fine samples in order, merged with the coarse ones as they come.
    var ci = 0u;
    var o = out;
    for (var k = 0u; k < nf; k++) {
        let uk = u[r * nf + k];
        // First cdf entry above uk.
        var above = 0u;
        while above < ncdf && cdf[above] <= uk {
            above++;
        }
        above = min(above, ncdf - 1u);
        let below = select(above - 1u, 0u, above == 0u);
        let denom = cdf[above] - cdf[below];
        var f = 0.0;
        if denom >= PDF_EPS {
            f = (uk - cdf[below]) / denom;
        }
        let s = bins[below] + f * (bins[above] - bins[below]);
        while ci < nc && tc[base + ci] <= s {
            tf[o] = tc[base + ci];
            o++;
            ci++;
        }
        tf[o] = s;
        o++;
    }
    while ci < nc {
        tf[o] = tc[base + ci];
        o++;
        ci++;
    }
}
