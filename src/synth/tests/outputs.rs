//! The files: determinism, formats, round trips, parameter checks.

use super::*;

#[test]
fn same_seed_gives_identical_bytes_and_other_seeds_differ() {
    let (a, b, c) = (
        tempfile::tempdir().expect("tmp"),
        tempfile::tempdir().expect("tmp"),
        tempfile::tempdir().expect("tmp"),
    );
    let p = SynthParams {
        lidar_points: Some(50_000),
        ..tiny(11)
    };
    generate(&p, a.path(), &NoProgress).expect("first run");
    // The second run on a single thread: scheduling must not change a byte.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    pool.install(|| generate(&p, b.path(), &NoProgress))
        .expect("second run");
    let (fa, fb) = (files(a.path()), files(b.path()));
    assert_eq!(fa, fb);
    assert!(fa.len() >= 30 + 3 + 5, "{fa:?}");
    for f in &fa {
        let (x, y) = (
            std::fs::read(a.path().join(f)).expect("read"),
            std::fs::read(b.path().join(f)).expect("read"),
        );
        assert!(
            x == y,
            "{} differs between runs with the same seed",
            f.display()
        );
    }
    generate(&SynthParams { seed: 12, ..p }, c.path(), &NoProgress).expect("third run");
    for f in [
        "lidar.laz",
        "truth.json",
        "labels.bin",
        "colmap/images/img_0001.jpg",
    ] {
        let (x, y) = (
            std::fs::read(a.path().join(f)).expect("read"),
            std::fs::read(c.path().join(f)).expect("read"),
        );
        assert_ne!(x, y, "{f} identical for different seeds");
    }
}

#[test]
fn colmap_model_round_trips_through_the_reader_text_and_binary() {
    for binary in [false, true] {
        let dir = tempfile::tempdir().expect("tmp");
        // The binary run also switches to PINHOLE cameras.
        let p = SynthParams {
            binary,
            pinhole: binary,
            ..small(5)
        };
        let (summary, art) = run(&p, dir.path(), &NoProgress).expect("generate");
        let sparse = dir.path().join("colmap/sparse/0");
        assert_eq!(sparse.join("cameras.bin").is_file(), binary);
        let model_name = art.model.cameras.get(&1).map(|c| c.model.name());
        assert_eq!(
            model_name,
            Some(if binary { "PINHOLE" } else { "SIMPLE_RADIAL" })
        );
        let read = read_model(&sparse, &NoProgress).expect("read_model");
        assert!(
            read == art.model,
            "model read back differs (binary = {binary})"
        );
        assert_eq!(read.points.len(), summary.points3d);
        assert!(
            read.points.len() > 300,
            "only {} points3D",
            read.points.len()
        );
        check_tracks(&read);
        for img in read.images.values() {
            assert!(dir.path().join("colmap/images").join(&img.name).is_file());
        }
    }
}

#[test]
fn laz_keeps_the_offset_and_matches_labels() {
    let dir = tempfile::tempdir().expect("tmp");
    let p = small(2);
    let summary = generate(&p, dir.path(), &NoProgress).expect("generate");
    let cloud = read_point_cloud(&dir.path().join("lidar.laz"), &NoProgress).expect("laz");
    let labels = std::fs::read(dir.path().join("labels.bin")).expect("labels");
    assert_eq!(cloud.len(), labels.len());
    assert_eq!(cloud.len(), summary.lidar_points);
    assert_eq!(cloud.len(), 20_000);
    let (lo, hi) = cloud.bounds().expect("bounds");
    assert!(
        lo.x > 499_900.0 && hi.x < 500_100.0 && lo.y > 3_999_900.0 && hi.y < 4_000_100.0,
        "{lo} {hi}"
    );
    assert!(cloud.colors.is_some() && cloud.intensity.is_some());
    let mut counts = [0usize; 4];
    for &l in &labels {
        assert!(l <= 3);
        counts[l as usize] += 1;
    }
    assert!(counts.iter().all(|&c| c > 0), "label counts {counts:?}");
    let t = truth(dir.path());
    assert_eq!(t["labels"]["counts"], serde_json::json!(counts));
    // Ground points lie on the terrain; a stem base is close to ground points.
    let base = DVec3::new(
        t["trees"][0]["x"].as_f64().unwrap_or(0.0),
        t["trees"][0]["y"].as_f64().unwrap_or(0.0),
        t["trees"][0]["z"].as_f64().unwrap_or(0.0),
    );
    let near = (0..cloud.len())
        .filter(|&i| labels[i] == 0 && (cloud.world(i) - base).length() < 1.0)
        .count();
    assert!(
        near > 10,
        "{near} ground points within 1 m of the first stem base"
    );
}

