//! LAZ decoding that no file can crash: point-wise LASzip (compressor types 1 and 2, point
//! formats 0–5, item versions 1 and 2) assembled from laz-rs's field decoders around
//! Sylva's own GPS-time decoder, and a sequential LAZ record reader for the files the fused
//! reader (`fused.rs`) leaves.
//!
//! Why Sylva decodes GPS time itself: laz-rs 0.13.0's GPS-time decoders (item version 2 in
//! `las/gps.rs`, and the layered one of formats 6–10 in `las/point6.rs`) call themselves once
//! for every "switch to another time sequence" symbol. A valid stream never holds two switches
//! for one point (LASzip's encoder switches only to a sequence whose last time is within 32
//! bits of the new one, and then encodes the difference), but a hostile one can hold any
//! number, and an adaptive model decodes hundreds of repeated symbols per byte: 500-byte files
//! made the decoder recurse over 100,000 frames deep and overflow the stack, which aborts the
//! whole process, not just the job (found by fuzzing, issue 43; the inputs are replayed from
//! `fuzz/regressions/laz`). [`GpsTimeV2`] does the same arithmetic in a loop and refuses more
//! than [`MAX_SWITCHES`] switches for one point. The layered formats are decoded without their
//! GPS-time layer (Sylva keeps no GPS time), so laz-rs's layered GPS decoder never runs.
//!
//! The format facts (symbol codes, integer-decoder contexts, the four interleaved time
//! sequences) are LASzip's GPS-time item version 2 (`lasreaditemcompressed_v2.cpp`), read
//! from laz-rs's decoder, which writes the same streams.

use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use laz::decoders::ArithmeticDecoder;
use laz::decompressors::{IntegerDecompressor, IntegerDecompressorBuilder};
use laz::las::selective::DecompressionSelection;
use laz::laszip::{ChunkTable, LazItem, LazItemType};
use laz::models::{ArithmeticModel, ArithmeticModelBuilder};
use laz::record::{FieldDecompressor, RecordDecompressor, SequentialPointRecordDecompressor};
use laz::{LasZipDecompressor, LazVlr};

use super::super::IoError;

/// Largest multiple of the last difference coded as its own symbol (LASzip
/// `LASZIP_GPSTIME_MULTI`).
const MULTI: i32 = 500;
/// Most negative multiple coded as its own symbol (LASzip `LASZIP_GPSTIME_MULTI_MINUS`).
const MULTI_MINUS: i32 = -10;
/// Symbol: the time did not change (non-zero-difference model).
const MULTI_UNCHANGED: i32 = MULTI - MULTI_MINUS + 1;
/// Symbol: a new sequence starts with a full 64-bit time; above it, a switch by
/// `symbol - MULTI_CODE_FULL` sequences.
const MULTI_CODE_FULL: i32 = MULTI - MULTI_MINUS + 2;
/// Symbols of the non-zero-difference model.
const MULTI_TOTAL: u32 = (MULTI - MULTI_MINUS + 6) as u32;
/// Symbols of the zero-difference model: 0 unchanged, 1 a 32-bit difference, 2 a new
/// sequence, 3–5 a switch by `symbol - 2` sequences.
const ZERO_DIFF_TOTAL: u32 = 6;

/// Most sequence switches accepted for one point. A valid stream holds at most one (see the
/// module doc); four would have visited every sequence.
pub(crate) const MAX_SWITCHES: u32 = 4;

/// Decoder of LASzip's GPS-time item, version 2: four interleaved time sequences, each with
/// its last time (the f64's bits as i64), last 32-bit difference and a counter of
/// differences far from that one.
pub(crate) struct GpsTimeV2 {
    multi: ArithmeticModel,
    zero_diff: ArithmeticModel,
    ic: IntegerDecompressor,
    last: usize,
    next: usize,
    times: [i64; 4],
    diffs: [i32; 4],
    extremes: [i32; 4],
}

