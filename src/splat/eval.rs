//! Evaluation of renders against held-out images: PSNR, SSIM, a per-view report, side-by-side
//! PNGs, and the training-loss log as CSV.
//!
//! SSIM is the loss's (docs/splatting.md "Loss"): 11×11 Gaussian window, σ = 1.5, normalised to sum 1,
//! C1 = 0.01², C2 = 0.03², zero padding at the border ("same" convolution of the reference
//! `ssim()`), averaged over pixels and the three channels. Images are RGB f32 in [0, 1],
//! row-major.

use std::borrow::Cow;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde::{Deserialize, Serialize};

use crate::splat::lpips::{Lpips, MIN_SIDE};

use crate::splat::packed_image::PackedImage;

/// PSNR reported for identical images, dB (instead of infinity, which JSON cannot hold).
pub const PSNR_IDENTICAL: f32 = 100.0;

/// Why an evaluation could not be made or saved.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("render has {render} pixels but the ground truth {truth}; expected {width}×{height}")]
    SizeMismatch {
        render: usize,
        truth: usize,
        width: u32,
        height: u32,
    },
    #[error("writing {path}: {source}")]
    Image {
        path: String,
        source: image::ImageError,
    },
    #[error("writing the report: {0}")]
    Io(#[from] io::Error),
    #[error("{0}")]
    Lpips(String),
}

/// Where this process's LPIPS weights are, when set by a command's `--lpips-weights`.
static LPIPS_PATH: OnceLock<PathBuf> = OnceLock::new();
/// The weights, loaded on first use.
static LPIPS: OnceLock<Result<Option<Lpips>, String>> = OnceLock::new();

/// Sets the LPIPS weights file for every later evaluation in this process (a command's
/// `--lpips-weights`); without it `SYLVA_LPIPS_WEIGHTS` is read. Later calls are ignored.
pub fn use_lpips_weights(path: PathBuf) {
    let _ = LPIPS_PATH.set(path);
}

/// The LPIPS model of this process: `None` when no weights file is configured
/// ([`use_lpips_weights`], else `SYLVA_LPIPS_WEIGHTS`), the error when the file cannot be used.
pub fn lpips() -> Result<Option<&'static Lpips>, EvalError> {
    let loaded = LPIPS.get_or_init(|| {
        let path = LPIPS_PATH.get().cloned().or_else(|| {
            std::env::var_os("SYLVA_LPIPS_WEIGHTS")
                .filter(|v| !v.is_empty())
                .map(PathBuf::from)
        });
        match path {
            None => Ok(None),
            Some(p) => Lpips::load(&p).map(Some).map_err(|e| e.to_string()),
        }
    });
    match loaded {
        Ok(l) => Ok(l.as_ref()),
        Err(e) => Err(EvalError::Lpips(e.clone())),
    }
}

fn check<T>(a: &[T], b: &[T], width: u32, height: u32) -> Result<(), EvalError> {
    let n = width as usize * height as usize;
    if a.len() != n || b.len() != n {
        return Err(EvalError::SizeMismatch {
            render: a.len(),
            truth: b.len(),
            width,
            height,
        });
    }
    Ok(())
}

/// PSNR in dB for values in [0, 1]: 10 log10(1 / MSE), MSE over pixels and channels;
/// [`PSNR_IDENTICAL`] for identical images.
pub fn psnr(
    render: &[[f32; 3]],
    truth: &[[f32; 3]],
    width: u32,
    height: u32,
) -> Result<f32, EvalError> {
    check(render, truth, width, height)?;
    let se: f64 = render
        .iter()
        .zip(truth)
        .flat_map(|(a, b)| (0..3).map(move |c| ((a[c] - b[c]) as f64).powi(2)))
        .sum();
    let mse = se / (3 * render.len().max(1)) as f64;
    Ok(if mse <= 1e-10 {
        PSNR_IDENTICAL
    } else {
        (-10.0 * mse.log10()) as f32
    })
}