#[test]
fn invalid_parameters_are_refused() {
    let dir = tempfile::tempdir().expect("tmp");
    let bad = SynthParams {
        noise_cm: -1.0,
        ..tiny(0)
    };
    assert!(matches!(
        generate(&bad, dir.path(), &NoProgress),
        Err(SynthError::InvalidParams(_))
    ));
    let bad = SynthParams {
        images: Some(1),
        ..tiny(0)
    };
    assert!(matches!(
        generate(&bad, dir.path(), &NoProgress),
        Err(SynthError::InvalidParams(_))
    ));
    assert_eq!(Preset::from_name("Stand"), Some(Preset::Stand));
    assert_eq!(Preset::from_name("forest"), None);
}

#[test]
fn leafless_trees_have_wood_but_no_leaves() {
    let dir = tempfile::tempdir().expect("tmp");
    let p = SynthParams {
        leafless: true,
        images: Some(3),
        ..small(6)
    };
    let summary = generate(&p, dir.path(), &NoProgress).expect("generate");
    let labels = std::fs::read(dir.path().join("labels.bin")).expect("labels");
    assert_eq!(labels.len(), summary.lidar_points);
    assert!(!labels.contains(&2), "leafless plot has leaf points");
    assert!(labels.iter().filter(|&&l| l == 1).count() > 500);
    let t = truth(dir.path());
    assert!(
        t["trees"]
            .as_array()
            .expect("trees")
            .iter()
            .all(|tr| tr["kind"] == "leafless")
    );
}

#[test]
fn the_object_preset_is_a_phone_walk_around_one_stem() {
    let dir = tempfile::tempdir().expect("tmp");
    let p = SynthParams {
        seed: 3,
        images: Some(16),
        width: Some(72),
        height: Some(128),
        lidar_points: Some(20_000),
        points3d: Some(800),
        ..SynthParams::new(Preset::Object)
    };
    assert_eq!(Preset::from_name("object"), Some(Preset::Object));
    let (summary, art) = run(&p, dir.path(), &NoProgress).expect("generate");
    assert_eq!(summary.trees, 1);
    assert_eq!(
        (summary.width, summary.height),
        (72, 128),
        "portrait frames"
    );
    assert_eq!(art.views.len(), 16);
    let stem = art.plot.trees[0].base;
    for v in &art.views {
        let flat = (v.center - stem).truncate().length();
        assert!(
            (1.8..=4.0).contains(&flat),
            "{}: {flat} m from the stem",
            v.name
        );
        let ground = art.plot.scene.terrain.height(v.center.x, v.center.y);
        let eye = v.center.z - ground;
        assert!(
            (1.35..=1.8).contains(&eye),
            "{}: eye height {eye} m",
            v.name
        );
        // The stem is in front of the camera and near the middle of the frame.
        let c = v.to_camera(stem + glam::DVec3::new(0.0, 0.0, 1.3));
        assert!(c.z > 0.0, "{}: the stem is behind the camera", v.name);
        assert!(
            (c.x / c.z).abs() < 0.5,
            "{}: the stem is off to the side",
            v.name
        );
    }
    // The field of view spans the longer (vertical) side, as a phone held upright.
    let fy_fov = 2.0 * (0.5 * 128.0 / art.intrinsics.f).atan().to_degrees();
    assert!((fy_fov - crate::synth::camera::HFOV_DEG).abs() < 1e-6);
}

