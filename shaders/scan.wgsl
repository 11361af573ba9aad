// Exclusive prefix sum of u32 in place, in blocks of 1024 (256 threads x 4 elements).
// `scan_blocks` scans each block and writes its total to `block_sums`; after the block sums are
// scanned (recursively, on the CPU's orders), `add_offsets` adds them back.

struct ScanParams {
    n: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<storage, read> sp: ScanParams;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> block_sums: array<u32>;

var<workgroup> partial: array<u32, 256>;

@compute @workgroup_size(256)
fn scan_blocks(inv: Invocation) {
    let block = flat_group(inv);
    let lid = inv.lid;
    if block * 1024u >= sp.n {
        return;
    }
    let base = block * 1024u + lid * 4u;
    var v: array<u32, 4>;
    var sum = 0u;
    for (var j = 0u; j < 4u; j++) {
        let idx = base + j;
        var x = 0u;
        if idx < sp.n {
            x = data[idx];
        }
        v[j] = sum;
        sum += x;
    }
    partial[lid] = sum;
    // Hillis-Steele inclusive scan over the 256 thread sums.
    for (var off = 1u; off < 256u; off *= 2u) {
        workgroupBarrier();
        var add = 0u;
        if lid >= off {
            add = partial[lid - off];
        }
        workgroupBarrier();
        partial[lid] += add;
    }
    workgroupBarrier();
    let excl = partial[lid] - sum;
    for (var j = 0u; j < 4u; j++) {
        let idx = base + j;
        if idx < sp.n {
            data[idx] = v[j] + excl;
        }
    }
    if lid == 255u {
        block_sums[block] = partial[255];
    }
}

@compute @workgroup_size(256)
fn add_offsets(inv: Invocation) {
    let block = flat_group(inv);
    let lid = inv.lid;
    if block * 1024u >= sp.n {
        return;
    }
    let add = block_sums[block];
    for (var j = 0u; j < 4u; j++) {
        let idx = block * 1024u + lid * 4u + j;
        if idx < sp.n {
            data[idx] += add;
        }
    }
}
