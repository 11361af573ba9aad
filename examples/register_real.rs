//! Why stage `register` takes or refuses a real photo/cloud pair with GPS (issue 39): from an
//! output folder where stage `ingest` ran (`sylva run ... --until ingest --out DIR`; with
//! `--photos`, `--until sfm`), the GPS
//! start of [`sylva::geom::coarse::from_positions`], then ICP and the surface passes as the
//! stage runs them, each step printed with the SfM points' distance to the cloud (to the
//! nearest cloud point, and to the plane through its 8 nearest), the on-cloud and elevated
//! shares the verification scores, the scale and the cameras against their GPS positions.
//!
//! `REG_SPLIT=1` adds the precision the stage gates on (normal matrix and split halves) for
//! the whole set and for subsets by track length and reprojection error.
//!
//! `cargo run --release --example register_real -- DIR`, e.g. after
//! `sylva run --lidar model.laz --colmap proj --until ingest --out DIR`.

use std::collections::BTreeMap;
use std::path::PathBuf;

use glam::{DVec3, Vec3};
use sylva::geom::register::{
    AUTOMATIC_REFINE_PASSES, ON_CLOUD_M, SurfaceTarget, icp_from, refine_on_surface,
};
use sylva::geom::{PointIndex, Similarity};
use sylva::io::gps::GpsFix;
use sylva::pipeline::params::RegisterParams;
use sylva::progress::NoProgress;

/// A named subset of the SfM points, by index.
type Bin<'a> = (&'static str, Box<dyn Fn(usize) -> bool + 'a>);

fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// Nearest-point and local-plane distances of the SfM points under `t` to the cloud.
fn distances(
    sfm: &[DVec3],
    t: &Similarity,
    cloud: &[Vec3],
    index: &PointIndex,
) -> (Vec<f64>, Vec<f64>) {
    let mut nn = Vec::with_capacity(sfm.len());
    let mut plane = Vec::with_capacity(sfm.len());
    for p in sfm {
        let q = t.apply(*p);
        let ks = index.knn(q.as_vec3(), 8);
        let Some(first) = ks.first() else { continue };
        nn.push(f64::from(first.dist2).sqrt());
        let Some((m, c)) = sylva::geom::covariance(cloud, ks.iter().map(|k| k.index as usize))
        else {
            continue;
        };
        let mut n = sylva::geom::symmetric_eigen3(m).vectors[2];
        if n.z < 0.0 {
            n = -n;
        }
        plane.push((q - c).dot(n));
    }
    (nn, plane)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dir = PathBuf::from(std::env::args().nth(1).ok_or("usage: register_real DIR")?);
    let ingest = dir.join("ingest");
    let cloud = sylva::io::pointcloud::read_point_cloud(&ingest.join("cloud.ply"), &NoProgress)?;
    // A job from photos has its model from stage sfm; one from a COLMAP project in ingest.
    let from_photos = dir.join("sfm").join("sparse");
    let sparse = if from_photos.is_dir() {
        from_photos
    } else {
        ingest.join("sparse")
    };
    let model = sylva::io::colmap::read_model(&sparse, &NoProgress)?;
    let p: RegisterParams = match std::env::var("REG_PARAMS") {
        Ok(json) => serde_json::from_str(&json)?,
        Err(_) => RegisterParams::default(),
    };
    let sfm: Vec<DVec3> = model.points.iter().map(|x| x.xyz).collect();
    let rays = sylva::pipeline::register::camera_rays(&model);
    let fixes: BTreeMap<String, GpsFix> =
        serde_json::from_slice(&std::fs::read(ingest.join("gps.json"))?)?;
    let crs = sylva::forest::output::read_crs(&ingest)?
        .crs
        .ok_or("no CRS")?;
    let offset = cloud.offset;
    let mut pairs = Vec::new();
    for im in model.images.values() {
        let Some(fix) = fixes.get(&im.name) else {
            continue;
        };
        let mut xy = [(fix.lon, fix.lat)];
        crs.from_wgs84(&mut xy)?;
        let c = sylva::geom::register::camera_ray(im.qvec, im.tvec).0;
        pairs.push((
            c,
            DVec3::new(xy[0].0, xy[0].1, fix.alt.unwrap_or(offset.z)) - offset,
        ));
    }
    let gps_rms = |t: &Similarity| {
        let s: f64 = pairs
            .iter()
            .map(|(c, g)| (t.apply(*c) - *g).truncate().length_squared())
            .sum();
        (s / pairs.len().max(1) as f64).sqrt()
    };
    let gps_dz = |t: &Similarity| {
        let mut v: Vec<f64> = pairs.iter().map(|(c, g)| t.apply(*c).z - g.z).collect();
        percentile(&mut v, 0.5)
    };
    let index_full = PointIndex::new(&cloud.positions)?;
    let target = sylva::geom::voxel_downsample(
        &cloud.positions,
        None,
        p.target_voxel_m as f32,
        &NoProgress,
    )?
    .positions;
    let index_t = PointIndex::new(&target)?;
    // Cloud density: median nearest-neighbour spacing of the cloud itself.
    let mut spacing: Vec<f64> = cloud
        .positions
        .iter()
        .step_by(97)
        .map(|q| {
            let k = index_full.knn(*q, 2);
            k.get(1).map_or(f64::NAN, |n| f64::from(n.dist2).sqrt())
        })
        .collect();
    println!(
        "cloud {} points, thinned (5 cm) {}; median point spacing {:.3} m; SfM {} points, {} photos with GPS",
        cloud.positions.len(),
        target.len(),
        percentile(&mut spacing, 0.5),
        sfm.len(),
        pairs.len()
    );
    let fit = sylva::geom::coarse::from_positions(&sfm, &rays, &pairs, &cloud.positions)?;
    println!(
        "GPS fit: rms {:.3} m, yaw {:.2}° ± {:.2}, scale {:.4}",
        fit.rms_m, fit.alignment.yaw_deg, fit.yaw_std_deg, fit.alignment.scale
    );
    let report = |name: &str, t: &Similarity| {
        let (mut nn, pl) = distances(&sfm, t, &cloud.positions, &index_full);
        let mut pl: Vec<f64> = pl.iter().map(|d| d.abs()).collect();
        let on_thin = sfm
            .iter()
            .filter(|x| {
                index_t
                    .nearest(t.apply(**x).as_vec3())
                    .is_some_and(|n| f64::from(n.dist2).sqrt() <= ON_CLOUD_M)
            })
            .count();
        let on_full = nn.iter().filter(|d| **d <= ON_CLOUD_M).count();
        println!(
            "{name:>22}: scale {:.4}; nearest point median {:.3} p90 {:.3}; local plane median {:.3} p90 {:.3}; \
             within {ON_CLOUD_M} m: thinned {:.3}, full {:.3}; cameras vs GPS {:.2} m RMS (horizontal), median dz {:.1} m",
            t.scale,
            percentile(&mut nn.clone(), 0.5),
            percentile(&mut nn, 0.9),
            percentile(&mut pl.clone(), 0.5),
            percentile(&mut pl, 0.9),
            on_thin as f64 / sfm.len() as f64,
            on_full as f64 / sfm.len() as f64,
            gps_rms(t),
            gps_dz(t),
        );
    };
    let analyse = |t: &Similarity| {
        let (_, signed) = distances(&sfm, t, &cloud.positions, &index_full);
        let moved: Vec<DVec3> = sfm.iter().map(|x| t.apply(*x)).collect();
        let c = moved.iter().copied().sum::<DVec3>() / moved.len() as f64;
        let cams: Vec<DVec3> = pairs.iter().map(|(k, _)| t.apply(*k)).collect();
        let top = moved.iter().map(|q| q.z).fold(f64::MIN, f64::max);
        println!(
            "  cameras' mean height {:.1} m over the highest SfM point",
            cams.iter().map(|k| k.z).sum::<f64>() / cams.len() as f64 - top
        );
        let bins: [Bin; 9] = [
            (
                "r < 15 m",
                Box::new(|i: usize| (moved[i] - c).truncate().length() < 15.0),
            ),
            (
                "r 15-30 m",
                Box::new(|i: usize| (15.0..30.0).contains(&(moved[i] - c).truncate().length())),
            ),
            (
                "r 30-45 m",
                Box::new(|i: usize| (30.0..45.0).contains(&(moved[i] - c).truncate().length())),
            ),
            (
                "r >= 45 m",
                Box::new(|i: usize| (moved[i] - c).truncate().length() >= 45.0),
            ),
            (
                "track 2",
                Box::new(|i: usize| model.points[i].track.len() == 2),
            ),
            (
                "track 3",
                Box::new(|i: usize| model.points[i].track.len() == 3),
            ),
            (
                "track 4-5",
                Box::new(|i: usize| (4..6).contains(&model.points[i].track.len())),
            ),
            (
                "track 6+",
                Box::new(|i: usize| model.points[i].track.len() >= 6),
            ),
            (
                "error > 1 px",
                Box::new(|i: usize| model.points[i].error > 1.0),
            ),
        ];
        for (name, f) in bins.iter() {
            let mut v: Vec<f64> = (0..sfm.len())
                .filter(|i| f(*i))
                .map(|i| signed[i])
                .collect();
            let mut a: Vec<f64> = v.iter().map(|d| d.abs()).collect();
            println!(
                "  {name:>12}: {:5} points, signed median {:+.3}, |d| median {:.3} p90 {:.3}",
                v.len(),
                percentile(&mut v, 0.5),
                percentile(&mut a.clone(), 0.5),
                percentile(&mut a, 0.9)
            );
        }
    };
    let start = fit.alignment.transform;
    report("GPS start", &start);
    let icp = sylva::geom::IcpParams {
        method: if p.point_to_plane {
            sylva::geom::IcpMethod::PointToPlane
        } else {
            sylva::geom::IcpMethod::PointToPoint
        },
        estimate_scale: p.estimate_scale,
        max_iterations: p.icp_max_iterations as usize,
        start_distance: p.icp_max_distance_m,
        min_distance: p.icp_min_distance_m,
        robust: sylva::geom::RobustKernel::Trimmed {
            keep_fraction: p.icp_keep_fraction,
        },
        relative_rmse_tolerance: p.icp_relative_rmse,
        ..Default::default()
    };
    let fine = icp_from(&sfm, &start, &target, &icp, &NoProgress)?;
    let after_icp = start.then(&fine.transform());
    report("after ICP", &after_icp);
    let st = SurfaceTarget::new(&cloud.positions, p.refine_voxel_m, &NoProgress)?;
    let sp = sylva::pipeline::register::surface_params(&p);
    let r = refine_on_surface(
        &sfm,
        &st,
        &after_icp,
        None,
        &sp,
        AUTOMATIC_REFINE_PASSES,
        &NoProgress,
    )?;
    println!(
        "surface: used {} ({:.3}), rms {:.4}, std rot {:.4?}° scale {:.4}%",
        r.used,
        r.fitness,
        r.rmse_m,
        r.std_rotation_deg,
        r.std_scale * 100.0
    );
    report("after surface passes", &r.transform);
    analyse(&after_icp);
    if let Ok(path) = std::env::var("REG_DUMP") {
        let (nn, signed) = distances(&sfm, &after_icp, &cloud.positions, &index_full);
        let mut out = String::from("x,y,z,nn,signed,track,error\n");
        for (i, x) in sfm.iter().enumerate() {
            let q = after_icp.apply(*x);
            out += &format!(
                "{},{},{},{},{},{},{}\n",
                q.x,
                q.y,
                q.z,
                nn[i],
                signed[i],
                model.points[i].track.len(),
                model.points[i].error
            );
        }
        std::fs::write(path, out)?;
    }
    analyse(&r.transform);
    // Relief contrast: the on-cloud share at the pose and with the pose shifted.
    for tol in [0.06, 0.1, 0.2] {
        let share = |t: &Similarity| {
            sfm.iter()
                .filter(|x| {
                    index_t
                        .nearest(t.apply(**x).as_vec3())
                        .is_some_and(|n| f64::from(n.dist2).sqrt() <= tol)
                })
                .count() as f64
                / sfm.len() as f64
        };
        let base = share(&r.transform);
        let mut line = format!("tol {tol}: at pose {base:.3};");
        for d in [0.5, 1.0, 2.0, 4.0] {
            let mut worst: f64 = 0.0;
            for k in 0..8 {
                let a = k as f64 * std::f64::consts::FRAC_PI_4;
                let sh = Similarity {
                    translation: r.transform.translation
                        + DVec3::new(d * a.cos(), d * a.sin(), 0.0),
                    ..r.transform
                };
                worst = worst.max(share(&sh));
            }
            line += &format!(" shifted {d} m best {worst:.3};");
        }
        println!("{line}");
    }
    for d in [0.0, 0.5, 1.0, 2.0, 4.0, 8.0] {
        let mut meds = Vec::new();
        for k in 0..8 {
            let a = k as f64 * std::f64::consts::FRAC_PI_4;
            let sh = Similarity {
                translation: r.transform.translation + DVec3::new(d * a.cos(), d * a.sin(), 0.0),
                ..r.transform
            };
            let (mut nn, _) = distances(&sfm, &sh, &cloud.positions, &index_full);
            meds.push(percentile(&mut nn, 0.5));
        }
        println!(
            "shift {d} m: median NN distance min {:.3} max {:.3}",
            meds.iter().copied().fold(f64::MAX, f64::min),
            meds.iter().copied().fold(0.0, f64::max)
        );
    }
    // Ground under the canopy: cloud points more than 2 m above their 0.5 m cell's lowest.
    let mut lowest: std::collections::HashMap<(i64, i64), f32> = Default::default();
    let key = |q: &Vec3| ((q.x / 0.5).floor() as i64, (q.y / 0.5).floor() as i64);
    for q in &cloud.positions {
        let e = lowest.entry(key(q)).or_insert(q.z);
        *e = e.min(q.z);
    }
    for h in [0.5f32, 1.0, 2.0, 4.0] {
        let above = cloud
            .positions
            .iter()
            .filter(|q| q.z - lowest[&key(q)] > h)
            .count();
        println!(
            "cloud points more than {h} m above their 0.5 m cell's lowest: {:.3}",
            above as f64 / cloud.positions.len() as f64
        );
    }
    // The stage's precision gate reads the larger of the normal matrix and the split halves:
    // both for all the SfM points and for subsets by track length and reprojection error
    // (REG_SPLIT=1; REG_SPLIT=all for the whole set only).
    // As the stage, no split halves when `uncertainty_splits` is 0.
    if let Ok(which) = std::env::var("REG_SPLIT")
        && p.uncertainty_splits > 0
    {
        let subsets: [Bin; 5] = [
            ("all", Box::new(|_| true)),
            ("track >= 3", Box::new(|i| model.points[i].track.len() >= 3)),
            ("track >= 4", Box::new(|i| model.points[i].track.len() >= 4)),
            ("error < 0.5 px", Box::new(|i| model.points[i].error < 0.5)),
            ("track 2", Box::new(|i| model.points[i].track.len() == 2)),
        ];
        let count = if which == "all" { 1 } else { subsets.len() };
        for (name, f) in subsets.iter().take(count) {
            let sub: Vec<DVec3> = (0..sfm.len()).filter(|i| f(*i)).map(|i| sfm[i]).collect();
            let rr = refine_on_surface(&sub, &st, &r.transform, None, &sp, 1, &NoProgress)?;
            let s = sylva::geom::surface::split_half_spread(
                &sub,
                &st.thin,
                &st.index,
                &rr.transform,
                &sp,
                p.uncertainty_splits as usize,
                &NoProgress,
            )?;
            let apart = r.transform.inverse().then(&rr.transform);
            println!(
                "{name:>14}: {} points ({} on surfaces); normal matrix rotation {:.4?}° scale {:.4}%; \
                 split halves rotation {:.4?}° scale {:.4}%; from the whole set's pose {:.4}°, {:+.4}%",
                sub.len(),
                rr.used,
                rr.std_rotation_deg,
                rr.std_scale * 100.0,
                s.std_rotation_deg,
                s.std_scale * 100.0,
                apart.rotation_angle_deg(),
                (apart.scale - 1.0) * 100.0
            );
        }
    }
    let rel = after_icp.inverse().then(&r.transform);
    println!(
        "surface moved rotation {:.3}°, scale {:.4}",
        rel.rotation_angle_deg(),
        rel.scale
    );
    Ok(())
}