#[test]
fn lidar_plot_is_the_scan_generate_writes_and_stem_dbh_sets_the_first_trees() {
    let dir = tempfile::tempdir().expect("tmp");
    let p = SynthParams {
        images: Some(3),
        trees: Some(3),
        stem_dbh_cm: vec![9.0, 40.0],
        ..small(4)
    };
    generate(&p, dir.path(), &NoProgress).expect("generate");
    let plot = lidar_plot(&p, &NoProgress).expect("lidar plot");
    let cloud = read_point_cloud(&dir.path().join("lidar.laz"), &NoProgress).expect("laz");
    let labels = std::fs::read(dir.path().join("labels.bin")).expect("labels");
    assert_eq!(plot.labels, labels);
    assert_eq!(plot.cloud.len(), cloud.len());
    assert_eq!(plot.cloud.offset, DVec3::from_array(p.geo_offset));
    // The same points, up to the LAS format's millimetre quantisation.
    for i in (0..cloud.len()).step_by(97) {
        let d = (plot.cloud.world(i) - cloud.world(i)).abs().max_element();
        assert!(d <= 0.001, "point {i} differs by {d} m");
    }
    assert_eq!(plot.cloud.colors.as_deref(), cloud.colors.as_deref());
    // The first two trees take the given DBH; the third keeps its draw.
    let t = truth(dir.path());
    let dbh: Vec<f64> = plot.trees.iter().map(|t| t.dbh_m * 100.0).collect();
    assert_eq!(dbh.len(), 3);
    assert!(
        (dbh[0] - 9.0).abs() < 1e-9 && (dbh[1] - 40.0).abs() < 1e-9,
        "{dbh:?}"
    );
    for (k, d) in dbh.iter().enumerate() {
        let written = t["trees"][k]["dbh_cm"].as_f64().expect("dbh_cm");
        assert!((written - d).abs() < 1e-9, "tree {k}: {written} vs {d}");
    }
    let drawn = lidar_plot(
        &SynthParams {
            stem_dbh_cm: Vec::new(),
            ..p.clone()
        },
        &NoProgress,
    )
    .expect("lidar plot");
    assert!((drawn.trees[2].dbh_m - plot.trees[2].dbh_m).abs() < 1e-12);
    let bad = SynthParams {
        stem_dbh_cm: vec![0.5],
        ..p
    };
    assert!(matches!(
        lidar_plot(&bad, &NoProgress),
        Err(SynthError::InvalidParams(_))
    ));
}

/// The registration cases' knobs: a leaf-off scan of a leafy plot has no leaf returns while
/// the same plot scanned leafy has them; a 60 % coverage keeps the low 60 % of the x extent;
/// the grade replaces the drawn slope; the SfM scale replaces the drawn one.
#[test]
fn leaf_off_scans_coverage_slope_and_sfm_scale_do_what_they_say() {
    let leafy = lidar_plot(&small(6), &NoProgress).expect("leafy");
    assert!(leafy.labels.contains(&2), "a leafy scan has leaf returns");
    let off = lidar_plot(
        &SynthParams {
            lidar_leaf_off: true,
            ..small(6)
        },
        &NoProgress,
    )
    .expect("leaf-off");
    assert!(!off.labels.contains(&2), "a leaf-off scan has leaf returns");
    assert!(off.labels.iter().filter(|&&l| l == 1).count() > 500);
    let x_extent = |c: &[glam::Vec3]| {
        let (lo, hi) = c
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), p| (a.min(p.x), b.max(p.x)));
        hi - lo
    };
    let part = lidar_plot(
        &SynthParams {
            lidar_coverage: Some(0.6),
            ..small(6)
        },
        &NoProgress,
    )
    .expect("partial");
    let ratio = x_extent(&part.cloud.positions) / x_extent(&leafy.cloud.positions);
    assert!((ratio - 0.6).abs() < 0.01, "x extent ratio {ratio}");
    assert_eq!(part.labels.len(), part.cloud.positions.len());
    assert!(part.cloud.positions.len() < leafy.cloud.positions.len());

    let dir = tempfile::tempdir().expect("tmp");
    let p = SynthParams {
        slope_pct: Some(40.0),
        sfm_scale: Some(10.0),
        images: Some(3),
        ..small(6)
    };
    let (_, art) = run(&p, dir.path(), &NoProgress).expect("generate");
    let [gx, gy] = art.plot.scene.terrain.slope;
    assert!((gx.hypot(gy) - 0.4).abs() < 1e-12, "grade {gx}, {gy}");
    assert!((similarity(&truth(dir.path())["world_to_sfm"]).scale - 10.0).abs() < 1e-9);
}

