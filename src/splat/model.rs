//! The Gaussian model: structure of arrays, one vector per parameter (see docs/splatting.md).

/// Number of SH coefficients per colour channel at degree 3.
pub const SH_COEFFS: usize = 16;
/// Floats of SH per Gaussian: 16 coefficients × RGB, coefficient-major (`sh[k * 3 + c]`).
pub const SH_FLOATS: usize = SH_COEFFS * 3;
/// Highest SH degree supported.
pub const MAX_SH_DEGREE: u32 = 3;
/// The DC basis constant Y0 = 1 / (2 sqrt(pi)).
pub const SH_C0: f32 = 0.282_094_8;

/// Number of SH coefficients used at `degree` (1, 4, 9, 16).
pub fn sh_coeffs_for_degree(degree: u32) -> usize {
    let d = degree.min(MAX_SH_DEGREE) as usize + 1;
    d * d
}

/// A set of 3-D Gaussians.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Gaussians {
    /// Centres, world metres.
    pub means: Vec<[f32; 3]>,
    /// Log of the axis standard deviations (metres).
    pub log_scales: Vec<[f32; 3]>,
    /// Rotation quaternions (w, x, y, z); normalised before use.
    pub rotations: Vec<[f32; 4]>,
    /// Opacity logits; opacity = sigmoid(logit).
    pub opacity_logits: Vec<f32>,
    /// SH coefficients, coefficient-major: `sh[i][k * 3 + c]`.
    pub sh: Vec<[f32; SH_FLOATS]>,
    /// Trunk probability P_i (docs/method.md Stage 4); not trained, inherited by children.
    pub trunk_prob: Vec<f32>,
    /// Active SH degree (0..=3).
    pub sh_degree: u32,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }
    /// The box of the centres (metres): per axis the least and the greatest; `None` when empty.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let first = *self.means.first()?;
        Some(self.means.iter().fold((first, first), |(lo, hi), m| {
            (
                std::array::from_fn(|k| lo[k].min(m[k])),
                std::array::from_fn(|k| hi[k].max(m[k])),
            )
        }))
    }

    /// True when every per-Gaussian vector has the same length.
    pub fn is_consistent(&self) -> bool {
        let n = self.means.len();
        self.log_scales.len() == n
            && self.rotations.len() == n
            && self.opacity_logits.len() == n
            && self.sh.len() == n
            && self.trunk_prob.len() == n
    }
    /// Appends one Gaussian.
    pub fn push(&mut self, g: Gaussian) {
        self.means.push(g.mean);
        self.log_scales.push(g.log_scale);
        self.rotations.push(g.rotation);
        self.opacity_logits.push(g.opacity_logit);
        self.sh.push(g.sh);
        self.trunk_prob.push(g.trunk_prob);
    }
    /// A copy of Gaussian `i`.
    pub fn get(&self, i: usize) -> Gaussian {
        Gaussian {
            mean: self.means[i],
            log_scale: self.log_scales[i],
            rotation: self.rotations[i],
            opacity_logit: self.opacity_logits[i],
            sh: self.sh[i],
            trunk_prob: self.trunk_prob[i],
        }
    }
    /// Keeps the Gaussians for which `keep[i]` is true, in order.
    pub fn retain_mask(&mut self, keep: &[bool]) {
        fn filt<T: Copy>(v: &mut Vec<T>, keep: &[bool]) {
            let mut k = keep.iter();
            v.retain(|_| *k.next().unwrap_or(&false));
        }
        filt(&mut self.means, keep);
        filt(&mut self.log_scales, keep);
        filt(&mut self.rotations, keep);
        filt(&mut self.opacity_logits, keep);
        filt(&mut self.sh, keep);
        filt(&mut self.trunk_prob, keep);
    }
}

/// One Gaussian, for building and editing models.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gaussian {
    pub mean: [f32; 3],
    pub log_scale: [f32; 3],
    pub rotation: [f32; 4],
    pub opacity_logit: f32,
    pub sh: [f32; SH_FLOATS],
    pub trunk_prob: f32,
}

impl Gaussian {
    /// An isotropic Gaussian of standard deviation `sigma` (m), colour `rgb` in [0, 1] (DC only),
    /// opacity `opacity` in (0, 1).
    pub fn isotropic(mean: [f32; 3], sigma: f32, rgb: [f32; 3], opacity: f32) -> Self {
        let mut sh = [0.0; SH_FLOATS];
        for c in 0..3 {
            sh[c] = (rgb[c] - 0.5) / SH_C0;
        }
        let o = opacity.clamp(1e-6, 1.0 - 1e-6);
        Gaussian {
            mean,
            log_scale: [sigma.ln(); 3],
            rotation: [1.0, 0.0, 0.0, 0.0],
            opacity_logit: (o / (1.0 - o)).ln(),
            sh,
            trunk_prob: 0.0,
        }
    }
}

/// Gradients of a loss with respect to every trained parameter (same layout as [`Gaussians`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GaussianGrads {
    pub means: Vec<[f32; 3]>,
    pub log_scales: Vec<[f32; 3]>,
    pub rotations: Vec<[f32; 4]>,
    pub opacity_logits: Vec<f32>,
    pub sh: Vec<[f32; SH_FLOATS]>,
}

impl GaussianGrads {
    /// Zero gradients for `n` Gaussians.
    pub fn zeros(n: usize) -> Self {
        GaussianGrads {
            means: vec![[0.0; 3]; n],
            log_scales: vec![[0.0; 3]; n],
            rotations: vec![[0.0; 4]; n],
            opacity_logits: vec![0.0; n],
            sh: vec![[0.0; SH_FLOATS]; n],
        }
    }
}

/// sigmoid(x).
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}
