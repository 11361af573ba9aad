//! Agreement of the data with the truth: DBH, stems in the images, the SfM similarity and
//! the control points.

use super::*;

#[test]
fn zero_noise_lidar_dbh_matches_tape_dbh_within_1mm() {
    for seed in [3, 21] {
        let dir = tempfile::tempdir().expect("tmp");
        let p = SynthParams {
            noise_cm: 0.0,
            trees: Some(3),
            images: Some(3),
            lidar_points: Some(1_000_000),
            ..tiny(seed)
        };
        generate(&p, dir.path(), &NoProgress).expect("generate");
        let cloud = read_point_cloud(&dir.path().join("lidar.laz"), &NoProgress).expect("laz");
        let labels = std::fs::read(dir.path().join("labels.bin")).expect("labels");
        let t = truth(dir.path());
        let trees = t["trees"].as_array().expect("trees");
        assert_eq!(trees.len(), 3);
        for tree in trees {
            let base = DVec3::new(
                tree["x"].as_f64().unwrap_or(0.0),
                tree["y"].as_f64().unwrap_or(0.0),
                tree["z"].as_f64().unwrap_or(0.0),
            );
            let axis = vec3(&tree["axis"]);
            let e1 = vec3(&tree["section_major_axis"]);
            let e2 = axis.cross(e1);
            let major = tree["section_semi_axes_m"][0].as_f64().unwrap_or(0.0);
            let dbh_cm = tree["dbh_cm"].as_f64().unwrap_or(0.0);
            // Wood points of the 1.2–1.4 m slice in the tree's own axis frame.
            let slice: Vec<[f64; 2]> = (0..cloud.len())
                .filter(|&i| labels[i] == 1)
                .filter_map(|i| {
                    let v = cloud.world(i) - base;
                    let s = v.dot(axis);
                    let q = [v.dot(e1), v.dot(e2)];
                    ((1.2..=1.4).contains(&s) && q[0].hypot(q[1]) < 1.5 * major + 0.05).then_some(q)
                })
                .collect();
            assert!(
                slice.len() > 200,
                "tree {}: only {} slice points",
                tree["id"],
                slice.len()
            );
            // Equalise the angular coverage (10° sectors) so the scanner's uneven sampling
            // does not bias the fit on the slightly elliptical section.
            let first = fit_circle_weighted(&slice, None).expect("first fit");
            let sector = |q: &[f64; 2]| {
                let a = (q[1] - first.center[1]).atan2(q[0] - first.center[0]);
                (((a + std::f64::consts::PI) / std::f64::consts::TAU * 36.0) as usize).min(35)
            };
            let mut counts = [0usize; 36];
            slice.iter().for_each(|q| counts[sector(q)] += 1);
            assert!(
                counts.iter().filter(|&&c| c > 0).count() >= 30,
                "tree {}: poor arc coverage {counts:?}",
                tree["id"]
            );
            let w: Vec<f64> = slice
                .iter()
                .map(|q| 1.0 / counts[sector(q)] as f64)
                .collect();
            let fit = fit_circle_weighted(&slice, Some(&w)).expect("fit");
            let got = 200.0 * fit.radius;
            assert!(
                (got - dbh_cm).abs() < 0.1,
                "seed {seed} tree {}: fitted {got:.3} cm vs truth {dbh_cm:.3} cm",
                tree["id"]
            );
            assert!(
                fit.center[0].hypot(fit.center[1]) < 0.002,
                "centre off the axis: {:?}",
                fit.center
            );
        }
    }
}

