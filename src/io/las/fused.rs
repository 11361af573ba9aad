//! Chunk-parallel LAZ reader that decodes and converts in one pass.
//!
//! LAZ splits the point records into chunks (50,000 points each by default) that decode
//! independently; the chunk table at the end of the point data gives each chunk's compressed
//! size (and, for variable-size chunks, its point count). This reader makes one rayon task per
//! chunk: it reads the chunk's compressed bytes with a positioned read, decodes them with
//! laz-rs into the task's own record buffer (one chunk: about 1 MB at 50,000 points of 20
//! bytes) and converts those records straight into the output columns at the chunk's point
//! offset (disjoint slices of columns allocated once for the header's point count). Rayon's
//! work stealing balances the chunks over the cores; there is no barrier until the last
//! chunk, no whole-file buffer of raw records and no sequential conversion pass. For the
//! layered point formats 6–10 only the layers we keep are decoded (x, y, z, intensity and
//! RGB: laz-rs `DecompressionSelection`).
//!
//! The result is the same cloud as the sequential path of [`super::read_las`] (same origin
//! rule, same arithmetic, same colour and intensity rules); anything this reader does not
//! handle makes it return `Ok(None)` so that the caller takes that path: files without a
//! chunk table, point-wise (unchunked) compression, unknown compressor versions, header
//! bounds that do not contain the first points, a chunk table whose counts do not add up to
//! the header's point count.

use std::fs::File;
use std::io::{BufReader, Seek, SeekFrom};
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use ::las::Transform;
use glam::{DVec3, Vec3};
use laz::LazVlr;
use laz::las::selective::DecompressionSelection;
use laz::laszip::{ChunkTable, ChunkTableEntry};
use rayon::prelude::*;

use super::super::pointcloud::{CloudFormat, PointCloud, colors_to_u8};
use super::super::{IoError, PROGRESS_STEP, check_cancel};
use super::LasInfo;
use crate::progress::Progress;

/// LASzip compressor type codes (first u16 of the LASzip VLR): 2 = point-wise chunked,
/// 3 = layered chunked (LASzip's `laszip.hpp`; laz-rs `CompressorType`). Type 1 (one chunk
/// without a table) is left to the sequential path (`pointwise.rs`).
const POINTWISE_CHUNKED: u16 = 2;
const LAYERED_CHUNKED: u16 = 3;

/// Most points per compressed byte the fused reader preallocates for: real LAZ holds 0.1–0.5
/// points per byte (`plot10m.laz`: 0.16), so 16 only turns away forged counts and degenerate
/// files of near-identical points, which the sequential path still reads.
const MAX_POINTS_PER_BYTE: u64 = 16;

/// Most bytes of records a chunk may decode to per compressed byte in the fused reader.
/// LASzip's adaptive models code a byte that never changes in about 0.011 bits, so a chunk
/// of constant extra bytes can expand about 700 times; 1,000 turns away only forged tables.
const MAX_EXPANSION: u64 = 1_000;

/// One chunk's work: where its compressed bytes are and where its points go.
struct Job<'a> {
    /// First point of the chunk (index into the cloud).
    first: u64,
    /// Absolute file position of the compressed bytes.
    pos: u64,
    /// Compressed length, bytes.
    bytes: usize,
    positions: &'a mut [std::mem::MaybeUninit<Vec3>],
    intensity: &'a mut [u16],
    colors: Option<&'a mut [[u16; 3]]>,
}

/// What a chunk reports back besides its columns.
struct ChunkOut {
    /// Any non-zero intensity in the chunk.
    any_intensity: bool,
    /// File-coordinate box of the chunk's points among the first [`PROGRESS_STEP`] of the
    /// cloud (the points the origin rule looks at).
    head_box: Option<(DVec3, DVec3)>,
}

/// Everything the per-chunk decoder needs, shared by all tasks.
struct Shared<'a> {
    path: &'a Path,
    file: &'a File,
    plan: &'a Plan,
    selection: DecompressionSelection,
    progress: &'a dyn Progress,
    done: AtomicU64,
    total: u64,
    /// Set once a chunk fails: the other tasks then stop early.
    failed: AtomicBool,
    /// The first chunk error (the one returned).
    first_err: Mutex<Option<IoError>>,
}

