//! Per-Gaussian projection (docs/splatting.md "Forward", steps 1–8) and its backward.
//!
//! Everything is f64; inputs are the f32 model and camera of `splat_core`.

use crate::splat::camera::{Camera, RenderOptions};
use crate::splat::cpu::ParamGrad;
use crate::splat::cpu::linalg::{
    Mat3, Mat23, dot, mul_t_vec, mul_vec, mul23_33, mul33, normalise_vjp, normalise4, quat_to_mat,
    quat_to_mat_vjp, transpose,
};
use crate::splat::cpu::sh::{eval_sh, eval_sh_backward};
use crate::splat::model::Gaussians;

/// Near plane, metres: Gaussians with camera-space `z < NEAR` are culled.
pub const NEAR: f64 = 0.01;
/// Low-pass (anti-aliasing) variance added to the 2-D covariance, pixels² (Kerbl et al. 2023).
/// With [`RenderOptions::antialias`] it is also the variance `s` of Mip-Splatting's 2-D filter,
/// whose opacity compensation is [`compensation`]: gsplat's `eps2d = 0.3` of
/// `rasterize_mode="antialiased"`, the filter used without Mip-Splatting's 3-D filter (the
/// paper's 0.1 px² goes with its 3-D filter, which Sylva does not have).
pub const LOW_PASS: f64 = 0.3;
/// Factor of the half field of view beyond which the Jacobian clamps `t.x / t.z` (reference: 1.3).
pub const JACOBIAN_CLAMP: f64 = 1.3;

/// One Gaussian as the rasteriser sees it. All-zero with `visible == false` when culled.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Projected {
    /// Projected centre, pixels (x right, y down; pixel (i, j) has its centre at (i+0.5, j+0.5)).
    pub mean2d: [f64; 2],
    /// Inverse 2-D covariance `[[a, b], [b, c]]` stored as `(a, b, c)`, 1/pixels².
    pub conic: [f64; 3],
    /// Camera-space depth `t.z`, metres (sort key).
    pub depth: f64,
    /// Screen radius `ceil(3 √λ_max)`, pixels.
    pub radius: u32,
    /// Colour after SH, +0.5 and clamp at 0 (unitless, usually in [0, 1]).
    pub rgb: [f64; 3],
    /// Opacity the rasteriser blends with: `sigmoid(logit)`, times the compensation `ρ` of
    /// [`compensation`] with [`RenderOptions::antialias`]; in [0, 1).
    pub opacity: f64,
    /// False when culled (behind the near plane, degenerate covariance or off-screen).
    pub visible: bool,
}

/// Gradient of the loss with respect to one [`Projected`] (what the raster backward produces).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ProjectedGrad {
    /// dL/dmean2d, per pixel.
    pub mean2d: [f64; 2],
    /// dL/d(a, b, c) of the conic, pixels².
    pub conic: [f64; 3],
    /// dL/drgb.
    pub rgb: [f64; 3],
    /// dL/dopacity (the blended opacity [`Projected::opacity`], not the logit).
    pub opacity: f64,
    /// dL/d(camera-space depth t.z), 1/m: from a loss on the rendered depth.
    pub depth: f64,
}

/// Forward intermediates shared by [`project`] and [`project_backward`].
struct Fwd {
    w: Mat3,
    t: [f64; 3],
    txc: f64,
    tyc: f64,
    clamped: [bool; 2],
    q: [f64; 4],
    q_len: f64,
    rq: Mat3,
    scale: [f64; 3],
    sigma: Mat3,
    tmat: Mat23,
    conic: [f64; 3],
    dir: [f64; 3],
    dir_len: f64,
    raw_rgb: [f64; 3],
    /// `sigmoid(logit)`, before the compensation.
    opacity: f64,
    /// The compensation `ρ` (1 without [`RenderOptions::antialias`]).
    rho: f64,
    antialias: bool,
    out: Projected,
}

fn f64x3(v: [f32; 3]) -> [f64; 3] {
    v.map(f64::from)
}