#[test]
fn images_show_bark_where_stems_are_visible() {
    let dir = tempfile::tempdir().expect("tmp");
    let p = SynthParams {
        png: true,
        trees: Some(3),
        width: Some(320),
        height: Some(240),
        ..small(9)
    };
    let (_, art) = run(&p, dir.path(), &NoProgress).expect("generate");
    let model = read_model(&dir.path().join("colmap/sparse/0"), &NoProgress).expect("model");
    let t = truth(dir.path());
    let file_to_sfm = similarity(&t["world_to_sfm"]);
    let offset = DVec3::from_array(p.geo_offset);
    let (mut checked, mut bark) = (0, 0);
    for img in model.images.values() {
        let pixels = image::open(dir.path().join("colmap/images").join(&img.name))
            .expect("decode")
            .to_rgb8();
        // Not blank: real variation in the picture.
        let mean: f64 =
            pixels.pixels().map(|p| p[1] as f64).sum::<f64>() / (pixels.len() / 3) as f64;
        let var: f64 = pixels
            .pixels()
            .map(|p| (p[1] as f64 - mean).powi(2))
            .sum::<f64>()
            / (pixels.len() / 3) as f64;
        assert!(var.sqrt() > 8.0, "{} looks blank", img.name);
        let view = &art.views[img.id as usize - 1];
        for (k, tree) in art.plot.trees.iter().enumerate() {
            let stem = tree.axis_point(1.3);
            let file_xy = vec3(&t["trees"][k]["breast_height_point"]);
            assert!((file_xy - offset - stem).length() < 1e-6);
            let Some(uv) = project(&model, img, file_to_sfm.apply(file_xy)) else {
                continue;
            };
            if !(uv[0] >= 0.0
                && uv[1] >= 0.0
                && uv[0] < pixels.width() as f64
                && uv[1] < pixels.height() as f64)
            {
                continue;
            }
            let dist = (stem - view.center).length();
            let width_px = art.intrinsics.f * 2.0 * tree.semi_axes_m[1] / dist;
            let o = view.center.as_vec3();
            let d = (stem.as_vec3() - o).normalize();
            let first = art
                .plot
                .scene
                .intersect(o, d, 0.0, 1e4)
                .map(|h| art.plot.scene.prims[h.prim as usize]);
            let visible = first.is_some_and(|pr| {
                pr.owner as usize == tree.id && pr.material == scene::Material::Bark
            });
            if !visible || width_px < 3.0 {
                continue;
            }
            let px = pixels.get_pixel(uv[0] as u32, uv[1] as u32).0;
            let [r, g, b] = px.map(f64::from);
            checked += 1;
            if r >= 0.95 * g && g >= 0.9 * b && r > 10.0 && r < 250.0 {
                bark += 1;
            } else {
                eprintln!(
                    "{} tree {}: pixel {px:?} at {uv:?}, stem {width_px:.1} px wide",
                    img.name, tree.id
                );
            }
        }
    }
    assert!(checked >= 10, "only {checked} visible stem projections");
    assert!(
        bark as f64 >= 0.9 * checked as f64,
        "{bark} of {checked} stem projections on bark-coloured pixels"
    );
}

/// Nearest-neighbour distances to a point set through a voxel hash (cells of `cell` m).
struct Grid {
    cell: f64,
    map: HashMap<[i64; 3], Vec<DVec3>>,
}

impl Grid {
    fn new(points: impl Iterator<Item = DVec3>, cell: f64) -> Grid {
        let mut map: HashMap<[i64; 3], Vec<DVec3>> = HashMap::new();
        for p in points {
            map.entry((p / cell).floor().as_i64vec3().to_array())
                .or_default()
                .push(p);
        }
        Grid { cell, map }
    }

    /// Distance to the nearest point, up to `cell` (infinity beyond).
    fn nearest(&self, q: DVec3) -> f64 {
        let c = (q / self.cell).floor().as_i64vec3();
        let mut best = f64::INFINITY;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(v) = self.map.get(&[c.x + dx, c.y + dy, c.z + dz]) {
                        best = v.iter().fold(best, |b, p| b.min(p.distance(q)));
                    }
                }
            }
        }
        if best <= self.cell {
            best
        } else {
            f64::INFINITY
        }
    }
}

