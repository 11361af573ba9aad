//! File input and output: point clouds (LAS/LAZ, PLY, XYZ), COLMAP sparse models and safe
//! archive extraction.
//!
//! Every reader returns [`IoError`]: `Format` for content that is bad, truncated or
//! inconsistent (the message names the file and the fault), `Io` for operating-system errors
//! (a missing file, permissions, a full disk: callers map `StorageFull` to HTTP 507), and
//! `Cancelled` when the [`Progress`](crate::progress::Progress) sink asked to stop.

pub mod archive;
pub mod colmap;
pub mod copc;
pub mod crs;
pub mod e57;
pub mod gpkg;
pub mod gps;
pub mod las;
pub mod photos;
pub mod ply;
pub mod pointcloud;
pub mod tables;
pub mod xyz;

use std::path::{Component, Path, PathBuf};

use crate::progress::Progress;

/// Error of every reader and writer in this module.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// Bad, truncated or inconsistent content; the message names the file and the fault.
    #[error("{path}: {fault}")]
    Format { path: PathBuf, fault: String },
    /// An operating-system error while opening, reading or writing `path`.
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The progress sink reported cancellation.
    #[error("cancelled")]
    Cancelled,
}

impl IoError {
    /// A `Format` error for `path` with a human-readable `fault`.
    pub fn format(path: impl Into<PathBuf>, fault: impl Into<String>) -> Self {
        IoError::Format {
            path: path.into(),
            fault: fault.into(),
        }
    }

    /// An `Io` error for `path`, kept as is (so `StorageFull` stays visible).
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        IoError::Io {
            path: path.into(),
            source,
        }
    }

    /// An error met while reading file *contents*: an unexpected end of file or invalid data
    /// is a `Format` error ("truncated ..."), anything else stays an `Io` error.
    pub fn read(path: impl Into<PathBuf>, source: std::io::Error, what: &str) -> Self {
        match source.kind() {
            std::io::ErrorKind::UnexpectedEof => {
                IoError::format(path, format!("file is truncated ({what})"))
            }
            std::io::ErrorKind::InvalidData => {
                IoError::format(path, format!("invalid data ({what}): {source}"))
            }
            _ => IoError::io(path, source),
        }
    }

    /// True when the disk (or quota) is full: callers answer HTTP 507.
    pub fn is_storage_full(&self) -> bool {
        matches!(self, IoError::Io { source, .. } if source.kind() == std::io::ErrorKind::StorageFull)
    }
}

/// Points (or records) handled between two progress updates / cancellation checks.
pub(crate) const PROGRESS_STEP: usize = 65_536;

/// Returns `Cancelled` when the progress sink asks to stop.
pub(crate) fn check_cancel(progress: &dyn Progress) -> Result<(), IoError> {
    if progress.is_cancelled() {
        Err(IoError::Cancelled)
    } else {
        Ok(())
    }
}

/// `path` relative to `base`, its components joined by `/` whatever the platform (`path`
/// itself when it does not lie under `base`): the names of stage outputs and of photos.
pub fn relative_name(path: &Path, base: &Path) -> String {
    path.strip_prefix(base)
        .unwrap_or(path)
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect::<Vec<_>>()
        .join("/")
}

/// Turns a name found inside a file (an archive entry, an image name in a COLMAP model) into a
/// relative path that cannot leave the folder it is joined to.
///
/// Both `/` and `\` separate components. Returns `None` for an empty name, an absolute name,
/// a drive prefix (`C:`), a `..` component or a NUL byte. `.` and empty components are dropped.
pub(crate) fn safe_relative_path(name: &str) -> Option<PathBuf> {
    if name.contains('\0') || name.starts_with('/') || name.starts_with('\\') {
        return None;
    }
    let bytes = name.as_bytes();
    if bytes.len() >= 2 && bytes[1] == b':' && bytes[0].is_ascii_alphabetic() {
        return None;
    }
    let mut out = PathBuf::new();
    for part in name.split(['/', '\\']) {
        match part {
            "" | "." => {}
            ".." => return None,
            p => out.push(p),
        }
    }
    // Defence in depth: the result must consist of normal components only.
    if out.as_os_str().is_empty() || !out.components().all(|c| matches!(c, Component::Normal(_))) {
        return None;
    }
    Some(out)
}

/// Size of a file in bytes, as an `Io` error when it cannot be read.
pub(crate) fn file_len(path: &Path) -> Result<u64, IoError> {
    std::fs::metadata(path)
        .map(|m| m.len())
        .map_err(|e| IoError::io(path, e))
}

/// `path` opened for buffered reading, as an `Io` error naming it when it cannot be.
pub(crate) fn open_buffered(path: &Path) -> Result<std::io::BufReader<std::fs::File>, IoError> {
    std::fs::File::open(path)
        .map(std::io::BufReader::new)
        .map_err(|e| IoError::io(path, e))
}

/// The real public point cloud `rel` (a path such as `TreeLS_extdata/pine.laz`) for the
/// real-data tests: the first of `$SYLVA_REAL_DATA`, `$CARGO_MANIFEST_DIR/../shared/data/real`
/// and the small set committed in `tests/data/real` that holds it. `None`, after printing why
/// (`testing::skip`), when none does.
#[cfg(test)]
pub(crate) fn real_data(rel: &str) -> Option<PathBuf> {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dirs = std::env::var_os("SYLVA_REAL_DATA")
        .map(PathBuf::from)
        .into_iter()
        .chain([
            manifest.join("../shared/data/real"),
            manifest.join("tests/data/real"),
        ]);
    let mut looked = Vec::new();
    for dir in dirs {
        let path = dir.join(rel);
        if path.is_file() {
            return Some(path);
        }
        looked.push(dir.display().to_string());
    }
    crate::testing::skip(
        "real-data",
        &format!(
            "{rel} is in none of {} (set SYLVA_REAL_DATA)",
            looked.join(", ")
        ),
    );
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn safe_relative_path_rejects_escapes() {
        for bad in [
            "../evil",
            "a/../../evil",
            "/etc/passwd",
            "\\windows\\evil",
            "C:evil",
            "c:\\evil",
            "a\\..\\..\\evil",
            "nul\0byte",
            "",
            "./",
        ] {
            assert!(safe_relative_path(bad).is_none(), "{bad:?} accepted");
        }
        assert_eq!(
            safe_relative_path("./a/b\\c.jpg"),
            Some(PathBuf::from("a/b/c.jpg"))
        );
    }

    #[test]
    fn storage_full_stays_an_io_error() {
        let e = IoError::read(
            "x",
            std::io::Error::from(std::io::ErrorKind::StorageFull),
            "points",
        );
        assert!(e.is_storage_full());
        let e = IoError::read(
            "x",
            std::io::Error::from(std::io::ErrorKind::UnexpectedEof),
            "points",
        );
        assert!(matches!(e, IoError::Format { .. }));
    }
}
