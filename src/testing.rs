//! Test support shared by the unit and integration tests: how a test that needs something the
//! machine lacks (a GPU adapter, Chromium, PostgreSQL, the real clouds, …) stops; and the
//! process's peak memory that the benchmarks (`sylva bench`, `examples/`) report.
//!
//! By default it prints why and passes, so `scripts/test` works on any machine. Where the
//! environment variable `SYLVA_TEST_REQUIRE` names the capability (a comma-separated list, or
//! `all`), the test fails instead: CI sets it for everything its machine installs, so a CI
//! machine that silently lost lavapipe or PostgreSQL goes red rather than green.

#[doc(hidden)]
pub mod postgres;

/// Capabilities tests may need, as `SYLVA_TEST_REQUIRE` names them.
pub const CAPABILITIES: &[&str] = &[
    "gpu",
    "browser",
    "postgres",
    "s3",
    "schemathesis",
    "gdal",
    "real-data",
    "pypi",
    "colmap",
    "mount",
    "gltf-validator",
    "cesium",
    "python",
    "lpips",
];

/// Whether `SYLVA_TEST_REQUIRE` (its value `required`) asks for `capability`.
pub fn is_required(required: &str, capability: &str) -> bool {
    required
        .split(',')
        .map(str::trim)
        .any(|c| c == "all" || c == capability)
}

/// A test cannot run for want of `capability`: prints `why` and returns (the caller then
/// returns too), or panics when `SYLVA_TEST_REQUIRE` requires the capability.
pub fn skip(capability: &str, why: &str) {
    skip_with(
        &std::env::var("SYLVA_TEST_REQUIRE").unwrap_or_default(),
        capability,
        why,
    );
}

/// [`skip`] with the value of `SYLVA_TEST_REQUIRE` given.
pub fn skip_with(required: &str, capability: &str, why: &str) {
    if is_required(required, capability) {
        panic!("{capability} is required (SYLVA_TEST_REQUIRE={required}) but missing: {why}");
    }
    eprintln!("skipping ({capability} missing): {why}");
}

/// The real photo set `rel` (a folder such as `nerfpl_tree/tree`) for the real-photo tests: the
/// first of `$SYLVA_REAL_DATA/real_photos`, `$SYLVA_REAL_DATA/../real_photos` (the variable
/// may name the data folder or its `real/` clouds) and `../shared/data/real_photos` beside the
/// crate that holds it. `None`, after printing why ([`skip`], capability `real-data`), when
/// none does.
pub fn real_photos(rel: &str) -> Option<std::path::PathBuf> {
    use std::path::{Path, PathBuf};
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    let from_env = std::env::var_os("SYLVA_REAL_DATA")
        .map(PathBuf::from)
        .into_iter()
        .flat_map(|d| [d.join("real_photos"), d.join("../real_photos")]);
    let mut looked = Vec::new();
    for dir in from_env.chain([manifest.join("../shared/data/real_photos")]) {
        let path = dir.join(rel);
        if path.is_dir() {
            return Some(path);
        }
        looked.push(dir.display().to_string());
    }
    skip(
        "real-data",
        &format!(
            "{rel} is in none of {} (set SYLVA_REAL_DATA)",
            looked.join(", ")
        ),
    );
    None
}

/// Peak resident memory of this process so far, MiB (Linux `VmHWM` from /proc/self/status; 0
/// where unknown).
pub fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

/// A cheap deterministic source of test coordinates: uniform in [-0.5, 0.5) from a 64-bit linear
/// congruential generator (Knuth's MMIX constants) seeded with `seed`, its top 24 bits per draw.
pub fn centred_unit(seed: u64) -> impl FnMut() -> f32 {
    let mut state = seed;
    move || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn required_capabilities_are_named_or_all() {
        assert!(is_required("gpu, postgres", "postgres"));
        assert!(is_required("all", "browser"));
        assert!(!is_required("gpu", "browser"));
        assert!(!is_required("", "gpu"));
        assert!(CAPABILITIES.contains(&"real-data"));
    }

    #[test]
    #[should_panic(expected = "gpu is required")]
    fn a_required_capability_fails_the_test() {
        skip_with("postgres,gpu", "gpu", "no adapter");
    }

    #[test]
    fn a_capability_not_required_only_prints() {
        skip_with("postgres", "gpu", "no adapter");
    }
}