/// GPS-tagged photos carry their camera's position within the noise, in WGS84 of the CRS
/// the LiDAR file now declares; PNG photos cannot carry them.
#[test]
fn gps_tags_place_the_photos_where_their_cameras_are() {
    let dir = tempfile::tempdir().expect("tmp");
    let p = SynthParams {
        gps_noise_m: Some(0.0),
        images: Some(4),
        ..small(7)
    };
    let (_, art) = run(&p, dir.path(), &NoProgress).expect("generate");
    let crs = crate::io::las::read_crs(&dir.path().join("lidar.laz"))
        .expect("read")
        .expect("parse")
        .expect("a declared CRS");
    assert_eq!(crs.epsg, Some(super::GPS_EPSG));
    let offset = glam::DVec3::from_array(p.geo_offset);
    for v in &art.views {
        let path = dir.path().join("colmap/images").join(&v.name);
        let fix = crate::io::gps::read_fix(&path)
            .expect("exif")
            .expect("a fix");
        let mut xy = [(fix.lon, fix.lat)];
        crs.from_wgs84(&mut xy).expect("project");
        let truth = v.center + offset;
        assert!((xy[0].0 - truth.x).abs() < 0.01 && (xy[0].1 - truth.y).abs() < 0.01);
        assert!((fix.alt.expect("altitude") - truth.z).abs() < 0.01);
    }
    let png = SynthParams { png: true, ..p };
    assert!(matches!(
        generate(&png, dir.path(), &NoProgress),
        Err(SynthError::InvalidParams(_))
    ));
}

/// Issue 40's knobs: with `hidden_stem_m` each tree's band (`truth.json` `hidden_m`, from its
/// crown base up, 0.3–3 m long) holds none of the tree's returns, where the same plot without
/// the knob has them; with `crown_interlock` the stems stand where they stood and each crown
/// covers more ground.
#[test]
fn hidden_stems_and_interlocking_crowns_do_what_they_say() {
    let one = SynthParams {
        trees: Some(1),
        lidar_points: Some(100_000),
        ..small(3)
    };
    let in_band = |plot: &crate::synth::LidarPlot, [lo, hi]: [f64; 2]| {
        let t = &plot.trees[0];
        plot.cloud
            .positions
            .iter()
            .zip(&plot.labels)
            .filter(|(p, l)| {
                let h = (p.as_dvec3() - t.base).dot(t.axis);
                // 5 cm inside the band: the range noise (1 cm) moves a return across its edge.
                **l != 0
                    && (lo + 0.05..=hi - 0.05).contains(&h)
                    && (p.as_dvec3() - t.base).truncate().length() < 3.0
            })
            .count()
    };
    let hidden = lidar_plot(
        &SynthParams {
            hidden_stem_m: Some(3.0),
            ..one.clone()
        },
        &NoProgress,
    )
    .expect("plot");
    let band = hidden.trees[0].hidden_m.expect("a hidden band");
    assert!((0.3..=3.0).contains(&(band[1] - band[0])), "{band:?}");
    assert!((band[0] - hidden.trees[0].crown_base_m).abs() < 1e-9);
    assert_eq!(in_band(&hidden, band), 0);
    assert!(hidden.cloud.positions.len() > 1000);
    let seen = lidar_plot(&one, &NoProgress).expect("plot");
    assert!(seen.trees[0].hidden_m.is_none());
    let n = in_band(&seen, band);
    assert!(n > 100, "{n} returns in the band {band:?} without the knob");

    let base = lidar_plot(&small(5), &NoProgress).expect("plot");
    let wide = lidar_plot(
        &SynthParams {
            crown_interlock: Some(0.5),
            ..small(5)
        },
        &NoProgress,
    )
    .expect("plot");
    for (a, b) in base.trees.iter().zip(&wide.trees) {
        assert!((a.base - b.base).length() < 1e-9);
        assert!((b.crown_radius_m / a.crown_radius_m - 1.5).abs() < 1e-9);
        assert!(b.crown_area_m2 > 1.3 * a.crown_area_m2, "{a:?}\n{b:?}");
    }
    let bad = SynthParams {
        hidden_stem_m: Some(0.1),
        ..small(5)
    };
    assert!(matches!(
        lidar_plot(&bad, &NoProgress),
        Err(SynthError::InvalidParams(_))
    ));
}