impl Default for GpsTimeV2 {
    fn default() -> Self {
        Self {
            multi: ArithmeticModelBuilder::new(MULTI_TOTAL).build(),
            zero_diff: ArithmeticModelBuilder::new(ZERO_DIFF_TOTAL).build(),
            ic: IntegerDecompressorBuilder::new()
                .bits(32)
                .contexts(9)
                .build_initialized(),
            last: 0,
            next: 0,
            times: [0; 4],
            diffs: [0; 4],
            extremes: [0; 4],
        }
    }
}

impl GpsTimeV2 {
    /// A new sequence: the next slot takes a full time (high word predicted from the current
    /// sequence's, low word raw) and becomes the current one.
    fn start_sequence<R: Read>(&mut self, dec: &mut ArithmeticDecoder<R>) -> std::io::Result<()> {
        self.next = (self.next + 1) & 3;
        let high = self
            .ic
            .decompress(dec, (self.times[self.last] >> 32) as i32, 8)?;
        let low = dec.read_int()?;
        self.times[self.next] = (i64::from(high) << 32) | i64::from(low);
        self.last = self.next;
        self.diffs[self.last] = 0;
        self.extremes[self.last] = 0;
        Ok(())
    }

    /// A difference far from the current one: after more than three in a row it becomes the
    /// sequence's difference.
    fn note_extreme(&mut self, diff: i32) {
        let l = self.last;
        self.extremes[l] += 1;
        if self.extremes[l] > 3 {
            self.diffs[l] = diff;
            self.extremes[l] = 0;
        }
    }

    /// Decodes one point's time into the current sequence; `Ok(true)` when the stream
    /// switched sequence instead (the time is then decoded against the new one).
    fn step<R: Read>(&mut self, dec: &mut ArithmeticDecoder<R>) -> std::io::Result<bool> {
        let l = self.last;
        if self.diffs[l] == 0 {
            match dec.decode_symbol(&mut self.zero_diff)? {
                0 => {}
                1 => {
                    let d = self.ic.decompress(dec, 0, 0)?;
                    self.diffs[l] = d;
                    self.times[l] = self.times[l].wrapping_add(i64::from(d));
                    self.extremes[l] = 0;
                }
                2 => self.start_sequence(dec)?,
                s => {
                    self.last = (l + s as usize - 2) & 3;
                    return Ok(true);
                }
            }
            return Ok(false);
        }
        let m = dec.decode_symbol(&mut self.multi)? as i32;
        let last_diff = self.diffs[l];
        if m == 1 {
            let d = self.ic.decompress(dec, last_diff, 1)?;
            self.times[l] = self.times[l].wrapping_add(i64::from(d));
            self.extremes[l] = 0;
        } else if m < MULTI_UNCHANGED {
            let diff = if m == 0 {
                let d = self.ic.decompress(dec, 0, 7)?;
                self.note_extreme(d);
                d
            } else if m < MULTI {
                let context = if m < 10 { 2 } else { 3 };
                self.ic
                    .decompress(dec, m.wrapping_mul(last_diff), context)?
            } else if m == MULTI {
                let d = self.ic.decompress(dec, m.wrapping_mul(last_diff), 4)?;
                self.note_extreme(d);
                d
            } else {
                let k = MULTI - m;
                if k > MULTI_MINUS {
                    self.ic.decompress(dec, k.wrapping_mul(last_diff), 5)?
                } else {
                    let d = self
                        .ic
                        .decompress(dec, MULTI_MINUS.wrapping_mul(last_diff), 6)?;
                    self.note_extreme(d);
                    d
                }
            };
            self.times[l] = self.times[l].wrapping_add(i64::from(diff));
        } else if m == MULTI_CODE_FULL {
            self.start_sequence(dec)?;
        } else if m > MULTI_CODE_FULL {
            self.last = (l + (m - MULTI_CODE_FULL) as usize) & 3;
            return Ok(true);
        }
        // m == MULTI_UNCHANGED: the time repeats.
        Ok(false)
    }
}

impl<R: Read> FieldDecompressor<R> for GpsTimeV2 {
    fn size_of_field(&self) -> usize {
        8
    }

