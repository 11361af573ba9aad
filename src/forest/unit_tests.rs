//! Unit tests of the small parts: circle fits, k-means, outputs and the field comparison.

use super::circle::{arc_coverage, refine_circle_geometric};
use super::kmeans::{kmeans, standardise};
use super::*;
use crate::io::crs::CrsRecord;
use crate::io::tables::FieldTree;
use crate::progress::NoProgress;
use crate::rng::SplitMix64;

fn ring(c: [f64; 2], r: f64, from_deg: f64, to_deg: f64, n: usize, noise: f64) -> Vec<[f64; 2]> {
    let mut rng = SplitMix64::new(3);
    (0..n)
        .map(|i| {
            let a = (from_deg + (to_deg - from_deg) * i as f64 / n as f64).to_radians();
            let rr = r + noise * (rng.uniform() - 0.5) * 2.0;
            [c[0] + rr * a.cos(), c[1] + rr * a.sin()]
        })
        .collect()
}

#[test]
fn weighted_algebraic_fit_recovers_an_exact_circle() {
    let pts = ring([3.0, -2.0], 0.15, 0.0, 360.0, 50, 0.0);
    let fit = fit_circle_weighted(&pts, None).expect("fit");
    assert!((fit.center[0] - 3.0).abs() < 1e-9 && (fit.center[1] + 2.0).abs() < 1e-9);
    assert!((fit.radius - 0.15).abs() < 1e-9 && fit.rms < 1e-9 && fit.n == 50);
    // Zero weights leave points out; a far outlier with weight 0 changes nothing.
    let mut with_outlier = pts.clone();
    with_outlier.push([10.0, 10.0]);
    let mut w = vec![1.0; 50];
    w.push(0.0);
    let fit2 = fit_circle_weighted(&with_outlier, Some(&w)).expect("fit");
    assert!((fit2.radius - 0.15).abs() < 1e-9 && fit2.n == 50);
}

#[test]
fn degenerate_inputs_give_no_circle() {
    assert!(fit_circle_weighted(&[[0.0, 0.0], [1.0, 1.0]], None).is_none());
    let line: Vec<[f64; 2]> = (0..10).map(|i| [i as f64, 2.0 * i as f64]).collect();
    assert!(fit_circle_weighted(&line, None).is_none());
    assert!(fit_circle_weighted(&line, Some(&[1.0; 3])).is_none());
    assert!(fit_circle_weighted(&[[0.0, f64::NAN], [1.0, 0.0], [0.0, 1.0]], None).is_none());
    assert!(fit_circle_robust(&line, &CircleParams::default()).is_none());
}

#[test]
fn gauss_newton_removes_the_algebraic_bias_on_a_noisy_partial_arc() {
    let pts = ring([0.0, 0.0], 0.1, 0.0, 90.0, 200, 0.01);
    let alg = fit_circle_weighted(&pts, None).expect("fit");
    let (geo, converged) = refine_circle_geometric(&pts, None, &alg, 50);
    assert!(converged);
    assert!(geo.rms <= alg.rms + 1e-12);
    assert!((geo.radius - 0.1).abs() <= (alg.radius - 0.1).abs() + 1e-9);
    assert!((geo.radius - 0.1).abs() < 0.01, "{geo:?}");
}

#[test]
fn ransac_ignores_gross_outliers_and_reports_quality() {
    let mut pts = ring([1.0, 1.0], 0.2, 0.0, 360.0, 120, 0.004);
    let mut rng = SplitMix64::new(9);
    for _ in 0..80 {
        pts.push([1.0 + rng.uniform() - 0.5, 1.0 + rng.uniform() - 0.5]);
    }
    let fit = fit_circle_robust(&pts, &CircleParams::default()).expect("fit");
    assert!((fit.fit.radius - 0.2).abs() < 0.003, "{fit:?}");
    assert!(fit.arc_coverage > 0.95 && !fit.partial_arc && fit.converged);
    assert!(fit.inlier_share > 0.55 && fit.inlier_share < 0.75);
    assert_eq!(Some(fit), fit_circle_robust(&pts, &CircleParams::default()));
    // A half circle is a partial arc.
    let half = ring([0.0, 0.0], 0.2, 0.0, 120.0, 60, 0.002);
    let fit = fit_circle_robust(&half, &CircleParams::default()).expect("fit");
    assert!(fit.partial_arc && (fit.arc_coverage - 12.0 / 36.0).abs() < 0.05);
    assert!((arc_coverage(&half, [0.0, 0.0]) - fit.arc_coverage).abs() < 0.03);
}

