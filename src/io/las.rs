//! LAS 1.0–1.4 (point formats 0–10, 64-bit point counts) through the `las` crate, and LAZ:
//! LAZ with a chunk table goes through the fused chunk-parallel reader of `las/fused.rs`
//! (decoding and conversion in one rayon task per chunk), other LAZ through the sequential
//! reader of `las/pointwise.rs`, which gives the same cloud. Neither runs laz-rs's GPS-time
//! decoders, which a hostile file can make recurse until the stack overflows (see
//! `pointwise.rs`).
//!
//! Before any point is decoded the declared point count is checked against the file: for
//! uncompressed LAS the point-record region must hold exactly the declared number of
//! records; for LAZ with fixed-size chunks the chunk table must have the number of chunks the
//! count implies. A mismatch is a `Format` error, never a silent short read.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom};
use std::path::Path;

use ::las::point::Format;
use ::las::{Builder, Color, Point, PointDataBuilder, Transform, Vector};
use glam::DVec3;
use serde::Serialize;

use super::pointcloud::{CloudBuilder, CloudFormat, PointCloud, colors_to_u8};
use super::{IoError, PROGRESS_STEP, check_cancel, file_len, open_buffered};
use crate::progress::Progress;

/// Header facts of a LAS/LAZ file.
#[derive(Debug, Clone, Serialize)]
pub struct LasInfo {
    /// LAS version, e.g. "1.4".
    pub version: String,
    /// Point data record format (0–10).
    pub point_format: u8,
    /// True for LAZ (compressed point records).
    pub compressed: bool,
    /// Bytes per point record.
    pub record_length: u16,
    /// Point count declared by the header (the 64-bit field for LAS 1.4).
    pub declared_points: u64,
    /// Header bounding box minimum, file coordinates (metres).
    pub bounds_min: [f64; 3],
    /// Header bounding box maximum, file coordinates (metres).
    pub bounds_max: [f64; 3],
    /// Coordinate scale factors (metres per integer step).
    pub scale: [f64; 3],
    /// Coordinate offsets (metres).
    pub offset: [f64; 3],
    /// True when the point format carries RGB.
    pub has_color: bool,
    /// The CRS the file's projection records declare (`EPSG:32649`, or `custom (…)`); `None`
    /// when it declares none or it could not be read (see `crs_problem`).
    pub crs: Option<String>,
    /// Why the file's projection records could not be read, when they could not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub crs_problem: Option<String>,
}

/// The CRS a LAS/LAZ header's projection records (VLRs and EVLRs) declare; `None` when none.
pub fn las_crs(header: &::las::Header) -> Result<Option<super::crs::Crs>, super::crs::CrsError> {
    super::crs::Crs::from_las_records(
        header
            .vlrs()
            .iter()
            .chain(header.evlrs())
            .map(|v| (v.user_id.as_str(), v.record_id, v.data.as_slice())),
    )
}

/// The CRS a LAS/LAZ file's header records declare (see [`las_crs`]).
pub fn read_crs(
    path: &Path,
) -> Result<Result<Option<super::crs::Crs>, super::crs::CrsError>, IoError> {
    check_raw_header(path)?;
    let mut read = open_buffered(path)?;
    let header = ::las::Header::new(&mut read).map_err(|e| las_err(path, e))?;
    Ok(las_crs(&header))
}

/// Maps a `las` crate error: I/O errors on content (end of file, invalid data, decoder
/// faults) become `Format`, genuine I/O errors stay `Io`; everything else is `Format`.
fn las_err(path: &Path, e: ::las::Error) -> IoError {
    match e {
        ::las::Error::Io(io) => match io.kind() {
            std::io::ErrorKind::UnexpectedEof
            | std::io::ErrorKind::InvalidData
            | std::io::ErrorKind::InvalidInput
            | std::io::ErrorKind::Other => IoError::format(path, format!("bad point data: {io}")),
            _ => IoError::io(path, io),
        },
        other => IoError::format(path, other.to_string()),
    }
}

