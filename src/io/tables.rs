//! Small CSV tables users bring with a plot: control point pairs and field-measured DBH.
//!
//! Both are comma-separated with a header row naming the columns (any order, extra columns
//! ignored, `#` comment lines skipped):
//! - control points: `sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z` (optional `name`), one pair
//!   per row, the same physical point in the SfM frame and in the LiDAR file's coordinates;
//! - field DBH: `x,y,dbh_cm` (optional `tree_id`), stem position in the LiDAR file's
//!   coordinates (metres) and the tape-measured diameter at 1.3 m in centimetres.

use std::path::Path;

use glam::DVec3;
use serde::Serialize;

use super::IoError;

/// One control point pair: the same point in both frames.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ControlPoint {
    pub name: Option<String>,
    pub sfm: DVec3,
    pub lidar: DVec3,
}

/// One tree measured in the field.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FieldTree {
    pub tree_id: Option<String>,
    pub x: f64,
    pub y: f64,
    /// Diameter at breast height, centimetres.
    pub dbh_cm: f64,
}

/// Minimum number of control point pairs (docs/method.md: >= 4).
pub const MIN_CONTROL_POINTS: usize = 4;

struct Table {
    header: Vec<String>,
    rows: Vec<(usize, Vec<String>)>,
}

fn read_table(path: &Path) -> Result<Table, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::Io {
        path: path.to_path_buf(),
        source: e,
    })?;
    // The `csv` crate (RFC 4180 quoting: a quoted field may hold commas and quotes).
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .flexible(true)
        .from_reader(bytes.as_slice());
    let mut records = Vec::new();
    for rec in reader.records() {
        let rec = rec.map_err(|e| match e.kind() {
            csv::ErrorKind::Utf8 { .. } => IoError::format(path, "not UTF-8 text"),
            _ => IoError::format(path, e.to_string()),
        })?;
        if rec.iter().all(str::is_empty) {
            continue;
        }
        let line = rec.position().map_or(0, |p| p.line() as usize);
        records.push((line, rec.iter().map(str::to_string).collect::<Vec<_>>()));
    }
    let mut rows = records.into_iter();
    let Some((_, header)) = rows.next() else {
        return Err(IoError::format(
            path,
            "empty table: a header row is required",
        ));
    };
    let header = header.iter().map(|h| h.to_ascii_lowercase()).collect();
    Ok(Table {
        header,
        rows: rows.collect(),
    })
}

impl Table {
    fn column(&self, path: &Path, name: &str) -> Result<usize, IoError> {
        self.header.iter().position(|h| h == name).ok_or_else(|| {
            IoError::format(
                path,
                format!(
                    "missing column `{name}` (header has: {})",
                    self.header.join(",")
                ),
            )
        })
    }

    fn optional(&self, name: &str) -> Option<usize> {
        self.header.iter().position(|h| h == name)
    }
}

fn number(
    path: &Path,
    line: usize,
    row: &[String],
    col: usize,
    name: &str,
) -> Result<f64, IoError> {
    let cell = row
        .get(col)
        .ok_or_else(|| IoError::format(path, format!("line {line}: no value for `{name}`")))?;
    let v: f64 = cell.parse().map_err(|_| {
        IoError::format(
            path,
            format!("line {line}: `{name}` = {cell:?} is not a number"),
        )
    })?;
    if !v.is_finite() {
        return Err(IoError::format(
            path,
            format!("line {line}: `{name}` is not finite"),
        ));
    }
    Ok(v)
}

/// Reads control point pairs; fewer than [`MIN_CONTROL_POINTS`] is an error.
pub fn read_control_points(path: &Path) -> Result<Vec<ControlPoint>, IoError> {
    let t = read_table(path)?;
    let names = ["sfm_x", "sfm_y", "sfm_z", "lidar_x", "lidar_y", "lidar_z"];
    let cols = names
        .iter()
        .map(|n| t.column(path, n))
        .collect::<Result<Vec<_>, _>>()?;
    let name_col = t.optional("name");
    let mut out = Vec::with_capacity(t.rows.len());
    for (line, row) in &t.rows {
        let mut v = [0.0; 6];
        for (k, (&c, n)) in cols.iter().zip(names).enumerate() {
            v[k] = number(path, *line, row, c, n)?;
        }
        out.push(ControlPoint {
            name: name_col.and_then(|c| row.get(c).cloned()),
            sfm: DVec3::new(v[0], v[1], v[2]),
            lidar: DVec3::new(v[3], v[4], v[5]),
        });
    }
    if out.len() < MIN_CONTROL_POINTS {
        return Err(IoError::format(
            path,
            format!(
                "{} control point pairs given; at least {MIN_CONTROL_POINTS} are needed",
                out.len()
            ),
        ));
    }
    Ok(out)
}

