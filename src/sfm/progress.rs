//! COLMAP's progress, read from the lines it prints (COLMAP 3.8, the version Debian 12
//! ships; the formats below were read from its output on real photos, 2026-11-28):
//!
//! - `feature_extractor`: `Processed file [i/n]` once per photo;
//! - `exhaustive_matcher`: `Matching block [a/A, b/B] in 10.3s` once per block of pairs;
//! - `sequential_matcher` and `spatial_matcher`: `Matching image [i/n] in 0.5s`;
//! - `mapper`: `Registering image #id (k)`, where `k` is how many photos the model being
//!   built holds after this one; the mapper may start a new model (`Initializing with image
//!   pair`), so `k` can fall back.
//!
//! A line that matches none of these says nothing about progress.

/// The steps of a reconstruction, in the order they run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step {
    Extract,
    Match,
    Map,
}

impl Step {
    pub const ALL: [Step; 3] = [Step::Extract, Step::Match, Step::Map];

    /// The name the report and the log give the step.
    pub fn name(self) -> &'static str {
        match self {
            Step::Extract => "features",
            Step::Match => "matching",
            Step::Map => "mapper",
        }
    }

    /// Share of the stage's progress bar: matching dominates once photos are large (18 drone
    /// photos at 1600 px on 2 cores: extraction 2.3 min, exhaustive matching 10.0 min, the
    /// mapper 0.7 min; 18 phone photos at 450 px: 0.1, 0.5 and 0.1 min).
    pub fn weight(self) -> f64 {
        match self {
            Step::Extract => 0.2,
            Step::Match => 0.55,
            Step::Map => 0.25,
        }
    }

    /// Where the step starts on the stage's progress bar.
    pub fn start(self) -> f64 {
        Step::ALL
            .iter()
            .take_while(|s| **s != self)
            .map(|s| s.weight())
            .sum()
    }
}

/// The `[i/n]` after `prefix` in `line`, as (i, n).
fn bracket(line: &str, prefix: &str) -> Option<(u64, u64)> {
    let rest = line.trim_start().strip_prefix(prefix)?.trim_start();
    let rest = rest.strip_prefix('[')?;
    let (inside, _) = rest.split_once(']')?;
    let (i, n) = inside.split_once('/')?;
    let (i, n) = (i.trim().parse().ok()?, n.trim().parse().ok()?);
    (n > 0 && i <= n).then_some((i, n))
}

/// The fraction of `step` done that `line` reports, in [0, 1], or `None` when the line
/// says nothing about progress. `photos` is how many photos the reconstruction has (the
/// mapper's progress is the share of them in the model).
pub fn fraction(step: Step, line: &str, photos: usize) -> Option<f64> {
    match step {
        Step::Extract => bracket(line, "Processed file").map(|(i, n)| i as f64 / n as f64),
        Step::Match => {
            if let Some((i, n)) = bracket(line, "Matching image") {
                return Some(i as f64 / n as f64);
            }
            // "Matching block [a/A, b/B]": blocks run row by row.
            let rest = line
                .trim_start()
                .strip_prefix("Matching block")?
                .trim_start();
            let inside = rest.strip_prefix('[')?.split_once(']')?.0;
            let (row, col) = inside.split_once(',')?;
            let pair = |s: &str| -> Option<(u64, u64)> {
                let (i, n) = s.split_once('/')?;
                let (i, n) = (i.trim().parse().ok()?, n.trim().parse().ok()?);
                (n > 0 && i >= 1 && i <= n).then_some((i, n))
            };
            let ((a, na), (b, nb)) = (pair(row)?, pair(col)?);
            Some(((a - 1) * nb + b) as f64 / (na * nb) as f64)
        }
        Step::Map => {
            let rest = line.trim_start().strip_prefix("Registering image #")?;
            let open = rest.find('(')?;
            let close = rest[open..].find(')')? + open;
            let k: u64 = rest[open + 1..close].trim().parse().ok()?;
            Some((k as f64 / photos.max(1) as f64).min(1.0))
        }
    }
}

/// Per-photo feature counts from the feature extractor's output: a `Name:` line followed,
/// a few lines later, by its `Features:` line.
#[derive(Debug, Default)]
pub struct FeatureCounts {
    pending: Option<String>,
    pub counts: std::collections::BTreeMap<String, u64>,
}

impl FeatureCounts {
    pub fn feed(&mut self, line: &str) {
        let t = line.trim();
        if let Some(name) = t.strip_prefix("Name:") {
            self.pending = Some(name.trim().to_string());
        } else if let Some(n) = t.strip_prefix("Features:")
            && let (Some(name), Ok(n)) = (self.pending.take(), n.trim().parse::<u64>())
        {
            self.counts.insert(name, n);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Lines as COLMAP 3.8 printed them on nerfpl_tree's photos (2026-11-28).
    #[test]
    fn colmap_lines_become_fractions() {
        assert_eq!(
            fraction(Step::Extract, "Processed file [3/18]", 18),
            Some(3.0 / 18.0)
        );
        assert_eq!(
            fraction(Step::Match, "Matching block [1/1, 1/1] in 10.331s", 18),
            Some(1.0)
        );
        // Second row, first column of a 3 × 3 grid of blocks: 4 of 9 done.
        assert_eq!(
            fraction(Step::Match, "Matching block [2/3, 1/3] in 1.0s", 0),
            Some(4.0 / 9.0)
        );
        assert_eq!(
            fraction(Step::Match, "Matching image [5/18] in 0.000s", 18),
            Some(5.0 / 18.0)
        );
        assert_eq!(
            fraction(Step::Map, "Registering image #17 (9)", 18),
            Some(0.5)
        );
        for noise in [
            "  Features:        1526",
            "Elapsed time: 0.172 [minutes]",
            "Processed file [x/18]",
            "Processed file [19/18]",
            "Matching block [0/1, 1/1]",
            "Initializing with image pair #6 and #9",
            "",
        ] {
            for step in Step::ALL {
                assert_eq!(fraction(step, noise, 18), None, "{step:?} {noise:?}");
            }
        }
        let shares: f64 = Step::ALL.iter().map(|s| s.weight()).sum();
        assert!((shares - 1.0).abs() < 1e-12);
        assert!((Step::Map.start() - 0.75).abs() < 1e-12);
    }

    #[test]
    fn feature_counts_pair_names_with_their_features() {
        let mut f = FeatureCounts::default();
        for l in [
            "Processed file [1/18]",
            "  Name:            20240808_145131.jpg",
            "  Dimensions:      300 x 400",
            "  Camera:          #1 - SIMPLE_RADIAL",
            "  Focal Length:    480.00px",
            "  Features:        1526",
            "Processed file [2/18]",
            "  Name:            sub/b.jpg",
            "  Features:        7",
        ] {
            f.feed(l);
        }
        assert_eq!(f.counts.get("20240808_145131.jpg"), Some(&1526));
        assert_eq!(f.counts.get("sub/b.jpg"), Some(&7));
    }
}