#[test]
fn two_means_separates_two_blobs_deterministically() {
    let mut rng = SplitMix64::new(1);
    let mut rows = Vec::new();
    for i in 0..2000 {
        let c = if i % 2 == 0 { 0.0 } else { 5.0 };
        rows.extend([
            c + rng.uniform() as f32,
            c + rng.uniform() as f32,
            rng.uniform() as f32,
        ]);
    }
    standardise(&mut rows, 3);
    let a = kmeans(&rows, 3, 2, 50, 11, &NoProgress).expect("kmeans");
    let b = kmeans(&rows, 3, 2, 50, 11, &NoProgress).expect("kmeans");
    assert_eq!(a, b);
    assert!(a.assignment.chunks(2).all(|p| p[0] != p[1]));
    assert!(kmeans(&rows[..3], 3, 2, 5, 0, &NoProgress).is_err());
}

fn row(id: u32, x: f64, y: f64, dbh: f64) -> TreeRow {
    TreeRow {
        tree_id: id,
        x,
        y,
        ground_z: 100.0,
        dbh_lidar_cm: dbh,
        dbh_gs_cm: None,
        n_points: 42,
        rms_mm: 3.5,
        arc_coverage: 0.75,
        quality: "good".into(),
        gs_quality: None,
        height_m: None,
        crown_base_m: None,
        crown_area_m2: None,
        crown_diameter_m: None,
        basal_area_m2: None,
        volume_m3: None,
        agb_kg: None,
        carbon_kg: None,
        height_quality: None,
        crown_gap_m: None,
    }
}

#[test]
fn trees_csv_has_the_fixed_header_and_an_empty_gaussian_dbh() {
    let csv = trees_csv(&[row(1, 500000.1234, 4000000.5, 23.456)]);
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some(
            "tree_id,x,y,ground_z,dbh_lidar_cm,dbh_gs_cm,n_points,rms_mm,arc_coverage,quality,gs_quality,\
             height_m,crown_base_m,crown_area_m2,crown_diameter_m,basal_area_m2,volume_m3,agb_kg,carbon_kg,\
             height_quality,crown_gap_m"
        )
    );
    assert_eq!(
        lines.next(),
        Some("1,500000.123,4000000.500,100.000,23.46,,42,3.50,0.750,good,,,,,,,,,,,")
    );
    let unknown = CrsRecord::unknown("no CRS in this test");
    let gj = trees_geojson(&[row(1, 5.0, 6.0, 20.0)], &unknown).expect("geojson");
    assert_eq!(gj["type"], "FeatureCollection");
    // No CRS: no geometry, rather than metres posing as degrees; x, y stay as properties
    // and the record says why.
    assert!(gj["features"][0]["geometry"].is_null());
    assert_eq!(gj["features"][0]["properties"]["x"], 5.0);
    assert!(gj["sylva_crs"]["label"].is_null());
    let note = gj["sylva_crs"]["notes"][0].as_str().unwrap_or_default();
    assert!(
        note.contains("params.crs") && note.contains("--crs"),
        "{note}"
    );
    assert_eq!(gj["features"][0]["properties"]["quality"], "good");
    assert!(gj["features"][0]["properties"]["dbh_gs_cm"].is_null());
    assert!(gj["features"][0]["properties"]["gs_quality"].is_null());
    // With a Gaussian diameter: its value and its fit's quality flag, last.
    let measured = TreeRow {
        dbh_gs_cm: Some(24.126),
        gs_quality: Some(FitQuality::PartialArc),
        ..row(2, 1.0, 2.0, 24.0)
    };
    let csv = trees_csv(std::slice::from_ref(&measured));
    assert_eq!(
        csv.lines().nth(1),
        Some("2,1.000,2.000,100.000,24.00,24.13,42,3.50,0.750,good,partial_arc,,,,,,,,,,")
    );
    let gj = trees_geojson(std::slice::from_ref(&measured), &unknown).expect("geojson");
    assert_eq!(gj["features"][0]["properties"]["gs_quality"], "partial_arc");
    // A row written before `gs_quality` existed still reads.
    let mut old = serde_json::to_value(row(3, 1.0, 2.0, 20.0)).expect("json");
    old.as_object_mut().map(|o| o.remove("gs_quality"));
    let back: TreeRow = serde_json::from_value(old).expect("old row");
    assert_eq!(back, row(3, 1.0, 2.0, 20.0));
    let dir = tempfile::tempdir().expect("tempdir");
    write_trees_csv(&dir.path().join("t.csv"), &[]).expect("write csv");
    write_trees_geojson(&dir.path().join("t.geojson"), &[], &unknown).expect("write geojson");
}

