//! Deterministic k-means (Lloyd) on standardised feature rows, used with K = 2 for the
//! wood/leaf split (docs/method.md Stage 3.3).
//!
//! Seeding is k-means++ (D² sampling, Arthur & Vassilvitskii 2007) driven by a fixed-seed
//! SplitMix64 generator over a strided subsample of at most 100 000 rows, so the result is
//! the same on every run and machine. Above 400 000 rows, Lloyd first runs on a strided
//! subsample of 200 000 and then continues on all rows from its centres (warm start) until
//! no more than 1 in 100 000 rows changes cluster. Lloyd iterations run on all rows in
//! parallel; partial
//! sums are combined in chunk order so the floating-point result does not depend on thread
//! scheduling.

use rayon::prelude::*;

use super::ForestError;
use crate::progress::Progress;
use crate::rng::SplitMix64;

/// Rows per parallel chunk (and per cancellation check).
const CHUNK: usize = 16_384;
/// Most rows the k-means++ seeding looks at.
const SEED_SAMPLE: usize = 100_000;
/// Rows of the warm-start subsample: above twice this many rows, Lloyd runs first on a
/// strided subsample of about this size (see [`kmeans`]).
const WARM_SAMPLE: usize = 200_000;

/// The result of [`kmeans`].
#[derive(Debug, Clone, PartialEq)]
pub struct KMeans {
    /// `k` centres of `dim` values each, row-major.
    pub centres: Vec<f32>,
    /// Cluster of every row.
    pub assignment: Vec<u8>,
    /// Lloyd iterations run (warm start on the subsample and on all rows together).
    pub iterations: usize,
}

/// Standardises every column of `rows` (`dim` values per row) to zero mean and unit standard
/// deviation in place; constant columns become 0. Returns the (mean, std) per column.
pub fn standardise(rows: &mut [f32], dim: usize) -> Vec<(f32, f32)> {
    let n = rows.len() / dim.max(1);
    let mut stats = Vec::with_capacity(dim);
    for d in 0..dim {
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for r in 0..n {
            let v = rows[r * dim + d] as f64;
            s += v;
            s2 += v * v;
        }
        let mean = s / n.max(1) as f64;
        let var = (s2 / n.max(1) as f64 - mean * mean).max(0.0);
        let std = var.sqrt();
        stats.push((mean as f32, std as f32));
    }
    rows.par_chunks_mut(dim).for_each(|row| {
        for (v, (m, s)) in row.iter_mut().zip(&stats) {
            *v = if *s > 1e-12 { (*v - m) / s } else { 0.0 };
        }
    });
    stats
}