/// Mean SSIM over pixels and channels: the loss's definition, computed by the CPU reference's
/// one implementation ([`crate::splat::cpu::loss`], in f64).
pub fn ssim(
    render: &[[f32; 3]],
    truth: &[[f32; 3]],
    width: u32,
    height: u32,
) -> Result<f32, EvalError> {
    check(render, truth, width, height)?;
    let wide = |img: &[[f32; 3]]| img.iter().map(|p| p.map(f64::from)).collect::<Vec<_>>();
    let s = crate::splat::cpu::loss::ssim_f64(
        &wide(render),
        &wide(truth),
        width as usize,
        height as usize,
    );
    Ok(s as f32)
}

/// Which pixels of the held-out views the metrics measure.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EvalRegion {
    /// The whole image (the reference's default protocol).
    #[default]
    Full,
    /// The right half, columns `x ≥ width / 2`: with exposure compensation the left half of
    /// every held-out view trains its exposure, so only the right half is unseen (the
    /// reference's `train_test_exp` protocol; docs/splatting.md "Exposure").
    RightHalf,
}

impl EvalRegion {
    /// A few words for logs and tables.
    pub fn describe(self) -> &'static str {
        match self {
            EvalRegion::Full => "full images",
            EvalRegion::RightHalf => "right halves, exposure compensated",
        }
    }
}

/// The columns `x ≥ width / 2` of a row-major `width × height` image, and their width.
pub fn right_half<T: Copy>(image: &[T], width: u32, height: u32) -> (Vec<T>, u32) {
    let (w, x0) = (width as usize, (width / 2) as usize);
    let out = (0..height as usize)
        .flat_map(|y| image[y * w + x0..(y + 1) * w].iter().copied())
        .collect();
    (out, width - width / 2)
}

/// Metrics of one held-out view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewMetrics {
    /// Image name (COLMAP).
    pub name: String,
    /// dB.
    pub psnr: f32,
    /// [−1, 1], 1 = identical.
    pub ssim: f32,
    /// LPIPS (AlexNet, v0.1; 0 = identical, lower is better) when weights are configured
    /// ([`lpips`]) and the measured region is at least [`MIN_SIDE`] pixels on each side.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f32>,
}

impl ViewMetrics {
    /// Metrics of a render against its 8-bit ground truth (converted to [0, 1]) over `region`
    /// of the images (SSIM of the right half as an image of its own, as the reference crops
    /// before measuring).
    pub fn measure(
        name: &str,
        render: &[[f32; 3]],
        truth: &PackedImage,
        region: EvalRegion,
    ) -> Result<Self, EvalError> {
        let (w, h) = (truth.width, truth.height);
        let t = truth.to_rgb_f32();
        check(render, &t, w, h)?;
        let (r, t, w) = match region {
            EvalRegion::Full => (Cow::Borrowed(render), t, w),
            EvalRegion::RightHalf => {
                let (r, rw) = right_half(render, w, h);
                (Cow::Owned(r), right_half(&t, w, h).0, rw)
            }
        };
        let lpips = match lpips()? {
            Some(l) if w >= MIN_SIDE && h >= MIN_SIDE => Some(
                l.distance(&r, &t, w, h)
                    .map_err(|e| EvalError::Lpips(e.to_string()))?,
            ),
            _ => None,
        };
        Ok(ViewMetrics {
            name: name.to_string(),
            psnr: psnr(&r, &t, w, h)?,
            ssim: ssim(&r, &t, w, h)?,
            lpips,
        })
    }
}

/// Averages over the held-out views and the views themselves (docs/method.md evaluation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Mean PSNR over views, dB (mean of per-view PSNR, as the reference `metrics.py`).
    pub psnr: f32,
    /// Mean SSIM over views.
    pub ssim: f32,
    /// Mean LPIPS over views when every view has one ([`ViewMetrics::lpips`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f32>,
    pub views: Vec<ViewMetrics>,
    /// The pixels measured: `full`, or `right_half` with exposure compensation.
    #[serde(default)]
    pub region: EvalRegion,
}

impl EvalReport {
    /// Report of `views` measured on full images; averages are 0 when there are none.
    pub fn from_views(views: Vec<ViewMetrics>) -> Self {
        Self::from_views_in(views, EvalRegion::Full)
    }