/// Mip-Splatting's opacity compensation `ρ = sqrt(max(0, det Σ / det(Σ + s·I)))` of the 2-D
/// covariance `Σ = [[c00, c01], [c01, c11]]` (pixels², before the low-pass) given
/// `det_blurred = det(Σ + s·I)` with `s` = [`LOW_PASS`]: the factor that keeps the integral of
/// the blurred Gaussian `o ρ exp(−½ dᵀ(Σ + s·I)⁻¹d)` equal to that of the unblurred one
/// (Yu et al. 2024, the 2-D Mip filter; gsplat `rasterize_mode="antialiased"`). Unitless, in
/// [0, 1).
pub fn compensation(c00: f64, c01: f64, c11: f64, det_blurred: f64) -> f64 {
    ((c00 * c11 - c01 * c01) / det_blurred).max(0.0).sqrt()
}

/// dρ/dΣ2D of [`compensation`], entry-wise over the symmetric blurred covariance (each of the
/// two off-diagonal entries gets `[0][1]`), from the blurred conic `Q = (a, b, c)`:
/// `(1 / 2ρ) ((1 − ρ²) Q − s det(Q) I)` (docs/splatting.md "Backward"). Zero where `ρ = 0`
/// (the clamp). The shift by `s · I` is constant, so this is also dρ/dΣ.
pub fn compensation_grad(rho: f64, conic: [f64; 3]) -> [[f64; 2]; 2] {
    if rho <= 0.0 {
        return [[0.0; 2]; 2];
    }
    let [a, b, c] = conic;
    let det_q = a * c - b * b;
    let k = 0.5 / rho;
    let one = 1.0 - rho * rho;
    [
        [k * (one * a - LOW_PASS * det_q), k * one * b],
        [k * one * b, k * (one * c - LOW_PASS * det_q)],
    ]
}

fn forward(model: &Gaussians, i: usize, cam: &Camera, opts: RenderOptions) -> Option<Fwd> {
    let (fx, fy) = (f64::from(cam.fx), f64::from(cam.fy));
    let (width, height) = (f64::from(cam.width), f64::from(cam.height));
    let w: Mat3 = cam.r.map(f64x3);
    let mu = f64x3(model.means[i]);
    let tc = mul_vec(&w, mu);
    let t = [0, 1, 2].map(|k| tc[k] + f64::from(cam.t[k]));
    if t[2] < NEAR {
        return None;
    }
    let lim_x = JACOBIAN_CLAMP * (width / 2.0) / fx;
    let lim_y = JACOBIAN_CLAMP * (height / 2.0) / fy;
    let (rx, ry) = (t[0] / t[2], t[1] / t[2]);
    let clamped = [rx.abs() > lim_x, ry.abs() > lim_y];
    let txc = rx.clamp(-lim_x, lim_x) * t[2];
    let tyc = ry.clamp(-lim_y, lim_y) * t[2];
    let tz2 = t[2] * t[2];
    let j: Mat23 = [
        [fx / t[2], 0.0, -fx * txc / tz2],
        [0.0, fy / t[2], -fy * tyc / tz2],
    ];
    let (q, q_len) = normalise4(model.rotations[i].map(f64::from));
    let rq = quat_to_mat(q);
    let scale = f64x3(model.log_scales[i]).map(f64::exp);
    let m = [0, 1, 2].map(|r| [0, 1, 2].map(|c| rq[r][c] * scale[c]));
    let sigma = mul33(&m, &transpose(&m));
    let tmat = mul23_33(&j, &w);
    // Σ2D = T Σ Tᵀ + LOW_PASS · I
    let ts = mul23_33(&tmat, &sigma);
    let cov = |r: usize, c: usize| (0..3).map(|k| ts[r][k] * tmat[c][k]).sum::<f64>();
    let (c00, c01, c11) = (cov(0, 0), cov(0, 1), cov(1, 1));
    let (s00, s01, s11) = (c00 + LOW_PASS, c01, c11 + LOW_PASS);
    let det = s00 * s11 - s01 * s01;
    if det <= 0.0 || !det.is_finite() {
        return None;
    }
    let rho = if opts.antialias {
        compensation(c00, c01, c11, det)
    } else {
        1.0
    };
    let conic = [s11 / det, -s01 / det, s00 / det];
    let mid = 0.5 * (s00 + s11);
    let lambda_max = mid + (mid * mid - det).max(0.1).sqrt();
    let radius = (3.0 * lambda_max.sqrt()).ceil();
    let mean2d = [
        fx * t[0] / t[2] + f64::from(cam.cx),
        fy * t[1] / t[2] + f64::from(cam.cy),
    ];
    let r = radius;
    if mean2d[0] + r < 0.0
        || mean2d[0] - r >= width
        || mean2d[1] + r < 0.0
        || mean2d[1] - r >= height
    {
        return None;
    }
    let centre = f64x3(cam.centre());
    let v = [0, 1, 2].map(|k| mu[k] - centre[k]);
    let dir_len = dot(v, v).sqrt();
    let dir = if dir_len > 0.0 {
        v.map(|a| a / dir_len)
    } else {
        [0.0, 0.0, 1.0]
    };
    let raw_rgb = eval_sh(model.sh_degree, &model.sh[i], dir);
    let opacity = 1.0 / (1.0 + (-f64::from(model.opacity_logits[i])).exp());
    let out = Projected {
        mean2d,
        conic,
        depth: t[2],
        radius: radius as u32,
        rgb: raw_rgb.map(|c| (c + 0.5).max(0.0)),
        opacity: opacity * rho,
        visible: true,
    };
    Some(Fwd {
        w,
        t,
        txc,
        tyc,
        clamped,
        q,
        q_len,
        rq,
        scale,
        sigma,
        tmat,
        conic,
        dir,
        dir_len,
        raw_rgb,
        opacity,
        rho,
        antialias: opts.antialias,
        out,
    })
}

