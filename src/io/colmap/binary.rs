//! COLMAP binary models (little endian): cameras.bin, images.bin, points3D.bin.
//!
//! Counts in the files are never trusted for allocation: preallocation is capped.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::Path;

use glam::DVec3;

use super::{Camera, CameraModel, ColmapModel, Image, Point2D, Point3D, insert_new};
use crate::io::{IoError, check_cancel, open_buffered};
use crate::progress::Progress;

/// Largest preallocation taken from a count found in a file.
const MAX_PREALLOC: u64 = 4096;
/// Longest accepted image name, bytes.
const MAX_NAME: usize = 4096;

/// Little-endian reader that names the record being read in its errors.
struct Bin<'a> {
    path: &'a Path,
    r: BufReader<File>,
    what: &'static str,
    record: u64,
}

impl<'a> Bin<'a> {
    fn open(path: &'a Path, what: &'static str) -> Result<Self, IoError> {
        Ok(Bin {
            path,
            r: open_buffered(path)?,
            what,
            record: 0,
        })
    }

    fn bad(&self, fault: impl std::fmt::Display) -> IoError {
        IoError::format(
            self.path,
            format!("{} record {}: {fault}", self.what, self.record),
        )
    }

    fn bytes<const N: usize>(&mut self) -> Result<[u8; N], IoError> {
        let mut b = [0u8; N];
        match self.r.read_exact(&mut b) {
            Ok(()) => Ok(b),
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => {
                Err(self.bad("file is truncated"))
            }
            Err(e) => Err(IoError::io(self.path, e)),
        }
    }
    fn u8(&mut self) -> Result<u8, IoError> {
        Ok(self.bytes::<1>()?[0])
    }
    fn u32(&mut self) -> Result<u32, IoError> {
        self.bytes().map(u32::from_le_bytes)
    }
    fn i32(&mut self) -> Result<i32, IoError> {
        self.bytes().map(i32::from_le_bytes)
    }
    fn u64(&mut self) -> Result<u64, IoError> {
        self.bytes().map(u64::from_le_bytes)
    }
    fn i64(&mut self) -> Result<i64, IoError> {
        self.bytes().map(i64::from_le_bytes)
    }
    fn f64(&mut self) -> Result<f64, IoError> {
        self.bytes().map(f64::from_le_bytes)
    }

    /// Starts record `k` of `count`, reporting progress and checking for cancellation every
    /// `every` records.
    fn start_record(
        &mut self,
        k: u64,
        count: u64,
        every: u64,
        progress: &dyn Progress,
    ) -> Result<(), IoError> {
        if k.is_multiple_of(every) {
            check_cancel(progress)?;
            progress.set(k as f64 / count as f64);
        }
        self.record = k;
        Ok(())
    }

    /// After the last record the file must end.
    fn finish(mut self) -> Result<(), IoError> {
        let mut b = [0u8; 1];
        match self.r.read(&mut b) {
            Ok(0) => Ok(()),
            Ok(_) => Err(IoError::format(
                self.path,
                "trailing bytes after the last record",
            )),
            Err(e) => Err(IoError::io(self.path, e)),
        }
    }
}

pub(super) fn read_cameras(path: &Path) -> Result<BTreeMap<u32, Camera>, IoError> {
    let mut b = Bin::open(path, "camera")?;
    let count = b.u64()?;
    let mut out = BTreeMap::new();
    for k in 0..count {
        b.record = k;
        let id = b.u32()?;
        let model_id = b.i32()?;
        let model = CameraModel::from_id(model_id)
            .ok_or_else(|| b.bad(format!("unknown camera model id {model_id}")))?;
        let width = b.u64()?;
        let height = b.u64()?;
        let params = (0..model.num_params())
            .map(|_| b.f64())
            .collect::<Result<Vec<_>, _>>()?;
        let camera = Camera::new(id, model, width, height, params).map_err(|m| b.bad(m))?;
        insert_new(&mut out, "camera", id, camera).map_err(|m| b.bad(m))?;
    }
    b.finish()?;
    Ok(out)
}

