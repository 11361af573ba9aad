//! The parallel LAS/LAZ point reader: point records are decoded from raw bytes at fixed
//! offsets, on all cores, group by group.
//!
//! - LAZ: the chunk table is read once; each group of whole chunks (about [`GROUP_POINTS`]
//!   points) is read from the file with one `read_exact` and decompressed chunk-parallel by
//!   `laz::par_decompress` (the laz-rs decoder that lazrs, laspy's parallel backend, wraps)
//!   straight into one flat record buffer.
//! - LAS: each group of records is read with one `read_exact`.
//!
//! The records of a group are then converted in parallel, [`CONVERT_CHUNK`] at a time, into
//! the cloud's columns (local f32 positions, intensity, colour) with the same arithmetic as
//! the sequential reader (`Transform::direct`, then minus the local origin), so both give
//! bit-identical clouds. The two buffers are reused from group to group: no per-point
//! allocation, and memory stays at the cloud plus one group (about 84 MB of format-0 records).
//!
//! Files this path does not handle (LAZ without a chunk table, chunks of more than
//! [`MAX_CHUNK_POINTS`] points, a LAZ item layout whose size differs from the header's record
//! length) return `None`, and the caller falls back to the `las` crate's reader.

use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use ::las::Transform;
use ::las::Vector;
use glam::{DVec3, Vec3};
use rayon::prelude::*;

use super::super::pointcloud::{CloudFormat, PointCloud, colors_to_u8, local_origin};
use super::super::{IoError, PROGRESS_STEP, check_cancel};
use super::LasInfo;
use crate::progress::Progress;

/// Points per group: 2^22, about 84 chunks of the usual 50,000 points, enough for every
/// core to get several chunks per group, and 84 MB of raw format-0 records (20 bytes each).
const GROUP_POINTS: u64 = 1 << 22;

/// Records converted per parallel work unit (about 0.1 ms of work).
const CONVERT_CHUNK: usize = 16_384;

/// Largest chunk (points) this path accepts: bounds the buffer one chunk of an untrusted
/// file can ask for (64 × the usual 50,000-point chunk, 1.2 GB of the largest records).
const MAX_CHUNK_POINTS: u64 = 1 << 22;

/// Where the fields of one point record lie, bytes from its start.
#[derive(Debug, Clone, Copy)]
struct Layout {
    stride: usize,
    rgb_at: Option<usize>,
}

impl Layout {
    /// x, y, z (i32) at 0, 4, 8 and intensity (u16) at 12 in every format; RGB after the
    /// 20-byte legacy core (formats 2, 3, 5: + 8 bytes of GPS time in 3 and 5) or the 30-byte
    /// extended core (formats 7, 8, 10), ASPRS LAS 1.4 R15 tables 7–17.
    fn new(path: &Path, fmt: &::las::point::Format, stride: usize) -> Result<Self, IoError> {
        let rgb_at = fmt.has_color.then_some(if fmt.is_extended {
            30
        } else if fmt.has_gps_time {
            28
        } else {
            20
        });
        let need = rgb_at.map_or(14, |o| o + 6);
        if stride < need {
            return Err(IoError::format(
                path,
                format!("point records of {stride} bytes are too short (need {need})"),
            ));
        }
        Ok(Layout { stride, rgb_at })
    }
}

/// The cloud's columns, filled group by group.
struct Sink<'a> {
    path: &'a Path,
    layout: Layout,
    transforms: Vector<Transform>,
    hint: Option<(DVec3, DVec3)>,
    offset: Option<DVec3>,
    positions: Vec<Vec3>,
    intensity: Vec<u16>,
    colors: Option<Vec<[u16; 3]>>,
}

fn i32_at(rec: &[u8], o: usize) -> i32 {
    i32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]])
}

fn u16_at(rec: &[u8], o: usize) -> u16 {
    u16::from_le_bytes([rec[o], rec[o + 1]])
}

