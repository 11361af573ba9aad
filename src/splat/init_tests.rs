//! Tests of SfM and anchor initialisation.

use super::*;
use crate::splat::camera::Camera;
use crate::splat::model::sigmoid;
use crate::splat::packed_image::PackedImage;

#[test]
fn sfm_scale_is_the_root_mean_square_of_three_neighbour_distances() {
    let pts = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [2.0, 0.0, 0.0],
        [3.0, 0.0, 0.0],
        [3.0, 0.0, 0.0],
    ];
    let cols = [[255, 0, 128]; 5];
    let g = from_sfm_points(&pts, &cols).expect("valid input");
    // Point 0: distances 1, 2, 3 → sqrt(14 / 3).
    assert!((g.log_scales[0][0] - (14.0f32 / 3.0).sqrt().ln()).abs() < 1e-6);
    assert_eq!(g.log_scales[0][0], g.log_scales[0][2]);
    assert_eq!(g.rotations[0], [1.0, 0.0, 0.0, 0.0]);
    assert!((sigmoid(g.opacity_logits[0]) - 0.1).abs() < 1e-6);
    // DC decodes back to the colour: 0.5 + C0 · dc.
    assert!((0.5 + SH_C0 * g.sh[0][0] - 1.0).abs() < 1e-6);
    assert!((0.5 + SH_C0 * g.sh[0][1]).abs() < 1e-6);
    assert!(g.sh[0][3..].iter().all(|&v| v == 0.0));
    assert!(g.is_consistent() && g.trunk_prob.iter().all(|&p| p == 0.0));
}

#[test]
fn sfm_scale_has_a_floor_for_coincident_points() {
    let g = from_sfm_points(&[[1.0; 3]; 4], &[[0; 3]; 4]).expect("valid input");
    assert!((g.log_scales[0][0] as f64 - 0.5 * MIN_DIST2.ln()).abs() < 1e-5);
    assert_eq!(
        from_sfm_points(&[[0.0; 3]], &[]),
        Err(InitError::ColourCountMismatch {
            points: 1,
            colours: 0
        })
    );
}

/// A 64×64 view looking down +z from the origin, filled with one grey level.
fn view(grey: u8) -> View {
    let camera = Camera::look_at(
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        [0.0, -1.0, 0.0],
        64,
        64,
        64.0,
    );
    View {
        name: format!("v{grey}"),
        camera,
        image: PackedImage::filled(64, 64, [grey, grey, grey, 255]).into(),
    }
}

#[test]
fn anchors_take_the_median_colour_of_the_views_that_see_them() {
    let anchors = [
        // Seen by every view.
        Anchor {
            position: [0.0, 0.0, 2.0],
            colour: [1, 2, 3],
            trunk_prob: 0.8,
        },
        // Right behind the first one: occluded, keeps its own colour.
        Anchor {
            position: [0.0, 0.0, 4.0],
            colour: [4, 5, 6],
            trunk_prob: 0.2,
        },
        // Behind the cameras: keeps its own colour.
        Anchor {
            position: [0.3, 0.0, -2.0],
            colour: [7, 8, 9],
            trunk_prob: 0.0,
        },
    ];
    let views = [view(10), view(200), view(30)];
    let params = AnchorInit::default();
    let colours = photometric_colours(&anchors, &views, &params);
    assert_eq!(colours, vec![[30, 30, 30], [4, 5, 6], [7, 8, 9]]);

    let g = from_anchors(&anchors, &views, &params).expect("anchors given");
    assert_eq!(g.trunk_prob, vec![0.8, 0.2, 0.0]);
    // Nearest other anchor of the first is 2 m away.
    assert!((g.log_scales[0][0] as f64 - 0.5 * (4.0 + params.eps).ln()).abs() < 1e-6);
    assert!((0.5 + SH_C0 * g.sh[0][0] - 30.0 / 255.0).abs() < 1e-6);
}

