//! Photometric loss `L = (1 − λ) L1 + λ (1 − SSIM)` (docs/splatting.md "Loss"; Kerbl et al. 2023),
//! its gradient with respect to the rendered image, and the PSNR / SSIM metrics.
//!
//! Images are row-major `[r, g, b]` per pixel, values nominally in [0, 1].

/// Weight λ of the D-SSIM term (Kerbl et al. 2023).
pub const SSIM_LAMBDA: f64 = 0.2;
/// SSIM window edge, pixels (Wang et al. 2004, as the reference `ssim()`).
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM Gaussian window, pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM stabiliser C1 = (0.01 · L)², L = 1 the dynamic range.
pub const SSIM_C1: f64 = 0.01 * 0.01;
/// SSIM stabiliser C2 = (0.03 · L)².
pub const SSIM_C2: f64 = 0.03 * 0.03;

/// Value of the loss and of its parts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LossValue {
    /// `(1 − λ) · l1 + λ · (1 − ssim)`.
    pub loss: f64,
    /// Mean absolute error over pixels and channels.
    pub l1: f64,
    /// Mean SSIM over pixels and channels.
    pub ssim: f64,
}

/// The normalised 1-D Gaussian window (the 2-D window is its outer product, summing to 1).
pub fn ssim_window() -> [f64; SSIM_WINDOW] {
    let half = (SSIM_WINDOW / 2) as f64;
    let mut w = [0.0; SSIM_WINDOW];
    for (k, v) in w.iter_mut().enumerate() {
        let x = k as f64 - half;
        *v = (-x * x / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let s: f64 = w.iter().sum();
    w.map(|v| v / s)
}

/// "Same" 2-D convolution of one channel plane with the separable window, zero padding.
/// The window is symmetric, so this operator is also its own adjoint.
pub(crate) fn blur(plane: &[f64], width: usize, height: usize) -> Vec<f64> {
    let rows = blur_1d(plane, width, height, false);
    blur_1d(&rows, width, height, true)
}

/// One 1-D pass of the window along every row (or, if `vertical`, every column), zero padding.
fn blur_1d(src: &[f64], width: usize, height: usize, vertical: bool) -> Vec<f64> {
    let w = ssim_window();
    let half = (SSIM_WINDOW / 2) as isize;
    let (len, stride) = if vertical {
        (height, width as isize)
    } else {
        (width, 1)
    };
    let mut out = vec![0.0; src.len()];
    for y in 0..height {
        for x in 0..width {
            let along = if vertical { y } else { x } as isize;
            let i = (y * width + x) as isize;
            let mut s = 0.0;
            for (k, wk) in w.iter().enumerate() {
                let d = k as isize - half;
                if (0..len as isize).contains(&(along + d)) {
                    s += wk * src[(i + d * stride) as usize];
                }
            }
            out[y * width + x] = s;
        }
    }
    out
}

fn plane(img: &[[f64; 3]], c: usize) -> Vec<f64> {
    img.iter().map(|p| p[c]).collect()
}

/// Per channel: the SSIM map sum, and if `grad` the dL/dx contribution of `scale · Σ SSIM`.
fn ssim_channel(
    x: &[f64],
    y: &[f64],
    width: usize,
    height: usize,
    grad: Option<(f64, &mut [f64])>,
) -> f64 {
    let sq = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| p * q).collect::<Vec<_>>();
    let mu_x = blur(x, width, height);
    let mu_y = blur(y, width, height);
    let e_xx = blur(&sq(x, x), width, height);
    let e_yy = blur(&sq(y, y), width, height);
    let e_xy = blur(&sq(x, y), width, height);
    let n = x.len();
    let mut total = 0.0;
    let (mut d_mu, mut d_xx, mut d_xy) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    for i in 0..n {
        let (mx, my) = (mu_x[i], mu_y[i]);
        let a1 = 2.0 * mx * my + SSIM_C1;
        let a2 = 2.0 * (e_xy[i] - mx * my) + SSIM_C2;
        let b1 = mx * mx + my * my + SSIM_C1;
        let b2 = (e_xx[i] - mx * mx) + (e_yy[i] - my * my) + SSIM_C2;
        let s = a1 * a2 / (b1 * b2);
        total += s;
        // ∂S/∂μx, ∂S/∂E[x²], ∂S/∂E[xy] with the blurred maps as independent variables.
        d_mu[i] = 2.0 * my * (a2 - a1) / (b1 * b2) - s * (2.0 * mx / b1 - 2.0 * mx / b2);
        d_xx[i] = -s / b2;
        d_xy[i] = 2.0 * a1 / (b1 * b2);
    }
    if let Some((scale, out)) = grad {
        let g_mu = blur(&d_mu, width, height);
        let g_xx = blur(&d_xx, width, height);
        let g_xy = blur(&d_xy, width, height);
        for i in 0..n {
            out[i] += scale * (g_mu[i] + 2.0 * x[i] * g_xx[i] + y[i] * g_xy[i]);
        }
    }
    total
}

/// Loss of `rendered` against `target` (both `width·height` pixels) and, if `want_grad`,
/// dL/drendered (zero-length otherwise). At |C − G| = 0 the L1 subgradient is 0.
pub(crate) fn loss_f64(
    rendered: &[[f64; 3]],
    target: &[[f64; 3]],
    width: usize,
    height: usize,
    want_grad: bool,
) -> (LossValue, Vec<[f64; 3]>) {
    let n = rendered.len();
    let count = (n * 3) as f64;
    let mut l1 = 0.0;
    let mut grad = if want_grad {
        vec![[0.0; 3]; n]
    } else {
        Vec::new()
    };
    for (i, (r, t)) in rendered.iter().zip(target).enumerate() {
        for c in 0..3 {
            let d = r[c] - t[c];
            l1 += d.abs();
            if want_grad {
                let sign = if d > 0.0 {
                    1.0
                } else if d < 0.0 {
                    -1.0
                } else {
                    0.0
                };
                grad[i][c] = (1.0 - SSIM_LAMBDA) * sign / count;
            }
        }
    }
    let mut ssim_sum = 0.0;
    for c in 0..3 {
        let (x, y) = (plane(rendered, c), plane(target, c));
        let mut g = if want_grad { vec![0.0; n] } else { Vec::new() };
        let arg = want_grad.then_some((-SSIM_LAMBDA / count, g.as_mut_slice()));
        ssim_sum += ssim_channel(&x, &y, width, height, arg);
        for (gi, v) in grad.iter_mut().zip(&g) {
            gi[c] += v;
        }
    }
    let (l1, ssim) = (l1 / count, ssim_sum / count);
    let value = LossValue {
        loss: (1.0 - SSIM_LAMBDA) * l1 + SSIM_LAMBDA * (1.0 - ssim),
        l1,
        ssim,
    };
    (value, grad)
}

/// Mean SSIM over pixels and channels (same window as the loss), f64 images.
pub(crate) fn ssim_f64(a: &[[f64; 3]], b: &[[f64; 3]], width: usize, height: usize) -> f64 {
    (0..3)
        .map(|c| ssim_channel(&plane(a, c), &plane(b, c), width, height, None))
        .sum::<f64>()
        / (a.len() * 3) as f64
}