fn dist2(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

fn nearest(row: &[f32], centres: &[f32], dim: usize) -> (u8, f32) {
    let mut best = (0u8, f32::INFINITY);
    for (c, centre) in centres.chunks(dim).enumerate() {
        let d = dist2(row, centre);
        if d < best.1 {
            best = (c as u8, d);
        }
    }
    best
}

/// k-means with deterministic k-means++ seeding; stops when no row changes cluster or after
/// `max_iterations`. `k` must be in 1..=255 and `rows.len()` a multiple of `dim`.
pub fn kmeans(
    rows: &[f32],
    dim: usize,
    k: usize,
    max_iterations: usize,
    seed: u64,
    progress: &dyn Progress,
) -> Result<KMeans, ForestError> {
    if dim == 0 || !rows.len().is_multiple_of(dim) || !(1..=255).contains(&k) {
        return Err(ForestError::Params(format!(
            "k-means needs 1 <= k <= 255 and whole rows (k = {k}, dim = {dim})"
        )));
    }
    let n = rows.len() / dim;
    if n < k {
        return Err(ForestError::NotEnoughPoints(format!(
            "k-means with k = {k} needs at least {k} rows, got {n}"
        )));
    }
    // k-means++ on a strided subsample.
    let stride = n.div_ceil(SEED_SAMPLE).max(1);
    let sample: Vec<&[f32]> = (0..n)
        .step_by(stride)
        .map(|r| &rows[r * dim..][..dim])
        .collect();
    let mut rng = SplitMix64::new(seed);
    let mut centres: Vec<f32> = sample[rng.below(sample.len() as u64) as usize].to_vec();
    let mut d2: Vec<f32> = sample.iter().map(|r| dist2(r, &centres[..dim])).collect();
    while centres.len() < k * dim {
        let total: f64 = d2.iter().map(|v| *v as f64).sum();
        let pick = if total > 0.0 {
            let target = rng.uniform() * total;
            let mut acc = 0.0;
            d2.iter()
                .position(|v| {
                    acc += *v as f64;
                    acc >= target
                })
                .unwrap_or(sample.len() - 1)
        } else {
            rng.below(sample.len() as u64) as usize
        };
        let c = sample[pick].to_vec();
        for (slot, r) in d2.iter_mut().zip(&sample) {
            *slot = slot.min(dist2(r, &c));
        }
        centres.extend(c);
    }
    // Warm start: Lloyd on a strided subsample until it settles, then on all rows from its
    // centres. Same fixed-point iteration, so the same kind of result; on millions of rows
    // the full passes drop from dozens to a handful.
    let mut iterations = 0;
    if n > 2 * WARM_SAMPLE {
        let stride = n.div_ceil(WARM_SAMPLE);
        let sample: Vec<f32> = (0..n)
            .step_by(stride)
            .flat_map(|r| rows[r * dim..][..dim].iter().copied())
            .collect();
        let mut sample_assignment = vec![u8::MAX; sample.len() / dim];
        iterations += lloyd(
            &sample,
            dim,
            &mut centres,
            &mut sample_assignment,
            max_iterations,
            0,
            progress,
        )?;
    }
    // From warm-started centres only a fringe of rows on the boundary between two clusters
    // is still moving, and on millions of rows a few of them can keep flipping for dozens of
    // passes: stop when no more than 1 in 100 000 rows changed (none for small inputs).
    let settle = if iterations > 0 { n / 100_000 } else { 0 };
    let mut assignment = vec![u8::MAX; n];
    iterations += lloyd(
        rows,
        dim,
        &mut centres,
        &mut assignment,
        max_iterations,
        settle,
        progress,
    )?;
    Ok(KMeans {
        centres,
        assignment,
        iterations,
    })
}

/// Lloyd iterations from `centres` until at most `settle` rows change cluster or
/// `max_iterations`; returns the iterations run.
fn lloyd(
    rows: &[f32],
    dim: usize,
    centres: &mut [f32],
    assignment: &mut [u8],
    max_iterations: usize,
    settle: usize,
    progress: &dyn Progress,
) -> Result<usize, ForestError> {
    let k = centres.len() / dim.max(1);
    let mut iterations = 0;
    for it in 0..max_iterations.max(1) {
        if progress.is_cancelled() {
            return Err(ForestError::Cancelled);
        }
        iterations = it + 1;
        // Assign and accumulate per chunk: (sums k×dim, counts k, changed).
        let current: &[f32] = centres;
        let partial: Vec<(Vec<f64>, Vec<u64>, usize)> = assignment
            .par_chunks_mut(CHUNK)
            .enumerate()
            .map(|(c, chunk)| {
                let mut sums = vec![0.0f64; k * dim];
                let mut counts = vec![0u64; k];
                let mut changed = 0;
                for (j, slot) in chunk.iter_mut().enumerate() {
                    let row = &rows[(c * CHUNK + j) * dim..][..dim];
                    let (best, _) = nearest(row, current, dim);
                    if *slot != best {
                        changed += 1;
                        *slot = best;
                    }
                    counts[best as usize] += 1;
                    for (s, v) in sums[best as usize * dim..][..dim].iter_mut().zip(row) {
                        *s += *v as f64;
                    }
                }
                (sums, counts, changed)
            })
            .collect();
        let mut sums = vec![0.0f64; k * dim];
        let mut counts = vec![0u64; k];
        let mut changed = 0;
        for (s, c, ch) in partial {
            sums.iter_mut().zip(s).for_each(|(a, b)| *a += b);
            counts.iter_mut().zip(c).for_each(|(a, b)| *a += b);
            changed += ch;
        }
        for c in 0..k {
            if counts[c] > 0 {
                for d in 0..dim {
                    centres[c * dim + d] = (sums[c * dim + d] / counts[c] as f64) as f32;
                }
            }
        }
        progress.set(((it + 1) as f64 / max_iterations.max(1) as f64).min(1.0));
        if changed <= settle && it > 0 {
            break;
        }
    }
    Ok(iterations)
}

/// Squared distance of `row` to centre `c` of a [`KMeans`] result.
pub fn distance2_to_centre(km: &KMeans, dim: usize, row: &[f32], c: usize) -> f32 {
    dist2(row, &km.centres[c * dim..][..dim])
}
