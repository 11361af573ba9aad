//! XYZ text point clouds (`.xyz`, `.txt`, `.csv`, `.pts`).
//!
//! One point per line, columns separated by whitespace, commas or semicolons. The column
//! count is fixed by the first data line and must be one of:
//!
//! | columns | meaning |
//! |---|---|
//! | 3 | x y z |
//! | 4 | x y z intensity |
//! | 6 | x y z red green blue |
//! | 7 | x y z intensity red green blue (the Leica PTS order) |
//!
//! Coordinates are metres. Intensity is rounded and clamped to 0..=65535. Colour channels
//! must lie in 0..=65535 and are scaled down by 257 when any exceeds 255 (16-bit colour).
//! Empty lines and lines starting with `#` or `//` are skipped, and so is a first data line
//! that is not numeric (a column header) or holds a single number (the PTS point count).
//! Any other malformed line is a `Format` error naming its line number.

use std::io::BufRead;
use std::path::Path;

use glam::DVec3;
use serde::Serialize;

use super::pointcloud::{CloudBuilder, CloudFormat, PointCloud, colors_to_u8};
use super::{IoError, PROGRESS_STEP, check_cancel, file_len, open_buffered};
use crate::progress::Progress;

/// What the first lines of an XYZ file hold.
#[derive(Debug, Clone, Serialize)]
pub struct XyzInfo {
    /// Columns per data line (3, 4, 6 or 7).
    pub columns: usize,
    pub has_intensity: bool,
    pub has_color: bool,
    /// A skipped first line (column header or PTS count), if any.
    pub header_line: Option<String>,
    /// The first data lines (at most 5), as found.
    pub first_lines: Vec<String>,
}

/// Outcome of looking at one line.
enum Line {
    Skip,
    Data(Vec<f64>),
}

fn split(line: &str) -> impl Iterator<Item = &str> {
    line.split(|c: char| c == ',' || c == ';' || c.is_whitespace())
        .filter(|s| !s.is_empty())
}

/// Line-by-line parser shared by the reader and `inspect_xyz`.
struct Parser<'a> {
    path: &'a Path,
    columns: Option<usize>,
    header_line: Option<String>,
    line_no: u64,
}

impl<'a> Parser<'a> {
    fn new(path: &'a Path) -> Self {
        Parser {
            path,
            columns: None,
            header_line: None,
            line_no: 0,
        }
    }

    fn bad(&self, what: impl std::fmt::Display) -> IoError {
        IoError::format(self.path, format!("line {}: {what}", self.line_no))
    }

    fn parse(&mut self, raw: &str) -> Result<Line, IoError> {
        self.line_no += 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') || line.starts_with("//") {
            return Ok(Line::Skip);
        }
        let values: Result<Vec<f64>, _> = split(line).map(str::parse::<f64>).collect();
        let Some(columns) = self.columns else {
            let first_data = self.header_line.is_none();
            match values {
                Ok(v) if v.len() == 1 && first_data => {}
                Err(_) if first_data => {}
                Ok(v) => {
                    if ![3, 4, 6, 7].contains(&v.len()) {
                        return Err(
                            self.bad(format!("{} columns (expected 3, 4, 6 or 7)", v.len()))
                        );
                    }
                    self.columns = Some(v.len());
                    return self.check(v);
                }
                Err(e) => return Err(self.bad(format!("not a number ({e})"))),
            }
            self.header_line = Some(line.to_string());
            return Ok(Line::Skip);
        };
        let v = values.map_err(|e| self.bad(format!("not a number ({e})")))?;
        if v.len() != columns {
            return Err(self.bad(format!("{} columns, expected {columns}", v.len())));
        }
        self.check(v)
    }

    fn check(&self, v: Vec<f64>) -> Result<Line, IoError> {
        if !v[..3].iter().all(|c| c.is_finite()) {
            return Err(self.bad("non-finite coordinate"));
        }
        if v.len() >= 6 && !v[v.len() - 3..].iter().all(|c| (0.0..=65535.0).contains(c)) {
            return Err(self.bad("colour outside 0..=65535"));
        }
        Ok(Line::Data(v))
    }
}

/// Reads the first data lines only: column count, colour and a sample.
pub fn inspect_xyz(path: &Path) -> Result<XyzInfo, IoError> {
    if file_len(path)? == 0 {
        return Err(IoError::format(path, "file is empty"));
    }
    let r = open_buffered(path)?;
    let mut parser = Parser::new(path);
    let mut first_lines = Vec::new();
    for line in r.lines().take(1000) {
        let line = line.map_err(|e| IoError::read(path, e, "text line"))?;
        if let Line::Data(_) = parser.parse(&line)? {
            first_lines.push(line.trim().to_string());
            if first_lines.len() == 5 {
                break;
            }
        }
    }
    let Some(columns) = parser.columns else {
        return Err(IoError::format(path, "no numeric data line found"));
    };
    Ok(XyzInfo {
        columns,
        has_intensity: columns == 4 || columns == 7,
        has_color: columns >= 6,
        header_line: parser.header_line,
        first_lines,
    })
}

