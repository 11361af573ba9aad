//! Rays, the samples along them and volume rendering (Mildenhall et al. 2020, Section 4 and 5.2),
//! on the CPU: the positional encoding, stratified coarse samples, fine samples drawn from the
//! coarse weights by inverse transform, and alpha compositing with its exact gradient.

/// Length given to the last sample of a ray, in normalised units (Mildenhall's `1e10`: the
/// last sample takes whatever light is left).
pub const LAST_DELTA: f32 = 1e10;
/// Added to the coarse weights before they become the fine samples' PDF (Mildenhall's `1e-5`).
const PDF_EPS: f32 = 1e-5;

/// `[x, sin(2⁰x), cos(2⁰x), …, sin(2^(L−1)x), cos(2^(L−1)x)]` per axis group: 3 + 6 L floats
/// appended to `out` (Mildenhall's γ, with the input itself included as in its code).
pub fn encode(x: [f32; 3], bands: usize, out: &mut Vec<f32>) {
    out.extend_from_slice(&x);
    let mut f = 1.0f32;
    for _ in 0..bands {
        for c in x {
            out.push((f * c).sin());
        }
        for c in x {
            out.push((f * c).cos());
        }
        f *= 2.0;
    }
}

/// Floats of [`encode`] with `bands` bands.
pub const fn encoded_len(bands: usize) -> usize {
    3 + 6 * bands
}

/// One ray in the normalised scene frame: origin, unit direction and the sampled interval.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: [f32; 3],
    pub dir: [f32; 3],
    pub near: f32,
    pub far: f32,
}

impl Ray {
    pub fn at(&self, t: f32) -> [f32; 3] {
        [
            self.origin[0] + t * self.dir[0],
            self.origin[1] + t * self.dir[1],
            self.origin[2] + t * self.dir[2],
        ]
    }
}

/// `n` stratified distances in [near, far]: bin i at offset `jitter(i)` ∈ [0, 1) (0.5, the
/// bins' middles, when evaluating).
pub fn stratified(ray: &Ray, n: usize, mut jitter: impl FnMut() -> f32) -> Vec<f32> {
    let step = (ray.far - ray.near) / n as f32;
    (0..n)
        .map(|i| ray.near + step * (i as f32 + jitter()))
        .collect()
}

/// The interval after sample `i` of distances `t`: to the next sample, [`LAST_DELTA`] after
/// the last.
fn delta(t: &[f32], i: usize) -> f32 {
    if i + 1 < t.len() {
        t[i + 1] - t[i]
    } else {
        LAST_DELTA
    }
}

/// What compositing one ray gives: its colour and each sample's weight.
#[derive(Debug, Clone, PartialEq)]
pub struct Composite {
    pub colour: [f32; 3],
    pub weights: Vec<f32>,
}

/// Alpha compositing of samples at distances `t` (ascending) with raw densities and colours:
/// σ = max(raw, 0), δᵢ = tᵢ₊₁ − tᵢ (the last [`LAST_DELTA`]), αᵢ = 1 − exp(−σᵢ δᵢ),
/// Tᵢ = Π_{j<i} (1 − α_j), wᵢ = Tᵢ αᵢ; colour Σ wᵢ cᵢ + T_n · background.
pub fn composite(
    t: &[f32],
    sigma_raw: &[f32],
    rgb: &[[f32; 3]],
    background: [f32; 3],
) -> Composite {
    let n = t.len();
    let mut weights = Vec::with_capacity(n);
    let mut colour = [0.0f32; 3];
    let mut trans = 1.0f32;
    for i in 0..n {
        let delta = delta(t, i);
        let alpha = 1.0 - (-sigma_raw[i].max(0.0) * delta).exp();
        let w = trans * alpha;
        for c in 0..3 {
            colour[c] += w * rgb[i][c];
        }
        weights.push(w);
        trans *= 1.0 - alpha;
    }
    for c in 0..3 {
        colour[c] += trans * background[c];
    }
    Composite { colour, weights }
}

