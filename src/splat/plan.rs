//! The memory plan of a training run on a GPU (docs/splatting.md "Memory plan"): from the
//! device's memory, the photos and what the run trains, how many Gaussians it may hold (the
//! budget, drawn by [`super::budget::cap_gaussians`] and kept by the densification) and where
//! the photos live: all on the GPU when they fit, otherwise a bounded cache of photo slots
//! filled from host memory while the steps run.
//!
//! The arithmetic follows the buffers of [`super::gpu`], by what each scales with:
//! - per Gaussian for the whole run ([`MODEL_BYTES_PER_GAUSSIAN`]): the 59 parameters, their
//!   gradients, the 3 densification statistics and Adam's two moments, all `f32`; with the
//!   trunk term, its probability and L_geo's target ([`TRUNK_TERM_BYTES_PER_GAUSSIAN`]); with
//!   MCMC, one flag word;
//! - per Gaussian for one step ([`STEP_BYTES_PER_GAUSSIAN`]): the projected record (48 B), the
//!   tile count (4 B, and 4 B more when the intersections are banded) and the screen-space
//!   gradients (40 B);
//! - per tile intersection ([`BYTES_PER_INTERSECTION`]): tile key, depth key and Gaussian id,
//!   and the sort's second copy of each, 4 B each;
//! - per pixel of the step's image ([`STEP_BYTES_PER_PIXEL`]): the render, its transmittance,
//!   contribution count, depth and depth gradient, dL/dimage, the loss's SSIM scratch; with
//!   exposure compensation, the exposed image and its gradient;
//! - per photo on the GPU: 4 B a pixel (RGBA8), and 4 B more for its LiDAR depth map when the
//!   depth loss is on;
//! - an upload in flight ([`staging_bytes`]): wgpu stages what it uploads beside the buffer
//!   until the GPU has copied it, so a model is uploaded in slices (at the start and after
//!   every refinement) and photos one at a time.
//!
//! `tests/gpu.rs` holds these figures against the allocator's own count of the buffers a run
//! makes on the GPU (wgpu's allocator report).

use serde::Serialize;

use super::backend::{Backend, DeviceKind};
use super::config::{StrategyKind, TrainConfig};
use super::dataset::Dataset;
use super::semantic::SemanticAnchors;

/// Floats of one Gaussian's parameters: mean 3, log-scales 3, rotation 4, opacity 1, SH 48.
pub const PARAMETER_FLOATS: u64 = 59;

/// Bytes per Gaussian held for the whole run: parameters, gradients, densification
/// statistics (3 floats) and Adam's first and second moments, `f32` each.
pub const MODEL_BYTES_PER_GAUSSIAN: u64 = (PARAMETER_FLOATS * 4 + 3) * 4;

/// Bytes per Gaussian the trunk term adds (trunk probability 4 B, L_geo target 32 B).
pub const TRUNK_TERM_BYTES_PER_GAUSSIAN: u64 = 36;

/// Bytes per Gaussian MCMC adds (one flag word).
pub const MCMC_BYTES_PER_GAUSSIAN: u64 = 4;

/// Bytes per Gaussian of one step's frame: projected record 48, tile count 4, band tile
/// count 4 (when the intersections are split in bands), screen-space gradients 40.
pub const STEP_BYTES_PER_GAUSSIAN: u64 = 48 + 4 + 4 + 40;

/// Bytes per tile intersection: three 4-byte arrays and the sort's alternates of each, plus
/// its histogram (16 words per 1024 keys, rounded up to a byte).
pub const BYTES_PER_INTERSECTION: u64 = 6 * 4 + 1;

/// Bytes per pixel of the step's image: render 12, transmittance 4, contribution count 4,
/// depth 4, dL/ddepth 4, dL/dimage 12; the loss's scratch (the SSIM statistics' horizontal
/// pass, 15 floats, and the two passes of its derivative maps, 9 floats each: 132 B); and the
/// tile ranges and the loss's partial sums (8 B per 256 pixels each, rounded up to a byte).
pub const STEP_BYTES_PER_PIXEL: u64 = 12 + 4 + 4 + 4 + 4 + 12 + 132 + 1;

/// Bytes per pixel exposure compensation adds to a step (the exposed image and its gradient).
pub const EXPOSURE_BYTES_PER_PIXEL: u64 = 24;

/// Bytes per pixel of a photo on the GPU (packed RGBA8).
pub const PHOTO_BYTES_PER_PIXEL: u64 = 4;