#[test]
fn anchor_samples_are_bounded_by_reservoir_sampling() {
    let anchors = [Anchor {
        position: [0.0, 0.0, 2.0],
        colour: [0; 3],
        trunk_prob: 0.0,
    }];
    let views: Vec<View> = (0..40).map(|i| view(100 + i as u8)).collect();
    let params = AnchorInit {
        max_samples: 5,
        ..AnchorInit::default()
    };
    let c = photometric_colours(&anchors, &views, &params)[0][0];
    assert!(
        (100..140).contains(&c),
        "median of a sample of 100..140 is in range: {c}"
    );
}

#[test]
fn the_sky_dome_covers_the_sphere_evenly_and_takes_the_colour_seen_past_the_scene() {
    // Evenly: every point on the sphere, and the largest gap about the lattice spacing.
    let dome = sky_dome([1.0, 2.0, 3.0], 10.0, 500);
    assert_eq!(dome.len(), 500);
    let spacing = 10.0 * (4.0 * std::f32::consts::PI / 500.0).sqrt();
    for p in &dome {
        let r = glam::Vec3::from_array(*p).distance(glam::Vec3::new(1.0, 2.0, 3.0));
        assert!((r - 10.0).abs() < 1e-4, "{r}");
    }
    let mut rng = SplitMix64::new(5);
    for _ in 0..200 {
        // A random direction: its nearest dome point is within a spacing.
        let d = glam::Vec3::new(
            rng.normal() as f32,
            rng.normal() as f32,
            rng.normal() as f32,
        )
        .normalize();
        let q = glam::Vec3::new(1.0, 2.0, 3.0) + d * 10.0;
        let near = dome
            .iter()
            .map(|p| glam::Vec3::from_array(*p).distance(q))
            .fold(f32::INFINITY, f32::min);
        assert!(
            near < spacing,
            "{near} m from the dome, spacing {spacing} m"
        );
    }
    // Past a scene of one Gaussian in front of the camera, the dome takes the views' colour.
    let mut g = Gaussians::default();
    g.push(seed_gaussian([0.0, 0.0, 2.0], 0.1f32.ln(), [9, 9, 9], 0.9));
    let views = [view(200), view(180), view(190)];
    add_sky(&mut g, &views, 400);
    assert_eq!(g.len(), 401);
    assert!(g.trunk_prob[1..].iter().all(|&p| p == BACKGROUND_PROB));
    let seen: Vec<usize> = (1..g.len())
        .filter(|&i| (0.5 + SH_C0 * g.sh[i][0] - 190.0 / 255.0).abs() < 1e-6)
        .collect();
    assert!(!seen.is_empty(), "no dome Gaussian took the median colour");
    // Those unseen (behind the cameras) are grey; all are as wide as their spacing.
    let radius = glam::Vec3::from_array(g.means[1]).length();
    let width = radius * (4.0 * std::f32::consts::PI / 400.0).sqrt();
    assert!(
        g.log_scales[1..]
            .iter()
            .all(|s| (s[0] - width.ln()).abs() < 1e-5)
    );
}

/// With a fallback depth, every cell of a photo that no Gaussian projects into gets one, at the depth of what the
/// photo sees, coloured by the cell; a second photo of the same hole adds nothing.
#[test]
fn uncovered_cells_are_filled_once_at_the_depth_of_the_scene() {
    let mut g = from_sfm_points(&[[0.1, 0.1, 3.0]], &[[10, 20, 30]]).expect("one point");
    // The default leaves a flat grey photo's cells alone: the photos agree on no depth.
    let mut unfilled = g.clone();
    let cells = CoverageFill {
        cells_long_side: 4,
        ..CoverageFill::default()
    };
    let skipped = fill_uncovered(&mut unfilled, &[view(90), view(90)], &cells);
    // Each photo finds the same 15 cells uncovered, none filled.
    assert_eq!((skipped.added, skipped.ambiguous), (0, 30));
    let params = CoverageFill {
        depth_percentile: Some(0.9),
        ..cells
    };
    let report = fill_uncovered(&mut g, &[view(90), view(90)], &params);
    // 4 × 4 cells of 16 px, one covered by the point; a flat grey photo agrees on no depth.
    assert_eq!(
        report,
        FillReport {
            added: 15,
            agreed: 0,
            unseen: 0,
            ambiguous: 0
        }
    );
    assert_eq!(g.len(), 16);
    for i in 1..g.len() {
        assert!(
            (g.means[i][2] - 3.0).abs() < 1e-4,
            "depth {}",
            g.means[i][2]
        );
        let grey = 0.5 + SH_C0 * g.sh[i][0];
        assert!((grey - 90.0 / 255.0).abs() < 1e-3);
        // σ = half a 16 px cell at 3 m with f = 64 px.
        assert!((g.log_scales[i][0] - (0.5f32 * 16.0 * 3.0 / 64.0).ln()).abs() < 1e-5);
    }
    // A photo that sees no Gaussian adds nothing (no depth to place a fill at).
    let mut empty = from_sfm_points(&[[0.0, 0.0, -3.0]], &[[0; 3]]).expect("one point");
    assert_eq!(fill_uncovered(&mut empty, &[view(90)], &params).added, 0);
}

