//! ICP tests on a structured synthetic plot: rolling ground plus a few stems.

use super::*;
use crate::geom::{Normals, estimate_normals};
use crate::progress::{Cancelled, NoProgress};
use glam::{DMat3, DQuat};
use rand::{RngExt, SeedableRng, rngs::ChaCha8Rng};

const STEMS: [(f32, f32, f32); 5] = [
    (2.0, 3.0, 0.15),
    (7.5, 2.5, 0.25),
    (4.0, 8.0, 0.2),
    (9.0, 9.5, 0.3),
    (1.5, 10.0, 0.12),
];

fn ground_z(x: f32, y: f32) -> f32 {
    0.3 * (x / 3.0).sin() * (y / 4.0).cos() + 0.05 * x
}

/// Points on the scene surfaces within x in [x0, x1), y in [0, 12).
fn scene(rng: &mut ChaCha8Rng, x0: f32, x1: f32, ground: usize, per_stem: usize) -> Vec<Vec3> {
    let mut pts = Vec::with_capacity(ground + 5 * per_stem);
    for _ in 0..ground {
        let (x, y) = (rng.random_range(x0..x1), rng.random_range(0.0..12.0));
        pts.push(Vec3::new(x, y, ground_z(x, y)));
    }
    for &(cx, cy, r) in &STEMS {
        if cx < x0 || cx >= x1 {
            continue;
        }
        for _ in 0..per_stem {
            let a = rng.random_range(0.0..std::f32::consts::TAU);
            let h = rng.random_range(0.0..6.0);
            pts.push(Vec3::new(
                cx + r * a.cos(),
                cy + r * a.sin(),
                ground_z(cx, cy) + h,
            ));
        }
    }
    pts
}

fn truth(scale: f64) -> Similarity {
    Similarity {
        scale,
        rotation: DMat3::from_euler(
            glam::EulerRot::ZYX,
            0.8f64.to_radians(),
            0.4f64.to_radians(),
            -0.3f64.to_radians(),
        ),
        translation: DVec3::new(0.08, -0.06, 0.05),
    }
}

/// Source in the "SfM frame": scene points mapped by the inverse of `truth`, 20% of them
/// replaced by uniform outliers in the plot's volume, plus `noise` metres of jitter.
fn source_from(
    scene_pts: &[Vec3],
    truth: &Similarity,
    rng: &mut ChaCha8Rng,
    noise: f32,
) -> Vec<Vec3> {
    let inv = truth.inverse();
    scene_pts
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let p = if i % 5 == 0 {
                Vec3::new(
                    rng.random_range(0.0..14.0),
                    rng.random_range(0.0..12.0),
                    rng.random_range(-1.0..8.0),
                )
            } else {
                *p + Vec3::new(
                    rng.random_range(-noise..noise),
                    rng.random_range(-noise..noise),
                    rng.random_range(-noise..noise),
                )
            };
            inv.apply_f32(p)
        })
        .collect()
}

/// Point-to-plane-capable ICP of `source` onto `target` with its `normals`, without progress.
fn icp_on(
    source: &[Vec3],
    target: &[Vec3],
    normals: &Normals,
    initial: &Similarity,
    params: &IcpParams,
) -> IcpResult {
    icp(
        source,
        target,
        Some(&normals.normals),
        initial,
        params,
        &NoProgress,
    )
    .unwrap()
}

fn assert_close(got: &IcpResult, want: &Similarity, what: &str) {
    let dr = DQuat::from_mat3(&(got.rotation * want.rotation.transpose()));
    let angle = dr.angle_between(DQuat::IDENTITY).to_degrees();
    let dt = (got.translation - want.translation).length();
    let ds = (got.scale / want.scale - 1.0).abs();
    assert!(
        angle < 0.05 && dt < 1e-3 && ds < 1e-3,
        "{what}: rotation error {angle}°, translation {dt} m, scale {ds}; {got:?}"
    );
}

#[test]
fn point_to_point_recovers_similarity_with_partial_overlap_and_outliers() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let target = scene(&mut rng, 0.0, 12.0, 80_000, 12_000);
    // Source: a subset of the target's own points (as SfM points on LiDAR-seen surfaces),
    // only from x in [0, 9), i.e. partial overlap of the plot.
    let sub: Vec<Vec3> = target
        .iter()
        .copied()
        .filter(|p| p.x < 9.0)
        .step_by(4)
        .collect();
    for scale in [1.0, 1.005] {
        let t = truth(scale);
        let source = source_from(&sub, &t, &mut rng, 0.0002);
        let params = IcpParams {
            estimate_scale: scale != 1.0,
            ..IcpParams::default()
        };
        let res = icp(
            &source,
            &target,
            None,
            &Similarity::IDENTITY,
            &params,
            &NoProgress,
        )
        .unwrap();
        assert!(res.converged, "{res:?}");
        assert_close(&res, &t, "point-to-point");
        assert!(
            res.fitness > 0.75 && res.fitness < 0.9,
            "fitness {}",
            res.fitness
        );
    }
}