/// Reads a whole XYZ text file (see the module documentation for the columns).
pub fn read_xyz(path: &Path, progress: &dyn Progress) -> Result<PointCloud, IoError> {
    let total = file_len(path)?;
    let mut r = open_buffered(path)?;
    let mut parser = Parser::new(path);
    let mut cloud = CloudBuilder::new(path, None, total / 30);
    let (mut intensity, mut colors) = (Vec::new(), Vec::new());
    let (mut line, mut done) = (String::new(), 0u64);
    loop {
        if parser.line_no.is_multiple_of(PROGRESS_STEP as u64) {
            check_cancel(progress)?;
            progress.set(done as f64 / total.max(1) as f64);
        }
        line.clear();
        let n = r
            .read_line(&mut line)
            .map_err(|e| IoError::read(path, e, format!("line {}", parser.line_no + 1).as_str()))?;
        if n == 0 {
            break;
        }
        done += n as u64;
        let Line::Data(v) = parser.parse(&line)? else {
            continue;
        };
        cloud.push(DVec3::new(v[0], v[1], v[2]))?;
        if v.len() == 4 || v.len() == 7 {
            intensity.push(v[3].round().clamp(0.0, 65535.0) as u16);
        }
        if v.len() >= 6 {
            let k = v.len() - 3;
            colors.push([v[k], v[k + 1], v[k + 2]].map(|c| c.round() as u16));
        }
    }
    if parser.columns.is_none() {
        return Err(IoError::format(path, "no numeric data line found"));
    }
    progress.set(1.0);
    let (offset, positions) = cloud.finish();
    Ok(PointCloud {
        offset,
        positions,
        colors: (!colors.is_empty()).then(|| colors_to_u8(&colors)),
        intensity: (!intensity.is_empty()).then_some(intensity),
        format: CloudFormat::Xyz,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::pointcloud::{inspect_point_cloud, read_point_cloud};
    use crate::io::real_data;
    use crate::progress::{Cancelled, NoProgress};

    fn write(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn column_layouts_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let three = write(
            dir.path(),
            "a.xyz",
            "# comment\nx y z\n1.5 2.5 3.5\n\n-1 -2 -3\n",
        );
        let c = read_point_cloud(&three, &NoProgress).unwrap();
        assert_eq!(c.len(), 2);
        assert_eq!(c.offset, DVec3::new(-1.0, -2.0, -3.0));
        assert_eq!(c.world(0), DVec3::new(1.5, 2.5, 3.5));
        assert!(c.colors.is_none() && c.intensity.is_none());

        let four = write(dir.path(), "b.csv", "1,2,3,40\n4,5,6,70000\n");
        assert_eq!(
            read_xyz(&four, &NoProgress).unwrap().intensity,
            Some(vec![40, 65535])
        );

        let six = write(dir.path(), "c.txt", "1 2 3 255 0 10\n");
        assert_eq!(
            read_xyz(&six, &NoProgress).unwrap().colors,
            Some(vec![[255, 0, 10]])
        );

        let seven = write(
            dir.path(),
            "d.pts",
            "2\n1 2 3 -5 255 128 0\n4 5 6 9 0 0 0\n",
        );
        let c = read_xyz(&seven, &NoProgress).unwrap();
        assert_eq!(c.intensity, Some(vec![0, 9]));
        assert_eq!(c.colors.as_ref().unwrap()[0], [255, 128, 0]);
        let info = inspect_xyz(&seven).unwrap();
        assert_eq!((info.columns, info.has_color), (7, true));
        assert_eq!(info.header_line.as_deref(), Some("2"));
    }

    #[test]
    fn malformed_line_names_its_number() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "bad.xyz", "1 2 3\n4 5 6\n7 eight 9\n");
        let e = read_xyz(&p, &NoProgress).unwrap_err().to_string();
        assert!(e.contains("line 3"), "{e}");
        let p = write(dir.path(), "cols.xyz", "1 2 3\n4 5 6 7\n");
        let e = read_xyz(&p, &NoProgress).unwrap_err().to_string();
        assert!(e.contains("line 2"), "{e}");
        let p = write(dir.path(), "five.xyz", "1 2 3 4 5\n");
        assert!(matches!(
            inspect_point_cloud(&p),
            Err(IoError::Format { .. })
        ));
        let p = write(dir.path(), "inf.xyz", "1 2 3\ninf 2 3\n");
        let e = read_xyz(&p, &NoProgress).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("non-finite"), "{e}");
        let p = write(dir.path(), "hdr.xyz", "# only comments\nx y z\n");
        assert!(matches!(
            read_xyz(&p, &NoProgress),
            Err(IoError::Format { .. })
        ));
    }

    #[test]
    fn cancellation_stops_reading() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "a.xyz", "1 2 3\n");
        assert!(matches!(read_xyz(&p, &Cancelled), Err(IoError::Cancelled)));
    }

    #[test]
    fn real_adtree_xyz_reads_fully() {
        let Some(path) = real_data("AdTree_trees/tree1.xyz") else {
            return;
        };
        assert_eq!(inspect_xyz(&path).unwrap().columns, 3);
        let c = read_point_cloud(&path, &NoProgress).unwrap();
        let lines = std::fs::read_to_string(&path).unwrap();
        let expect = lines.lines().filter(|l| !l.trim().is_empty()).count();
        assert_eq!(c.len(), expect);
        assert!(c.len() > 10_000);
        let (lo, hi) = c.bounds().unwrap();
        assert!(lo.is_finite() && hi.is_finite() && (hi.z - lo.z) > 3.0);
    }
}