/// What the header, the LASzip VLR and the chunk table say, checked: everything the
/// parallel decode needs.
struct Plan {
    vlr: LazVlr,
    /// Layered compression (formats 6–10), else point-wise.
    layered: bool,
    /// Bytes of one point record.
    record_len: usize,
    /// Byte offset of RGB in a record, when the format has colour.
    rgb_at: Option<usize>,
    /// The chunk table, the last fixed-size chunk's count set from the header's total.
    entries: Vec<ChunkTableEntry>,
    /// File position of the first chunk's compressed bytes.
    points_start: u64,
    /// The header's bounding box (file coordinates).
    header_box: (DVec3, DVec3),
    transforms: ::las::Vector<Transform>,
    /// The cloud's origin: the header's minimum corner floored to whole metres.
    offset: DVec3,
}

/// Reads and checks the header, the LASzip VLR and the chunk table of `file`. `Ok(None)`
/// when the file needs the sequential path; an error only for a chunk table that lists more
/// bytes than the file holds.
fn plan(file: &File, path: &Path, info: &LasInfo) -> Result<Option<Plan>, IoError> {
    let total = info.declared_points;
    let mut read = BufReader::new(file);
    let Ok(raw) = ::las::raw::Header::read_from(&mut read) else {
        return Ok(None);
    };
    if read.seek(SeekFrom::Start(0)).is_err() {
        return Ok(None);
    }
    let Ok(header) = ::las::Header::new(&mut read) else {
        return Ok(None);
    };
    let fmt = *header.point_format();
    let Some(vlr_data) = header
        .vlrs()
        .iter()
        .find(|v| {
            v.user_id.trim_end_matches('\0') == LazVlr::USER_ID && v.record_id == LazVlr::RECORD_ID
        })
        .map(|v| v.data.as_slice())
    else {
        return Ok(None);
    };
    let compressor = vlr_data.get(0..2).map(|b| u16::from_le_bytes([b[0], b[1]]));
    let layered = match compressor {
        Some(POINTWISE_CHUNKED) => false,
        Some(LAYERED_CHUNKED) => true,
        _ => return Ok(None),
    };
    let Ok(vlr) = LazVlr::from_buffer(vlr_data) else {
        return Ok(None);
    };
    let versions_ok = vlr.items().iter().all(|item| match item.version() {
        1 | 2 => !layered,
        3 | 4 => layered,
        _ => false,
    });
    let record_len = usize::from(raw.point_data_record_length);
    if vlr.items().is_empty()
        || !versions_ok
        || vlr.items_size() != u64::from(raw.point_data_record_length)
        || record_len < 14
    {
        return Ok(None);
    }
    let rgb_at = fmt.has_color.then(|| super::rgb_offset(&fmt));
    if rgb_at.is_some_and(|at| at + 6 > record_len) {
        return Ok(None);
    }

    // Chunk table (read_from leaves the reader just after the 8-byte table offset).
    let data_start = u64::from(raw.offset_to_point_data);
    if read.seek(SeekFrom::Start(data_start)).is_err() {
        return Ok(None);
    }
    // laz-rs reserves the table for its declared chunk count before reading it: leave counts
    // the file cannot hold (each chunk starts with one raw record) to the sequential path.
    let file_len = file.metadata().map_err(|e| IoError::io(path, e))?.len();
    match declared_chunks(file, data_start) {
        Some(chunks) if chunks <= file_len / record_len as u64 => {}
        _ => return Ok(None),
    }
    let Ok(table) = super::read_chunk_table(path, &mut read, &vlr) else {
        return Ok(None);
    };
    let mut entries: Vec<ChunkTableEntry> = table.as_ref().to_vec();
    if entries.is_empty() {
        return Ok(None);
    }
    if !vlr.uses_variable_size_chunks() {
        // Fixed-size tables repeat the chunk size; the last chunk holds the remainder.
        let cs = u64::from(vlr.chunk_size());
        let before = (entries.len() as u64 - 1) * cs;
        if total <= before || total > before + cs {
            return Ok(None); // inspect_las reports this; never reached after it
        }
        if let Some(last) = entries.last_mut() {
            last.point_count = total - before;
        }
    }
    if entries
        .iter()
        .try_fold(0u64, |sum, e| sum.checked_add(e.point_count))
        != Some(total)
    {
        return Ok(None);
    }
    let points_start = data_start + ChunkTable::OFFSET_SIZE as u64;
    let chunk_bytes = entries
        .iter()
        .try_fold(0u64, |sum, e| sum.checked_add(e.byte_count))
        .unwrap_or(u64::MAX);
    if points_start.saturating_add(chunk_bytes) > file_len {
        return Err(IoError::format(
            path,
            format!(
                "file is truncated: the LAZ chunk table lists {chunk_bytes} bytes of points but \
                 only {} follow the point data offset",
                file_len.saturating_sub(points_start)
            ),
        ));
    }
    // The columns are allocated up front for the declared count: leave implausibly dense
    // files (more than MAX_POINTS_PER_BYTE points per compressed byte) to the sequential path,
    // which allocates only as points decode, so a forged count cannot claim the memory.
    if total > chunk_bytes.saturating_mul(MAX_POINTS_PER_BYTE) {
        return Ok(None);
    }
    // Each task holds one chunk's decoded records at once: leave chunks that would decode to
    // more than MAX_EXPANSION times their bytes (a hostile table or VLR: 50,000 points of
    // 65,535-byte records is 3.3 GB) to the sequential path, which decodes in small batches.
    if entries.iter().any(|e| {
        e.point_count.saturating_mul(record_len as u64)
            > e.byte_count.max(1).saturating_mul(MAX_EXPANSION)
    }) {
        return Ok(None);
    }

    // Origin: the header's minimum corner floored to whole metres, valid only when the header
    // box holds the first points (checked after decoding; else the sequential path decides).
    let (hlo, hhi) = (
        DVec3::from_array(info.bounds_min),
        DVec3::from_array(info.bounds_max),
    );
    if !(hlo.is_finite() && hhi.is_finite() && hlo.cmple(hhi).all()) {
        return Ok(None);
    }
    let t = *header.transforms();
    let finite = |t: &Transform| t.direct(i32::MIN).is_finite() && t.direct(i32::MAX).is_finite();
    if !(finite(&t.x) && finite(&t.y) && finite(&t.z)) {
        return Ok(None);
    }
    let offset = hlo.floor();
    Ok(Some(Plan {
        vlr,
        layered,
        record_len,
        rgb_at,
        entries,
        points_start,
        header_box: (hlo, hhi),
        transforms: t,
        offset,
    }))
}