#[test]
fn point_to_plane_recovers_similarity_from_independent_samples() {
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let target = scene(&mut rng, 0.0, 12.0, 100_000, 20_000);
    // Independent samples of the same surfaces, a partly different region (x in [3, 14):
    // the part beyond x = 12 has no target).
    let sub = scene(&mut rng, 3.0, 14.0, 15_000, 3_000);
    let normals = estimate_normals(&target, &NormalParams::default(), &NoProgress).unwrap();
    for (scale, robust) in [
        (1.0, RobustKernel::Trimmed { keep_fraction: 0.7 }),
        (0.97, RobustKernel::Huber { scale: 0.01 }),
    ] {
        let t = truth(scale);
        let source = source_from(&sub, &t, &mut rng, 0.0005);
        let params = IcpParams {
            method: IcpMethod::PointToPlane,
            estimate_scale: scale != 1.0,
            robust,
            min_distance: 0.03,
            ..IcpParams::default()
        };
        let res = icp_on(&source, &target, &normals, &Similarity::IDENTITY, &params);
        assert_close(&res, &t, &format!("point-to-plane {robust:?}"));
        assert!(res.inlier_rmse < 0.02, "{res:?}");
    }
}

#[test]
fn target_weights_keep_a_surface_seen_differently_from_biasing_the_fit() {
    // The source sees the ground and stems where the target does, plus a "canopy" layer that
    // the target holds 8 cm lower (the scanner sees the crown from below, the UAV from
    // above). Without prior weights the canopy drags the fit down; with the canopy's target
    // points weighted 0 the fit is exact.
    let mut rng = ChaCha8Rng::seed_from_u64(24);
    let mut target = scene(&mut rng, 0.0, 12.0, 60_000, 10_000);
    let mut sub = scene(&mut rng, 0.0, 12.0, 12_000, 2_000);
    let canopy = |rng: &mut ChaCha8Rng, n: usize, dz: f32| -> Vec<Vec3> {
        (0..n)
            .map(|_| {
                let (x, y) = (rng.random_range(0.0..12.0), rng.random_range(0.0..12.0));
                Vec3::new(x, y, 7.0 + dz)
            })
            .collect()
    };
    let ground_and_stems = target.len();
    target.extend(canopy(&mut rng, 60_000, -0.08));
    sub.extend(canopy(&mut rng, 12_000, 0.0));
    let normals = estimate_normals(&target, &NormalParams::default(), &NoProgress).unwrap();
    let index = PointIndex::new(&target).unwrap();
    let prior: Vec<f32> = (0..target.len())
        .map(|i| if i < ground_and_stems { 1.0 } else { 0.0 })
        .collect();
    let t = truth(1.002);
    let inv = t.inverse();
    let source: Vec<Vec3> = sub.iter().map(|p| inv.apply_f32(*p)).collect();
    let params = IcpParams {
        method: IcpMethod::PointToPlane,
        robust: RobustKernel::Huber { scale: 0.02 },
        start_distance: 0.3,
        min_distance: 0.1,
        ..IcpParams::default()
    };
    let fit = |w: IcpWeights<'_>| {
        icp_weighted(
            &source,
            &target,
            Some(&index),
            Some(&normals.normals),
            w,
            &Similarity::IDENTITY,
            &params,
            &NoProgress,
        )
    };
    let run = |target_w: Option<&[f32]>| {
        fit(IcpWeights {
            source: None,
            target: target_w,
        })
        .unwrap()
    };
    let plain = run(None);
    let dz = (plain.translation - t.translation).length() + (plain.scale / t.scale - 1.0).abs();
    assert!(
        dz > 2e-3,
        "the canopy should bias the unweighted fit: {plain:?}"
    );
    assert_close(&run(Some(&prior)), &t, "weighted point-to-plane");
    // Weights outside [0, 1] or of the wrong length are refused.
    let bad = vec![2.0f32; target.len()];
    let r = fit(IcpWeights {
        source: None,
        target: Some(&bad),
    });
    assert!(matches!(r, Err(GeomError::InvalidParameter(_))));
    let short = [1.0f32; 3];
    let r = fit(IcpWeights {
        source: Some(&short),
        target: None,
    });
    assert!(matches!(r, Err(GeomError::LengthMismatch { .. })));
}

