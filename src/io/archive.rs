//! Safe extraction of uploaded zip, tar and tar.gz archives (detected by magic bytes).
//!
//! Entry names are checked before anything is written ([`super::safe_relative_path`]):
//! absolute names, drive prefixes, `..` components (with `/` or `\` separators) and NUL are
//! refused; so are links and special files. Sizes declared by the archive are never trusted:
//! entries and the bytes actually written are counted while streaming and extraction stops as
//! soon as a limit is passed. On any error the destination is emptied again.

use std::cell::Cell;
use std::fs::{File, OpenOptions};
use std::io::{BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::rc::Rc;

use serde::Serialize;

use super::{IoError, safe_relative_path};
use crate::progress::Progress;

/// Limits of one extraction.
#[derive(Debug, Clone)]
pub struct ExtractLimits {
    /// Most entries (files, folders, ...) accepted.
    pub max_entries: u64,
    /// Most bytes written in all, counted while writing.
    pub max_unpacked_bytes: u64,
    /// Most unpacked bytes per archive byte. Checked once more than [`RATIO_GRACE`] bytes are
    /// written, so a small archive of text files is not refused; a zip bomb trips it long
    /// before the disk fills.
    pub max_ratio: f64,
}

/// Bytes that may be written before the ratio limit applies (16 MiB).
pub const RATIO_GRACE: u64 = 16 << 20;

impl Default for ExtractLimits {
    fn default() -> Self {
        ExtractLimits {
            max_entries: 100_000,
            max_unpacked_bytes: 200 << 30,
            max_ratio: 200.0,
        }
    }
}

/// What an extraction wrote.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct ExtractSummary {
    /// Entries seen (files, folders).
    pub entries: u64,
    /// Regular files written.
    pub files: u64,
    /// Bytes written.
    pub unpacked_bytes: u64,
}

/// Why an extraction was refused.
#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    #[error("not a zip, tar or tar.gz archive")]
    UnknownFormat,
    #[error("the archive holds no regular file")]
    Empty,
    #[error("unsafe entry name {entry:?}")]
    UnsafePath { entry: String },
    #[error("entry {entry:?} is a link; links are not allowed")]
    Link { entry: String },
    #[error("entry {entry:?} is a device, fifo or other special file")]
    SpecialFile { entry: String },
    #[error("more than {limit} entries")]
    TooManyEntries { limit: u64 },
    #[error("unpacks to more than {limit} bytes")]
    TooLarge { limit: u64 },
    #[error("compression ratio {ratio:.0} exceeds {limit:.0}")]
    RatioExceeded { ratio: f64, limit: f64 },
    #[error("corrupt archive: {fault}")]
    Corrupt { fault: String },
    /// A file could not be read or written (`IoError::Io`, so a full disk stays visible), or
    /// the progress sink cancelled (`IoError::Cancelled`).
    #[error(transparent)]
    File(#[from] IoError),
}

fn io_err(path: &Path) -> impl Fn(std::io::Error) -> ArchiveError + '_ {
    move |source| IoError::io(path, source).into()
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Kind {
    Zip,
    Tar,
    TarGz,
}

fn detect(path: &Path) -> Result<Kind, ArchiveError> {
    let mut head = Vec::with_capacity(512);
    File::open(path)
        .and_then(|f| f.take(512).read_to_end(&mut head))
        .map_err(io_err(path))?;
    if head.starts_with(b"PK\x03\x04") || head.starts_with(b"PK\x05\x06") {
        Ok(Kind::Zip)
    } else if head.starts_with(&[0x1f, 0x8b]) {
        Ok(Kind::TarGz)
    } else if head.get(257..262) == Some(b"ustar") {
        Ok(Kind::Tar)
    } else {
        Err(ArchiveError::UnknownFormat)
    }
}

