//! Blob storage on the local filesystem (the embedded default).
//!
//! Layout under the data directory:
//! ```text
//! uploads/<id>/parts/<n>         received parts, each written to a temp name, synced, renamed
//! uploads/<id>/blob.<ext>        the assembled upload (ext from a fixed list, never the
//!                                client's file name)
//! uploads/<id>/unpacked/         an extracted COLMAP archive
//! jobs/<id>/<stage>/             a job's finished stage outputs (artifacts)
//! ```
//! Everything is streamed; nothing holds a whole upload in memory.

use std::path::{Path, PathBuf};

use futures::{Stream, StreamExt};
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the part is larger than {limit} bytes")]
    TooLarge { limit: u64 },
    #[error("the request body could not be read: {0}")]
    Body(String),
}

impl StoreError {
    pub fn is_storage_full(&self) -> bool {
        matches!(self, StoreError::Io { source, .. } if source.kind() == std::io::ErrorKind::StorageFull)
    }
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Extensions an upload blob may carry, so format detection by name still works. A client's
/// file name contributes at most one of these, never a path.
const KNOWN_EXTENSIONS: &[&str] = &[
    "las", "laz", "ply", "e57", "xyz", "txt", "csv", "pts", "zip", "tar", "gz", "tgz",
];

/// The blob extension for a client file name: a known extension, or `bin`.
pub fn blob_extension(filename: &str) -> &'static str {
    let ext = filename
        .rsplit('.')
        .next()
        .unwrap_or("")
        .to_ascii_lowercase();
    KNOWN_EXTENSIONS
        .iter()
        .copied()
        .find(|k| *k == ext)
        .unwrap_or("bin")
}

/// The local blob store rooted at the data directory.
#[derive(Debug, Clone)]
pub struct BlobStore {
    root: PathBuf,
}

impl BlobStore {
    pub fn open(root: &Path) -> Result<Self, StoreError> {
        for sub in ["uploads", "jobs"] {
            let p = root.join(sub);
            std::fs::create_dir_all(&p).map_err(io(&p))?;
        }
        Ok(Self {
            root: root.to_path_buf(),
        })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn upload_dir(&self, id: &str) -> PathBuf {
        self.root.join("uploads").join(id)
    }

    pub fn upload_blob(&self, id: &str, filename: &str) -> PathBuf {
        self.upload_dir(id)
            .join(format!("blob.{}", blob_extension(filename)))
    }

    pub fn upload_unpacked(&self, id: &str) -> PathBuf {
        self.upload_dir(id).join("unpacked")
    }

    fn part_path(&self, id: &str, n: i64) -> PathBuf {
        self.upload_dir(id).join("parts").join(n.to_string())
    }

    pub fn job_dir(&self, id: &str) -> PathBuf {
        self.root.join("jobs").join(id)
    }

    /// Streams a part to disk (temp file, sync, rename), hashing as it goes. Fails without
    /// leaving anything behind when the body exceeds `limit` bytes.
    pub async fn write_part<S, E>(
        &self,
        id: &str,
        n: i64,
        mut body: S,
        limit: u64,
    ) -> Result<(u64, String), StoreError>
    where
        S: Stream<Item = Result<bytes::Bytes, E>> + Unpin,
        E: std::fmt::Display,
    {
        let dir = self.upload_dir(id).join("parts");
        tokio::fs::create_dir_all(&dir).await.map_err(io(&dir))?;
        let tmp = dir.join(format!(".{n}.{}.tmp", uuid::Uuid::new_v4().simple()));
        let result = async {
            let mut file = tokio::fs::File::create(&tmp).await.map_err(io(&tmp))?;
            let mut hasher = Sha256::new();
            let mut size = 0u64;
            while let Some(chunk) = body.next().await {
                let chunk = chunk.map_err(|e| StoreError::Body(e.to_string()))?;
                size += chunk.len() as u64;
                if size > limit {
                    return Err(StoreError::TooLarge { limit });
                }
                hasher.update(&chunk);
                file.write_all(&chunk).await.map_err(io(&tmp))?;
            }
            file.sync_all().await.map_err(io(&tmp))?;
            Ok((size, hex::encode(hasher.finalize())))
        }
        .await;
        match result {
            Ok(v) => {
                let dest = self.part_path(id, n);
                tokio::fs::rename(&tmp, &dest).await.map_err(io(&dest))?;
                Ok(v)
            }
            Err(e) => {
                let _ = tokio::fs::remove_file(&tmp).await;
                Err(e)
            }
        }
    }

    /// Concatenates parts 0..parts into the upload's blob, returning size and SHA-256.
    /// Blocking: call from `spawn_blocking`.
    pub fn assemble(
        &self,
        id: &str,
        filename: &str,
        parts: i64,
    ) -> Result<(u64, String), StoreError> {
        use std::io::{Read, Write};
        let dest = self.upload_blob(id, filename);
        let tmp = dest.with_extension(format!("{}.assembling", uuid::Uuid::new_v4().simple()));
        let mut out = std::fs::File::create(&tmp).map_err(io(&tmp))?;
        let mut hasher = Sha256::new();
        let mut size = 0u64;
        let mut buf = vec![0u8; 1 << 20];
        for n in 0..parts {
            let p = self.part_path(id, n);
            let mut f = std::fs::File::open(&p).map_err(io(&p))?;
            loop {
                let k = f.read(&mut buf).map_err(io(&p))?;
                if k == 0 {
                    break;
                }
                hasher.update(&buf[..k]);
                out.write_all(&buf[..k]).map_err(io(&tmp))?;
                size += k as u64;
            }
        }
        out.sync_all().map_err(io(&tmp))?;
        std::fs::rename(&tmp, &dest).map_err(io(&dest))?;
        Ok((size, hex::encode(hasher.finalize())))
    }

    /// Removes the parts of a completed upload (the blob holds them now).
    pub fn drop_parts(&self, id: &str) {
        let _ = std::fs::remove_dir_all(self.upload_dir(id).join("parts"));
    }

    /// Removes a job's files.
    pub fn remove_job(&self, id: &str) -> Result<(), StoreError> {
        let dir = self.job_dir(id);
        match std::fs::remove_dir_all(&dir) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io(&dir)(e)),
            _ => Ok(()),
        }
    }

    /// Removes the output folders of the named stages of a job (before a retry).
    pub fn remove_stages(&self, id: &str, stages: &[String]) -> Result<(), StoreError> {
        for s in stages {
            for dir in [
                self.job_dir(id).join(s),
                self.job_dir(id).join(format!("{s}.partial")),
            ] {
                match std::fs::remove_dir_all(&dir) {
                    Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io(&dir)(e)),
                    _ => {}
                }
            }
        }
        Ok(())
    }

    /// Free bytes on the filesystem holding the data directory.
    pub fn free_bytes(&self) -> Result<u64, StoreError> {
        free_bytes(&self.root).map_err(io(&self.root))
    }
}