/// Reads a LAZ file chunk-parallel; `Ok(None)` when the file needs the sequential path.
/// `info` is the already checked header ([`super::inspect_las`]).
pub(super) fn read_laz_fused(
    path: &Path,
    info: &LasInfo,
    progress: &dyn Progress,
) -> Result<Option<PointCloud>, IoError> {
    let total = info.declared_points;
    if total == 0 {
        return Ok(None);
    }
    let file = File::open(path).map_err(|e| IoError::io(path, e))?;
    let Some(plan) = plan(&file, path, info)? else {
        return Ok(None);
    };

    // Output columns, split into one disjoint slice per chunk.
    let n = usize::try_from(total).map_err(|_| IoError::format(path, "too many points"))?;
    let mut positions: Vec<Vec3> = Vec::with_capacity(n);
    let mut intensity = vec![0u16; n];
    let mut colors = plan.rgb_at.map(|_| vec![[0u16; 3]; n]);
    let mut jobs = Vec::with_capacity(plan.entries.len());
    {
        let mut pos_rest = &mut positions.spare_capacity_mut()[..n];
        let mut int_rest = intensity.as_mut_slice();
        let mut col_rest = colors.as_deref_mut();
        let (mut first, mut pos) = (0u64, plan.points_start);
        for e in &plan.entries {
            if e.point_count == 0 {
                // An empty chunk (laz-rs's writer ends variable-size files with one): skip it.
                pos += e.byte_count;
                continue;
            }
            let k = e.point_count as usize;
            let (p, pr) = pos_rest.split_at_mut(k);
            let (i, ir) = int_rest.split_at_mut(k);
            let (c, cr) = match col_rest {
                Some(c) => {
                    let (c, cr) = c.split_at_mut(k);
                    (Some(c), Some(cr))
                }
                None => (None, None),
            };
            (pos_rest, int_rest, col_rest) = (pr, ir, cr);
            jobs.push(Job {
                first,
                pos,
                bytes: usize::try_from(e.byte_count)
                    .map_err(|_| IoError::format(path, "LAZ chunk too large"))?,
                positions: p,
                intensity: i,
                colors: c,
            });
            first += e.point_count;
            pos += e.byte_count;
        }
    }

    let mut selection = DecompressionSelection::base()
        .decompress_z()
        .decompress_intensity();
    if plan.rgb_at.is_some() {
        selection = selection.decompress_rgb();
    }
    let shared = Shared {
        path,
        file: &file,
        plan: &plan,
        selection,
        progress,
        done: AtomicU64::new(0),
        total,
        failed: AtomicBool::new(false),
        first_err: Mutex::new(None),
    };
    let outs: Option<Vec<ChunkOut>> = jobs
        .into_par_iter()
        .map_init(Buffers::default, |buf, job| {
            if shared.failed.load(Ordering::Relaxed) {
                return None;
            }
            let decoded = super::decoding(path, || decode_chunk(&shared, job, buf)).and_then(|r| r);
            match decoded {
                Ok(out) => Some(out),
                Err(e) => {
                    shared.failed.store(true, Ordering::Relaxed);
                    if let Ok(mut first) = shared.first_err.lock() {
                        first.get_or_insert(e);
                    }
                    None
                }
            }
        })
        .collect();
    if let Some(e) = shared.first_err.into_inner().ok().flatten() {
        return Err(e);
    }
    let Some(outs) = outs else {
        return Err(IoError::format(path, "LAZ decoding stopped early"));
    };

    // The origin rule of `CloudBuilder`: the header corner only when the header box (± 1 m)
    // holds the first PROGRESS_STEP points.
    let head = outs
        .iter()
        .filter_map(|o| o.head_box)
        .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)));
    match head {
        Some((lo, hi))
            if (plan.header_box.0 - DVec3::ONE).cmple(lo).all()
                && hi.cmple(plan.header_box.1 + DVec3::ONE).all() => {}
        _ => return Ok(None),
    }
    // SAFETY: the jobs covered `spare_capacity_mut()[..n]` with disjoint slices, and every job
    // returned Ok (`outs` holds one result per job), which means it wrote every element of its
    // slice: the `decode_chunk` loop zips its slice with exactly as many decoded records and
    // writes one element per record, and only returns Ok after all of them.
    unsafe { positions.set_len(n) };
    let any_intensity = outs.iter().any(|o| o.any_intensity);
    Ok(Some(PointCloud {
        offset: plan.offset,
        positions,
        colors: colors.map(|c| colors_to_u8(&c)),
        intensity: any_intensity.then_some(intensity),
        format: CloudFormat::Laz,
    }))
}