/// A textured plane at 5 m (0.3 m squares of random grey) seen by `n` 64×64 cameras in a row
/// along x, 0.5 m apart, looking down +z from z = 0 (f = 64 px).
fn plane_views(n: usize) -> Vec<View> {
    plane_views_with(n, &squares)
}

/// Grey level of the random 0.3 m squares at (`x`, `y`) on the plane.
fn squares(x: f32, y: f32) -> u8 {
    let (i, j) = ((x / 0.3).floor() as i64, (y / 0.3).floor() as i64);
    let mut rng = SplitMix64::new((i * 7919 + j * 104_729) as u64);
    (rng.below(200) + 30) as u8
}

/// [`plane_views`] with the plane's grey level given by `texture` (metres on the plane).
fn plane_views_with(n: usize, texture: &dyn Fn(f32, f32) -> u8) -> Vec<View> {
    (0..n)
        .map(|k| {
            let x0 = 0.5 * k as f32;
            let camera = Camera::look_at(
                [x0, 0.0, 0.0],
                [x0, 0.0, 1.0],
                [0.0, -1.0, 0.0],
                64,
                64,
                64.0,
            );
            let mut image = PackedImage::filled(64, 64, [0, 0, 0, 255]);
            for y in 0..64u32 {
                for x in 0..64u32 {
                    // The ray through the pixel's centre meets z = 5 at these coordinates.
                    let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
                    let (wx, wy) = (
                        x0 + (px - camera.cx) / camera.fx * 5.0,
                        (py - camera.cy) / camera.fy * 5.0,
                    );
                    let v = texture(wx, -wy);
                    image.pixels[(y * 64 + x) as usize] =
                        crate::splat::packed_image::pack([v, v, v, 255]);
                }
            }
            View {
                name: format!("p{k}"),
                camera,
                image: image.into(),
            }
        })
        .collect()
}

/// The SfM start of the plane scenes: a far wall at 10 m and a few near points at 4 m, none on
/// the plane at 5 m.
fn wall_and_near_points() -> Gaussians {
    let mut pts = Vec::new();
    for k in 0..80 {
        pts.push([-3.0 + 0.05 * k as f32, -4.5, 10.0]);
    }
    for k in 0..20 {
        pts.push([-1.2 + 0.02 * k as f32, -1.9, 4.0]);
    }
    let cols = vec![[128u8; 3]; pts.len()];
    from_sfm_points(&pts, &cols).expect("points")
}