#[test]
fn a_fixed_rotation_refines_translation_only() {
    let mut rng = ChaCha8Rng::seed_from_u64(25);
    let target = scene(&mut rng, 0.0, 12.0, 60_000, 10_000);
    let sub = scene(&mut rng, 0.0, 12.0, 12_000, 2_000);
    let normals = estimate_normals(&target, &NormalParams::default(), &NoProgress).unwrap();
    let t = truth(1.0);
    let inv = t.inverse();
    let source: Vec<Vec3> = sub.iter().map(|p| inv.apply_f32(*p)).collect();
    // Start from the true rotation with the translation off by several centimetres.
    let initial = Similarity {
        translation: t.translation + DVec3::new(0.04, -0.05, 0.03),
        ..t
    };
    let params = IcpParams {
        method: IcpMethod::PointToPlane,
        estimate_scale: false,
        estimate_rotation: false,
        start_distance: 0.3,
        min_distance: 0.1,
        robust: RobustKernel::Huber { scale: 0.02 },
        ..IcpParams::default()
    };
    let res = icp_on(&source, &target, &normals, &initial, &params);
    assert_eq!(res.rotation, t.rotation, "the rotation must not move");
    assert_close(&res, &t, "translation-only point-to-plane");
    // Point-to-point has no translation-only step.
    let p2p = IcpParams {
        method: IcpMethod::PointToPoint,
        ..params
    };
    assert!(matches!(
        icp(&source, &target, None, &initial, &p2p, &NoProgress),
        Err(GeomError::InvalidParameter(_))
    ));
}

#[test]
fn icp_stops_on_cancel_and_rejects_bad_input() {
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    let target = scene(&mut rng, 0.0, 12.0, 2_000, 200);
    let p = IcpParams::default();
    let id = Similarity::IDENTITY;
    assert_eq!(
        icp(&target, &target, None, &id, &p, &Cancelled).unwrap_err(),
        GeomError::Cancelled
    );
    let bad = IcpParams { shrink: 0.0, ..p };
    assert!(matches!(
        icp(&target, &target, None, &id, &bad, &NoProgress),
        Err(GeomError::InvalidParameter(_))
    ));
    let far: Vec<Vec3> = target.iter().map(|v| *v + Vec3::splat(100.0)).collect();
    assert!(matches!(
        icp(&far, &target, None, &id, &p, &NoProgress),
        Err(GeomError::Empty(_))
    ));
    // Identical clouds: exact identity, full fitness.
    let res = icp(&target, &target, None, &id, &p, &NoProgress).unwrap();
    assert!(
        res.fitness == 1.0 && res.inlier_rmse < 1e-9 && res.converged,
        "{res:?}"
    );
}

/// The cached search answers exactly what a brute-force search does while a query wanders
/// by sub-millimetre steps (cache hits), centimetre steps and jumps (refills), also where
/// no target point lies within the max distance.
#[test]
fn cached_neighbours_answer_exactly_as_brute_force() {
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    let target = scene(&mut rng, 0.0, 12.0, 20_000, 2_000);
    let search = Search {
        target: &target,
        normals: &[],
        index: None,
        lazy: OnceLock::new(),
        grid: ColumnGrid::new(&target),
    };
    let (mut hits, mut total) = (0, 0);
    for walk in 0..60 {
        let mut slot = Slot::default();
        let mut scratch = Knn::default();
        // Mostly near the surface; every fourth walk starts 0.4 m above it.
        let lift = if walk % 4 == 3 { 0.4 } else { 0.005 };
        let mut q = target[rng.random_range(0..target.len())] + Vec3::new(0.0, 0.0, lift);
        let max_d = [0.05f32, 0.2, 1.0][walk % 3];
        let max_d2 = max_d * max_d;
        for step in 0..40 {
            let size = match step % 10 {
                9 => 0.5,
                6..=8 => 0.02,
                _ => 0.0005,
            };
            q += Vec3::new(
                rng.random_range(-size..size),
                rng.random_range(-size..size),
                rng.random_range(-size..size),
            );
            let cached = slot.clear > 0.0;
            let anchor = slot.anchor;
            let got = search.nearest_cached(q, max_d2, [NONE, NONE], &mut slot, &mut scratch);
            let want = grid::tests::brute(&target, q, max_d2);
            match (got, want) {
                (None, None) => {}
                (Some((m, pos)), Some(w)) => {
                    assert_eq!(pos, target[m.index as usize]);
                    let e = pos - q;
                    assert!((e.length_squared() - w).abs() <= 1e-9, "{m:?} vs {w}");
                }
                _ => panic!("walk {walk} step {step}: got {got:?}, want {want:?}"),
            }
            // The first small steps near the surface: answered from the cache (the anchor
            // stays).
            if step < 6 && lift < 0.1 && cached {
                total += 1;
                hits += usize::from(slot.anchor == anchor);
            }
        }
    }
    assert!(hits * 10 > total * 8, "{hits} cache answers of {total}");
}