#[test]
fn truth_maps_sfm_points_and_control_points_onto_the_lidar() {
    let dir = tempfile::tempdir().expect("tmp");
    let p = SynthParams {
        lidar_points: Some(1_000_000),
        ..tiny(4)
    };
    let (_, art) = run(&p, dir.path(), &NoProgress).expect("generate");
    let t = truth(dir.path());
    let s2w = similarity(&t["sfm_to_world"]);
    let w2s = similarity(&t["world_to_sfm"]);
    let probe = DVec3::new(500_010.0, 4_000_003.0, 51.0);
    assert!((s2w.apply(w2s.apply(probe)) - probe).length() < 1e-6);
    assert!((0.2..=5.0).contains(&(1.0 / s2w.scale)));

    let cloud = read_point_cloud(&dir.path().join("lidar.laz"), &NoProgress).expect("laz");
    let grid = Grid::new((0..cloud.len()).map(|i| cloud.world(i)), 0.2);
    let model = read_model(&dir.path().join("colmap/sparse/0"), &NoProgress).expect("model");
    let mut d: Vec<f64> = model
        .points
        .iter()
        .map(|pt| grid.nearest(s2w.apply(pt.xyz)))
        .collect();
    d.sort_by(f64::total_cmp);
    let median = d[d.len() / 2];
    let within = d.iter().filter(|&&x| x < 0.1).count() as f64 / d.len() as f64;
    eprintln!(
        "SfM→LiDAR distances: median {median:.3} m, {:.1} % within 10 cm",
        within * 100.0
    );
    assert!(
        median < 0.04,
        "median distance of SfM points to the LiDAR {median:.3} m"
    );
    assert!(
        within > 0.8,
        "only {:.0} % of SfM points within 10 cm of the LiDAR",
        within * 100.0
    );
    // ... and on the scene's surfaces.
    let on_surface = model
        .points
        .iter()
        .filter(|pt| {
            let w = (s2w.apply(pt.xyz) - DVec3::from_array(p.geo_offset)).as_vec3();
            [
                Vec3::X,
                Vec3::Y,
                Vec3::Z,
                Vec3::NEG_X,
                Vec3::NEG_Y,
                Vec3::NEG_Z,
            ]
            .iter()
            .any(|&dir| {
                art.plot
                    .scene
                    .intersect(w - dir * 0.06, dir, 0.0, 0.12)
                    .is_some()
            })
        })
        .count();
    assert!(
        on_surface as f64 > 0.95 * model.points.len() as f64,
        "{on_surface} of {} points3D on a surface",
        model.points.len()
    );

    let csv = std::fs::read_to_string(dir.path().join("control_points.csv")).expect("csv");
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some("name,sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z")
    );
    let rows: Vec<Vec<f64>> = lines
        .map(|l| {
            l.split(',')
                .skip(1)
                .map(|v| v.parse().expect("number"))
                .collect()
        })
        .collect();
    assert!(rows.len() >= 6, "{} control points", rows.len());
    for r in &rows {
        let (sfm, lidar) = (DVec3::new(r[0], r[1], r[2]), DVec3::new(r[3], r[4], r[5]));
        let e = (s2w.apply(sfm) - lidar).length();
        assert!(e < 0.08, "control point residual {e:.3} m");
    }
    let field = std::fs::read_to_string(dir.path().join("field_dbh.csv")).expect("csv");
    assert_eq!(field.lines().next(), Some("tree_id,x,y,dbh_cm"));
    assert_eq!(
        field.lines().count() - 1,
        t["trees"].as_array().map_or(0, Vec::len)
    );
    let names: Vec<String> = model.images.values().map(|i| i.name.clone()).collect();
    let tests: Vec<String> = serde_json::from_value(t["test_images"].clone()).expect("test_images");
    assert_eq!(tests, truth::test_images(&names));
    assert_eq!(tests.len(), names.len().div_ceil(8));
}
