//! Tests of the tileset: the octree's bounds and counts, the merge, the coordinates of the
//! tiles' content, and the georeference.

use super::*;
use crate::splat::cpu::test_scenes::{Draw, camera_facing_origin, random_gaussians};

/// `n` small Gaussians over a 20 × 20 × 8 m block about the origin (a stand of foliage).
fn stand(n: usize, seed: u64) -> Gaussians {
    let draw = Draw {
        dc: 0.9,
        rest: 0.2,
        mean: [10.0, 10.0, 4.0],
        log_scale: (-3.0, -1.5),
        opacity: (-1.0, 2.0),
    };
    random_gaussians(seed, n, 3, &draw)
}

fn leaves<'a>(tile: &'a Value, out: &mut Vec<&'a Value>) {
    match tile["children"].as_array() {
        Some(children) => children.iter().for_each(|c| leaves(c, out)),
        None => out.push(tile),
    }
}

#[test]
fn every_gaussian_lands_in_one_leaf_and_no_tile_holds_more_than_the_limit() {
    let g = stand(5000, 1);
    let params = TileParams { max_per_tile: 400 };
    let set = build(&g, None, &[], &params).expect("tiles");
    assert!(set.per_level.len() >= 3, "{:?}", set.per_level);
    assert_eq!(set.per_level[0], 1);
    assert!(set.root_gaussians <= 400, "{}", set.root_gaussians);
    let by_path: HashMap<&str, &TileFile> =
        set.tiles.iter().map(|t| (t.path.as_str(), t)).collect();
    let mut leaf_tiles = Vec::new();
    leaves(&set.json["root"], &mut leaf_tiles);
    let mut seen = 0;
    for t in &set.tiles {
        let back = export_gltf::read_glb(t.glb.as_slice()).expect("tile");
        assert!(back.len() <= 400, "{}: {}", t.path, back.len());
    }
    let mut means: Vec<[f64; 3]> = Vec::new();
    for leaf in leaf_tiles {
        assert_eq!(leaf["geometricError"], 0.0);
        let uri = leaf["content"]["uri"].as_str().expect("uri");
        let back = export_gltf::read_glb(by_path[uri].glb.as_slice()).expect("leaf");
        let b = leaf["boundingVolume"]["box"].as_array().expect("box");
        let c: Vec<f64> = b[..3].iter().map(|v| v.as_f64().expect("f64")).collect();
        // Content is relative to the box centre.
        means.extend(
            back.means
                .iter()
                .map(|m| std::array::from_fn(|k| f64::from(m[k]) + c[k])),
        );
        seen += back.len();
    }
    assert_eq!(seen, g.len());
    // Every Gaussian is back where it was, within SPZ's 0.24 mm steps.
    let off = g
        .means
        .iter()
        .map(|m| {
            means
                .iter()
                .map(|p| {
                    (0..3)
                        .map(|k| (p[k] - f64::from(m[k])).abs())
                        .fold(0.0, f64::max)
                })
                .fold(f64::INFINITY, f64::min)
        })
        .fold(0.0, f64::max);
    assert!(off < 2.5e-4, "a leaf centre off by {off} m");
}

#[test]
fn geometric_errors_shrink_down_the_tree_and_boxes_nest() {
    let g = stand(3000, 2);
    let set = build(&g, None, &[], &TileParams { max_per_tile: 300 }).expect("tiles");
    fn check(tile: &Value) {
        let e = tile["geometricError"].as_f64().expect("error");
        let b: Vec<f64> = tile["boundingVolume"]["box"]
            .as_array()
            .expect("box")
            .iter()
            .map(|v| v.as_f64().expect("f64"))
            .collect();
        for c in tile["children"].as_array().into_iter().flatten() {
            assert!(c["geometricError"].as_f64().expect("error") <= e);
            let cb: Vec<f64> = c["boundingVolume"]["box"]
                .as_array()
                .expect("box")
                .iter()
                .map(|v| v.as_f64().expect("f64"))
                .collect();
            for k in 0..3 {
                let half = b[3 + 4 * k];
                let chalf = cb[3 + 4 * k];
                assert!(cb[k] - chalf >= b[k] - half - 1e-9 && cb[k] + chalf <= b[k] + half + 1e-9);
            }
            check(c);
        }
    }
    check(&set.json["root"]);
    assert!(
        set.json["geometricError"].as_f64().expect("e")
            > set.json["root"]["geometricError"].as_f64().expect("e")
    );
    assert_eq!(
        set.json["extensions"]["3DTILES_content_gltf"]["extensionsRequired"],
        json!([EXTENSION, SPZ_EXTENSION])
    );
    assert!(set.json["root"].get("transform").is_none());
}