/// Bytes of an extended VLR's header (LAS 1.4 R15 §2.7): reserved (2), user id (16), record
/// id (2), record length after the header (8), description (32).
const EVLR_HEADER_BYTES: u64 = 60;

/// Reads a LAS/LAZ file's fixed header and checks what the `las` crate would otherwise trust
/// when it reads the rest (found by fuzzing, issue 43): that the points' declared extent
/// (count × record length past the offset to the point data) is a number at all, and that
/// each extended VLR's declared length fits in the file, since the crate allocates each one's
/// data at its declared length before reading it (a header claiming 40 GB of EVLR asked for
/// 40 GB). Returns the header and the file's length.
fn check_raw_header(path: &Path) -> Result<(::las::raw::Header, u64), IoError> {
    let len = file_len(path)?;
    if len == 0 {
        return Err(IoError::format(path, "file is empty"));
    }
    let mut read = open_buffered(path)?;
    let raw = ::las::raw::Header::read_from(&mut read).map_err(|e| las_err(path, e))?;
    let count = match (&raw.large_file, raw.number_of_point_records) {
        (Some(l), 0) => l.number_of_point_records,
        (_, legacy) => u64::from(legacy),
    };
    let points_end = count
        .checked_mul(u64::from(raw.point_data_record_length))
        .and_then(|b| b.checked_add(u64::from(raw.offset_to_point_data)));
    if points_end.is_none() {
        return Err(IoError::format(
            path,
            format!(
                "header declares {count} points of {} bytes, more than any file can hold",
                raw.point_data_record_length
            ),
        ));
    }
    if let Some(evlr) = raw.evlr.filter(|e| e.number_of_evlrs > 0) {
        let mut at = evlr.start_of_first_evlr;
        for i in 0..evlr.number_of_evlrs {
            if at
                .checked_add(EVLR_HEADER_BYTES)
                .is_none_or(|end| end > len)
            {
                return Err(IoError::format(
                    path,
                    format!(
                        "header declares {} extended VLRs but extended VLR {} would start at byte {at}, past the file's {len} bytes",
                        evlr.number_of_evlrs,
                        i + 1
                    ),
                ));
            }
            read.seek(SeekFrom::Start(at + 20))
                .map_err(|e| IoError::io(path, e))?;
            let mut word = [0u8; 8];
            read.read_exact(&mut word)
                .map_err(|e| IoError::format(path, format!("extended VLR {}: {e}", i + 1)))?;
            let body = u64::from_le_bytes(word);
            match (at + EVLR_HEADER_BYTES).checked_add(body) {
                Some(end) if end <= len => at = end,
                _ => {
                    return Err(IoError::format(
                        path,
                        format!(
                            "extended VLR {} declares {body} bytes, past the file's end ({len} bytes)",
                            i + 1
                        ),
                    ));
                }
            }
        }
    }
    Ok((raw, len))
}