/// A source past [`COARSE_MIN_SOURCE`] points converges on its subsample first, then on all
/// points, to the truth.
#[test]
fn large_sources_refine_a_subsample_then_all_points() {
    struct Log(std::sync::Mutex<Vec<String>>);
    impl Progress for Log {
        fn set(&self, _: f64) {}
        fn log(&self, m: &str) {
            if let Ok(mut l) = self.0.lock() {
                l.push(m.to_string());
            }
        }
    }
    let mut rng = ChaCha8Rng::seed_from_u64(32);
    let target = scene(&mut rng, 0.0, 12.0, 100_000, 20_000);
    let sub = scene(&mut rng, 3.0, 14.0, 60_000, 3_000);
    assert!(sub.len() >= COARSE_MIN_SOURCE);
    let normals = estimate_normals(&target, &NormalParams::default(), &NoProgress).unwrap();
    let t = truth(1.01);
    let source = source_from(&sub, &t, &mut rng, 0.0005);
    let params = IcpParams {
        method: IcpMethod::PointToPlane,
        robust: RobustKernel::Trimmed { keep_fraction: 0.7 },
        min_distance: 0.03,
        ..IcpParams::default()
    };
    let log = Log(std::sync::Mutex::new(Vec::new()));
    let res = icp(
        &source,
        &target,
        Some(&normals.normals),
        &Similarity::IDENTITY,
        &params,
        &log,
    )
    .unwrap();
    assert_close(&res, &t, "point-to-plane, large source");
    assert!(res.inlier_rmse < 0.02, "{res:?}");
    let lines = log.0.lock().map(|l| l.clone()).unwrap_or_default();
    let n_coarse = sub.len().div_ceil(COARSE_STRIDE);
    let coarse = format!("on {n_coarse} of the {}", sub.len());
    assert!(lines.iter().any(|l| l.contains(&coarse)), "{lines:?}");
    // The last iteration ran on all points: more correspondences than the subsample has.
    let last = lines
        .iter()
        .rev()
        .find(|l| l.starts_with("ICP iteration"))
        .and_then(|l| l.split(", ").nth(1))
        .and_then(|c| c.split(' ').next())
        .and_then(|c| c.parse::<usize>().ok());
    assert!(last.is_some_and(|n| n > 2 * n_coarse), "{lines:?}");
}

/// Point-to-plane with scale on noisy ground alone, started at the truth: the scale column
/// measured with each source point's own offset along the normal prefers to shrink the noise
/// with the points (see `plane.rs`): -1.9 % here. With the foot's lever arm: +0.097 % here,
/// -0.23 to +0.10 % over seeds 31-36 (spread 0.13 %); asserted within 0.5 %.
#[test]
fn point_to_plane_scale_is_not_biased_by_the_source_noise() {
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    let target = scene(&mut rng, 0.0, 12.0, 150_000, 0);
    let normals = estimate_normals(&target, &NormalParams::default(), &NoProgress).unwrap();
    let t = truth(1.0);
    let inv = t.inverse();
    let noise = 0.02;
    let source: Vec<Vec3> = scene(&mut rng, 0.5, 11.5, 8_000, 0)
        .iter()
        .map(|p| {
            let jitter = Vec3::new(
                rng.random_range(-noise..noise),
                rng.random_range(-noise..noise),
                rng.random_range(-noise..noise),
            );
            inv.apply_f32(*p + jitter)
        })
        .collect();
    let params = IcpParams {
        method: IcpMethod::PointToPlane,
        estimate_scale: true,
        start_distance: 0.1,
        min_distance: 0.1,
        robust: RobustKernel::Huber { scale: 0.05 },
        ..IcpParams::default()
    };
    let res = icp_on(&source, &target, &normals, &t, &params);
    let ds = res.scale / t.scale - 1.0;
    println!("scale error {:.4} %", ds * 100.0);
    assert!(ds.abs() < 5e-3, "scale error {ds}; {res:?}");
}