/// Projects Gaussian `i` of `model` into `cam` with `opts`. Culled Gaussians return
/// `Projected::default()` (`visible == false`). Panics if `i` is out of range for any parameter
/// vector.
pub fn project(model: &Gaussians, i: usize, cam: &Camera, opts: RenderOptions) -> Projected {
    forward(model, i, cam, opts)
        .map(|f| f.out)
        .unwrap_or_default()
}

/// Projects every Gaussian of a consistent model.
pub fn project_all(model: &Gaussians, cam: &Camera, opts: RenderOptions) -> Vec<Projected> {
    (0..model.len())
        .map(|i| project(model, i, cam, opts))
        .collect()
}

/// Backward of [`project`] for Gaussian `i`: turns dL/d(mean2d, conic, rgb, opacity) into
/// dL/d(parameters). Culled Gaussians get zero. Where the Jacobian clamp is active the clamped
/// `t.x` (or `t.y`) inside J is treated as a constant (docs/splatting.md step 3, as the reference).
/// With [`RenderOptions::antialias`] the blended opacity is `sigmoid(logit) · ρ(Σ2D)`, and the
/// gradient of `ρ` flows into the 2-D covariance ([`compensation_grad`]).
pub fn project_backward(
    model: &Gaussians,
    i: usize,
    cam: &Camera,
    opts: RenderOptions,
    g: &ProjectedGrad,
) -> ParamGrad {
    let Some(f) = forward(model, i, cam, opts) else {
        return ParamGrad::default();
    };
    let mut out = ParamGrad {
        opacity_logit: g.opacity * f.rho * f.opacity * (1.0 - f.opacity),
        ..ParamGrad::default()
    };
    // Colour: rgb = max(raw + 0.5, 0). The gradient passes at the clamp itself, as PyTorch's
    // `clamp_min` backward in the reference and the f32 GPU twin, where a black-seeded colour
    // lands exactly on it (this f64 path does not).
    let d_raw = [0, 1, 2].map(|c| {
        if f.raw_rgb[c] + 0.5 >= 0.0 {
            g.rgb[c]
        } else {
            0.0
        }
    });
    let (dsh, ddir) = eval_sh_backward(model.sh_degree, &model.sh[i], f.dir, d_raw);
    out.sh = dsh;
    let mut dmu = normalise_vjp(f.dir, f.dir_len, ddir);
    // Conic Q = Σ2D⁻¹: dL/dΣ2D = −Q G Q, G the symmetric dL/dQ.
    let [a, b, c] = f.conic;
    let q2 = [[a, b], [b, c]];
    let g2 = [
        [g.conic[0], 0.5 * g.conic[1]],
        [0.5 * g.conic[1], g.conic[2]],
    ];
    let mut qg = [[0.0; 2]; 2];
    let mut dcov = [[0.0; 2]; 2];
    for r in 0..2 {
        for s in 0..2 {
            qg[r][s] = q2[r][0] * g2[0][s] + q2[r][1] * g2[1][s];
        }
    }
    for r in 0..2 {
        for s in 0..2 {
            dcov[r][s] = -(qg[r][0] * q2[0][s] + qg[r][1] * q2[1][s]);
        }
    }
    // Blended opacity o · ρ(Σ2D): dL/dρ = dL/d(o ρ) · o.
    if f.antialias {
        let drho = compensation_grad(f.rho, f.conic);
        let g_rho = g.opacity * f.opacity;
        for r in 0..2 {
            for s in 0..2 {
                dcov[r][s] += g_rho * drho[r][s];
            }
        }
    }
    // Σ2D = T Σ Tᵀ: dT = 2 dΣ2D T Σ, dΣ = Tᵀ dΣ2D T.
    let ts = mul23_33(&f.tmat, &f.sigma);
    let mut dt_mat: Mat23 = [[0.0; 3]; 2];
    for r in 0..2 {
        for k in 0..3 {
            dt_mat[r][k] = 2.0 * (dcov[r][0] * ts[0][k] + dcov[r][1] * ts[1][k]);
        }
    }
    let mut dsigma: Mat3 = [[0.0; 3]; 3];
    for (r, row) in dsigma.iter_mut().enumerate() {
        for (s, v) in row.iter_mut().enumerate() {
            *v = (0..2)
                .map(|p| {
                    (0..2)
                        .map(|q| f.tmat[p][r] * dcov[p][q] * f.tmat[q][s])
                        .sum::<f64>()
                })
                .sum();
        }
    }
    // T = J W: dJ = dT Wᵀ.
    let dj = mul23_33(&dt_mat, &transpose(&f.w));
    let (fx, fy) = (f64::from(cam.fx), f64::from(cam.fy));
    let [tx, ty, tz] = f.t;
    let (tz2, tz3) = (tz * tz, tz * tz * tz);
    let mut dt = [0.0; 3];
    dt[2] += -fx / tz2 * dj[0][0] - fy / tz2 * dj[1][1]
        + 2.0 * fx * f.txc / tz3 * dj[0][2]
        + 2.0 * fy * f.tyc / tz3 * dj[1][2];
    if !f.clamped[0] {
        dt[0] += -fx / tz2 * dj[0][2];
    }
    if !f.clamped[1] {
        dt[1] += -fy / tz2 * dj[1][2];
    }
    // The depth channel: z = t.z.
    dt[2] += g.depth;
    // Mean in pixels (unclamped).
    dt[0] += fx / tz * g.mean2d[0];
    dt[1] += fy / tz * g.mean2d[1];
    dt[2] += -fx * tx / tz2 * g.mean2d[0] - fy * ty / tz2 * g.mean2d[1];
    let dmu_t = mul_t_vec(&f.w, dt);
    for k in 0..3 {
        dmu[k] += dmu_t[k];
    }
    out.mean = dmu;
    // Σ = M Mᵀ, M = Rq S: dM = 2 dΣ M; dRq = dM S; dscale_j = Σ_i Rq_ij dM_ij.
    let m = [0, 1, 2].map(|r| [0, 1, 2].map(|c| f.rq[r][c] * f.scale[c]));
    let dm = mul33(&dsigma, &m).map(|row| row.map(|v| 2.0 * v));
    let drq = [0, 1, 2].map(|r| [0, 1, 2].map(|c| dm[r][c] * f.scale[c]));
    for (j, v) in out.log_scale.iter_mut().enumerate() {
        let ds: f64 = (0..3).map(|r| f.rq[r][j] * dm[r][j]).sum();
        *v = ds * f.scale[j];
    }
    let dq = quat_to_mat_vjp(f.q, &drq);
    out.rotation = normalise_vjp(f.q, f.q_len, dq);
    out
}
