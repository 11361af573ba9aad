//! COLMAP text models: cameras.txt, images.txt (two lines per image; the second, the 2-D
//! points, may be empty) and points3D.txt, with `#` comment lines.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::Path;
use std::str::FromStr;

use glam::DVec3;

use super::{Camera, CameraModel, ColmapModel, Image, Point2D, Point3D, insert_new};
use crate::io::{IoError, PROGRESS_STEP, check_cancel, file_len, open_buffered};
use crate::progress::Progress;

/// Numbered lines of a text file.
struct Lines<'a> {
    path: &'a Path,
    r: BufReader<File>,
    no: u64,
    buf: String,
    done: u64,
}

impl<'a> Lines<'a> {
    fn open(path: &'a Path) -> Result<Self, IoError> {
        Ok(Lines {
            path,
            r: open_buffered(path)?,
            no: 0,
            buf: String::new(),
            done: 0,
        })
    }

    /// The next line (trimmed), `None` at end of file.
    fn next_raw(&mut self) -> Result<Option<&str>, IoError> {
        self.buf.clear();
        let n = self
            .r
            .read_line(&mut self.buf)
            .map_err(|e| IoError::read(self.path, e, &format!("line {}", self.no + 1)))?;
        self.no += 1;
        self.done += n as u64;
        Ok((n > 0).then(|| self.buf.trim()))
    }

    /// The next line that is neither empty nor a comment.
    fn next_data(&mut self) -> Result<Option<Vec<String>>, IoError> {
        loop {
            match self.next_raw()? {
                None => return Ok(None),
                Some(l) if l.is_empty() || l.starts_with('#') => {}
                Some(l) => return Ok(Some(l.split_whitespace().map(str::to_string).collect())),
            }
        }
    }

    fn bad(&self, what: impl std::fmt::Display) -> IoError {
        IoError::format(self.path, format!("line {}: {what}", self.no))
    }

    fn num<T: FromStr>(&self, tok: Option<&String>, what: &str) -> Result<T, IoError> {
        tok.and_then(|t| t.parse().ok())
            .ok_or_else(|| self.bad(format!("missing or invalid {what}")))
    }
}

fn point3d_id(lines: &Lines<'_>, tok: &String) -> Result<Option<u64>, IoError> {
    match tok.parse::<i64>() {
        Ok(-1) => Ok(None),
        Ok(v) if v >= 0 => Ok(Some(v as u64)),
        _ => lines.num(Some(tok), "POINT3D_ID").map(Some),
    }
}

pub(super) fn read_cameras(path: &Path) -> Result<BTreeMap<u32, Camera>, IoError> {
    let mut lines = Lines::open(path)?;
    let mut out = BTreeMap::new();
    while let Some(t) = lines.next_data()? {
        let id: u32 = lines.num(t.first(), "CAMERA_ID")?;
        let name = t.get(1).map_or("", String::as_str);
        let model = CameraModel::from_name(name)
            .ok_or_else(|| lines.bad(format!("unknown camera model {name:?}")))?;
        let width = lines.num(t.get(2), "WIDTH")?;
        let height = lines.num(t.get(3), "HEIGHT")?;
        let params = t[4.min(t.len())..]
            .iter()
            .map(|p| lines.num(Some(p), "parameter"))
            .collect::<Result<Vec<f64>, _>>()?;
        let camera = Camera::new(id, model, width, height, params).map_err(|m| lines.bad(m))?;
        insert_new(&mut out, "camera", id, camera).map_err(|m| lines.bad(m))?;
    }
    Ok(out)
}

pub(super) fn read_images(
    path: &Path,
    progress: &dyn Progress,
) -> Result<BTreeMap<u32, Image>, IoError> {
    let total = file_len(path)?.max(1) as f64;
    let mut lines = Lines::open(path)?;
    let mut out = BTreeMap::new();
    while let Some(t) = lines.next_data()? {
        if out.len() % 1024 == 0 {
            check_cancel(progress)?;
            progress.set(lines.done as f64 / total);
        }
        if t.len() < 10 {
            return Err(lines.bad("image line needs IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"));
        }
        let id: u32 = lines.num(t.first(), "IMAGE_ID")?;
        let mut q = [0f64; 4];
        for (k, v) in q.iter_mut().enumerate() {
            *v = lines.num(t.get(1 + k), "quaternion")?;
        }
        let mut tv = [0f64; 3];
        for (k, v) in tv.iter_mut().enumerate() {
            *v = lines.num(t.get(5 + k), "translation")?;
        }
        let camera_id = lines.num(t.get(8), "CAMERA_ID")?;
        let name = t[9..].join(" ");
        let pts: Vec<String> = match lines.next_raw()? {
            Some(l) => l.split_whitespace().map(str::to_string).collect(),
            None => Vec::new(),
        };
        if !pts.len().is_multiple_of(3) {
            return Err(lines.bad("2-D points must come as X Y POINT3D_ID triples"));
        }
        let mut points2d = Vec::with_capacity(pts.len() / 3);
        for c in pts.chunks_exact(3) {
            let xy = [lines.num(c.first(), "X")?, lines.num(c.get(1), "Y")?];
            points2d.push(Point2D {
                xy,
                point3d_id: point3d_id(&lines, &c[2])?,
            });
        }
        let img = Image {
            id,
            qvec: q,
            tvec: tv,
            camera_id,
            name,
            points2d,
        };
        insert_new(&mut out, "image", id, img).map_err(|m| lines.bad(m))?;
    }
    Ok(out)
}