/// Reads the header of a LAS/LAZ file and checks the declared point count against the file.
pub fn inspect_las(path: &Path) -> Result<LasInfo, IoError> {
    let (raw, len) = check_raw_header(path)?;
    let mut read = open_buffered(path)?;
    let header = ::las::Header::new(&mut read).map_err(|e| las_err(path, e))?;
    let fmt = *header.point_format();
    let declared = header.number_of_points();
    let start = u64::from(raw.offset_to_point_data);
    let record_length = raw.point_data_record_length;
    if record_length == 0 {
        return Err(IoError::format(path, "point record length is 0"));
    }
    if fmt.is_compressed {
        check_laz_chunks(path, &header, &mut read, (start, record_length), declared)?;
    } else {
        // Point records end where the extended VLRs start (LAS 1.4), else at the end of file.
        let end = match raw.evlr {
            Some(e) if e.start_of_first_evlr >= start && e.start_of_first_evlr <= len => {
                e.start_of_first_evlr
            }
            _ => len,
        };
        let held = end.saturating_sub(start) / u64::from(record_length);
        if held != declared {
            return Err(IoError::format(
                path,
                format!("header declares {declared} points but the file holds {held}"),
            ));
        }
    }
    let t = header.transforms();
    let b = header.bounds();
    let (crs, crs_problem) = match las_crs(&header) {
        Ok(c) => (c.map(|c| c.label()), None),
        Err(e) => (None, Some(e.to_string())),
    };
    Ok(LasInfo {
        version: format!("{}.{}", raw.version.major, raw.version.minor),
        point_format: raw.point_data_record_format & 0x3f,
        compressed: fmt.is_compressed,
        record_length,
        declared_points: declared,
        bounds_min: [b.min.x, b.min.y, b.min.z],
        bounds_max: [b.max.x, b.max.y, b.max.z],
        scale: [t.x.scale, t.y.scale, t.z.scale],
        offset: [t.x.offset, t.y.offset, t.z.offset],
        has_color: fmt.has_color,
        crs,
        crs_problem,
    })
}

/// For LAZ with fixed-size chunks: `declared` points need exactly ceil(declared / chunk_size)
/// chunks. With variable-size chunks, no chunk may hold more points than the file declares
/// (or [`MAX_EMPTY_CHUNK_POINTS`]) and the chunks no more bytes than the points take. Files
/// without a chunk table are left to the decoder, which fails on missing data.
fn check_laz_chunks<R: Read + Seek>(
    path: &Path,
    header: &::las::Header,
    read: &mut R,
    (start, record_length): (u64, u16),
    declared: u64,
) -> Result<(), IoError> {
    let Some(vlr) = header
        .vlrs()
        .iter()
        .find(|v| v.user_id.trim_end_matches('\0') == "laszip encoded" && v.record_id == 22204)
    else {
        return Err(IoError::format(
            path,
            "compressed point format without a LAZ VLR",
        ));
    };
    // The decoder sizes its points by the VLR's items and asserts they match the header's
    // records (found by fuzzing, issue 43): check first, and say so.
    // Summed here as u64: the crate's own sum is a u16 that overflows on hostile sizes.
    let items: u64 = laz::LazVlr::from_buffer(&vlr.data)
        .map_err(|e| IoError::format(path, format!("LAZ VLR: {e}")))?
        .items()
        .iter()
        .map(|i| u64::from(i.size()))
        .sum();
    if items == 0 || items != u64::from(record_length) {
        return Err(IoError::format(
            path,
            format!(
                "the LAZ VLR's items make {items}-byte points but the header's records are {record_length} bytes"
            ),
        ));
    }
    let Some(chunk_size) = vlr
        .data
        .get(12..16)
        .and_then(|b| b.try_into().ok())
        .map(u32::from_le_bytes)
    else {
        return Err(IoError::format(path, "LAZ VLR is too short"));
    };
    let variable = chunk_size == u32::MAX || chunk_size == 0;
    // The decoder holds a whole chunk's points at once, at the chunk size the VLR declares
    // (a hostile 4-billion-point chunk asked for 111 GB; found by fuzzing, issue 43). A
    // chunk never needs more points than the file declares; writers use 50 000.
    if !variable && u64::from(chunk_size) > declared.max(MAX_EMPTY_CHUNK_POINTS) {
        return Err(IoError::format(
            path,
            format!(
                "the LAZ VLR declares chunks of {chunk_size} points for a file of {declared} points"
            ),
        ));
    }
    let mut word = [0u8; 8];
    let mut read_at = |pos: SeekFrom, buf: &mut [u8]| -> Result<(), IoError> {
        read.seek(pos)
            .and_then(|_| read.read_exact(buf))
            .map_err(|e| IoError::read(path, e, "LAZ chunk table"))
    };
    read_at(SeekFrom::Start(start), &mut word)?;
    let mut table = i64::from_le_bytes(word);
    if table <= start as i64 {
        // Writers that could not seek back store the table offset in the last 8 bytes.
        read_at(SeekFrom::End(-8), &mut word)?;
        table = i64::from_le_bytes(word);
        if table <= start as i64 {
            return Ok(());
        }
    }
    read_at(SeekFrom::Start(table as u64), &mut word)?;
    let chunks = u64::from(u32::from_le_bytes([word[4], word[5], word[6], word[7]]));
    // Every chunk holds at least one byte of compressed points before the table; the decoder
    // allocates its table at the declared count (found by fuzzing, issue 43).
    let room = table as u64 - start;
    if chunks > room {
        return Err(IoError::format(
            path,
            format!(
                "the LAZ chunk table declares {chunks} chunks but the points take {room} bytes"
            ),
        ));
    }
    if variable {
        // Point counts are in the (compressed) table; the decoder sizes a buffer by the largest
        // (a hostile count overflowed its allocation; found by fuzzing, issue 43). A chunk
        // never holds more points than the file declares, nor more bytes than the points take.
        let vlr = laz::LazVlr::from_buffer(&vlr.data)
            .map_err(|e| IoError::format(path, format!("LAZ VLR: {e}")))?;
        read.seek(SeekFrom::Start(start))
            .map_err(|e| IoError::read(path, e, "LAZ chunk table"))?;
        let table = read_chunk_table(path, &mut *read, &vlr)?;
        let most = declared.max(MAX_EMPTY_CHUNK_POINTS);
        let bytes: u64 = table
            .as_ref()
            .iter()
            .map(|e| e.byte_count)
            .fold(0u64, u64::saturating_add);
        if let Some(e) = table.as_ref().iter().find(|e| e.point_count > most) {
            return Err(IoError::format(
                path,
                format!(
                    "the LAZ chunk table declares a chunk of {} points for a file of {declared} points",
                    e.point_count
                ),
            ));
        }
        if bytes > room {
            return Err(IoError::format(
                path,
                format!(
                    "the LAZ chunk table's chunks take {bytes} bytes but the points take {room}"
                ),
            ));
        }
        return Ok(());
    }
    let cs = u64::from(chunk_size);
    if declared > chunks * cs || (chunks > 0 && declared <= (chunks - 1) * cs) {
        let most = chunks * cs;
        return Err(IoError::format(
            path,
            format!(
                "header declares {declared} points but the file holds {} to {most} ({chunks} chunks of {cs})",
                (chunks.saturating_sub(1) * cs + 1).min(most)
            ),
        ));
    }
    Ok(())
}