/// Free bytes available to unprivileged users on the filesystem holding `path`.
pub fn free_bytes(path: &Path) -> std::io::Result<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(path.as_os_str().as_bytes())
        .map_err(|_| std::io::Error::new(std::io::ErrorKind::InvalidInput, "NUL in path"))?;
    let mut s: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `c` is a valid NUL-terminated path and `s` a properly sized out-parameter.
    let rc = unsafe { libc::statvfs(c.as_ptr(), &mut s) };
    if rc != 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(s.f_bavail as u64 * s.f_frsize as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn client_names_contribute_only_known_extensions() {
        assert_eq!(blob_extension("plot.LAZ"), "laz");
        assert_eq!(blob_extension("../../etc/passwd"), "bin");
        assert_eq!(blob_extension("x.tar.gz"), "gz");
        assert_eq!(blob_extension("noext"), "bin");
    }

    #[tokio::test]
    async fn parts_assemble_in_order_with_checksum() {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = BlobStore::open(dir.path()).expect("store");
        let body = |b: &'static [u8]| {
            futures::stream::iter(vec![Ok::<_, std::io::Error>(bytes::Bytes::from_static(b))])
        };
        store
            .write_part("u", 1, body(b"world"), 16)
            .await
            .expect("part 1");
        store
            .write_part("u", 0, body(b"hello "), 16)
            .await
            .expect("part 0");
        let err = store
            .write_part("u", 2, body(b"this part is too long"), 16)
            .await;
        assert!(matches!(err, Err(StoreError::TooLarge { .. })));
        let (size, sha) = store.assemble("u", "a.xyz", 2).expect("assemble");
        assert_eq!(size, 11);
        assert_eq!(sha, hex::encode(Sha256::digest(b"hello world")));
        assert_eq!(
            std::fs::read(store.upload_blob("u", "a.xyz")).expect("blob"),
            b"hello world"
        );
        assert!(store.free_bytes().expect("statvfs") > 0);
    }
}