/// Running totals and the checks applied while writing.
struct Sink<'a> {
    dest: &'a Path,
    limits: &'a ExtractLimits,
    packed: u64,
    progress: &'a dyn Progress,
    summary: ExtractSummary,
}

impl Sink<'_> {
    fn entry(&mut self, name: &str) -> Result<Option<PathBuf>, ArchiveError> {
        if self.progress.is_cancelled() {
            return Err(ArchiveError::File(IoError::Cancelled));
        }
        self.summary.entries += 1;
        if self.summary.entries > self.limits.max_entries {
            return Err(ArchiveError::TooManyEntries {
                limit: self.limits.max_entries,
            });
        }
        if name.contains('\0') {
            return Err(ArchiveError::UnsafePath {
                entry: name.replace('\0', "\\0"),
            });
        }
        if name.split(['/', '\\']).all(|p| p.is_empty() || p == ".") && !name.is_empty() {
            return Ok(None); // "./" : the destination itself
        }
        safe_relative_path(name)
            .map(|rel| Some(self.dest.join(rel)))
            .ok_or_else(|| ArchiveError::UnsafePath {
                entry: name.to_string(),
            })
    }

    fn dir(&mut self, path: &Path) -> Result<(), ArchiveError> {
        std::fs::create_dir_all(path).map_err(io_err(path))
    }

    /// Streams one file, counting the bytes actually written.
    fn file(&mut self, path: &Path, mut data: impl Read) -> Result<(), ArchiveError> {
        if let Some(parent) = path.parent() {
            self.dir(parent)?;
        }
        let mut out = OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(path)
            .map_err(|e| {
                if e.kind() == std::io::ErrorKind::AlreadyExists {
                    ArchiveError::Corrupt {
                        fault: format!("duplicate entry {}", path.display()),
                    }
                } else {
                    io_err(path)(e)
                }
            })?;
        let mut buf = vec![0u8; 64 << 10];
        loop {
            let n = match data.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    return Err(ArchiveError::Corrupt {
                        fault: e.to_string(),
                    });
                }
            };
            let total = self.summary.unpacked_bytes + n as u64;
            if total > self.limits.max_unpacked_bytes {
                return Err(ArchiveError::TooLarge {
                    limit: self.limits.max_unpacked_bytes,
                });
            }
            let ratio = total as f64 / self.packed.max(1) as f64;
            if total > RATIO_GRACE && ratio > self.limits.max_ratio {
                return Err(ArchiveError::RatioExceeded {
                    ratio,
                    limit: self.limits.max_ratio,
                });
            }
            if self.progress.is_cancelled() {
                return Err(ArchiveError::File(IoError::Cancelled));
            }
            out.write_all(&buf[..n]).map_err(io_err(path))?;
            self.summary.unpacked_bytes = total;
        }
        self.summary.files += 1;
        Ok(())
    }
}

/// Extracts `archive` (zip, tar or tar.gz, by magic bytes) into `dest`, which must not exist
/// or be an empty folder. Directory entries are created; permissions are not copied.
pub fn extract_archive(
    archive: &Path,
    dest: &Path,
    limits: &ExtractLimits,
    progress: &dyn Progress,
) -> Result<ExtractSummary, ArchiveError> {
    let kind = detect(archive)?;
    let packed = std::fs::metadata(archive).map_err(io_err(archive))?.len();
    let existed = dest.exists();
    if existed {
        let mut entries = std::fs::read_dir(dest).map_err(io_err(dest))?;
        if entries.next().is_some() {
            let e = std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "destination is not empty",
            );
            return Err(io_err(dest)(e));
        }
    } else {
        std::fs::create_dir_all(dest).map_err(io_err(dest))?;
    }
    let mut sink = Sink {
        dest,
        limits,
        packed,
        progress,
        summary: ExtractSummary::default(),
    };
    let result = match kind {
        Kind::Zip => extract_zip(archive, &mut sink),
        Kind::Tar | Kind::TarGz => extract_tar(archive, kind == Kind::TarGz, &mut sink),
    };
    let result = match result {
        Ok(()) if sink.summary.files == 0 => Err(ArchiveError::Empty),
        other => other,
    };
    match result {
        Ok(()) => {
            progress.set(1.0);
            Ok(sink.summary)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(dest);
            if existed {
                let _ = std::fs::create_dir(dest);
            }
            Err(e)
        }
    }
}