/// Runs one call into a point decoder, a panic of which is this file's fault, not the
/// worker's end: laz-rs checks its own state with assertions and indexes its chunk table
/// unchecked, and a hostile file breaks both (found by fuzzing, issue 43). The one place
/// Sylva catches a decoder's panic; every LAS/LAZ decoder call goes through it.
pub(crate) fn decoding<T>(path: &Path, call: impl FnOnce() -> T) -> Result<T, IoError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(call)).map_err(|panic| {
        IoError::format(
            path,
            format!(
                "the point decoder failed on this file: {}",
                panic_text(panic.as_ref())
            ),
        )
    })
}

/// What a caught panic says.
fn panic_text(panic: &(dyn std::any::Any + Send)) -> &str {
    panic
        .downcast_ref::<String>()
        .map(String::as_str)
        .or_else(|| panic.downcast_ref::<&str>().copied())
        .unwrap_or("a fault")
}

/// laz-rs's chunk-table reader (`read` at the point data's start), through [`decoding`]:
/// the table's point counts are arithmetic-coded and a corrupt table breaks the decoder's
/// assertions. Err when the table is missing, unreadable or corrupt.
pub(super) fn read_chunk_table<R: Read + Seek>(
    path: &Path,
    read: &mut R,
    vlr: &laz::LazVlr,
) -> Result<laz::laszip::ChunkTable, IoError> {
    decoding(path, || laz::laszip::ChunkTable::read_from(&mut *read, vlr))?
        .map_err(|e| IoError::format(path, format!("LAZ chunk table: {e}")))
}

