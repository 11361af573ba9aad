// The MCMC strategy's per-step terms (src/splat/mcmc.rs; Kheradmand et al. 2024), one thread
// per Gaussian of one chunk. This header is shared by `mcmc_regularise.wgsl` and
// `mcmc_noise.wgsl` (src/splat/gpu/mcmc.rs joins them). CPU twins: mcmc::regularise_grads,
// mcmc::add_noise, mcmc::normal3.

struct McmcParams {
    // Gaussians in the whole model (the regularisers are means over all of them).
    n_total: u32,
    // Optimiser step (1-based) and seed of the noise.
    step: u32,
    seed: u32,
    _p0: u32,
    // lambda_o / N and lambda_s / (3 N).
    opacity_coef: f32,
    scale_coef: f32,
    // Position learning rate x noise_lr.
    scaler: f32,
    _p1: f32,
}

const FLAG_BOUND: u32 = 1u;
const FLAG_BACKGROUND: u32 = 2u;

fn gid(wg: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return (wg.y * nwg.x + wg.x) * 256u + lid;
}

fn sigmoid1(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-x));
}

// PCG "RXS-M-XS" output hash of one word (Jarzynski & Olano 2020).
fn pcg_hash(v: u32) -> u32 {
    let s = v * 747796405u + 2891336453u;
    let w = ((s >> ((s >> 28u) + 4u)) ^ s) * 277803737u;
    return (w >> 22u) ^ w;
}

fn unit_of(h: u32) -> f32 {
    return (f32(h >> 8u) + 0.5) * (1.0 / 16777216.0);
}