/// Bytes per pixel of a view's LiDAR depth map on the GPU (f32).
pub const DEPTH_MAP_BYTES_PER_PIXEL: u64 = 4;

/// Share of the device's memory the plan leaves to the driver, the compiled kernels and the
/// allocator's blocks (Sylva's choice: 10 %, about 0.8 GB of an 8 GB card).
pub const HEADROOM_SHARE: f64 = 0.10;

/// Bytes the plan sets aside for an upload in flight: the larger of one photo and one slice
/// of a model upload (`crate::gpu::buffers::UPLOAD_SLICE_BYTES`, 8 MiB), which wgpu stages
/// beside the buffer it fills until the GPU has copied it.
pub fn staging_bytes(bytes_per_photo: u64) -> u64 {
    bytes_per_photo.max(crate::gpu::buffers::UPLOAD_SLICE_BYTES as u64)
}

/// Bytes the plan sets aside for the small buffers of a run (parameters of each pass, scan
/// sums, exposure parameters, loss output): 32 MiB (Sylva's choice; they take under 1 MiB on
/// `stand`).
pub const FIXED_BYTES: u64 = 32 << 20;

/// Share of the plannable memory all the photos may take and still live on the GPU: a half
/// (Sylva's choice), so photos never take the room of most Gaussians.
pub const ALL_PHOTOS_SHARE: f64 = 0.5;

/// Share of the plannable memory a photo cache gets when the photos do not all fit: a fifth
/// (Sylva's choice: 1.3 GB of an 8 GB card, about 170 photos at 1920×1080).
pub const PHOTO_CACHE_SHARE: f64 = 0.2;

/// The fewest photo slots a cache has: the step's photo and the next one, uploaded while the
/// step runs.
pub const MIN_PHOTO_SLOTS: usize = 2;

/// Tile intersections per Gaussian the plan reserves room for, at least (16×16-px tiles).
/// Measured: 1.4 (UAV photos at 320 px) to 6.8 (close-up at 320 px) and 21.2 (close-up at
/// 640 px; docs/results/splatting.md, "Where the time goes"), and at most 27.9 in a step of
/// `stand` at 640 px from its LiDAR start of 10 000 Gaussians (issue 41; 16 was too few
/// there). 32 covers them all; memory the budget leaves goes to intersections as well, and a
/// step whose intersections exceed the room is skipped and counted (`over_plan_steps`).
pub const INTERSECTIONS_PER_GAUSSIAN: f64 = 32.0;

/// Where the device's memory figure came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MemorySource {
    /// The parameter (`params.train.gpu_memory_mb`).
    Params,
    /// The driver (Vulkan's largest device-local heap).
    Device,
}

/// What a plan is made from.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlanInput {
    /// The GPU's memory, bytes.
    pub device_bytes: u64,
    pub source: MemorySource,
    /// Photos the steps train on.
    pub photos: usize,
    /// Pixels of the largest of them.
    pub photo_pixels: u64,
    /// LiDAR depth maps beside the photos (the depth loss).
    pub depth_maps: bool,
    /// Per-photo exposure compensation.
    pub exposure: bool,
    /// The paper's trunk term or Sylva's binding.
    pub trunk_term: bool,
    /// The MCMC strategy.
    pub mcmc: bool,
    /// The trunk term's anchors on the GPU, bytes
    /// (`crate::splat::semantic::SemanticAnchors::device_bytes`; 0 without the term).
    pub anchor_bytes: u64,
    /// The budget asked for, or the device's speed default; `None`: as many as fit.
    pub budget: Option<u32>,
    /// Room to reserve per Gaussian for tile intersections ([`INTERSECTIONS_PER_GAUSSIAN`]).
    pub intersections_per_gaussian: f64,
}

/// The plan (see the module doc); bytes throughout.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MemoryPlan {
    pub input: PlanInput,
    /// What the plan may use: the device's memory less [`HEADROOM_SHARE`].
    pub usable_bytes: u64,
    /// Photos on the GPU at once: all of them, or the slots of the cache.
    pub photo_slots: usize,
    /// Whether every photo lives on the GPU (no cache).
    pub all_photos: bool,
    pub photo_bytes: u64,
    /// The step's per-pixel buffers.
    pub frame_bytes: u64,
    /// An upload in flight ([`staging_bytes`]).
    pub staging_bytes: u64,
    /// Bytes one Gaussian takes: for the run, for a step and its reserved intersections.
    pub bytes_per_gaussian: u64,
    /// The Gaussian budget.
    pub budget: u32,
    /// Whether memory set the budget (below the one asked for, or none was asked).
    pub memory_bound: bool,
    /// Model and step buffers at the budget.
    pub gaussian_bytes: u64,
    /// Tile intersections a step may have: what the rest of the plan leaves.
    pub max_intersections: u64,
    /// Everything planned: fixed, photos, frame, Gaussians and intersections.
    pub total_bytes: u64,
}