/// Largest fixed LAZ chunk (points) accepted beyond a file's declared point count: the
/// decoder allocates a chunk's points at once, so this bounds what a small file can make it
/// allocate (70 MB at 70-byte records). LAStools and PDAL write chunks of 50 000.
const MAX_EMPTY_CHUNK_POINTS: u64 = 1_000_000;

/// Most bytes of raw records the sequential path decodes per call (16 MiB).
const BATCH_BYTES: u64 = 16 << 20;

/// Byte offset of RGB in a point record: 20 in format 2 (after the 20-byte core), 28 in
/// formats 3 and 5 (after GPS time), 30 in formats 7, 8 and 10 (ASPRS LAS 1.4 R15, tables 9–19).
pub(super) fn rgb_offset(fmt: &Format) -> usize {
    if fmt.is_extended {
        30
    } else if fmt.has_gps_time {
        28
    } else {
        20
    }
}

/// Raw point records in batches: LAS through the `las` crate, LAZ through
/// [`pointwise::LazRecords`] (Sylva's own GPS-time decoder, or none at all; see that module).
enum Records {
    Las {
        reader: Box<::las::Reader>,
        pd: ::las::PointData,
    },
    Laz {
        laz: pointwise::LazRecords,
        buf: Vec<u8>,
    },
}

impl Records {
    fn open(path: &Path, info: &LasInfo) -> Result<Self, IoError> {
        if !info.compressed {
            let file = File::open(path).map_err(|e| IoError::io(path, e))?;
            let reader = ::las::Reader::new(BufReader::new(file)).map_err(|e| las_err(path, e))?;
            let pd = PointDataBuilder::new().for_header(reader.header()).build();
            return Ok(Self::Las {
                reader: Box::new(reader),
                pd,
            });
        }
        let (raw, _) = check_raw_header(path)?;
        let mut read = open_buffered(path)?;
        let header = ::las::Header::new(&mut read).map_err(|e| las_err(path, e))?;
        let vlr = header
            .vlrs()
            .iter()
            .find(|v| {
                v.user_id.trim_end_matches('\0') == laz::LazVlr::USER_ID
                    && v.record_id == laz::LazVlr::RECORD_ID
            })
            .ok_or_else(|| IoError::format(path, "compressed point format without a LAZ VLR"))?;
        let laz = pointwise::LazRecords::open(
            path,
            &vlr.data,
            u64::from(raw.offset_to_point_data),
            (info.declared_points, usize::from(info.record_length)),
            info.has_color,
        )?;
        Ok(Self::Laz {
            laz,
            buf: Vec::new(),
        })
    }

    /// The next batch of at most `n` records and the record length; empty at the end.
    fn next(&mut self, path: &Path, n: u64) -> Result<(&[u8], usize), IoError> {
        match self {
            Self::Las { reader, pd } => {
                decoding(path, || reader.fill_points(n, pd))?.map_err(|e| las_err(path, e))?;
                Ok((pd.raw_bytes(), pd.record_len()))
            }
            Self::Laz { laz, buf } => {
                decoding(path, || laz.fill(n, buf))?
                    .map_err(|e| IoError::format(path, format!("bad LAZ point data: {e}")))?;
                Ok((buf.as_slice(), laz.record_len()))
            }
        }
    }
}

/// Reads a LAS or LAZ file. Colour is kept when the point format has RGB, intensity when any
/// point has a non-zero intensity. The local origin is the header's minimum corner rounded
/// down to whole metres (or the first points' minimum when the header bounds are wrong).
/// Chunked LAZ is read by the fused chunk-parallel reader (`las/fused.rs`), everything else
/// (and LAZ that reader leaves) sequentially.
pub fn read_las(path: &Path, progress: &dyn Progress) -> Result<PointCloud, IoError> {
    let info = inspect_las(path)?;
    #[cfg(unix)]
    if info.compressed
        && let Some(cloud) = fused::read_laz_fused(path, &info, progress)?
    {
        return Ok(cloud);
    }
    read_las_sequential(path, &info, progress)
}

