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
        image: PackedImage::filled(64, 64, [grey, grey, grey, 255]),
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

/// Every cell of a photo that no Gaussian projects into gets one, at the depth of what the
/// photo sees, coloured by the cell; a second photo of the same hole adds nothing.
#[test]
fn uncovered_cells_are_filled_once_at_the_depth_of_the_scene() {
    let mut g = from_sfm_points(&[[0.1, 0.1, 3.0]], &[[10, 20, 30]]).expect("one point");
    let params = CoverageFill {
        cells_long_side: 4,
        depth_percentile: 0.9,
    };
    let added = fill_uncovered(&mut g, &[view(90), view(90)], &params);
    // 4 × 4 cells of 16 px, one covered by the point.
    assert_eq!(added, 15);
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
    assert_eq!(fill_uncovered(&mut empty, &[view(90)], &params), 0);
}