pub(super) fn read_points(path: &Path, progress: &dyn Progress) -> Result<Vec<Point3D>, IoError> {
    let total = file_len(path)?.max(1) as f64;
    let mut lines = Lines::open(path)?;
    let mut out = Vec::new();
    while let Some(t) = lines.next_data()? {
        if out.len() % PROGRESS_STEP == 0 {
            check_cancel(progress)?;
            progress.set(lines.done as f64 / total);
        }
        if t.len() < 8 || (t.len() - 8) % 2 != 0 {
            return Err(
                lines.bad("point needs ID X Y Z R G B ERROR and (IMAGE_ID, POINT2D_IDX) pairs")
            );
        }
        let id = lines.num(t.first(), "POINT3D_ID")?;
        let xyz = DVec3::new(
            lines.num(t.get(1), "X")?,
            lines.num(t.get(2), "Y")?,
            lines.num(t.get(3), "Z")?,
        );
        let rgb = [
            lines.num(t.get(4), "R")?,
            lines.num(t.get(5), "G")?,
            lines.num(t.get(6), "B")?,
        ];
        let error = lines.num(t.get(7), "ERROR")?;
        let track = t[8..]
            .chunks_exact(2)
            .map(|p| {
                Ok((
                    lines.num(p.first(), "IMAGE_ID")?,
                    lines.num(p.get(1), "POINT2D_IDX")?,
                ))
            })
            .collect::<Result<Vec<_>, IoError>>()?;
        out.push(Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    Ok(out)
}

fn write_file(
    path: &Path,
    header: &str,
    body: impl Fn(&mut String, usize) -> bool,
) -> Result<(), IoError> {
    let io = |e| IoError::io(path, e);
    let mut w = BufWriter::new(File::create(path).map_err(io)?);
    w.write_all(header.as_bytes()).map_err(io)?;
    let mut s = String::new();
    for k in 0.. {
        s.clear();
        if !body(&mut s, k) {
            break;
        }
        w.write_all(s.as_bytes()).map_err(io)?;
    }
    w.flush().map_err(io)
}

/// Writes the three text files; floats use Rust's shortest exact representation, so a
/// text round trip is lossless.
pub(super) fn write(model: &ColmapModel, dir: &Path) -> Result<(), IoError> {
    let cams: Vec<&Camera> = model.cameras.values().collect();
    let header = format!(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: {}\n",
        cams.len()
    );
    write_file(&dir.join("cameras.txt"), &header, |s, k| {
        let Some(c) = cams.get(k) else { return false };
        let _ = write!(s, "{} {} {} {}", c.id, c.model.name(), c.width, c.height);
        c.params.iter().for_each(|p| {
            let _ = write!(s, " {p}");
        });
        s.push('\n');
        true
    })?;
    let imgs: Vec<&Image> = model.images.values().collect();
    let obs: usize = imgs.iter().map(|i| i.points2d.len()).sum();
    let header = format!(
        "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n# Number of images: {}, mean observations per image: {}\n",
        imgs.len(),
        obs as f64 / imgs.len().max(1) as f64
    );
    write_file(&dir.join("images.txt"), &header, |s, k| {
        let Some(i) = imgs.get(k) else { return false };
        let [qw, qx, qy, qz] = i.qvec;
        let [tx, ty, tz] = i.tvec;
        let _ = writeln!(
            s,
            "{} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {} {}",
            i.id, i.camera_id, i.name
        );
        for (n, p) in i.points2d.iter().enumerate() {
            let id = p.point3d_id.map_or(-1, |v| v as i128);
            let _ = write!(
                s,
                "{}{} {} {id}",
                if n > 0 { " " } else { "" },
                p.xy[0],
                p.xy[1]
            );
        }
        s.push('\n');
        true
    })?;
    let track: usize = model.points.iter().map(|p| p.track.len()).sum();
    let header = format!(
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n# Number of points: {}, mean track length: {}\n",
        model.points.len(),
        track as f64 / model.points.len().max(1) as f64
    );
    write_file(&dir.join("points3D.txt"), &header, |s, k| {
        let Some(p) = model.points.get(k) else {
            return false;
        };
        let [r, g, b] = p.rgb;
        let _ = write!(
            s,
            "{} {} {} {} {r} {g} {b} {}",
            p.id, p.xyz.x, p.xyz.y, p.xyz.z, p.error
        );
        for (img, idx) in &p.track {
            let _ = write!(s, " {img} {idx}");
        }
        s.push('\n');
        true
    })
}