/// Reads field-measured trees; DBH must be positive and below 10 m.
pub fn read_field_dbh(path: &Path) -> Result<Vec<FieldTree>, IoError> {
    let t = read_table(path)?;
    let (cx, cy, cd) = (
        t.column(path, "x")?,
        t.column(path, "y")?,
        t.column(path, "dbh_cm")?,
    );
    let id_col = t.optional("tree_id");
    let mut out = Vec::with_capacity(t.rows.len());
    for (line, row) in &t.rows {
        let dbh_cm = number(path, *line, row, cd, "dbh_cm")?;
        if !(dbh_cm > 0.0 && dbh_cm < 1000.0) {
            return Err(IoError::format(
                path,
                format!("line {line}: dbh_cm = {dbh_cm} is outside (0, 1000) cm"),
            ));
        }
        out.push(FieldTree {
            tree_id: id_col.and_then(|c| row.get(c).cloned()),
            x: number(path, *line, row, cx, "x")?,
            y: number(path, *line, row, cy, "y")?,
            dbh_cm,
        });
    }
    if out.is_empty() {
        return Err(IoError::format(path, "no trees listed"));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(text: &str) -> tempfile::NamedTempFile {
        let f = tempfile::NamedTempFile::new().expect("temp file");
        std::fs::write(f.path(), text).expect("write");
        f
    }

    #[test]
    fn control_points_parse_in_any_column_order() {
        let f = write(
            "# pairs\nname,lidar_x,lidar_y,lidar_z,sfm_x,sfm_y,sfm_z\n\
             a,1,2,3,0.1,0.2,0.3\nb,4,5,6,0.4,0.5,0.6\nc,7,8,9,0.7,0.8,0.9\nd,1,1,1,0,0,0\n",
        );
        let cps = read_control_points(f.path()).expect("valid");
        assert_eq!(cps.len(), 4);
        assert_eq!(cps[0].lidar, DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(cps[0].sfm, DVec3::new(0.1, 0.2, 0.3));
        assert_eq!(cps[0].name.as_deref(), Some("a"));
    }

    #[test]
    fn too_few_control_points_are_refused() {
        let f = write("sfm_x,sfm_y,sfm_z,lidar_x,lidar_y,lidar_z\n1,2,3,4,5,6\n");
        let e = read_control_points(f.path()).expect_err("one pair");
        assert!(e.to_string().contains("at least 4"), "{e}");
    }

    #[test]
    fn bad_number_names_the_line() {
        let f = write("x,y,dbh_cm\n1,2,30\n3,four,20\n");
        let e = read_field_dbh(f.path()).expect_err("bad number");
        assert!(e.to_string().contains("line 3"), "{e}");
    }

    #[test]
    fn quoted_fields_may_hold_commas_and_quotes() {
        let f = write(
            "\"tree_id\",x,y,dbh_cm\n\"oak, the \"\"old\"\" one\",1.5,2,31.5\n\n# note\nbeech,3,4,20\n",
        );
        let trees = read_field_dbh(f.path()).expect("valid");
        assert_eq!(trees.len(), 2);
        assert_eq!(trees[0].tree_id.as_deref(), Some("oak, the \"old\" one"));
        assert_eq!((trees[0].x, trees[0].dbh_cm), (1.5, 31.5));
        assert_eq!(trees[1].tree_id.as_deref(), Some("beech"));
        let e =
            read_field_dbh(write("x,y,dbh_cm\n1,2,3\n\"4,5,6\n").path()).expect_err("open quote");
        assert!(
            e.to_string().contains("dbh_cm") || e.to_string().contains("line"),
            "{e}"
        );
    }

    #[test]
    fn missing_column_is_named() {
        let f = write("x,y,diameter\n1,2,30\n");
        let e = read_field_dbh(f.path()).expect_err("no dbh_cm");
        assert!(e.to_string().contains("dbh_cm"), "{e}");
    }
}