    fn decompress_first(&mut self, src: &mut R, first_point: &mut [u8]) -> std::io::Result<()> {
        let mut word = [0u8; 8];
        src.read_exact(&mut word)?;
        first_point.copy_from_slice(&word);
        self.times[0] = i64::from_le_bytes(word);
        Ok(())
    }

    fn decompress_with(
        &mut self,
        decoder: &mut ArithmeticDecoder<R>,
        buf: &mut [u8],
    ) -> std::io::Result<()> {
        let mut switches = 0;
        while self.step(decoder)? {
            switches += 1;
            if switches > MAX_SWITCHES {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    format!(
                        "corrupt GPS time: more than {MAX_SWITCHES} time-sequence switches for one point"
                    ),
                ));
            }
        }
        buf.copy_from_slice(&self.times[self.last].to_le_bytes());
        Ok(())
    }
}

/// Adds the field decoders of point-wise `items` (versions 1 and 2) to `d`, in record order:
/// laz-rs's, except GPS time version 2, which is [`GpsTimeV2`].
pub(crate) fn add_pointwise_fields<'a, R: Read + 'a>(
    d: &mut SequentialPointRecordDecompressor<'a, R>,
    items: &[LazItem],
) -> Result<(), String> {
    use laz::las::{v1, v2};
    for item in items {
        let size = usize::from(item.size());
        match (item.version(), item.item_type()) {
            (1, LazItemType::Point10) => {
                d.add_field_decompressor(v1::LasPoint0Decompressor::default())
            }
            (1, LazItemType::GpsTime) => {
                d.add_field_decompressor(v1::LasGpsTimeDecompressor::default())
            }
            (1, LazItemType::RGB12) => d.add_field_decompressor(v1::LasRGBDecompressor::default()),
            (1, LazItemType::Byte(_)) => {
                d.add_field_decompressor(v1::LasExtraByteDecompressor::new(size))
            }
            // LASzip has one wave-packet decoder for versions 1 and 2.
            (1 | 2, LazItemType::WavePacket13) => {
                d.add_field_decompressor(v1::LasWavepacketDecompressor::default())
            }
            (2, LazItemType::Point10) => {
                d.add_field_decompressor(v2::LasPoint0Decompressor::default())
            }
            (2, LazItemType::GpsTime) => d.add_field_decompressor(GpsTimeV2::default()),
            (2, LazItemType::RGB12) => d.add_field_decompressor(v2::LasRGBDecompressor::default()),
            (2, LazItemType::Byte(_)) => {
                d.add_field_decompressor(v2::LasExtraByteDecompressor::new(size))
            }
            (v, t) => {
                return Err(format!(
                    "LAZ item {t:?} version {v} is not a point-wise item"
                ));
            }
        }
    }
    Ok(())
}

/// Decodes one point-wise chunk (`records.len()` / record length points) from `compressed`.
pub(crate) fn decode_pointwise_chunk(
    compressed: &[u8],
    items: &[LazItem],
    records: &mut [u8],
) -> Result<(), String> {
    let mut d = SequentialPointRecordDecompressor::new(std::io::Cursor::new(compressed));
    add_pointwise_fields(&mut d, items)?;
    if d.record_size() == 0 || !records.len().is_multiple_of(d.record_size()) {
        return Err(format!(
            "LAZ items make {}-byte points, which do not divide the {} bytes asked for",
            d.record_size(),
            records.len()
        ));
    }
    d.decompress_many(records).map_err(|e| e.to_string())
}

/// LASzip compressor type codes (first u16 of the LASzip VLR; LASzip's `laszip.hpp`).
const POINTWISE: u16 = 1;
const POINTWISE_CHUNKED: u16 = 2;
const LAYERED_CHUNKED: u16 = 3;

/// Points in each chunk of a point-wise file.
enum ChunkPlan {
    /// One chunk of every point (compressor type 1).
    One,
    /// Fixed-size chunks read one after another.
    Fixed(u64),
    /// The chunk table's counts and the file position of each chunk.
    Table(Vec<(u64, u64)>),
}

