// The raster backward's per-Gaussian flush without subgroup operations: every thread that hit
// adds its own sums (`raster_bwd.rs` prepends this or `flush_subgroup.wgsl`).
fn flush(lid: u32, g: u32, hit: bool, hit_geo: bool, g_rgb: vec4<f32>, g_mean: vec2<f32>,
         g_conic: vec3<f32>, g_opacity: f32) {
    if !hit {
        return;
    }
    add_grad(g, 5u, g_rgb.x);
    add_grad(g, 6u, g_rgb.y);
    add_grad(g, 7u, g_rgb.z);
    add_grad(g, 9u, g_rgb.w);
    if hit_geo {
        add_grad(g, 0u, g_mean.x);
        add_grad(g, 1u, g_mean.y);
        add_grad(g, 2u, g_conic.x);
        add_grad(g, 3u, g_conic.y);
        add_grad(g, 4u, g_conic.z);
        add_grad(g, 8u, g_opacity);
    }
}