/// The chunk count in the chunk table's header, located as laz-rs does: the i64 at the start
/// of the point data, or the file's last 8 bytes when that one does not point past it.
fn declared_chunks(file: &File, data_start: u64) -> Option<u64> {
    let mut word = [0u8; 8];
    file.read_exact_at(&mut word, data_start).ok()?;
    let mut table = i64::from_le_bytes(word);
    if table <= data_start as i64 {
        let len = file.metadata().ok()?.len();
        file.read_exact_at(&mut word, len.checked_sub(8)?).ok()?;
        table = i64::from_le_bytes(word);
        if table <= data_start as i64 {
            return None;
        }
    }
    file.read_exact_at(&mut word, table as u64).ok()?;
    Some(u64::from(u32::from_le_bytes([
        word[4], word[5], word[6], word[7],
    ])))
}

/// Maps a decoder error: running out of bytes or invalid data is a `Format` error naming the
/// chunk.
fn chunk_err(path: &Path, first: u64, e: impl std::fmt::Display) -> IoError {
    IoError::format(
        path,
        format!("bad point data in the LAZ chunk starting at point {first}: {e}"),
    )
}

/// A task's reusable buffers: one chunk's compressed bytes and its decoded records.
#[derive(Default)]
struct Buffers {
    compressed: Vec<u8>,
    records: Vec<u8>,
}

