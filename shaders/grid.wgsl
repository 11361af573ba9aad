// The 1-D dispatch of `gpu::buffers::grid` (Rust): workgroups counted along x, then y (at most
// 65535 along x). Prepended to every kernel by `gpu::buffers::pipeline`: an entry point takes
// an `Invocation` and finds its place with `flat_group` (an item per workgroup) or `flat_index`
// (an item per invocation, workgroups of 256).
struct Invocation {
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
}

// Index of this invocation's workgroup in the dispatch.
fn flat_group(inv: Invocation) -> u32 {
    return inv.wg.y * inv.nwg.x + inv.wg.x;
}

// Index of this invocation in the dispatch, for workgroups of 256 invocations.
fn flat_index(inv: Invocation) -> u32 {
    return flat_group(inv) * 256u + inv.lid;
}