/// The sequential path of [`read_las`]: LAS (through the `las` crate), and LAZ that the
/// fused reader leaves (no chunk table, unchunked compression, header bounds that miss the
/// points).
fn read_las_sequential(
    path: &Path,
    info: &LasInfo,
    progress: &dyn Progress,
) -> Result<PointCloud, IoError> {
    let mut records = Records::open(path, info)?;
    let total = info.declared_points;
    let hint = Some((
        DVec3::from_array(info.bounds_min),
        DVec3::from_array(info.bounds_max),
    ));
    // Preallocate no more than the file could hold (a LAZ count is only partly checked).
    let cap_points = total.min(file_len(path)?);
    let mut cloud = CloudBuilder::new(path, hint, cap_points);
    let cap = cap_points.min(1 << 24) as usize;
    let fmt = Format::new(info.point_format).map_err(|e| las_err(path, e))?;
    let rgb_at = info.has_color.then(|| rgb_offset(&fmt));
    let mut colors: Option<Vec<[u16; 3]>> = rgb_at.map(|_| Vec::with_capacity(cap));
    let mut intensity: Vec<u16> = Vec::with_capacity(cap);
    let t = Vector {
        x: Transform {
            scale: info.scale[0],
            offset: info.offset[0],
        },
        y: Transform {
            scale: info.scale[1],
            offset: info.offset[1],
        },
        z: Transform {
            scale: info.scale[2],
            offset: info.offset[2],
        },
    };
    // Sequential decoding gains nothing from large calls; keep progress and cancel fine, and
    // a batch's records within 16 MiB whatever record length a header claims.
    let batch = (PROGRESS_STEP as u64).min((BATCH_BYTES / u64::from(info.record_length)).max(1));
    loop {
        check_cancel(progress)?;
        let (raw, stride) = records.next(path, batch)?;
        if raw.is_empty() {
            break;
        }
        // One pass over the raw records (x, y, z as i32 at bytes 0, 4, 8 and intensity as
        // u16 at byte 12 in every point format), the same arithmetic as `Transform::direct`.
        if stride < 14 || rgb_at.is_some_and(|at| at + 6 > stride) {
            return Err(IoError::format(
                path,
                format!("point records of {stride} bytes are too short for their format"),
            ));
        }
        let u16_at = |rec: &[u8], o: usize| u16::from_le_bytes([rec[o], rec[o + 1]]);
        for rec in raw.chunks_exact(stride) {
            let i32_at =
                |o: usize| i32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]]);
            cloud.push(DVec3::new(
                t.x.direct(i32_at(0)),
                t.y.direct(i32_at(4)),
                t.z.direct(i32_at(8)),
            ))?;
            intensity.push(u16_at(rec, 12));
            if let (Some(c), Some(at)) = (colors.as_mut(), rgb_at) {
                c.push([u16_at(rec, at), u16_at(rec, at + 2), u16_at(rec, at + 4)]);
            }
        }
        progress.set(cloud.count() as f64 / total.max(1) as f64);
    }
    if cloud.count() != total {
        return Err(IoError::format(
            path,
            format!(
                "header declares {total} points but the file holds {}",
                cloud.count()
            ),
        ));
    }
    let (offset, positions) = cloud.finish();
    Ok(PointCloud {
        offset,
        positions,
        colors: colors.map(|c| colors_to_u8(&c)),
        intensity: intensity.iter().any(|&i| i != 0).then_some(intensity),
        format: if info.compressed {
            CloudFormat::Laz
        } else {
            CloudFormat::Las
        },
    })
}