/// Decodes one chunk into its slices.
///
/// A layered chunk is decoded by `laz::par_decompress_selective` with a one-entry chunk
/// table (it runs in this task: one chunk is one job), without the GPS-time layer. That
/// function is not generic, so the decoder is the copy compiled inside laz-rs with its own
/// (release) settings rather than one instantiated in this crate; against driving laz-rs's
/// record decompressor point by point from here it measured 1–4 % less CPU on `plot10m.laz`
/// (shared machine). A point-wise chunk is decoded by Sylva's assembly of laz-rs's field
/// decoders (`pointwise.rs`): laz-rs's own GPS-time decoder can overflow the stack on a
/// hostile chunk. That costs 1.2 % more CPU on `plot10m.laz`'s 9.2 M points (4.61 against
/// 4.56 CPU s for three decodes of every chunk each, alternated in one process, 2026-11-29).
fn decode_chunk(s: &Shared<'_>, job: Job<'_>, buf: &mut Buffers) -> Result<ChunkOut, IoError> {
    check_cancel(s.progress)?;
    let Job {
        first,
        pos,
        bytes,
        positions,
        intensity,
        mut colors,
    } = job;
    let n = positions.len() as u64;
    buf.compressed.resize(bytes, 0);
    s.file
        .read_exact_at(&mut buf.compressed, pos)
        .map_err(|e| IoError::read(s.path, e, "LAZ chunk"))?;
    buf.records.resize(positions.len() * s.plan.record_len, 0);
    let entry = ChunkTableEntry {
        point_count: n,
        byte_count: bytes as u64,
    };
    if s.plan.layered {
        laz::par_decompress_selective(
            &buf.compressed,
            &mut buf.records,
            &s.plan.vlr,
            &[entry],
            s.selection,
        )
        .map_err(|e| chunk_err(s.path, first, e))?;
    } else {
        super::pointwise::decode_pointwise_chunk(
            &buf.compressed,
            s.plan.vlr.items(),
            &mut buf.records,
        )
        .map_err(|e| chunk_err(s.path, first, e))?;
    }
    let t = &s.plan.transforms;
    // Points of this chunk that fall among the cloud's first PROGRESS_STEP.
    let head = (PROGRESS_STEP as u64).saturating_sub(first) as usize;
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    let mut any_intensity = false;
    let records = buf.records.chunks_exact(s.plan.record_len);
    for (k, ((slot, inten), rec)) in positions
        .iter_mut()
        .zip(intensity.iter_mut())
        .zip(records)
        .enumerate()
    {
        // x, y, z as i32 at bytes 0, 4, 8 and intensity as u16 at byte 12 in every format;
        // the same arithmetic as `Transform::direct` and `CloudBuilder::push`.
        let Some(&[x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3, i0, i1]) =
            rec.first_chunk::<14>()
        else {
            return Err(chunk_err(
                s.path,
                first,
                "point record shorter than 14 bytes",
            ));
        };
        let p = DVec3::new(
            t.x.direct(i32::from_le_bytes([x0, x1, x2, x3])),
            t.y.direct(i32::from_le_bytes([y0, y1, y2, y3])),
            t.z.direct(i32::from_le_bytes([z0, z1, z2, z3])),
        );
        if k < head {
            lo = lo.min(p);
            hi = hi.max(p);
        }
        slot.write((p - s.plan.offset).as_vec3());
        let i = u16::from_le_bytes([i0, i1]);
        any_intensity |= i != 0;
        *inten = i;
        if let (Some(c), Some(at)) = (colors.as_deref_mut(), s.plan.rgb_at)
            && let Some(&[r0, r1, g0, g1, b0, b1]) =
                rec.get(at..).and_then(|r| r.first_chunk::<6>())
        {
            c[k] = [
                u16::from_le_bytes([r0, r1]),
                u16::from_le_bytes([g0, g1]),
                u16::from_le_bytes([b0, b1]),
            ];
        }
    }
    let done = s.done.fetch_add(n, Ordering::Relaxed) + n;
    s.progress.set(done as f64 / s.total as f64);
    Ok(ChunkOut {
        any_intensity,
        head_box: (head > 0).then_some((lo, hi)),
    })
}