/// Gradient of a loss through [`composite`]: given dL/dcolour, returns dL/d raw density and
/// dL/d colour per sample. With Sᵢ = Σ_{j>i} w_j c_j + T_n bg (the light behind sample i),
/// dC/dσᵢ = δᵢ (Tᵢ (1 − αᵢ) cᵢ − Sᵢ), zero where raw ≤ 0; dC/dcᵢ = wᵢ.
pub fn composite_backward(
    t: &[f32],
    sigma_raw: &[f32],
    rgb: &[[f32; 3]],
    background: [f32; 3],
    d_colour: [f32; 3],
) -> (Vec<f32>, Vec<[f32; 3]>) {
    let n = t.len();
    let mut alpha = Vec::with_capacity(n);
    let mut trans = Vec::with_capacity(n + 1);
    let mut tr = 1.0f32;
    for (i, s) in sigma_raw.iter().enumerate().take(n) {
        let a = 1.0 - (-s.max(0.0) * delta(t, i)).exp();
        trans.push(tr);
        alpha.push(a);
        tr *= 1.0 - a;
    }
    let dot = |c: [f32; 3]| c[0] * d_colour[0] + c[1] * d_colour[1] + c[2] * d_colour[2];
    // Behind the last sample: the background through what is left.
    let mut behind = tr * dot(background);
    let mut d_sigma = vec![0.0f32; n];
    let mut d_rgb = vec![[0.0f32; 3]; n];
    for i in (0..n).rev() {
        let delta = delta(t, i);
        let w = trans[i] * alpha[i];
        d_rgb[i] = d_colour.map(|d| d * w);
        if sigma_raw[i] > 0.0 {
            d_sigma[i] = delta * (trans[i] * (1.0 - alpha[i]) * dot(rgb[i]) - behind);
        }
        behind += w * dot(rgb[i]);
    }
    (d_sigma, d_rgb)
}

/// `n` fine distances drawn from the piecewise-constant PDF the coarse weights give over the
/// bins between the coarse samples' midpoints (Mildenhall's `sample_pdf`): inverse transform
/// of `u` ∈ [0, 1), given ascending (evaluation: `(i + 0.5) / n`; training: sorted uniform).
pub fn sample_pdf(coarse_t: &[f32], coarse_w: &[f32], u: &[f32]) -> Vec<f32> {
    let n = coarse_t.len();
    if n < 3 {
        return u
            .iter()
            .map(|_| coarse_t.first().copied().unwrap_or(0.0))
            .collect();
    }
    let bins: Vec<f32> = (0..n - 1)
        .map(|i| 0.5 * (coarse_t[i] + coarse_t[i + 1]))
        .collect();
    let w: Vec<f32> = coarse_w[1..n - 1].iter().map(|w| w + PDF_EPS).collect();
    let total: f32 = w.iter().sum();
    let mut cdf = Vec::with_capacity(w.len() + 1);
    cdf.push(0.0f32);
    let mut acc = 0.0f32;
    for x in &w {
        acc += x / total;
        cdf.push(acc.min(1.0));
    }
    u.iter()
        .map(|&u| {
            // First cdf entry above u; the sample lies in the bin before it.
            let above = cdf.partition_point(|&c| c <= u).min(cdf.len() - 1);
            let below = above.saturating_sub(1);
            let denom = cdf[above] - cdf[below];
            let f = if denom < PDF_EPS {
                0.0
            } else {
                (u - cdf[below]) / denom
            };
            bins[below] + f * (bins[above] - bins[below])
        })
        .collect()
}

/// Two ascending lists merged in ascending order, an element of `a` before an equal one of `b`
/// (the fine network's distances: the coarse ones and the fine draws, as `sample_fine.wgsl`).
pub fn merge_sorted(a: &[f32], b: &[f32]) -> Vec<f32> {
    let mut out = Vec::with_capacity(a.len() + b.len());
    let mut i = 0;
    for &s in b {
        while i < a.len() && a[i] <= s {
            out.push(a[i]);
            i += 1;
        }
        out.push(s);
    }
    out.extend_from_slice(&a[i..]);
    out
}
