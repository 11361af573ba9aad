//! Comparison of an inventory with field-measured DBH (docs/method.md Stage 5: "match trees by
//! position and report RMSE (cm), bias, R², mean relative error"), plus detection recall and
//! precision.
//!
//! Matching is one-to-one and greedy by distance: all (detected, field) pairs closer than
//! `max_distance_m` are sorted by distance and taken from the closest, skipping trees already
//! matched. Ties are broken by the row order, so the result is deterministic.

use std::path::Path;

use serde::Serialize;

use super::ForestError;
use super::inventory::TreeRow;
use crate::io::tables::{FieldTree, read_field_dbh};

/// Default matching radius, metres.
pub const MATCH_DISTANCE_M: f64 = 1.0;

/// One detected tree matched with one field tree.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MatchedTree {
    pub tree_id: u32,
    pub field_id: Option<String>,
    /// Horizontal distance between the two positions, metres.
    pub distance_m: f64,
    pub dbh_lidar_cm: f64,
    pub dbh_field_cm: f64,
}

/// Accuracy figures of an inventory against field data.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FieldComparison {
    pub n_detected: usize,
    pub n_field: usize,
    pub n_matched: usize,
    /// Matched / field trees, [0, 1].
    pub recall: f64,
    /// Matched / detected trees, [0, 1].
    pub precision: f64,
    /// Root-mean-square DBH error over the matched trees, cm (`None` without matches).
    pub rmse_cm: Option<f64>,
    /// Mean of (LiDAR − field) DBH, cm.
    pub bias_cm: Option<f64>,
    /// Coefficient of determination of the LiDAR DBH against the field DBH,
    /// 1 − SS_res / SS_tot (`None` with fewer than 2 matches or no spread in the field DBH).
    pub r2: Option<f64>,
    /// Mean of |LiDAR − field| / field, as a fraction.
    pub mean_relative_error: Option<f64>,
    pub matches: Vec<MatchedTree>,
}

/// Matches `rows` with `field` by position (both in the same coordinates, metres) and
/// computes the accuracy figures.
pub fn compare_with_field(
    rows: &[TreeRow],
    field: &[FieldTree],
    max_distance_m: f64,
) -> FieldComparison {
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (i, r) in rows.iter().enumerate() {
        for (j, f) in field.iter().enumerate() {
            let d = (r.x - f.x).hypot(r.y - f.y);
            if d <= max_distance_m {
                pairs.push((d, i, j));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let (mut used_r, mut used_f) = (vec![false; rows.len()], vec![false; field.len()]);
    let mut matches = Vec::new();
    for (d, i, j) in pairs {
        if used_r[i] || used_f[j] {
            continue;
        }
        used_r[i] = true;
        used_f[j] = true;
        matches.push(MatchedTree {
            tree_id: rows[i].tree_id,
            field_id: field[j].tree_id.clone(),
            distance_m: d,
            dbh_lidar_cm: rows[i].dbh_lidar_cm,
            dbh_field_cm: field[j].dbh_cm,
        });
    }
    let m = matches.len();
    let ratio = |a: usize, b: usize| if b > 0 { a as f64 / b as f64 } else { 0.0 };
    let mean = |f: &dyn Fn(&MatchedTree) -> f64| {
        (m > 0).then(|| matches.iter().map(f).sum::<f64>() / m as f64)
    };
    let rmse_cm = mean(&|t| (t.dbh_lidar_cm - t.dbh_field_cm).powi(2)).map(f64::sqrt);
    let bias_cm = mean(&|t| t.dbh_lidar_cm - t.dbh_field_cm);
    let mean_relative_error = mean(&|t| (t.dbh_lidar_cm - t.dbh_field_cm).abs() / t.dbh_field_cm);
    let r2 = mean(&|t| t.dbh_field_cm).and_then(|fm| {
        let ss_tot: f64 = matches.iter().map(|t| (t.dbh_field_cm - fm).powi(2)).sum();
        let ss_res: f64 = matches
            .iter()
            .map(|t| (t.dbh_lidar_cm - t.dbh_field_cm).powi(2))
            .sum();
        (m >= 2 && ss_tot > 0.0).then(|| 1.0 - ss_res / ss_tot)
    });
    FieldComparison {
        n_detected: rows.len(),
        n_field: field.len(),
        n_matched: m,
        recall: ratio(m, field.len()),
        precision: ratio(m, rows.len()),
        rmse_cm,
        bias_cm,
        r2,
        mean_relative_error,
        matches,
    }
}

/// Reads field DBH (x, y, dbh_cm; see [`read_field_dbh`]) and compares it with `rows` using
/// the default 1 m matching radius.
pub fn compare_with_field_file(
    rows: &[TreeRow],
    path: &Path,
) -> Result<FieldComparison, ForestError> {
    let field = read_field_dbh(path)?;
    Ok(compare_with_field(rows, &field, MATCH_DISTANCE_M))
}

/// The comparison as lines of text for a terminal or a job log.
pub fn accuracy_lines(c: &FieldComparison) -> Vec<String> {
    let opt = |v: Option<f64>, unit: &str, scale: f64| {
        v.map_or("n/a".to_string(), |v| format!("{:.2}{unit}", v * scale))
    };
    vec![
        format!(
            "trees: {} detected, {} in the field, {} matched within {MATCH_DISTANCE_M} m",
            c.n_detected, c.n_field, c.n_matched
        ),
        format!(
            "detection: recall {:.1}%, precision {:.1}%",
            c.recall * 100.0,
            c.precision * 100.0
        ),
        format!(
            "DBH: RMSE {}, bias {}, R² {}, mean relative error {}",
            opt(c.rmse_cm, " cm", 1.0),
            opt(c.bias_cm, " cm", 1.0),
            c.r2.map_or("n/a".to_string(), |v| format!("{v:.3}")),
            opt(c.mean_relative_error, "%", 100.0)
        ),
    ]
}