/// RFC 7946 with a known CRS: WGS84 longitude, latitude (no altitude) in the geometry, the
/// native x, y, ground_z as properties, and the CRS record as a foreign member; the sidecar
/// reads back as written.
#[test]
fn trees_geojson_places_the_stems_in_wgs84_when_the_crs_is_known() {
    let utm = crate::io::crs::Crs::parse("EPSG:32649").expect("utm");
    let record = CrsRecord::new(Some(utm), crate::io::crs::CrsSource::File);
    let gj = trees_geojson(&[row(7, 500_000.0, 3_000_000.0, 30.0)], &record).expect("geojson");
    let f = &gj["features"][0];
    assert_eq!(f["geometry"]["type"], "Point");
    let c = f["geometry"]["coordinates"]
        .as_array()
        .expect("coordinates");
    assert_eq!(c.len(), 2, "{c:?}");
    assert!((c[0].as_f64().unwrap_or(0.0) - 111.0).abs() < 1e-8, "{c:?}");
    assert!(
        (c[1].as_f64().unwrap_or(0.0) - 27.122_469_6).abs() < 1e-6,
        "{c:?}"
    );
    assert_eq!(f["properties"]["x"], 500_000.0);
    assert_eq!(f["properties"]["ground_z"], 100.0);
    assert_eq!(gj["sylva_crs"]["label"], "EPSG:32649");
    assert_eq!(gj["sylva_crs"]["source"], "file");
    let dir = tempfile::tempdir().expect("tempdir");
    write_crs(dir.path(), &record).expect("write");
    assert_eq!(read_crs(dir.path()).expect("read"), record);
    // A folder without one (written before CRS records) reads as unknown.
    let empty = tempfile::tempdir().expect("tempdir");
    assert_eq!(read_crs(empty.path()).expect("read").crs, None);
}

#[test]
fn field_comparison_matches_one_to_one_and_computes_the_figures() {
    let rows = vec![
        row(1, 0.0, 0.0, 21.0),
        row(2, 5.0, 0.0, 29.0),
        row(3, 9.0, 9.0, 15.0),
    ];
    let field = |x, y, d| FieldTree {
        tree_id: None,
        x,
        y,
        dbh_cm: d,
    };
    // Two field trees near row 1: only the closer one matches it.
    let trees = vec![
        field(0.2, 0.0, 20.0),
        field(0.5, 0.0, 22.0),
        field(5.0, 0.3, 30.0),
    ];
    let c = compare_with_field(&rows, &trees, 1.0);
    assert_eq!(c.n_matched, 2);
    assert!((c.recall - 2.0 / 3.0).abs() < 1e-12 && (c.precision - 2.0 / 3.0).abs() < 1e-12);
    assert!((c.rmse_cm.expect("rmse") - 1.0).abs() < 1e-12);
    assert!(c.bias_cm.expect("bias").abs() < 1e-12);
    assert!((c.r2.expect("r2") - (1.0 - 2.0 / 50.0)).abs() < 1e-12);
    assert!((c.mean_relative_error.expect("mre") - (0.05 + 1.0 / 30.0) / 2.0).abs() < 1e-12);
    assert_eq!(accuracy_lines(&c).len(), 3);
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("field_dbh.csv");
    std::fs::write(&path, "x,y,dbh_cm\n0.2,0,20\n5,0.3,30\n").expect("write");
    let c = accuracy::compare_with_field_file(&rows, &path).expect("compare");
    assert_eq!((c.n_matched, c.n_field), (2, 2));
    assert!(serde_json::to_string(&c).is_ok());
}