/// Writes a LAS 1.2 file (LAZ when `compress`): point format 2 with colour, else 0; scale
/// 0.001 m, offset = `cloud.offset`. 8-bit colour is stored as 16-bit (× 257).
pub fn write_las(path: &Path, cloud: &PointCloud, compress: bool) -> Result<(), IoError> {
    write_las_with_crs(path, cloud, compress, None)
}

/// [`write_las`], declaring `crs` in a `LASF_Projection` record: GeoTIFF keys (record 34735,
/// what LAS 1.2 readers expect) when it has an EPSG code that fits them, else its definition
/// as OGC WKT (record 2112, LAS 1.4's form). A CRS given only as a PROJ string has no LAS
/// form and is refused.
pub fn write_las_with_crs(
    path: &Path,
    cloud: &PointCloud,
    compress: bool,
    crs: Option<&super::crs::Crs>,
) -> Result<(), IoError> {
    let mut builder = Builder::from((1, 2));
    if let Some(crs) = crs {
        let (record_id, data) = match crs.epsg.and_then(|c| u16::try_from(c).ok()) {
            Some(code) => {
                // Version 1.1.0, 2 keys: GTModelTypeGeoKey (1024) = 1 projected / 2
                // geographic, then ProjectedCSTypeGeoKey (3072) or GeographicTypeGeoKey (2048).
                let (model, key) = if crs.is_geographic() {
                    (2, 2048)
                } else {
                    (1, 3072)
                };
                let words = [1u16, 1, 0, 2, 1024, 0, 1, model, key, 0, 1, code];
                let bytes = words.iter().flat_map(|w| w.to_le_bytes()).collect();
                (super::crs::LAS_GEOKEY_RECORD, bytes)
            }
            None if crs.definition.contains('[') => (
                super::crs::LAS_WKT_RECORD,
                crs.definition.clone().into_bytes(),
            ),
            None => {
                return Err(IoError::format(
                    path,
                    format!(
                        "cannot declare {} in a LAS file: give the CRS as EPSG:<code> or WKT",
                        crs.label()
                    ),
                ));
            }
        };
        builder.vlrs.push(::las::Vlr {
            user_id: super::crs::LAS_PROJECTION_USER_ID.into(),
            record_id,
            description: "CRS".into(),
            data,
        });
    }
    let mut fmt =
        Format::new(if cloud.colors.is_some() { 2 } else { 0 }).map_err(|e| las_err(path, e))?;
    fmt.is_compressed = compress;
    builder.point_format = fmt;
    builder.generating_software = "sylva".to_string();
    let t = |offset: f64| Transform {
        scale: 0.001,
        offset,
    };
    builder.transforms = Vector {
        x: t(cloud.offset.x),
        y: t(cloud.offset.y),
        z: t(cloud.offset.z),
    };
    let header = builder.into_header().map_err(|e| las_err(path, e))?;
    let file = File::create(path).map_err(|e| IoError::io(path, e))?;
    let write_err = |e: ::las::Error| match e {
        ::las::Error::Io(io) => IoError::io(path, io),
        other => IoError::format(path, format!("cannot write point: {other}")),
    };
    let mut writer = ::las::Writer::new(BufWriter::new(file), header).map_err(write_err)?;
    for i in 0..cloud.len() {
        let p = cloud.world(i);
        let point = Point {
            x: p.x,
            y: p.y,
            z: p.z,
            intensity: cloud
                .intensity
                .as_ref()
                .and_then(|v| v.get(i).copied())
                .unwrap_or(0),
            color: cloud.colors.as_ref().map(|c| {
                let [r, g, b] = c
                    .get(i)
                    .copied()
                    .unwrap_or_default()
                    .map(|v| u16::from(v) * 257);
                Color::new(r, g, b)
            }),
            ..Default::default()
        };
        writer.write_point(point).map_err(write_err)?;
    }
    writer.close().map_err(write_err)
}

#[cfg(unix)]
mod fused;
mod pointwise;
#[cfg(test)]
mod tests;
