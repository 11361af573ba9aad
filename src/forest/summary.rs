//! The plot's stand figures from its trees (issue 27.3): area, stems, basal area, quadratic
//! mean diameter, mean and dominant height, volume, biomass and carbon per hectare, and the
//! DBH distribution.
//!
//! Every figure says which DBH it used: the LiDAR circle fits by default, the Gaussians' when
//! asked (`dbh_source`), and the trees without that diameter are left out and counted.
//!
//! - Area: the user's boundary (a polygon in the cloud's own coordinates; stems outside it are
//!   not counted), else the cloud's footprint: the convex hull of its x, y, from the lowest
//!   and highest y of each 0.25 m column of x and the lowest and highest x of each 0.25 m row
//!   of y (which holds every vertex of the full hull to within a column's width, at a
//!   fraction of its cost on 10 M points).
//! - Quadratic mean diameter: QMD = sqrt(Σ DBH² / n).
//! - Dominant height: the mean height of the 100 thickest trees per hectare (Assmann's top
//!   height; on a plot of A ha, the round(100 A) thickest, at least one).
//! - Volume, biomass, carbon: the trees' `forest::allometry` figures from the chosen DBH and
//!   their height, summed over the area; trees without a height add none and are counted.

use geo::{Area, Contains, ConvexHull, LineString, MultiPoint, Point, Polygon};
use glam::DVec3;
use serde::{Deserialize, Serialize};

use super::ForestError;
use super::allometry::{AllometryParams, Equations};
use super::inventory::TreeRow;

/// Which diameter the stand figures use.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum DbhSource {
    /// The circle fitted to the LiDAR points (default: the reference).
    #[default]
    Lidar,
    /// The circle fitted to the trunk Gaussians (after stage `dbh`).
    Gaussians,
}

/// How the plot summary is made.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct SummaryParams {
    /// Which DBH the figures use (default `lidar`).
    pub dbh_source: DbhSource,
    /// The plot boundary: a polygon of at least three (x, y) vertices in the cloud's own
    /// coordinates (metres, the CRS of the file). Its area is the plot's, and only stems inside
    /// it are counted. Default: none, the cloud's footprint.
    pub boundary: Option<Vec<[f64; 2]>>,
}

/// One DBH class of the distribution.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DbhClass {
    /// Lower bound, centimetres (inclusive).
    pub from_cm: f64,
    /// Upper bound, centimetres (exclusive).
    pub to_cm: f64,
    pub stems: usize,
}

/// The stand figures of one plot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlotSummary {
    /// The DBH the figures use.
    pub dbh_source: DbhSource,
    /// Plot area, m².
    pub area_m2: f64,
    /// `boundary` (given) or `footprint` (the cloud's convex hull).
    pub area_from: String,
    /// Stems counted (inside the boundary, with the chosen DBH).
    pub stems: usize,
    /// Trees left out for lack of the chosen DBH.
    pub stems_without_dbh: usize,
    /// Trees left out as outside the boundary.
    pub stems_outside: usize,
    pub stems_per_ha: f64,
    pub basal_area_m2_per_ha: f64,
    /// Quadratic mean diameter, cm (`None` with no stems).
    pub qmd_cm: Option<f64>,
    pub mean_dbh_cm: Option<f64>,
    /// Mean total height of the trees with one, metres.
    pub mean_height_m: Option<f64>,
    /// Mean height of the round(100 · ha) thickest trees with a height, metres.
    pub dominant_height_m: Option<f64>,
    /// Stems that have a height (volume, biomass and carbon sum over these).
    pub stems_with_height: usize,
    pub volume_m3_per_ha: f64,
    /// Above-ground biomass, tonnes dry mass per hectare.
    pub agb_t_per_ha: f64,
    pub carbon_t_per_ha: f64,
    /// DBH classes of 5 cm from 0 to the thickest stem.
    pub dbh_classes: Vec<DbhClass>,
    /// The equations behind the per-tree figures.
    pub equations: Equations,
}

/// Width of a DBH class, cm (the customary 5 cm classes of forest inventories).
pub const DBH_CLASS_CM: f64 = 5.0;