#[test]
fn weights_change_the_robust_fit_and_unit_weights_change_nothing() {
    // Two interleaved rings 1 cm apart, both within the RANSAC threshold of each other.
    let inner = ring([0.3, -0.2], 0.15, 0.0, 360.0, 60, 0.0);
    let outer = ring([0.3, -0.2], 0.16, 3.0, 363.0, 60, 0.0);
    let pts: Vec<[f64; 2]> = inner.iter().chain(&outer).copied().collect();
    let heavy_outer: Vec<f64> = (0..120).map(|i| if i < 60 { 0.02 } else { 1.0 }).collect();
    for refine in [0, 20] {
        let p = CircleParams {
            refine_iterations: refine,
            ..CircleParams::default()
        };
        let plain = fit_circle_robust(&pts, &p).expect("fit");
        assert!((plain.fit.radius - 0.155).abs() < 0.001, "{plain:?}");
        let ones = vec![1.0; pts.len()];
        assert_eq!(
            fit_circle_robust_weighted(&pts, Some(&ones), None, &p),
            Some(plain)
        );
        let w = fit_circle_robust_weighted(&pts, Some(&heavy_outer), None, &p).expect("fit");
        assert!((w.fit.radius - 0.16).abs() < 0.0005, "{w:?}");
        assert_eq!(w.fit.n, 120);
        // Bad weights give no circle.
        assert!(fit_circle_robust_weighted(&pts, Some(&ones[1..]), None, &p).is_none());
        let mut neg = ones.clone();
        neg[7] = -1.0;
        assert!(fit_circle_robust_weighted(&pts, Some(&neg), None, &p).is_none());
    }
}

#[test]
fn the_centre_prior_rejects_circles_centred_elsewhere() {
    let pts = ring([1.0, 1.0], 0.2, 0.0, 360.0, 72, 0.002);
    let near = CenterPrior {
        center: [1.02, 1.0],
        max_offset_m: 0.05,
        weight: 0.0,
    };
    let far = CenterPrior {
        center: [1.3, 1.0],
        max_offset_m: 0.05,
        weight: 0.0,
    };
    let p = CircleParams::default();
    assert_eq!(
        fit_circle_robust_weighted(&pts, None, Some(&near), &p),
        fit_circle_robust(&pts, &p)
    );
    assert!(fit_circle_robust_weighted(&pts, None, Some(&far), &p).is_none());
}

#[test]
fn slice_offsets_are_signed_distances_in_the_plane_across_the_axis() {
    let base = glam::Vec3::new(2.0, -1.0, 0.5);
    let axis = glam::Vec3::new(0.3, 0.1, 1.0).normalize();
    let e1 = axis.any_orthonormal_vector();
    let e2 = axis.cross(e1);
    let at = |s: f32, deg: f32, r: f32| {
        let a = deg.to_radians();
        base + axis * s + (e1 * a.cos() + e2 * a.sin()) * r
    };
    let points = [
        at(1.3, 0.0, 0.21),   // 1 cm outside
        at(1.35, 90.0, 0.19), // 1 cm inside
        at(1.25, 200.0, 0.2), // on it
        at(1.5, 0.0, 0.21),   // outside the slice
        at(1.3, 45.0, 0.6),   // beyond reach
    ];
    // The centre given at another height along the axis: only its place in the plane counts.
    let center = base + axis * 0.7;
    // `axis` need not be unit length.
    let got = slice_offsets(&points, base, axis * 2.0, 1.3, 0.1, 0.5, center, 0.2);
    let idx: Vec<usize> = got.iter().map(|g| g.0).collect();
    assert_eq!(idx, vec![0, 1, 2]);
    assert!((got[0].1 - 0.01).abs() < 1e-5, "{got:?}");
    assert!((got[1].1 + 0.01).abs() < 1e-5, "{got:?}");
    assert!(got[2].1.abs() < 1e-5, "{got:?}");
    assert!(slice_offsets(&points, base, glam::Vec3::ZERO, 1.3, 0.1, 0.5, center, 0.2).is_empty());
}

