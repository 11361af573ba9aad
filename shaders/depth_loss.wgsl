// The LiDAR depth loss's gradient (src/splat/depth.rs, CPU twin depth::grad_at), one thread per
// pixel: dL/dD = coef * sign(D - L) / L where the LiDAR map has a depth L > 0, else 0, with
// coef = lambda / |V|. Writes the frame's depth gradient, which the raster backward reads. The
// parameter buffer `DepthParams` is prepended by `depth.rs` (its `wgsl_struct!`).

@group(0) @binding(0) var<storage, read> dp: DepthParams;
@group(0) @binding(1) var<storage, read> depth: array<f32>;
@group(0) @binding(2) var<storage, read> lidar: array<f32>;
@group(0) @binding(3) var<storage, read_write> depth_grad: array<f32>;

@compute @workgroup_size(256)
fn main(inv: Invocation) {
    let o = flat_index(inv);
    if o >= dp.pixels {
        return;
    }
    let l = lidar[o];
    var g = 0.0;
    if l > 0.0 {
        let d = depth[o];
        if d > l {
            g = dp.coef / l;
        } else if d < l {
            g = -dp.coef / l;
        }
    }
    depth_grad[o] = g;
}