enum Decoder {
    /// Formats 6–10: laz-rs's layered decoder without the GPS-time layer.
    Layered(Box<LasZipDecompressor<'static, BufReader<File>>>),
    PointWise {
        dec: Box<SequentialPointRecordDecompressor<'static, BufReader<File>>>,
        items: Vec<LazItem>,
        plan: ChunkPlan,
        /// Index of the chunk being read.
        chunk: usize,
        /// Points of that chunk not yet decoded.
        left_in_chunk: u64,
    },
}

/// Sequential LAZ record reader: raw point records (as a LAS file would hold them, with
/// x, y, z, intensity and RGB filled; GPS time is zero in the layered formats).
pub(crate) struct LazRecords {
    decoder: Decoder,
    record_len: usize,
    /// Points the header declares and not yet decoded.
    left: u64,
}

impl LazRecords {
    /// Opens `path` (already checked by [`super::inspect_las`]) for `declared` points of
    /// `record_len` bytes; `vlr_data` is the LASzip VLR's body and `data_start` the header's
    /// offset to point data. `keep_rgb` decodes colour in the layered formats.
    pub(crate) fn open(
        path: &Path,
        vlr_data: &[u8],
        data_start: u64,
        (declared, record_len): (u64, usize),
        keep_rgb: bool,
    ) -> Result<Self, IoError> {
        let vlr = LazVlr::from_buffer(vlr_data)
            .map_err(|e| IoError::format(path, format!("LAZ VLR: {e}")))?;
        if vlr.items_size() != record_len as u64 || record_len == 0 {
            return Err(IoError::format(
                path,
                format!(
                    "the LAZ VLR's items make {}-byte points but the header's records are {record_len} bytes",
                    vlr.items_size()
                ),
            ));
        }
        let file = File::open(path).map_err(|e| IoError::io(path, e))?;
        let mut read = BufReader::new(file);
        read.seek(SeekFrom::Start(data_start))
            .map_err(|e| IoError::read(path, e, "LAZ point data"))?;
        let compressor = vlr_data.get(0..2).map(|b| u16::from_le_bytes([b[0], b[1]]));
        let decoder = match compressor {
            Some(LAYERED_CHUNKED) => {
                // laz-rs picks its decoder by the items' versions, not the compressor type:
                // point-wise items here would reach its recursive GPS-time decoder (found by
                // fuzzing, issue 43).
                if let Some(item) = vlr.items().iter().find(|i| !matches!(i.version(), 3 | 4)) {
                    return Err(IoError::format(
                        path,
                        format!(
                            "the LAZ VLR declares layered compression but item {:?} is version {}, a point-wise one",
                            item.item_type(),
                            item.version()
                        ),
                    ));
                }
                let mut selection = DecompressionSelection::base()
                    .decompress_z()
                    .decompress_intensity();
                if keep_rgb {
                    selection = selection.decompress_rgb();
                }
                // It reads the chunk table, whose decoder can panic on a corrupt one (see
                // `read_chunk_table`).
                let dec =
                    super::decoding(path, || LasZipDecompressor::selective(read, vlr, selection))?
                        .map_err(|e| IoError::format(path, format!("LAZ: {e}")))?;
                Decoder::Layered(Box::new(dec))
            }
            Some(c @ (POINTWISE | POINTWISE_CHUNKED)) => {
                let variable = vlr.uses_variable_size_chunks() || vlr.chunk_size() == 0;
                let plan = if c == POINTWISE {
                    ChunkPlan::One
                } else {
                    // read_from leaves the reader after the 8-byte table offset when it fails
                    // only for want of a table (LASzip writers that could not seek back).
                    match super::read_chunk_table(path, &mut read, &vlr) {
                        Ok(table) => {
                            let mut at = data_start + ChunkTable::OFFSET_SIZE as u64;
                            let mut chunks = Vec::with_capacity(table.as_ref().len());
                            for e in table.as_ref() {
                                chunks.push((e.point_count, at));
                                at = at.saturating_add(e.byte_count);
                            }
                            if variable {
                                ChunkPlan::Table(chunks)
                            } else {
                                let cs = u64::from(vlr.chunk_size());
                                ChunkPlan::Table(
                                    chunks.into_iter().map(|(_, at)| (cs, at)).collect(),
                                )
                            }
                        }
                        Err(e) if variable => {
                            let why = match e {
                                IoError::Format { fault, .. } => fault,
                                other => other.to_string(),
                            };
                            return Err(IoError::format(
                                path,
                                format!(
                                    "LAZ with variable-size chunks needs its chunk table, which this file lacks or cannot decode ({why})"
                                ),
                            ));
                        }
                        Err(_) => {
                            read.seek(SeekFrom::Start(data_start + ChunkTable::OFFSET_SIZE as u64))
                                .map_err(|e| IoError::read(path, e, "LAZ point data"))?;
                            ChunkPlan::Fixed(u64::from(vlr.chunk_size()))
                        }
                    }
                };
                let items = vlr.items().clone();
                let mut dec = Box::new(SequentialPointRecordDecompressor::new(read));
                // Refuses items Sylva cannot decode here, at open; `start_chunk` adds the
                // fields afresh at each chunk (a reset decoder drops them).
                add_pointwise_fields(&mut dec, &items).map_err(|e| IoError::format(path, e))?;
                Decoder::PointWise {
                    dec,
                    items,
                    plan,
                    chunk: 0,
                    left_in_chunk: 0,
                }
            }
            Some(other) => {
                return Err(IoError::format(
                    path,
                    format!("unknown LAZ compressor type {other}"),
                ));
            }
            None => return Err(IoError::format(path, "LAZ VLR is too short")),
        };
        Ok(Self {
            decoder,
            record_len,
            left: declared,
        })
    }

