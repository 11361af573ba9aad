//! A loss-curve PNG drawn pixel by pixel with the `image` crate (no plotting library): white
//! background, black axes with tick marks at fifths of each range, the loss as a blue polyline.
//! Enough to see at a glance whether a run converged; the CSV holds the numbers.

use std::path::Path;

use image::{Rgb, RgbImage};

use crate::splat::eval::{EvalError, LossRecord};

/// Background colour.
pub const BACKGROUND: Rgb<u8> = Rgb([255, 255, 255]);
/// Axis and tick colour.
pub const AXIS: Rgb<u8> = Rgb([0, 0, 0]);
/// Curve colour.
pub const CURVE: Rgb<u8> = Rgb([30, 90, 200]);
/// Empty border around the plot area, pixels.
pub const MARGIN: u32 = 30;
/// Tick length, pixels.
const TICK: i64 = 5;
/// Ticks per axis (excluding the origin).
const TICKS: i64 = 5;

/// Maps records to plot pixels: x from the step range, y from the loss range (0 at the bottom).
pub struct PlotFrame {
    width: u32,
    height: u32,
    steps: (f64, f64),
    losses: (f64, f64),
}

impl PlotFrame {
    /// The frame of `records` in a `width × height` image.
    pub fn new(records: &[LossRecord], width: u32, height: u32) -> Self {
        let range = |it: &mut dyn Iterator<Item = f64>| {
            let (lo, hi) = it.fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
                (l.min(v), h.max(v))
            });
            if lo.is_finite() && hi > lo {
                (lo, hi)
            } else if lo.is_finite() {
                (lo - 0.5, lo + 0.5)
            } else {
                (0.0, 1.0)
            }
        };
        let steps = range(&mut records.iter().map(|r| r.step as f64));
        let losses = range(
            &mut records
                .iter()
                .map(|r| r.loss as f64)
                .filter(|v| v.is_finite()),
        );
        PlotFrame {
            width: width.max(2 * MARGIN + 2),
            height: height.max(2 * MARGIN + 2),
            steps,
            losses,
        }
    }

    /// Pixel (column, row) of a point of the curve.
    pub fn pixel(&self, step: f64, loss: f64) -> (i64, i64) {
        let (w, h) = (
            (self.width - 2 * MARGIN) as f64,
            (self.height - 2 * MARGIN) as f64,
        );
        let fx = (step - self.steps.0) / (self.steps.1 - self.steps.0);
        let fy = (loss - self.losses.0) / (self.losses.1 - self.losses.0);
        (
            (MARGIN as f64 + fx * w).round() as i64,
            (MARGIN as f64 + (1.0 - fy) * h).round() as i64,
        )
    }
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, c);
    }
}

/// Bresenham line from `a` to `b`.
fn line(img: &mut RgbImage, a: (i64, i64), b: (i64, i64), c: Rgb<u8>) {
    let (dx, dy) = ((b.0 - a.0).abs(), -(b.1 - a.1).abs());
    let (sx, sy) = ((b.0 - a.0).signum(), (b.1 - a.1).signum());
    let (mut x, mut y, mut err) = (a.0, a.1, dx + dy);
    loop {
        put(img, x, y, c);
        if (x, y) == b {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x += sx;
        }
        if e2 <= dx {
            err += dx;
            y += sy;
        }
    }
}

/// Draws the loss curve of `records` into a new `width × height` image.
pub fn plot_loss_curve(records: &[LossRecord], width: u32, height: u32) -> RgbImage {
    let f = PlotFrame::new(records, width, height);
    let mut img = RgbImage::from_pixel(f.width, f.height, BACKGROUND);
    let (x0, y0) = (MARGIN as i64, (f.height - MARGIN) as i64);
    let (x1, y1) = ((f.width - MARGIN) as i64, MARGIN as i64);
    line(&mut img, (x0, y0), (x1, y0), AXIS);
    line(&mut img, (x0, y0), (x0, y1), AXIS);
    for t in 1..=TICKS {
        let x = x0 + (x1 - x0) * t / TICKS;
        let y = y0 + (y1 - y0) * t / TICKS;
        line(&mut img, (x, y0), (x, y0 + TICK), AXIS);
        line(&mut img, (x0 - TICK, y), (x0, y), AXIS);
    }
    let points: Vec<(i64, i64)> = records
        .iter()
        .filter(|r| r.loss.is_finite())
        .map(|r| f.pixel(r.step as f64, r.loss as f64))
        .collect();
    for pair in points.windows(2) {
        line(&mut img, pair[0], pair[1], CURVE);
    }
    if let [only] = points.as_slice() {
        put(&mut img, only.0, only.1, CURVE);
    }
    img
}

/// Draws the loss curve and saves it as PNG.
pub fn save_loss_plot(
    path: &Path,
    records: &[LossRecord],
    width: u32,
    height: u32,
) -> Result<(), EvalError> {
    plot_loss_curve(records, width, height)
        .save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| EvalError::Image {
            path: path.display().to_string(),
            source,
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn records() -> Vec<LossRecord> {
        (1..=50)
            .map(|s| LossRecord {
                step: s * 10,
                loss: 0.5 * (-(s as f32) / 10.0).exp() + 0.05,
                l1: 0.0,
                ssim: 0.0,
                geo: 0.0,
                n_gaussians: 100,
                seconds: s as f64,
                trunk: None,
            })
            .collect()
    }

    #[test]
    fn the_curve_passes_through_every_record() {
        let recs = records();
        let img = plot_loss_curve(&recs, 320, 200);
        let frame = PlotFrame::new(&recs, 320, 200);
        for r in &recs {
            let (x, y) = frame.pixel(r.step as f64, r.loss as f64);
            assert_eq!(*img.get_pixel(x as u32, y as u32), CURVE, "step {}", r.step);
        }
        // First record top-left, last bottom-right of the plot area.
        assert_eq!(
            frame.pixel(10.0, recs[0].loss as f64),
            (MARGIN as i64, MARGIN as i64)
        );
        assert_eq!(*img.get_pixel(MARGIN, 200 - MARGIN), AXIS);
        let curve = img.pixels().filter(|p| **p == CURVE).count();
        assert!(
            curve > 250,
            "a connected curve across the width: {curve} pixels"
        );
    }

    #[test]
    fn degenerate_logs_still_plot() {
        let img = plot_loss_curve(&[], 10, 10);
        assert!(img.width() > 2 * MARGIN);
        let one = &records()[..1];
        let img = plot_loss_curve(one, 100, 100);
        assert_eq!(img.pixels().filter(|p| **p == CURVE).count(), 1);
    }
}