/// File coordinates of one record (metres), as `Transform::direct`.
fn world(t: &Vector<Transform>, rec: &[u8]) -> DVec3 {
    DVec3::new(
        t.x.direct(i32_at(rec, 0)),
        t.y.direct(i32_at(rec, 4)),
        t.z.direct(i32_at(rec, 8)),
    )
}

impl Sink<'_> {
    /// Appends the records of `raw` (a whole number of records).
    fn add(&mut self, raw: &[u8]) -> Result<(), IoError> {
        let stride = self.layout.stride;
        let m = raw.len() / stride;
        if m == 0 {
            return Ok(());
        }
        let offset = match self.offset {
            Some(o) => o,
            None => {
                // As `CloudBuilder`: the origin comes from the first PROGRESS_STEP points.
                let mut lo = DVec3::splat(f64::INFINITY);
                let mut hi = DVec3::splat(f64::NEG_INFINITY);
                for rec in raw.chunks_exact(stride).take(PROGRESS_STEP) {
                    let p = world(&self.transforms, rec);
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
                let o = if lo.is_finite() && hi.is_finite() {
                    local_origin(self.hint, lo, hi)
                } else {
                    DVec3::ZERO // a non-finite point fails below
                };
                self.offset = Some(o);
                o
            }
        };
        let base = self.positions.len();
        self.positions.resize(base + m, Vec3::ZERO);
        self.intensity.resize(base + m, 0);
        let t = self.transforms;
        let bad = self.positions[base..]
            .par_chunks_mut(CONVERT_CHUNK)
            .zip(self.intensity[base..].par_chunks_mut(CONVERT_CHUNK))
            .zip(raw.par_chunks(CONVERT_CHUNK * stride))
            .enumerate()
            .filter_map(|(c, ((pos, inten), recs))| {
                for (k, ((p, i), rec)) in pos
                    .iter_mut()
                    .zip(inten.iter_mut())
                    .zip(recs.chunks_exact(stride))
                    .enumerate()
                {
                    let w = world(&t, rec);
                    if !w.is_finite() {
                        return Some(c * CONVERT_CHUNK + k);
                    }
                    *p = (w - offset).as_vec3();
                    *i = u16_at(rec, 12);
                }
                None
            })
            .min();
        if let Some(k) = bad {
            return Err(IoError::format(
                self.path,
                format!("point {} has a non-finite coordinate", base + k),
            ));
        }
        if let (Some(colors), Some(o)) = (self.colors.as_mut(), self.layout.rgb_at) {
            colors.extend(
                raw.chunks_exact(stride)
                    .map(|rec| [u16_at(rec, o), u16_at(rec, o + 2), u16_at(rec, o + 4)]),
            );
        }
        Ok(())
    }

    fn finish(self, compressed: bool) -> PointCloud {
        let intensity = self.intensity;
        PointCloud {
            offset: self.offset.unwrap_or(DVec3::ZERO),
            positions: self.positions,
            colors: self.colors.map(|c| colors_to_u8(&c)),
            intensity: intensity.par_iter().any(|&i| i != 0).then_some(intensity),
            format: if compressed {
                CloudFormat::Laz
            } else {
                CloudFormat::Las
            },
        }
    }
}