#[test]
fn slab_mass_is_the_share_of_a_gaussian_inside_the_slab() {
    use super::dbh::slab_mass;
    // A point is in or out.
    assert_eq!(slab_mass(0.05, 0.1, 0.0), 1.0);
    assert_eq!(slab_mass(0.15, 0.1, 0.0), 0.0);
    assert_eq!(slab_mass(0.15, 0.1, f64::NAN), 0.0);
    // Centred: 2 Φ(h / σ) − 1 (σ = h: 0.6827).
    assert!((slab_mass(0.0, 0.1, 0.1) - 0.682_689).abs() < 1e-5);
    // Symmetric, and half the mass when the centre sits on the slab's face and σ ≪ h.
    assert!((slab_mass(0.07, 0.1, 0.05) - slab_mass(-0.07, 0.1, 0.05)).abs() < 1e-12);
    assert!((slab_mass(0.1, 0.1, 1e-4) - 0.5).abs() < 1e-9);
    // Wide: about the slab's share of the density, 2h / (σ √(2π)) at the centre.
    let wide = slab_mass(0.0, 0.01, 1.0);
    assert!((wide - 0.02 / (2.0 * std::f64::consts::PI).sqrt()).abs() < 1e-5);
}

#[test]
fn a_soft_centre_prior_holds_a_partial_arc_and_leaves_a_full_circle_its_own_centre() {
    // A quarter of a 15 cm circle, 20 points scattered ±7 mm: its centre is poorly fixed.
    let arc = ring([0.0, 0.0], 0.15, 0.0, 90.0, 20, 0.007);
    let p = CircleParams::default();
    let prior = |weight: f64| CenterPrior {
        center: [0.0, 0.0],
        max_offset_m: 0.05,
        weight,
    };
    let free = fit_circle_robust_weighted(&arc, None, Some(&prior(0.0)), &p).expect("fit");
    let held = fit_circle_robust_weighted(&arc, None, Some(&prior(16.0)), &p).expect("fit");
    let (e_free, e_held) = (
        (free.fit.radius - 0.15).abs(),
        (held.fit.radius - 0.15).abs(),
    );
    assert!(e_held < 0.002, "held {e_held} m");
    assert!(e_held < e_free, "held {e_held} m, free {e_free} m");
    // A full circle of 72 points centred 3 mm off the prior keeps most of its own centre:
    // its points fix each centre coordinate as n / 2 = 36 would, against the prior's 16, so
    // the estimate is about 3 mm · 36 / 52 = 2.1 mm.
    let full = ring([0.003, 0.0], 0.15, 0.0, 360.0, 72, 0.004);
    let fit = fit_circle_robust_weighted(&full, None, Some(&prior(16.0)), &p).expect("fit");
    assert!(
        (0.0016..0.0026).contains(&fit.fit.center[0]),
        "{:?}",
        fit.fit.center
    );
    assert!((fit.fit.radius - 0.15).abs() < 0.002, "{fit:?}");
}

#[test]
fn trees_csv_quotes_a_field_that_needs_it_and_reads_back() {
    let odd = TreeRow {
        quality: "odd, \"q\"".into(),
        ..row(4, 1.0, 2.0, 20.0)
    };
    let text = trees_csv(std::slice::from_ref(&odd));
    assert_eq!(
        text.lines().nth(1),
        Some("4,1.000,2.000,100.000,20.00,,42,3.50,0.750,\"odd, \"\"q\"\"\",,,,,,,,,,,")
    );
    let mut r = csv::Reader::from_reader(text.as_bytes());
    let rec = r.records().next().expect("a row").expect("parses");
    assert_eq!(rec.len(), 21);
    assert_eq!(&rec[9], "odd, \"q\"");
}