/// Why no plan fits.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error(
        "the GPU's {have_mb} MB cannot train these photos: one step at {pixels} pixels with {MIN_PHOTO_SLOTS} photo slots and {min_gaussians} Gaussians needs {need_mb} MB; train at a lower resolution or on a larger GPU"
    )]
    TooSmall {
        have_mb: u64,
        need_mb: u64,
        pixels: u64,
        min_gaussians: u64,
    },
    #[error("no photos to train on")]
    NoPhotos,
}

/// The fewest Gaussians a plan accepts (a budget below it is not worth training).
pub const MIN_GAUSSIANS: u64 = 1_000;

impl PlanInput {
    /// Bytes one Gaussian takes for the whole run.
    pub fn model_bytes_per_gaussian(&self) -> u64 {
        MODEL_BYTES_PER_GAUSSIAN
            + if self.trunk_term {
                TRUNK_TERM_BYTES_PER_GAUSSIAN
            } else {
                0
            }
            + if self.mcmc {
                MCMC_BYTES_PER_GAUSSIAN
            } else {
                0
            }
    }

    /// Bytes one photo takes on the GPU (with its depth map).
    pub fn bytes_per_photo(&self) -> u64 {
        self.photo_pixels
            * (PHOTO_BYTES_PER_PIXEL
                + if self.depth_maps {
                    DEPTH_MAP_BYTES_PER_PIXEL
                } else {
                    0
                })
    }

    /// Bytes of one step's per-pixel buffers.
    pub fn frame_bytes(&self) -> u64 {
        self.photo_pixels
            * (STEP_BYTES_PER_PIXEL
                + if self.exposure {
                    EXPOSURE_BYTES_PER_PIXEL
                } else {
                    0
                })
    }

    /// Bytes per Gaussian with its step buffers and reserved intersections.
    pub fn bytes_per_gaussian(&self) -> u64 {
        let isect = (self.intersections_per_gaussian.max(0.0) * BYTES_PER_INTERSECTION as f64)
            .ceil() as u64;
        self.model_bytes_per_gaussian() + STEP_BYTES_PER_GAUSSIAN + isect
    }
}

/// The plan for `input` (see the module doc): the photos all on the GPU when they take at most
/// [`ALL_PHOTOS_SHARE`] of the plannable memory and leave room for the budget asked for (with
/// no budget asked for, when they take at most a cache's share); otherwise a cache of
/// [`PHOTO_CACHE_SHARE`] of it (at least [`MIN_PHOTO_SLOTS`] photos).
/// The budget is the one asked for, lowered to what the rest holds; the intersections get the
/// remainder.
pub fn plan(input: &PlanInput) -> Result<MemoryPlan, PlanError> {
    if input.photos == 0 || input.photo_pixels == 0 {
        return Err(PlanError::NoPhotos);
    }
    let usable = (input.device_bytes as f64 * (1.0 - HEADROOM_SHARE)) as u64;
    let frame = input.frame_bytes();
    let per_photo = input.bytes_per_photo();
    let per_gaussian = input.bytes_per_gaussian();
    let staging = staging_bytes(per_photo);
    let fixed = FIXED_BYTES + input.anchor_bytes;
    let too_small = || {
        let need = fixed
            + staging
            + frame
            + MIN_PHOTO_SLOTS as u64 * per_photo
            + MIN_GAUSSIANS * per_gaussian;
        PlanError::TooSmall {
            have_mb: input.device_bytes >> 20,
            need_mb: ((need as f64 / (1.0 - HEADROOM_SHARE)) as u64).div_ceil(1 << 20),
            pixels: input.photo_pixels,
            min_gaussians: MIN_GAUSSIANS,
        }
    };
    let plannable = usable
        .checked_sub(fixed + staging + frame)
        .ok_or_else(too_small)?;
    let all = input.photos as u64 * per_photo;
    let asked = input.budget.map_or(0, u64::from) * per_gaussian;
    // With a budget asked for, the photos stay when they leave room for it; with none (as
    // many Gaussians as fit), only when they take no more than a cache would, so that more
    // memory never plans fewer Gaussians.
    let all_fit = match input.budget {
        Some(_) => {
            all as f64 <= ALL_PHOTOS_SHARE * plannable as f64
                && all + asked.max(MIN_GAUSSIANS * per_gaussian) <= plannable
        }
        None => all as f64 <= PHOTO_CACHE_SHARE * plannable as f64,
    };
    let (photo_slots, all_photos) = if all_fit {
        (input.photos, true)
    } else {
        let slots = ((PHOTO_CACHE_SHARE * plannable as f64) as u64 / per_photo.max(1)) as usize;
        (slots.clamp(MIN_PHOTO_SLOTS, input.photos), false)
    };
    let photo_bytes = photo_slots as u64 * per_photo;
    let left = plannable.checked_sub(photo_bytes).ok_or_else(too_small)?;
    let fit = (left / per_gaussian).min(u64::from(u32::MAX / 64));
    if fit < MIN_GAUSSIANS {
        return Err(too_small());
    }
    let (budget, memory_bound) = match input.budget {
        Some(b) if u64::from(b) <= fit => (b, false),
        _ => (fit as u32, true),
    };
    let model_and_step =
        u64::from(budget) * (input.model_bytes_per_gaussian() + STEP_BYTES_PER_GAUSSIAN);
    let max_intersections = (left - model_and_step) / BYTES_PER_INTERSECTION;
    let gaussian_bytes = model_and_step;
    Ok(MemoryPlan {
        input: input.clone(),
        usable_bytes: usable,
        photo_slots,
        all_photos,
        photo_bytes,
        frame_bytes: frame,
        staging_bytes: staging,
        bytes_per_gaussian: per_gaussian,
        budget,
        memory_bound,
        gaussian_bytes,
        max_intersections,
        total_bytes: fixed
            + staging
            + frame
            + photo_bytes
            + gaussian_bytes
            + max_intersections * BYTES_PER_INTERSECTION,
    })
}

