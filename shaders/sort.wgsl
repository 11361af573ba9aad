// Stable LSD radix sort of (key_hi, key_lo, value) triples, 4 bits per pass.
// `count`: per-block digit histogram, stored digit-major (hist[d * num_blocks + block]) so that
// one exclusive scan over it yields every block's output offset per digit.
// `scatter`: stable ranks within the block (thread-ordered counters), then scatter.

struct SortParams {
    n: u32,
    shift: u32,
    use_hi: u32,     // 1: the digit comes from key_hi, 0: from key_lo
    num_blocks: u32,
}

const WG: u32 = 128u;
const EPT: u32 = 8u;        // elements per thread
const BLOCK: u32 = 1024u;   // WG * EPT
const BINS: u32 = 16u;

@group(0) @binding(0) var<storage, read> sp: SortParams;
@group(0) @binding(1) var<storage, read> hi_in: array<u32>;
@group(0) @binding(2) var<storage, read> lo_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> hist: array<u32>;
@group(0) @binding(4) var<storage, read> val_in: array<u32>;
@group(0) @binding(5) var<storage, read_write> hi_out: array<u32>;
@group(0) @binding(6) var<storage, read_write> lo_out: array<u32>;
@group(0) @binding(7) var<storage, read_write> val_out: array<u32>;

var<workgroup> wg_hist: array<atomic<u32>, 16>;
var<workgroup> counters: array<u32, 2048>; // [digit * WG + thread]
var<workgroup> seg: array<u32, 128>;       // [digit * 8 + segment]

fn digit_of(i: u32) -> u32 {
    var k = lo_in[i];
    if sp.use_hi != 0u {
        k = hi_in[i];
    }
    return (k >> sp.shift) & 15u;
}

@compute @workgroup_size(128)
fn count(inv: Invocation) {
    let block = flat_group(inv);
    let lid = inv.lid;
    if block >= sp.num_blocks {
        return;
    }
    if lid < BINS {
        atomicStore(&wg_hist[lid], 0u);
    }
    workgroupBarrier();
    for (var j = 0u; j < EPT; j++) {
        let i = block * BLOCK + j * WG + lid;
        if i < sp.n {
            atomicAdd(&wg_hist[digit_of(i)], 1u);
        }
    }
    workgroupBarrier();
    if lid < BINS {
        hist[lid * sp.num_blocks + block] = atomicLoad(&wg_hist[lid]);
    }
}

@compute @workgroup_size(128)
fn scatter(inv: Invocation) {
    let block = flat_group(inv);
    let lid = inv.lid;
    if block >= sp.num_blocks {
        return;
    }
    // Thread lid owns the contiguous elements base .. base + EPT (stability needs index order).
    let base = block * BLOCK + lid * EPT;
    var local: array<u32, 16>;
    for (var j = 0u; j < EPT; j++) {
        if base + j < sp.n {
            local[digit_of(base + j)] += 1u;
        }
    }
    for (var d = 0u; d < BINS; d++) {
        counters[d * WG + lid] = local[d];
    }
    workgroupBarrier();
    // Exclusive scan of each digit's 128 counters: 8 segments of 16 per digit.
    let dd = lid / 8u;
    let sg = lid % 8u;
    var s = 0u;
    for (var k = 0u; k < 16u; k++) {
        s += counters[dd * WG + sg * 16u + k];
    }
    seg[lid] = s;
    workgroupBarrier();
    if lid < BINS {
        var run = 0u;
        for (var k = 0u; k < 8u; k++) {
            let c = seg[lid * 8u + k];
            seg[lid * 8u + k] = run;
            run += c;
        }
    }
    workgroupBarrier();
    var run = seg[lid];
    for (var k = 0u; k < 16u; k++) {
        let idx = dd * WG + sg * 16u + k;
        let c = counters[idx];
        counters[idx] = run;
        run += c;
    }
    workgroupBarrier();
    var seen: array<u32, 16>;
    for (var j = 0u; j < EPT; j++) {
        let i = base + j;
        if i < sp.n {
            let d = digit_of(i);
            let dst = hist[d * sp.num_blocks + block] + counters[d * WG + lid] + seen[d];
            seen[d] += 1u;
            hi_out[dst] = hi_in[i];
            lo_out[dst] = lo_in[i];
            val_out[dst] = val_in[i];
        }
    }
}