    /// Report of `views` measured on `region`; averages are 0 when there are none.
    pub fn from_views_in(views: Vec<ViewMetrics>, region: EvalRegion) -> Self {
        let n = views.len().max(1) as f32;
        EvalReport {
            psnr: views.iter().map(|v| v.psnr).sum::<f32>() / n,
            ssim: views.iter().map(|v| v.ssim).sum::<f32>() / n,
            lpips: views
                .iter()
                .map(|v| v.lpips)
                .sum::<Option<f32>>()
                .filter(|_| !views.is_empty())
                .map(|s| s / n),
            views,
            region,
        }
    }
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// A render in [0, 1] as 8-bit RGB (clamped and rounded), what its PNG holds.
pub fn to_rgb8(render: &[[f32; 3]]) -> Vec<[u8; 3]> {
    render.iter().map(|p| p.map(to_u8)).collect()
}

/// 8-bit RGB back to [0, 1].
pub fn from_rgb8(image: &[[u8; 3]]) -> Vec<[f32; 3]> {
    image
        .iter()
        .map(|p| p.map(|v| f32::from(v) / 255.0))
        .collect()
}

/// Saves render (left) and ground truth (right), 8-bit RGB, side by side as an RGB PNG.
pub fn save_side_by_side(
    path: &Path,
    render: &[[u8; 3]],
    truth: &[[u8; 3]],
    width: u32,
    height: u32,
) -> Result<(), EvalError> {
    check(render, truth, width, height)?;
    let img = image::RgbImage::from_fn(2 * width, height, |x, y| {
        let (src, x) = if x < width {
            (render, x)
        } else {
            (truth, x - width)
        };
        image::Rgb(src[(y * width + x) as usize])
    });
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| EvalError::Image {
            path: path.display().to_string(),
            source,
        })
}

/// One line of the training log.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LossRecord {
    /// Step, 1-based.
    pub step: u32,
    /// Total loss.
    pub loss: f32,
    /// L1 term (mean absolute error, [0, 1]).
    pub l1: f32,
    /// Mean SSIM of the step's view.
    pub ssim: f32,
    /// The semantic term L_geo before its weight gamma (0 while off).
    pub geo: f32,
    /// Gaussians in the model.
    pub n_gaussians: usize,
    /// Wall time since training started, seconds.
    pub seconds: f64,
    /// What holds the trunk Gaussians, on the steps the monitor measured
    /// ([`super::trunk_diag`]).
    #[serde(default)]
    pub trunk: Option<super::trunk_diag::TrunkDiag>,
}

/// Writes the log as CSV with header `step,loss,l1,ssim,n_gaussians,seconds,geo` followed by
/// the trunk monitor's columns `s_count,s_weight,slice_count,slice_in_s,geo_photo_grad_ratio,
/// surface_offset_mm,surface_abs_mm` (empty on the steps it did not measure).
pub fn write_loss_csv<W: Write>(out: W, records: &[LossRecord]) -> io::Result<()> {
    let mut w = csv::Writer::from_writer(out);
    w.write_record([
        "step",
        "loss",
        "l1",
        "ssim",
        "n_gaussians",
        "seconds",
        "geo",
        "s_count",
        "s_weight",
        "slice_count",
        "slice_in_s",
        "geo_photo_grad_ratio",
        "surface_offset_mm",
        "surface_abs_mm",
    ])?;
    let opt = |v: Option<f64>| v.map_or(String::new(), |x| format!("{x:.4}"));
    for r in records {
        let mut row = vec![
            r.step.to_string(),
            r.loss.to_string(),
            r.l1.to_string(),
            r.ssim.to_string(),
            r.n_gaussians.to_string(),
            format!("{:.3}", r.seconds),
            r.geo.to_string(),
        ];
        match r.trunk {
            Some(d) => row.extend([
                d.s_count.to_string(),
                format!("{:.4}", d.s_weight),
                d.slice_count.to_string(),
                opt(d.slice_in_s),
                opt(d.geo_photo_grad_ratio),
                opt(d.surface_offset_mm),
                opt(d.surface_abs_mm),
            ]),
            None => row.extend(std::iter::repeat_n(String::new(), 7)),
        }
        w.write_record(&row)?;
    }
    w.flush()
}

#[cfg(test)]
#[path = "eval_tests.rs"]
mod tests;