    /// Bytes of one point record.
    pub(crate) fn record_len(&self) -> usize {
        self.record_len
    }

    /// Decodes up to `n` points into `out` (resized to hold them); returns how many (0 at
    /// the end). A decoder error is returned as it is (the caller names the file).
    pub(crate) fn fill(&mut self, n: u64, out: &mut Vec<u8>) -> Result<usize, String> {
        let take = n.min(self.left) as usize;
        out.resize(take * self.record_len, 0);
        match &mut self.decoder {
            Decoder::Layered(dec) => dec.decompress_many(out).map_err(|e| e.to_string())?,
            Decoder::PointWise {
                dec,
                items,
                plan,
                chunk,
                left_in_chunk,
            } => {
                for rec in out.chunks_exact_mut(self.record_len) {
                    if *left_in_chunk == 0 {
                        *left_in_chunk = start_chunk(dec, items, plan, chunk)?;
                    }
                    dec.decompress_next(rec).map_err(|e| e.to_string())?;
                    *left_in_chunk -= 1;
                }
            }
        }
        self.left -= take as u64;
        Ok(take)
    }
}

/// Moves a point-wise decoder to the next chunk that holds points (decoder state starts over,
/// and with a chunk table the stream moves to the chunk's bytes); returns its point count.
fn start_chunk(
    dec: &mut SequentialPointRecordDecompressor<'static, BufReader<File>>,
    items: &[LazItem],
    plan: &ChunkPlan,
    chunk: &mut usize,
) -> Result<u64, String> {
    loop {
        let (count, at) = match plan {
            ChunkPlan::One => (u64::MAX, None),
            ChunkPlan::Fixed(cs) => (*cs, None),
            ChunkPlan::Table(chunks) => {
                let &(count, at) = chunks.get(*chunk).ok_or_else(|| {
                    format!(
                        "the chunk table lists {} chunks, fewer than the points need",
                        chunks.len()
                    )
                })?;
                (count, Some(at))
            }
        };
        *chunk += 1;
        if count == 0 {
            continue; // laz-rs's writer ends variable-size files with an empty chunk
        }
        dec.reset();
        add_pointwise_fields(dec, items)?;
        if let Some(at) = at {
            dec.get_mut()
                .seek(SeekFrom::Start(at))
                .map_err(|e| e.to_string())?;
        }
        return Ok(count);
    }
}