/// A plane whose left part is a smooth ramp, as sky is, and whose right part is textured: with
/// `textured` the ramp's cells are left alone, though at some depths their neighbours' patches cross onto
/// the texture and at others stay on the ramp (a clear minimum of the cost that is no depth),
/// while the textured cells still go to the plane.
#[test]
fn a_textureless_cell_beside_texture_gets_no_depth() {
    let edge = 1.0;
    let sky = move |x: f32, y: f32| {
        if x < edge {
            (140.0 + 4.0 * x + 2.0 * y).round().clamp(0.0, 255.0) as u8
        } else {
            squares(x, y)
        }
    };
    let views = plane_views_with(4, &sky);
    let start = wall_and_near_points();
    let params = CoverageFill {
        cells_long_side: 8,
        textured: true,
        ..CoverageFill::default()
    };
    // The default rule places ramp cells: a minimum of the cost, at no depth.
    let mut plain = start.clone();
    fill_uncovered(
        &mut plain,
        &views,
        &CoverageFill {
            textured: false,
            ..params
        },
    );
    assert!(
        plain.means[start.len()..]
            .iter()
            .any(|m| m[0] < edge - 0.35),
        "the rule without texture placed no ramp cell"
    );
    let mut g = start.clone();
    let report = fill_uncovered(&mut g, &views, &params);
    assert!(report.ambiguous > 0, "{report:?}");
    assert!(report.agreed > 10, "{report:?}");
    let fills = &g.means[start.len()..];
    // Every cell placed lies on the plane, and on its textured part (the ramp's σ-wide cells
    // reach at most half a cell, 0.3 m, past the edge).
    for m in fills {
        assert!((m[2] - 5.0).abs() < 0.4, "a fill at {m:?}: {report:?}");
        assert!(
            m[0] > edge - 0.35,
            "a fill on the ramp at {m:?}: {report:?}"
        );
    }
}

/// Where SfM saw only a far wall (10 m) and a few near points (4 m), a textured surface at
/// 5 m that no point covers is placed at 5 m by agreement between the photos, not at the
/// 90th-percentile depth (10 m) that the rule before put it at.
#[test]
fn uncovered_texture_goes_to_the_depth_the_photos_agree_on() {
    let views = plane_views(4);
    let start = wall_and_near_points();
    let params = CoverageFill {
        cells_long_side: 8,
        depth_percentile: Some(0.9),
        ..CoverageFill::default()
    };
    let mut g = start.clone();
    let report = fill_uncovered(&mut g, &views, &params);
    assert!(report.added > 40, "{report:?}");
    // The first photo's leftmost cells are seen by no other photo: those are left out.
    assert!(
        report.agreed as f64 >= 0.75 * report.added as f64,
        "only {report:?} agreed"
    );
    assert!(report.unseen > 0, "{report:?}");
    // Every agreed depth within 0.4 m of the plane (one candidate is 0.3 m apart at 5 m);
    // the rest at the fallback depth.
    let depths: Vec<f32> = g.means[start.len()..].iter().map(|m| m[2]).collect();
    let at_plane = depths.iter().filter(|&&z| (z - 5.0).abs() < 0.4).count();
    let at_fallback = depths.iter().filter(|&&z| (z - 10.0).abs() < 1e-3).count();
    assert_eq!(at_plane, report.agreed, "{depths:?}");
    assert_eq!(at_plane + at_fallback, depths.len(), "{depths:?}");
    // With `place_unseen`, the cells no other photo sees go to the fallback depth too.
    let mut all = start.clone();
    let placing = CoverageFill {
        place_unseen: true,
        ..params
    };
    let every = fill_uncovered(&mut all, &views, &placing);
    assert_eq!(every.unseen, 0);
    assert!(every.added > report.added, "{every:?} against {report:?}");
    // With no fallback depth, only the cells the photos agree on are filled.
    let mut agreed_only = start.clone();
    let no_fallback = CoverageFill {
        depth_percentile: None,
        ..params
    };
    let only = fill_uncovered(&mut agreed_only, &views, &no_fallback);
    assert_eq!(only.added, only.agreed);
    assert!(only.agreed > 40, "{only:?}");
    assert!(
        agreed_only.means[start.len()..]
            .iter()
            .all(|m| (m[2] - 5.0).abs() < 0.4)
    );
    // Without the sweep every cell goes to the fallback depth.
    let mut old = start.clone();
    let rule_before = CoverageFill {
        depth_candidates: 0,
        ..params
    };
    let before = fill_uncovered(&mut old, &views, &rule_before);
    assert_eq!((before.agreed, before.unseen), (0, 0));
    assert!(
        old.means[start.len()..]
            .iter()
            .all(|m| (m[2] - 10.0).abs() < 1e-3)
    );
}