/// The plot's footprint: the convex hull of `positions` (local, metres) moved by `offset` to
/// the file's coordinates, from the extremes of 0.25 m columns and rows (see the module doc).
pub fn footprint(positions: &[glam::Vec3], offset: DVec3) -> Polygon<f64> {
    const CELL: f32 = 0.25;
    let finite = || positions.iter().filter(|p| p.is_finite());
    let lo = finite().fold(glam::Vec3::splat(f32::INFINITY), |a, p| a.min(*p));
    let hi = finite().fold(glam::Vec3::splat(f32::NEG_INFINITY), |a, p| a.max(*p));
    if !(lo.is_finite() && hi.is_finite()) {
        return Polygon::new(LineString::new(Vec::new()), Vec::new());
    }
    let bins = |extent: f32| ((extent / CELL) as usize).min(1 << 24) + 1;
    // Per column of x: (lowest y, its x, highest y, its x); per row of y likewise.
    let empty = (f32::INFINITY, 0.0, f32::NEG_INFINITY, 0.0);
    let mut columns = vec![empty; bins(hi.x - lo.x)];
    let mut rows = vec![empty; bins(hi.y - lo.y)];
    let widen = |e: &mut (f32, f32, f32, f32), along: f32, across: f32| {
        if along < e.0 {
            (e.0, e.1) = (along, across);
        }
        if along > e.2 {
            (e.2, e.3) = (along, across);
        }
    };
    for p in finite() {
        let c = (((p.x - lo.x) / CELL) as usize).min(columns.len() - 1);
        widen(&mut columns[c], p.y, p.x);
        let r = (((p.y - lo.y) / CELL) as usize).min(rows.len() - 1);
        widen(&mut rows[r], p.x, p.y);
    }
    let at = |x: f32, y: f32| Point::new(f64::from(x) + offset.x, f64::from(y) + offset.y);
    let points: MultiPoint<f64> = columns
        .iter()
        .filter(|e| e.0.is_finite())
        .flat_map(|e| [at(e.1, e.0), at(e.3, e.2)])
        .chain(
            rows.iter()
                .filter(|e| e.0.is_finite())
                .flat_map(|e| [at(e.0, e.1), at(e.2, e.3)]),
        )
        .collect();
    points.convex_hull()
}

