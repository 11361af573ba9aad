//! Real spherical harmonics up to degree 3: evaluation of the colour of a Gaussian seen along a
//! direction and its backward (docs/splatting.md "Forward", step 8; constants and band order as in
//! Kerbl et al. 2023).

use crate::splat::model::{SH_COEFFS, SH_FLOATS, sh_coeffs_for_degree};

/// Y0 = 1 / (2 √π).
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// Degree-1 constant √3 / (2 √π).
pub const SH_C1: f64 = 0.488_602_511_902_919_9;
/// Degree-2 constants.
pub const SH_C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
/// Degree-3 constants.
pub const SH_C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// The 16 basis values Y_k(d) for a direction `d = (x, y, z)` (unit length expected; the
/// polynomials are evaluated as written, without renormalising). Bands above `degree` are 0.
pub fn sh_basis(degree: u32, d: [f64; 3]) -> [f64; SH_COEFFS] {
    let [x, y, z] = d;
    let mut b = [0.0; SH_COEFFS];
    b[0] = SH_C0;
    if degree >= 1 {
        b[1] = -SH_C1 * y;
        b[2] = SH_C1 * z;
        b[3] = -SH_C1 * x;
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        b[4] = SH_C2[0] * x * y;
        b[5] = SH_C2[1] * y * z;
        b[6] = SH_C2[2] * (2.0 * zz - xx - yy);
        b[7] = SH_C2[3] * x * z;
        b[8] = SH_C2[4] * (xx - yy);
        if degree >= 3 {
            b[9] = SH_C3[0] * y * (3.0 * xx - yy);
            b[10] = SH_C3[1] * x * y * z;
            b[11] = SH_C3[2] * y * (4.0 * zz - xx - yy);
            b[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            b[13] = SH_C3[4] * x * (4.0 * zz - xx - yy);
            b[14] = SH_C3[5] * z * (xx - yy);
            b[15] = SH_C3[6] * x * (xx - 3.0 * yy);
        }
    }
    b
}

/// Gradients `∂Y_k/∂(x, y, z)` of the basis polynomials of [`sh_basis`].
pub fn sh_basis_grad(degree: u32, d: [f64; 3]) -> [[f64; 3]; SH_COEFFS] {
    let [x, y, z] = d;
    let mut g = [[0.0; 3]; SH_COEFFS];
    if degree >= 1 {
        g[1] = [0.0, -SH_C1, 0.0];
        g[2] = [0.0, 0.0, SH_C1];
        g[3] = [-SH_C1, 0.0, 0.0];
    }
    if degree >= 2 {
        let c = SH_C2;
        g[4] = [c[0] * y, c[0] * x, 0.0];
        g[5] = [0.0, c[1] * z, c[1] * y];
        g[6] = [-2.0 * c[2] * x, -2.0 * c[2] * y, 4.0 * c[2] * z];
        g[7] = [c[3] * z, 0.0, c[3] * x];
        g[8] = [2.0 * c[4] * x, -2.0 * c[4] * y, 0.0];
    }
    if degree >= 3 {
        let c = SH_C3;
        let (xx, yy, zz) = (x * x, y * y, z * z);
        g[9] = [6.0 * c[0] * x * y, c[0] * (3.0 * xx - 3.0 * yy), 0.0];
        g[10] = [c[1] * y * z, c[1] * x * z, c[1] * x * y];
        g[11] = [
            -2.0 * c[2] * x * y,
            c[2] * (4.0 * zz - xx - 3.0 * yy),
            8.0 * c[2] * y * z,
        ];
        g[12] = [
            -6.0 * c[3] * x * z,
            -6.0 * c[3] * y * z,
            c[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy),
        ];
        g[13] = [
            c[4] * (4.0 * zz - 3.0 * xx - yy),
            -2.0 * c[4] * x * y,
            8.0 * c[4] * x * z,
        ];
        g[14] = [2.0 * c[5] * x * z, -2.0 * c[5] * y * z, c[5] * (xx - yy)];
        g[15] = [c[6] * (3.0 * xx - 3.0 * yy), -6.0 * c[6] * x * y, 0.0];
    }
    g
}

/// Raw SH colour `Σ_k sh[k·3 + c] Y_k(d)` per channel, before the +0.5 offset and the clamp.
/// Only the first `sh_coeffs_for_degree(degree)` coefficients are used.
pub fn eval_sh(degree: u32, sh: &[f32; SH_FLOATS], d: [f64; 3]) -> [f64; 3] {
    let basis = sh_basis(degree, d);
    let mut rgb = [0.0; 3];
    for (k, y) in basis.iter().enumerate().take(sh_coeffs_for_degree(degree)) {
        for (c, v) in rgb.iter_mut().enumerate() {
            *v += f64::from(sh[k * 3 + c]) * y;
        }
    }
    rgb
}

/// Backward of [`eval_sh`]: given `dL/d(raw rgb)`, returns `(dL/dsh, dL/dd)`; coefficients
/// above the active degree get zero gradient. `dL/dd` is with respect to the unnormalised
/// polynomial arguments; chain through the normalisation of the view direction separately.
pub fn eval_sh_backward(
    degree: u32,
    sh: &[f32; SH_FLOATS],
    d: [f64; 3],
    dl_drgb: [f64; 3],
) -> ([f64; SH_FLOATS], [f64; 3]) {
    let basis = sh_basis(degree, d);
    let grad = sh_basis_grad(degree, d);
    let mut dsh = [0.0; SH_FLOATS];
    let mut dd = [0.0; 3];
    for k in 0..sh_coeffs_for_degree(degree) {
        let mut w = 0.0;
        for c in 0..3 {
            dsh[k * 3 + c] = basis[k] * dl_drgb[c];
            w += f64::from(sh[k * 3 + c]) * dl_drgb[c];
        }
        for a in 0..3 {
            dd[a] += w * grad[k][a];
        }
    }
    (dsh, dd)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::ChaCha8Rng;
    use rand::{RngExt, SeedableRng};

    fn random_sh(rng: &mut ChaCha8Rng) -> [f32; SH_FLOATS] {
        let mut sh = [0.0f32; SH_FLOATS];
        for v in sh.iter_mut() {
            *v = rng.random_range(-1.0..1.0);
        }
        sh
    }

    #[test]
    fn dc_only_colour_is_c0_times_coefficient() {
        let mut sh = [0.0f32; SH_FLOATS];
        sh[0] = 1.0;
        sh[1] = -2.0;
        sh[5] = 9.0; // degree-1 coefficient, ignored at degree 0
        let rgb = eval_sh(0, &sh, [0.0, 0.6, 0.8]);
        assert!((rgb[0] - SH_C0).abs() < 1e-12 && (rgb[1] + 2.0 * SH_C0).abs() < 1e-12);
        assert_eq!(rgb[2], 0.0);
    }

    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        // Monte-Carlo-free check: quadrature on a Fibonacci sphere, 20k points.
        let n = 20_000;
        let mut gram = [[0.0f64; 16]; 16];
        for i in 0..n {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
            let b = sh_basis(3, [r * phi.cos(), r * phi.sin(), z]);
            for a in 0..16 {
                for c in 0..16 {
                    gram[a][c] += b[a] * b[c] * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for (a, row) in gram.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                let e = if a == c { 1.0 } else { 0.0 };
                assert!((v - e).abs() < 2e-3, "gram[{a}][{c}] = {v}");
            }
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for degree in 0..=3 {
            let sh = random_sh(&mut rng);
            let d = [0.3, -0.5, 0.81];
            let w = [0.7, -1.3, 0.4];
            let f = |sh: &[f32; SH_FLOATS], d: [f64; 3]| {
                let c = eval_sh(degree, sh, d);
                c[0] * w[0] + c[1] * w[1] + c[2] * w[2]
            };
            let (dsh, dd) = eval_sh_backward(degree, &sh, d, w);
            for a in 0..3 {
                let (mut dp, mut dm) = (d, d);
                dp[a] += 1e-6;
                dm[a] -= 1e-6;
                let fd = (f(&sh, dp) - f(&sh, dm)) / 2e-6;
                assert!(
                    (fd - dd[a]).abs() < 1e-6 * (1.0 + fd.abs()),
                    "deg {degree} d{a}: {fd} vs {}",
                    dd[a]
                );
            }
            for k in 0..SH_FLOATS {
                let (mut sp, mut sm) = (sh, sh);
                sp[k] += 0.25;
                sm[k] -= 0.25;
                let fd = (f(&sp, d) - f(&sm, d)) / 0.5; // linear in sh: exact
                assert!(
                    (fd - dsh[k]).abs() < 1e-6,
                    "deg {degree} sh{k}: {fd} vs {}",
                    dsh[k]
                );
            }
        }
    }
}