const S_IFMT: u32 = 0o170_000;
const S_IFREG: u32 = 0o100_000;
const S_IFDIR: u32 = 0o040_000;
const S_IFLNK: u32 = 0o120_000;

fn extract_zip(archive: &Path, sink: &mut Sink<'_>) -> Result<(), ArchiveError> {
    let file = BufReader::new(File::open(archive).map_err(io_err(archive))?);
    let corrupt = |e: zip::result::ZipError| ArchiveError::Corrupt {
        fault: e.to_string(),
    };
    let mut zip = zip::ZipArchive::new(file).map_err(corrupt)?;
    if zip.len() as u64 > sink.limits.max_entries {
        return Err(ArchiveError::TooManyEntries {
            limit: sink.limits.max_entries,
        });
    }
    for i in 0..zip.len() {
        sink.progress.set(i as f64 / zip.len() as f64);
        let entry = zip.by_index(i).map_err(corrupt)?;
        let name = String::from_utf8_lossy(entry.name_raw()).into_owned();
        let target = sink.entry(&name)?;
        let mode = entry.unix_mode().map(|m| m & S_IFMT).filter(|&m| m != 0);
        match mode {
            Some(S_IFLNK) => return Err(ArchiveError::Link { entry: name }),
            Some(S_IFREG) | Some(S_IFDIR) | None => {}
            Some(_) => return Err(ArchiveError::SpecialFile { entry: name }),
        }
        let Some(target) = target else { continue };
        if entry.is_dir() || mode == Some(S_IFDIR) {
            sink.dir(&target)?;
        } else {
            sink.file(&target, entry)?;
        }
    }
    Ok(())
}

/// Counts bytes read from the archive file, for progress.
struct Counting<R> {
    inner: R,
    read: Rc<Cell<u64>>,
}

impl<R: Read> Read for Counting<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.read.set(self.read.get() + n as u64);
        Ok(n)
    }
}

fn extract_tar(archive: &Path, gz: bool, sink: &mut Sink<'_>) -> Result<(), ArchiveError> {
    let read = Rc::new(Cell::new(0u64));
    let file = Counting {
        inner: BufReader::new(File::open(archive).map_err(io_err(archive))?),
        read: Rc::clone(&read),
    };
    let stream: Box<dyn Read> = if gz {
        Box::new(flate2::read::MultiGzDecoder::new(file))
    } else {
        Box::new(file)
    };
    let mut tar = tar::Archive::new(stream);
    let corrupt = |e: std::io::Error| ArchiveError::Corrupt {
        fault: e.to_string(),
    };
    for entry in tar.entries().map_err(corrupt)? {
        let entry = entry.map_err(corrupt)?;
        sink.progress
            .set(read.get() as f64 / sink.packed.max(1) as f64);
        let ty = entry.header().entry_type();
        if ty.is_pax_global_extensions() || ty.is_pax_local_extensions() {
            continue;
        }
        let name = String::from_utf8_lossy(&entry.path_bytes()).into_owned();
        let target = sink.entry(&name)?;
        use tar::EntryType as T;
        match ty {
            T::Symlink | T::Link => return Err(ArchiveError::Link { entry: name }),
            T::Regular | T::Continuous | T::GNUSparse | T::Directory => {}
            _ => return Err(ArchiveError::SpecialFile { entry: name }),
        }
        let Some(target) = target else { continue };
        if ty == T::Directory {
            sink.dir(&target)?;
        } else {
            sink.file(&target, entry)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;