/// The stand figures of `rows` on a plot of `footprint` (file coordinates) unless the
/// parameters give a boundary.
pub fn summarise(
    rows: &[TreeRow],
    footprint: &Polygon<f64>,
    params: &SummaryParams,
    allometry: &AllometryParams,
) -> Result<PlotSummary, ForestError> {
    let (area_polygon, area_from) = match &params.boundary {
        Some(vertices) => {
            if vertices.len() < 3 || vertices.iter().flatten().any(|v| !v.is_finite()) {
                return Err(ForestError::Params(
                    "summary.boundary needs at least three finite (x, y) vertices".into(),
                ));
            }
            let ring: LineString<f64> = vertices.iter().map(|v| (v[0], v[1])).collect();
            (Polygon::new(ring, Vec::new()), "boundary")
        }
        None => (footprint.clone(), "footprint"),
    };
    let area_m2 = area_polygon.unsigned_area();
    if area_m2.is_nan() || area_m2 <= 0.0 {
        return Err(ForestError::NotEnoughPoints(format!(
            "the plot's {area_from} has no area; give summary.boundary"
        )));
    }
    let ha = area_m2 / 10_000.0;
    let dbh_of = |r: &TreeRow| match params.dbh_source {
        DbhSource::Lidar => Some(r.dbh_lidar_cm),
        DbhSource::Gaussians => r.dbh_gs_cm,
    };
    let mut stems_outside = 0;
    let mut stems_without_dbh = 0;
    let mut counted: Vec<(f64, &TreeRow)> = Vec::new();
    for r in rows {
        if params.boundary.is_some() && !area_polygon.contains(&Point::new(r.x, r.y)) {
            stems_outside += 1;
            continue;
        }
        match dbh_of(r).filter(|d| d.is_finite() && *d > 0.0) {
            Some(d) => counted.push((d, r)),
            None => stems_without_dbh += 1,
        }
    }
    let n = counted.len();
    let mean = |values: &[f64]| {
        (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
    };
    let dbhs: Vec<f64> = counted.iter().map(|(d, _)| *d).collect();
    let basal: f64 = dbhs
        .iter()
        .map(|d| std::f64::consts::PI * (d / 200.0).powi(2))
        .sum();
    let qmd_cm = (n > 0).then(|| (dbhs.iter().map(|d| d * d).sum::<f64>() / n as f64).sqrt());
    let mut with_height: Vec<(f64, f64)> = counted
        .iter()
        .filter_map(|(d, r)| Some((*d, r.height_m?)))
        .collect();
    let heights: Vec<f64> = with_height.iter().map(|(_, h)| *h).collect();
    with_height.sort_by(|a, b| b.0.total_cmp(&a.0));
    let dominant_n = ((100.0 * ha).round() as usize)
        .max(1)
        .min(with_height.len());
    let dominant: Vec<f64> = with_height[..dominant_n].iter().map(|(_, h)| *h).collect();
    // Volume, biomass and carbon from the DBH the figures use (the rows carry the LiDAR one's).
    let per_tree: Vec<_> = counted
        .iter()
        .map(|(d, r)| super::allometry::tree_allometry(*d, r.height_m, allometry))
        .collect();
    let sum = |f: fn(&super::allometry::TreeAllometry) -> Option<f64>| {
        per_tree.iter().filter_map(f).sum::<f64>()
    };
    let top = dbhs.iter().copied().fold(0.0, f64::max);
    let classes = (top / DBH_CLASS_CM).floor() as usize + 1;
    let mut dbh_classes: Vec<DbhClass> = (0..if n > 0 { classes } else { 0 })
        .map(|k| DbhClass {
            from_cm: k as f64 * DBH_CLASS_CM,
            to_cm: (k + 1) as f64 * DBH_CLASS_CM,
            stems: 0,
        })
        .collect();
    for d in &dbhs {
        let k = ((d / DBH_CLASS_CM).floor() as usize).min(dbh_classes.len().saturating_sub(1));
        if let Some(c) = dbh_classes.get_mut(k) {
            c.stems += 1;
        }
    }
    Ok(PlotSummary {
        dbh_source: params.dbh_source,
        area_m2,
        area_from: area_from.into(),
        stems: n,
        stems_without_dbh,
        stems_outside,
        stems_per_ha: n as f64 / ha,
        basal_area_m2_per_ha: basal / ha,
        qmd_cm,
        mean_dbh_cm: mean(&dbhs),
        mean_height_m: mean(&heights),
        dominant_height_m: mean(&dominant),
        stems_with_height: heights.len(),
        volume_m3_per_ha: sum(|a| a.volume_m3) / ha,
        agb_t_per_ha: sum(|a| a.agb_kg) / 1000.0 / ha,
        carbon_t_per_ha: sum(|a| a.carbon_kg) / 1000.0 / ha,
        dbh_classes,
        equations: allometry.equations(),
    })
}

/// The summary as the console prints it (`sylva inventory --summary`).
pub fn summary_lines(s: &PlotSummary) -> Vec<String> {
    let opt =
        |v: Option<f64>, unit: &str| v.map_or("—".to_string(), |v| format!("{v:.1} {unit}"));
    let mut lines = vec![
        format!(
            "plot: {:.0} m² ({}), {} stems, DBH from {}",
            s.area_m2,
            s.area_from,
            s.stems,
            match s.dbh_source {
                DbhSource::Lidar => "the LiDAR",
                DbhSource::Gaussians => "the Gaussians",
            }
        ),
        format!(
            "  {:.0} stems/ha · basal area {:.1} m²/ha · QMD {} · mean DBH {}",
            s.stems_per_ha,
            s.basal_area_m2_per_ha,
            opt(s.qmd_cm, "cm"),
            opt(s.mean_dbh_cm, "cm")
        ),
        format!(
            "  height: mean {} · dominant {} ({} stems with a height)",
            opt(s.mean_height_m, "m"),
            opt(s.dominant_height_m, "m"),
            s.stems_with_height
        ),
        format!(
            "  volume {:.1} m³/ha · biomass {:.1} t/ha · carbon {:.1} t/ha",
            s.volume_m3_per_ha, s.agb_t_per_ha, s.carbon_t_per_ha
        ),
        format!("  volume: {}", s.equations.volume),
        format!("  biomass: {}", s.equations.biomass),
        format!("  carbon: {}", s.equations.carbon),
    ];
    if s.stems_without_dbh + s.stems_outside > 0 {
        lines.push(format!(
            "  left out: {} without that DBH, {} outside the boundary",
            s.stems_without_dbh, s.stems_outside
        ));
    }
    let classes: Vec<String> = s
        .dbh_classes
        .iter()
        .filter(|c| c.stems > 0)
        .map(|c| format!("{:.0}–{:.0}: {}", c.from_cm, c.to_cm, c.stems))
        .collect();
    lines.push(format!("  DBH classes (cm): {}", classes.join(", ")));
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tree(id: u32, x: f64, y: f64, dbh: f64, height: Option<f64>) -> TreeRow {
        let a = super::super::allometry::tree_allometry(dbh, height, &AllometryParams::default());
        TreeRow {
            tree_id: id,
            x,
            y,
            ground_z: 0.0,
            dbh_lidar_cm: dbh,
            dbh_gs_cm: Some(dbh + 1.0),
            n_points: 100,
            rms_mm: 1.0,
            arc_coverage: 1.0,
            quality: "good".into(),
            gs_quality: None,
            height_m: height,
            crown_base_m: None,
            crown_area_m2: None,
            crown_diameter_m: None,
            basal_area_m2: Some(a.basal_area_m2),
            volume_m3: a.volume_m3,
            agb_kg: a.agb_kg,
            carbon_kg: a.carbon_kg,
            height_quality: None,
            crown_gap_m: None,
        }
    }

    /// A 100 m × 100 m plot (1 ha) of four trees, figures worked by hand.
    #[test]
    fn stand_figures_of_a_hectare() {
        let square: LineString<f64> =
            vec![(0.0, 0.0), (100.0, 0.0), (100.0, 100.0), (0.0, 100.0)].into();
        let plot = Polygon::new(square, Vec::new());
        let rows = vec![
            tree(1, 10.0, 10.0, 10.0, Some(10.0)),
            tree(2, 20.0, 10.0, 20.0, Some(20.0)),
            tree(3, 30.0, 10.0, 30.0, None),
            tree(4, 40.0, 10.0, 40.0, Some(30.0)),
        ];
        let p = AllometryParams::default();
        let s = summarise(&rows, &plot, &SummaryParams::default(), &p).expect("summary");
        assert_eq!((s.area_m2, s.area_from.as_str()), (10_000.0, "footprint"));
        assert_eq!((s.stems, s.stems_per_ha), (4, 4.0));
        // BA = π/40000 (100 + 400 + 900 + 1600) = 0.235619 m².
        assert!((s.basal_area_m2_per_ha - 0.235_619).abs() < 1e-5, "{s:?}");
        // QMD = sqrt(3000 / 4) = 27.386 cm.
        assert!((s.qmd_cm.unwrap_or(0.0) - 27.386).abs() < 1e-3, "{s:?}");
        assert_eq!(s.mean_dbh_cm, Some(25.0));
        assert_eq!(s.mean_height_m, Some(20.0));
        // 1 ha: the 100 thickest, here all three with a height.
        assert_eq!(s.dominant_height_m, Some(20.0));
        let agb: f64 = rows.iter().filter_map(|r| r.agb_kg).sum();
        assert!((s.agb_t_per_ha - agb / 1000.0).abs() < 1e-9);
        assert_eq!(s.stems_with_height, 3);
        let counts: Vec<usize> = s.dbh_classes.iter().map(|c| c.stems).collect();
        assert_eq!(counts, vec![0, 0, 1, 0, 1, 0, 1, 0, 1]);
        // The Gaussian DBH on request, and a boundary that leaves two trees out.
        let params = SummaryParams {
            dbh_source: DbhSource::Gaussians,
            boundary: Some(vec![[0.0, 0.0], [25.0, 0.0], [25.0, 40.0], [0.0, 40.0]]),
        };
        let s = summarise(&rows, &plot, &params, &p).expect("summary");
        assert_eq!((s.area_m2, s.stems, s.stems_outside), (1000.0, 2, 2));
        assert_eq!(s.mean_dbh_cm, Some(16.0));
        // Biomass from the Gaussian DBH (11 and 21 cm), not the rows' LiDAR figures.
        let agb: f64 = [(11.0, 10.0), (21.0, 20.0)]
            .iter()
            .filter_map(|&(d, h)| super::super::allometry::tree_allometry(d, Some(h), &p).agb_kg)
            .sum();
        assert!((s.agb_t_per_ha - agb / 1000.0 / 0.1).abs() < 1e-9, "{s:?}");
        // 0.1 ha: round(10) = 10 thickest, but only two have a height.
        assert_eq!(s.dominant_height_m, Some(15.0));
        assert!(summary_lines(&s)[0].contains("Gaussians"));
        let bad = SummaryParams {
            boundary: Some(vec![[0.0, 0.0], [1.0, 1.0]]),
            ..SummaryParams::default()
        };
        assert!(summarise(&rows, &plot, &bad, &p).is_err());
    }

    #[test]
    fn the_footprint_is_the_clouds_hull() {
        // A disc of radius 10 m sampled on a 5 cm grid: its hull is a little under π 100 m².
        let mut pts = Vec::new();
        for ix in -200..=200 {
            for iy in -200..=200 {
                let (x, y) = (ix as f32 * 0.05, iy as f32 * 0.05);
                if x * x + y * y <= 100.0 {
                    pts.push(glam::Vec3::new(x, y, 0.0));
                }
            }
        }
        let hull = footprint(&pts, DVec3::new(500_000.0, 4_000_000.0, 0.0));
        let area = hull.unsigned_area();
        assert!(area > 312.0 && area < 314.16, "{area}");
        assert!(hull.contains(&Point::new(500_000.0, 4_000_000.0)));
    }
}