/// Reads the point records of a LAS/LAZ file whose header is `header` (already checked by
/// [`super::inspect_las`] into `info`); `None` when this path cannot handle the file.
pub(super) fn read(
    path: &Path,
    info: &LasInfo,
    header: &::las::Header,
    start: u64,
    file: File,
    progress: &dyn Progress,
) -> Result<Option<PointCloud>, IoError> {
    let total = info.declared_points;
    if total == 0 {
        return Ok(None);
    }
    let layout = Layout::new(path, header.point_format(), usize::from(info.record_length))?;
    let b = header.bounds();
    let hint = Some((
        DVec3::new(b.min.x, b.min.y, b.min.z),
        DVec3::new(b.max.x, b.max.y, b.max.z),
    ))
    .filter(|(lo, hi)| lo.is_finite() && hi.is_finite() && lo.cmple(*hi).all());
    // Preallocate no more than the file could hold.
    let cap = total.min(super::file_len(path)?) as usize;
    let mut sink = Sink {
        path,
        layout,
        transforms: *header.transforms(),
        hint,
        offset: None,
        positions: Vec::with_capacity(cap),
        intensity: Vec::with_capacity(cap),
        colors: layout.rgb_at.map(|_| Vec::with_capacity(cap)),
    };
    let mut file = BufReader::new(file);
    let mut raw: Vec<u8> = Vec::new();
    let stride = layout.stride as u64;
    if info.compressed {
        let Some(vlr) = header
            .vlrs()
            .iter()
            .find(|v| v.user_id.trim_end_matches('\0') == "laszip encoded" && v.record_id == 22204)
        else {
            return Ok(None);
        };
        let Ok(laz_vlr) = laz::LazVlr::read_from(vlr.data.as_slice()) else {
            return Ok(None);
        };
        if laz_vlr.items_size() != stride {
            return Ok(None);
        }
        file.seek(SeekFrom::Start(start))
            .map_err(|e| IoError::io(path, e))?;
        let Ok(table) = laz::laszip::ChunkTable::read_from(&mut file, &laz_vlr) else {
            return Ok(None);
        };
        let mut chunks = table.as_ref().to_vec();
        if !laz_vlr.uses_variable_size_chunks() {
            // Fixed-size chunks: the table repeats the chunk size; the last chunk holds the rest.
            let cs = u64::from(laz_vlr.chunk_size());
            let before = (chunks.len() as u64).saturating_sub(1) * cs;
            match chunks.last_mut() {
                Some(last) if total > before && total <= before + cs => {
                    last.point_count = total - before;
                }
                _ => {
                    return Err(IoError::format(
                        path,
                        format!(
                            "header declares {total} points but the chunk table has {} chunks of {cs}",
                            chunks.len()
                        ),
                    ));
                }
            }
        }
        let held: u64 = chunks.iter().map(|c| c.point_count).sum();
        if held != total {
            return Err(IoError::format(
                path,
                format!("header declares {total} points but the chunk table holds {held}"),
            ));
        }
        if chunks.iter().any(|c| c.point_count > MAX_CHUNK_POINTS) {
            return Ok(None);
        }
        let data_end = super::file_len(path)?;
        let mut pos = start + 8;
        let mut compressed: Vec<u8> = Vec::new();
        let mut i = 0;
        while i < chunks.len() {
            check_cancel(progress)?;
            let (mut j, mut points, mut bytes) = (i, 0u64, 0u64);
            while j < chunks.len() && (j == i || points + chunks[j].point_count <= GROUP_POINTS) {
                points += chunks[j].point_count;
                bytes += chunks[j].byte_count;
                j += 1;
            }
            if pos.saturating_add(bytes) > data_end {
                return Err(IoError::format(
                    path,
                    "file is truncated (LAZ chunks end past the end of the file)",
                ));
            }
            compressed.resize(bytes as usize, 0);
            file.seek(SeekFrom::Start(pos))
                .and_then(|_| file.read_exact(&mut compressed))
                .map_err(|e| IoError::read(path, e, "LAZ chunks"))?;
            raw.resize((points * stride) as usize, 0);
            laz::par_decompress(&compressed, &mut raw, &laz_vlr, &chunks[i..j])
                .map_err(|e| IoError::format(path, format!("bad point data: {e}")))?;
            sink.add(&raw)?;
            progress.set(sink.positions.len() as f64 / total as f64);
            pos += bytes;
            i = j;
        }
    } else {
        file.seek(SeekFrom::Start(start))
            .map_err(|e| IoError::io(path, e))?;
        let mut done = 0u64;
        while done < total {
            check_cancel(progress)?;
            let points = (total - done).min(GROUP_POINTS);
            raw.resize((points * stride) as usize, 0);
            file.read_exact(&mut raw)
                .map_err(|e| IoError::read(path, e, "point records"))?;
            sink.add(&raw)?;
            done += points;
            progress.set(done as f64 / total as f64);
        }
    }
    Ok(Some(sink.finish(info.compressed)))
}