pub(super) fn read_images(
    path: &Path,
    progress: &dyn Progress,
) -> Result<BTreeMap<u32, Image>, IoError> {
    let mut b = Bin::open(path, "image")?;
    let count = b.u64()?;
    let mut out = BTreeMap::new();
    for k in 0..count {
        b.start_record(k, count, 256, progress)?;
        let id = b.u32()?;
        let qvec = [b.f64()?, b.f64()?, b.f64()?, b.f64()?];
        let tvec = [b.f64()?, b.f64()?, b.f64()?];
        let camera_id = b.u32()?;
        let mut name = Vec::new();
        loop {
            match b.u8()? {
                0 => break,
                c if name.len() < MAX_NAME => name.push(c),
                _ => return Err(b.bad("image name is too long")),
            }
        }
        let name = String::from_utf8(name).map_err(|_| b.bad("image name is not UTF-8"))?;
        let n = b.u64()?;
        let mut points2d = Vec::with_capacity(n.min(MAX_PREALLOC) as usize);
        for _ in 0..n {
            let xy = [b.f64()?, b.f64()?];
            let point3d_id = match b.i64()? {
                -1 => None,
                v if v >= 0 => Some(v as u64),
                v => return Err(b.bad(format!("invalid POINT3D_ID {v}"))),
            };
            points2d.push(Point2D { xy, point3d_id });
        }
        let img = Image {
            id,
            qvec,
            tvec,
            camera_id,
            name,
            points2d,
        };
        insert_new(&mut out, "image", id, img).map_err(|m| b.bad(m))?;
    }
    b.finish()?;
    Ok(out)
}

pub(super) fn read_points(path: &Path, progress: &dyn Progress) -> Result<Vec<Point3D>, IoError> {
    let mut b = Bin::open(path, "point3D")?;
    let count = b.u64()?;
    let mut out = Vec::with_capacity(count.min(MAX_PREALLOC) as usize);
    for k in 0..count {
        b.start_record(k, count, 65_536, progress)?;
        let id = b.u64()?;
        let xyz = DVec3::new(b.f64()?, b.f64()?, b.f64()?);
        let rgb = [b.u8()?, b.u8()?, b.u8()?];
        let error = b.f64()?;
        let n = b.u64()?;
        let mut track = Vec::with_capacity(n.min(MAX_PREALLOC) as usize);
        for _ in 0..n {
            track.push((b.u32()?, b.u32()?));
        }
        out.push(Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    b.finish()?;
    Ok(out)
}

/// Writes the three binary files.
pub(super) fn write(model: &ColmapModel, dir: &Path) -> Result<(), IoError> {
    let mut buf = Vec::new();
    buf.extend((model.cameras.len() as u64).to_le_bytes());
    for c in model.cameras.values() {
        buf.extend(c.id.to_le_bytes());
        buf.extend(c.model.model_id().to_le_bytes());
        buf.extend(c.width.to_le_bytes());
        buf.extend(c.height.to_le_bytes());
        c.params.iter().for_each(|p| buf.extend(p.to_le_bytes()));
    }
    save(&dir.join("cameras.bin"), &buf)?;

    let path = dir.join("images.bin");
    let io = |e| IoError::io(&path, e);
    let mut w = BufWriter::new(File::create(&path).map_err(io)?);
    w.write_all(&(model.images.len() as u64).to_le_bytes())
        .map_err(io)?;
    for i in model.images.values() {
        buf.clear();
        buf.extend(i.id.to_le_bytes());
        i.qvec
            .iter()
            .chain(&i.tvec)
            .for_each(|v| buf.extend(v.to_le_bytes()));
        buf.extend(i.camera_id.to_le_bytes());
        buf.extend(i.name.as_bytes());
        buf.push(0);
        buf.extend((i.points2d.len() as u64).to_le_bytes());
        for p in &i.points2d {
            buf.extend(p.xy[0].to_le_bytes());
            buf.extend(p.xy[1].to_le_bytes());
            buf.extend(p.point3d_id.map_or(-1i64, |v| v as i64).to_le_bytes());
        }
        w.write_all(&buf).map_err(io)?;
    }
    w.flush().map_err(io)?;

    let path = dir.join("points3D.bin");
    let io = |e| IoError::io(&path, e);
    let mut w = BufWriter::new(File::create(&path).map_err(io)?);
    w.write_all(&(model.points.len() as u64).to_le_bytes())
        .map_err(io)?;
    for p in &model.points {
        buf.clear();
        buf.extend(p.id.to_le_bytes());
        p.xyz
            .to_array()
            .iter()
            .for_each(|v| buf.extend(v.to_le_bytes()));
        buf.extend(p.rgb);
        buf.extend(p.error.to_le_bytes());
        buf.extend((p.track.len() as u64).to_le_bytes());
        for (img, idx) in &p.track {
            buf.extend(img.to_le_bytes());
            buf.extend(idx.to_le_bytes());
        }
        w.write_all(&buf).map_err(io)?;
    }
    w.flush().map_err(io)
}

fn save(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    std::fs::write(path, bytes).map_err(|e| IoError::io(path, e))
}