#[test]
fn a_merged_cell_keeps_its_centre_spread_colour_and_cover() {
    // Two equal round Gaussians 0.2 m apart along x, σ 0.05 m, opacity 0.5, one colour.
    let mut g = Gaussians {
        sh_degree: 0,
        ..Default::default()
    };
    for x in [-0.1f32, 0.1] {
        g.means.push([x, 0.0, 0.0]);
        g.log_scales.push([0.05f32.ln(); 3]);
        g.rotations.push([1.0, 0.0, 0.0, 0.0]);
        g.opacity_logits.push(0.0);
        let mut sh = [0.0; SH_FLOATS];
        sh[..3].copy_from_slice(&[0.4, -0.2, 0.1]);
        g.sh.push(sh);
        g.trunk_prob.push(1.0);
    }
    let (mean, log_scales, _rot, logit, sh, trunk) = merge_one(&g, &[0, 1]);
    assert!(mean.iter().all(|v| v.abs() < 1e-6), "{mean:?}");
    let mut s: Vec<f32> = log_scales.iter().map(|v| v.exp()).collect();
    s.sort_by(f32::total_cmp);
    // Along x: sqrt(0.05² + 0.1²); across: 0.05.
    assert!(
        (s[2] - (0.05f32.powi(2) + 0.01).sqrt()).abs() < 1e-5,
        "{s:?}"
    );
    assert!(
        (s[0] - 0.05).abs() < 1e-5 && (s[1] - 0.05).abs() < 1e-5,
        "{s:?}"
    );
    assert_eq!(&sh[..3], &[0.4, -0.2, 0.1]);
    assert!((trunk - 1.0).abs() < 1e-6);
    // Covers about what the two covered: 2 · 0.5 · A(0.05) against its own larger area.
    let opacity = sigmoid(logit);
    let a_own = mean_area([0.05; 3]);
    let a_merged = mean_area(
        s.iter()
            .map(|&v| f64::from(v))
            .collect::<Vec<_>>()
            .try_into()
            .expect("3"),
    );
    assert!(
        (f64::from(opacity) - (a_own / a_merged).min(0.99)).abs() < 1e-4,
        "{opacity}"
    );
}

#[test]
fn the_coarsest_level_looks_like_the_whole_from_afar() {
    let g = stand(6000, 3);
    let set = build(&g, None, &[], &TileParams { max_per_tile: 600 }).expect("tiles");
    let root = export_gltf::read_glb(set.tiles[0].glb.as_slice()).expect("root");
    let b = &set.json["root"]["boundingVolume"]["box"];
    let c: Vec<f32> = (0..3).map(|k| b[k].as_f64().expect("f64") as f32).collect();
    let mut coarse = root.clone();
    for m in &mut coarse.means {
        for k in 0..3 {
            m[k] += c[k];
        }
    }
    // Seen from 120 m, where a root cell (its geometric error) is about a pixel.
    let cam = camera_facing_origin([0.0, -120.0, 30.0], 96, 48, 400.0);
    let full = crate::splat::cpu::render(&g, &cam, [0.0; 3]).expect("render");
    let near = crate::splat::cpu::render(&coarse, &cam, [0.0; 3]).expect("render");
    // An even draw of the same count, for comparison: what a tile without merging would show.
    let step = g.len().div_ceil(coarse.len());
    let idx: Vec<usize> = (0..g.len()).step_by(step).collect();
    let thin = crate::splat::cpu::render(&subset(&g, &idx), &cam, [0.0; 3]).expect("render");
    let p = |r: &crate::splat::cpu::Render| {
        crate::splat::eval::psnr(&r.image, &full.image, cam.width, cam.height).expect("psnr")
    };
    let (merged, drawn) = (p(&near), p(&thin));
    eprintln!(
        "{} of {} Gaussians at the root (error {:.2} m): {merged:.2} dB merged, {drawn:.2} dB drawn evenly",
        coarse.len(),
        g.len(),
        set.json["root"]["geometricError"]
    );
    assert!(merged > drawn + 3.0, "merged {merged} dB, drawn {drawn} dB");
}

#[test]
fn the_root_transform_places_a_utm_plot_on_the_earth_within_a_millimetre() {
    let crs = crate::io::crs::Crs::parse("EPSG:32633").expect("utm 33N");
    let offset = [500_123.0, 4_000_456.0, 120.0];
    let (lo, hi) = ([-60.0, -50.0, -5.0], [60.0, 50.0, 35.0]);
    let (m, residual) = local_to_ecef(&crs, offset, lo, hi).expect("fit");
    assert!(residual < 1e-3, "fit residual {residual} m");
    let m = glam::DMat4::from_cols_array(&m);
    // Points off the fit's grid land where the CRS puts them.
    for p in [[13.7, -41.2, 3.3], [-55.0, 49.0, 30.0], [0.1, 0.2, 0.3]] {
        let mut xy = [(p[0] + offset[0], p[1] + offset[1])];
        crs.to_wgs84(&mut xy).expect("wgs84");
        let want = DVec3::from_array(wgs84_to_ecef(xy[0].0, xy[0].1, p[2] + offset[2]));
        let got = m.transform_point3(DVec3::from_array(p));
        assert!((got - want).length() < 1e-3, "{p:?}: {got} vs {want}");
    }
}

#[test]
fn ecef_of_known_places() {
    // The equator at Greenwich, and the north pole.
    let e = wgs84_to_ecef(0.0, 0.0, 0.0);
    assert!((e[0] - 6_378_137.0).abs() < 1e-6 && e[1].abs() < 1e-6 && e[2].abs() < 1e-6);
    let n = wgs84_to_ecef(0.0, 90.0, 0.0);
    assert!((n[2] - 6_356_752.314_245).abs() < 1e-3, "{n:?}");
}
