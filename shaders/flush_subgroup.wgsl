// The raster backward's per-Gaussian flush with subgroup operations (feature SUBGROUP): the
// threads of a subgroup sum their contributions in registers (`subgroupAdd`) and one of them,
// the first active, makes the global atomic adds, so a Gaussian costs one set of atomics per
// subgroup instead of one per thread. Any subgroup size works (lavapipe's is 8, GPUs' 32 or
// 64). Called by every thread of the workgroup for every staged Gaussian (subgroup-uniform
// control flow), threads that missed it adding zeros.
fn flush(lid: u32, g: u32, hit: bool, hit_geo: bool, g_rgb: vec4<f32>, g_mean: vec2<f32>,
         g_conic: vec3<f32>, g_opacity: f32) {
    if !subgroupAny(hit) {
        return;
    }
    let s_rgb = subgroupAdd(g_rgb);
    let geo = subgroupAny(hit_geo);
    var s_mean = vec2<f32>(0.0);
    var s_conic = vec3<f32>(0.0);
    var s_opacity = 0.0;
    if geo {
        s_mean = subgroupAdd(g_mean);
        s_conic = subgroupAdd(g_conic);
        s_opacity = subgroupAdd(g_opacity);
    }
    if subgroupBroadcastFirst(lid) != lid {
        return;
    }
    add_grad(g, 5u, s_rgb.x);
    add_grad(g, 6u, s_rgb.y);
    add_grad(g, 7u, s_rgb.z);
    add_grad(g, 9u, s_rgb.w);
    if geo {
        add_grad(g, 0u, s_mean.x);
        add_grad(g, 1u, s_mean.y);
        add_grad(g, 2u, s_conic.x);
        add_grad(g, 3u, s_conic.y);
        add_grad(g, 4u, s_conic.z);
        add_grad(g, 8u, s_opacity);
    }
}