impl MemoryPlan {
    /// One line for the log.
    pub fn describe(&self) -> String {
        let mb = |b: u64| b as f64 / (1 << 20) as f64;
        format!(
            "memory plan for {:.0} MB of GPU memory ({}): {} Gaussians{} ({:.0} MB), photos {} ({:.0} MB), up to {} tile intersections a step ({:.0} MB); {:.0} MB planned",
            mb(self.input.device_bytes),
            match self.input.source {
                MemorySource::Params => "params.train.gpu_memory_mb",
                MemorySource::Device => "the device",
            },
            self.budget,
            if self.memory_bound {
                ", set by memory"
            } else {
                ""
            },
            mb(self.gaussian_bytes),
            if self.all_photos {
                format!("all {} on the GPU", self.photo_slots)
            } else {
                format!(
                    "in a cache of {} of {} streamed from host memory",
                    self.photo_slots, self.input.photos
                )
            },
            mb(self.photo_bytes),
            self.max_intersections,
            mb(self.max_intersections * BYTES_PER_INTERSECTION),
            mb(self.total_bytes),
        )
    }
}

/// What a run on `backend` should plan with: the memory `gpu_memory_mb` gives (MiB; 0 = what
/// the device reports), the photos of `data` that `cfg`'s steps train on, `cfg`'s budget (0 =
/// none asked), exposure and strategy, `depth_maps` and the trunk term's `anchors`. `None` for the CPU
/// reference (host memory) and for a device that does not report its memory when no figure is
/// given.
pub fn run_input(
    backend: &dyn Backend,
    data: &Dataset,
    cfg: &TrainConfig,
    gpu_memory_mb: u64,
    depth_maps: bool,
    anchors: Option<&SemanticAnchors>,
) -> Option<PlanInput> {
    if backend.device_kind() == DeviceKind::CpuReference {
        return None;
    }
    let (device_bytes, source) = match gpu_memory_mb {
        0 => (backend.device_memory()?, MemorySource::Device),
        mb => (mb.saturating_mul(1 << 20), MemorySource::Params),
    };
    let steps = data.step_views(cfg.exposure);
    let photo_pixels = steps
        .iter()
        .map(|(v, _)| u64::from(v.camera.width) * u64::from(v.camera.height))
        .max()
        .unwrap_or(0);
    Some(PlanInput {
        device_bytes,
        source,
        photos: steps.len(),
        photo_pixels,
        depth_maps,
        exposure: cfg.exposure,
        trunk_term: anchors.is_some(),
        mcmc: cfg.strategy == StrategyKind::Mcmc,
        anchor_bytes: anchors.map_or(0, SemanticAnchors::device_bytes),
        budget: cfg.max_gaussians.map(|m| m.min(u32::MAX as usize) as u32),
        intersections_per_gaussian: INTERSECTIONS_PER_GAUSSIAN,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const GB: u64 = 1 << 30;

    /// The paper's plot 3 (857 photos at 1920×1080, every eighth held out) with the defaults
    /// of stage `train` (exposure, the trunk binding).
    fn paper(device_bytes: u64, budget: Option<u32>) -> PlanInput {
        PlanInput {
            device_bytes,
            source: MemorySource::Params,
            photos: 857 - 857 / 8,
            photo_pixels: 1920 * 1080,
            depth_maps: false,
            exposure: true,
            trunk_term: true,
            mcmc: false,
            anchor_bytes: 0,
            budget,
            intersections_per_gaussian: INTERSECTIONS_PER_GAUSSIAN,
        }
    }

    #[test]
    fn the_paper_plot_fits_an_8_gb_card_with_streamed_photos_and_millions_of_gaussians() {
        let p = plan(&paper(8 * GB, None)).expect("plan");
        // 750 photos at 8.3 MB are 6.2 GB: they cannot all stay.
        assert!(!p.all_photos);
        assert!(p.photo_slots >= 100 && p.photo_slots < 750, "{p:?}");
        assert!(p.memory_bound);
        assert!(p.budget > 3_000_000, "{}", p.budget);
        // Room for the intersections the plan promises, and nothing past the usable memory.
        assert!(p.max_intersections >= (p.budget as f64 * INTERSECTIONS_PER_GAUSSIAN) as u64);
        assert!(p.total_bytes <= p.usable_bytes);
        assert!(p.usable_bytes - p.total_bytes < BYTES_PER_INTERSECTION + 64);
        // The parts add up.
        assert_eq!(
            p.total_bytes,
            FIXED_BYTES
                + p.input.anchor_bytes
                + p.staging_bytes
                + p.frame_bytes
                + p.photo_bytes
                + p.gaussian_bytes
                + p.max_intersections * BYTES_PER_INTERSECTION
        );
    }

    #[test]
    fn photos_stay_on_a_large_card_and_a_budget_asked_for_is_kept_when_it_fits() {
        let p = plan(&paper(80 * GB, Some(2_000_000))).expect("plan");
        assert!(p.all_photos && p.photo_slots == 750, "{p:?}");
        assert_eq!((p.budget, p.memory_bound), (2_000_000, false));
        // On 8 GB the same budget fits too, with the photos streamed.
        let p = plan(&paper(8 * GB, Some(2_000_000))).expect("plan");
        assert_eq!(
            (p.budget, p.memory_bound, p.all_photos),
            (2_000_000, false, false)
        );
        // A budget past what fits is lowered, and says so.
        let p = plan(&paper(8 * GB, Some(50_000_000))).expect("plan");
        assert!(p.memory_bound && p.budget < 50_000_000);
    }

    #[test]
    fn a_card_too_small_for_one_step_is_refused_with_what_it_needs() {
        let e = plan(&paper(64 << 20, None)).expect_err("64 MB");
        let PlanError::TooSmall { need_mb, .. } = e else {
            panic!("{e:?}");
        };
        assert!(need_mb > 64, "{need_mb}");
        // What it says it needs is enough.
        let p = plan(&paper(need_mb << 20, None)).expect("the size it asked for");
        assert!(p.budget as u64 >= MIN_GAUSSIANS);
        assert!(
            plan(&PlanInput {
                photos: 0,
                ..paper(8 * GB, None)
            })
            .is_err()
        );
    }

    #[test]
    fn what_the_run_trains_changes_the_bytes_per_gaussian_and_pixel() {
        let plain = PlanInput {
            exposure: false,
            trunk_term: false,
            ..paper(8 * GB, None)
        };
        assert_eq!(plain.model_bytes_per_gaussian(), 956);
        assert_eq!(
            paper(8 * GB, None).model_bytes_per_gaussian(),
            956 + TRUNK_TERM_BYTES_PER_GAUSSIAN
        );
        assert_eq!(plain.frame_bytes(), 1920 * 1080 * STEP_BYTES_PER_PIXEL);
        let depth = PlanInput {
            depth_maps: true,
            ..plain.clone()
        };
        assert_eq!(depth.bytes_per_photo(), 2 * plain.bytes_per_photo());
        // More memory never plans fewer Gaussians.
        let mut last = 0;
        for gb in [4, 6, 8, 12, 16, 24] {
            let b = plan(&paper(gb * GB, None)).expect("plan").budget;
            assert!(b >= last, "{gb} GB: {b} < {last}");
            last = b;
        }
    }
}
