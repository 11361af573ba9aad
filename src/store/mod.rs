//! Blob storage: the local filesystem (the embedded default), optionally backed by an object
//! store (`--store s3://bucket/prefix`, see [`remote`]) that holds the copy that counts when API
//! replicas and workers run on different machines.
//!
//! Layout under the data directory (and, for uploads and stage outputs, under the store's
//! prefix):
//! ```text
//! uploads/<id>/parts/<n>         received parts, each written to a temp name, synced, renamed
//! uploads/<id>/blob.<ext>        the assembled upload (ext from a fixed list, never the
//!                                client's file name)
//! uploads/<id>/unpacked/         an extracted COLMAP archive
//! jobs/<id>/<stage>/             a job's finished stage outputs (artifacts)
//! ```
//! Everything is streamed; nothing holds a whole upload in memory.

pub mod remote;

use std::path::{Path, PathBuf};

use futures::{Stream, StreamExt};
use remote::Remote;
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
    #[error("object store: {0}")]
    Remote(String),
    #[error("{0}")]
    Config(String),
    #[error("{0} is missing from the object store")]
    NotFound(String),
    #[error("{0}")]
    Internal(String),
}

impl StoreError {
    pub fn is_storage_full(&self) -> bool {
        matches!(self, StoreError::Io { source, .. } if source.kind() == std::io::ErrorKind::StorageFull)
    }
}

pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// A request body as it arrives: pieces of bytes, or the error that cut it short (reported as
/// [`StoreError::Body`]). Every stream of `Result<Bytes, E: Display>` is one.
pub trait Body: Stream<Item = Result<bytes::Bytes, Self::Fault>> + Unpin {
    /// What a failed read of the body says.
    type Fault: std::fmt::Display;
}

impl<S, E> Body for S
where
    S: Stream<Item = Result<bytes::Bytes, E>> + Unpin,
    E: std::fmt::Display,
{
    type Fault = E;
}

/// The size and SHA-256 of bytes as they stream past.
#[derive(Default)]
struct Tally {
    hasher: Sha256,
    size: u64,
}

impl Tally {
    /// Counts and hashes `bytes`.
    fn add(&mut self, bytes: &[u8]) {
        self.hasher.update(bytes);
        self.size += bytes.len() as u64;
    }

    /// Counts and hashes the next piece of a request body, refused ([`StoreError::TooLarge`])
    /// once the body passes `limit` bytes.
    fn take<E: std::fmt::Display>(
        &mut self,
        chunk: Result<bytes::Bytes, E>,
        limit: u64,
    ) -> Result<bytes::Bytes, StoreError> {
        let chunk = chunk.map_err(|e| StoreError::Body(e.to_string()))?;
        if self.size + chunk.len() as u64 > limit {
            return Err(StoreError::TooLarge { limit });
        }
        self.add(&chunk);
        Ok(chunk)
    }

    /// Size and lower-case hex SHA-256.
    fn finish(self) -> (u64, String) {
        (self.size, hex::encode(self.hasher.finalize()))
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

/// The blob store: the data directory, and the object store behind it when there is one.
#[derive(Debug, Clone)]
pub struct BlobStore {
    root: PathBuf,
    remote: Option<Remote>,
}

impl BlobStore {
    /// Local files only, under `root`.
    pub fn open(root: &Path) -> Result<Self, StoreError> {
        Self::open_with(root, None)
    }

    /// Under `root`, backed by the object store at `store` (`s3://...`, `file:///...`) when
    /// one is named.
    pub fn open_with(root: &Path, store: Option<&str>) -> Result<Self, StoreError> {
        for sub in ["uploads", "jobs"] {
            let p = root.join(sub);
            std::fs::create_dir_all(&p).map_err(io(&p))?;
        }
        let remote = match store.map(str::trim) {
            None | Some("") | Some("local") => None,
            Some(url) => Some(Remote::open(url)?),
        };
        Ok(Self {
            root: root.to_path_buf(),
            remote,
        })
    }

    /// `local`, `s3` or `file`: where blobs live.
    pub fn kind(&self) -> &'static str {
        self.remote.as_ref().map_or("local", |r| r.kind)
    }

    /// The object store, when blobs live in one.
    pub fn remote(&self) -> Option<&Remote> {
        self.remote.as_ref()
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

    /// Stores part `n` of upload `id`, hashing as it goes: on disk (temp file, sync, rename)
    /// or as one object. Fails without leaving anything behind when the body exceeds `limit`
    /// bytes. Returns size and SHA-256 (hex).
    pub async fn write_part(
        &self,
        id: &str,
        n: i64,
        body: impl Body,
        limit: u64,
    ) -> Result<(u64, String), StoreError> {
        match &self.remote {
            Some(r) => {
                r.put_stream(&format!("uploads/{id}/parts/{n}"), body, limit)
                    .await
            }
            None => self.write_part_local(id, n, body, limit).await,
        }
    }

    async fn write_part_local(
        &self,
        id: &str,
        n: i64,
        mut body: impl Body,
        limit: u64,
    ) -> Result<(u64, String), StoreError> {
        let dir = self.upload_dir(id).join("parts");
        tokio::fs::create_dir_all(&dir).await.map_err(io(&dir))?;
        let tmp = dir.join(format!(".{n}.{}.tmp", uuid::Uuid::new_v4().simple()));
        let result = async {
            let mut file = tokio::fs::File::create(&tmp).await.map_err(io(&tmp))?;
            let mut tally = Tally::default();
            while let Some(chunk) = body.next().await {
                let chunk = tally.take(chunk, limit)?;
                file.write_all(&chunk).await.map_err(io(&tmp))?;
            }
            file.sync_all().await.map_err(io(&tmp))?;
            Ok(tally.finish())
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

    /// Concatenates parts 0..parts into the upload's blob, returning size and SHA-256. With an
    /// object store the blob is written there and a working copy kept locally (for inspection
    /// and for a worker on the same machine).
    pub async fn assemble(
        &self,
        id: &str,
        filename: &str,
        parts: i64,
    ) -> Result<(u64, String), StoreError> {
        match &self.remote {
            Some(r) => {
                let keys: Vec<String> = (0..parts)
                    .map(|n| format!("uploads/{id}/parts/{n}"))
                    .collect();
                let dest = format!("uploads/{id}/blob.{}", blob_extension(filename));
                r.concat(&keys, &dest, &self.upload_blob(id, filename))
                    .await
            }
            None => {
                let (me, id, filename) = (self.clone(), id.to_string(), filename.to_string());
                tokio::task::spawn_blocking(move || me.assemble_local(&id, &filename, parts))
                    .await
                    .map_err(|e| StoreError::Internal(format!("assembly crashed: {e}")))?
            }
        }
    }

    fn assemble_local(
        &self,
        id: &str,
        filename: &str,
        parts: i64,
    ) -> Result<(u64, String), StoreError> {
        use std::io::{Read, Write};
        let dest = self.upload_blob(id, filename);
        let tmp = dest.with_extension(format!("{}.assembling", uuid::Uuid::new_v4().simple()));
        let mut out = std::fs::File::create(&tmp).map_err(io(&tmp))?;
        let mut tally = Tally::default();
        let mut buf = vec![0u8; 1 << 20];
        for n in 0..parts {
            let p = self.part_path(id, n);
            let mut f = std::fs::File::open(&p).map_err(io(&p))?;
            loop {
                let k = f.read(&mut buf).map_err(io(&p))?;
                if k == 0 {
                    break;
                }
                tally.add(&buf[..k]);
                out.write_all(&buf[..k]).map_err(io(&tmp))?;
            }
        }
        out.sync_all().map_err(io(&tmp))?;
        std::fs::rename(&tmp, &dest).map_err(io(&dest))?;
        Ok(tally.finish())
    }

    /// Removes an assembled blob found unusable (and its extracted folder).
    pub async fn discard_blob(&self, id: &str, filename: &str) {
        let _ = tokio::fs::remove_file(self.upload_blob(id, filename)).await;
        let _ = tokio::fs::remove_dir_all(self.upload_unpacked(id)).await;
        if let Some(r) = &self.remote {
            let _ = r
                .delete(&format!("uploads/{id}/blob.{}", blob_extension(filename)))
                .await;
        }
    }

    /// Removes the parts of a completed upload (the blob holds them now).
    pub async fn drop_parts(&self, id: &str) {
        let _ = tokio::fs::remove_dir_all(self.upload_dir(id).join("parts")).await;
        if let Some(r) = &self.remote
            && let Err(e) = r.delete_prefix(&format!("uploads/{id}/parts")).await
        {
            tracing::warn!(upload = id, error = %e, "could not delete the parts of an assembled upload");
        }
    }

    /// Removes a job's files (locally and in the object store).
    pub async fn remove_job(&self, id: &str) -> Result<(), StoreError> {
        self.remove_tree(&self.job_dir(id), &format!("jobs/{id}"))
            .await
    }

    /// Removes an upload's files (parts, blob, extracted folder), locally and in the object
    /// store.
    pub async fn remove_upload(&self, id: &str) -> Result<(), StoreError> {
        self.remove_tree(&self.upload_dir(id), &format!("uploads/{id}"))
            .await
    }

    /// Removes the local folder `dir` and the object-store prefix `rel`.
    async fn remove_tree(&self, dir: &Path, rel: &str) -> Result<(), StoreError> {
        match tokio::fs::remove_dir_all(dir).await {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io(dir)(e)),
            _ => {}
        }
        if let Some(r) = &self.remote {
            r.delete_prefix(rel).await?;
        }
        Ok(())
    }

    /// Removes the output folders of the named stages of a job (before a retry).
    pub async fn remove_stages(&self, id: &str, stages: &[String]) -> Result<(), StoreError> {
        for s in stages {
            for dir in [
                self.job_dir(id).join(s),
                self.job_dir(id).join(format!("{s}.partial")),
            ] {
                match tokio::fs::remove_dir_all(&dir).await {
                    Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io(&dir)(e)),
                    _ => {}
                }
            }
            if let Some(r) = &self.remote {
                r.delete_prefix(&format!("jobs/{id}/{s}")).await?;
            }
        }
        Ok(())
    }

    /// The local path of an input upload's blob, or of its extracted folder for an archive
    /// (`unpack`), fetching the blob from the object store and extracting it when this
    /// machine has no copy yet.
    pub async fn local_input(
        &self,
        id: &str,
        filename: &str,
        unpack: Option<&crate::io::archive::ExtractLimits>,
    ) -> Result<PathBuf, StoreError> {
        let blob = self.upload_blob(id, filename);
        if let Some(r) = &self.remote
            && !tokio::fs::try_exists(&blob).await.unwrap_or(false)
        {
            r.get_file(
                &format!("uploads/{id}/blob.{}", blob_extension(filename)),
                &blob,
            )
            .await?;
        }
        let Some(limits) = unpack else {
            return Ok(blob);
        };
        let dir = self.upload_unpacked(id);
        if self.remote.is_some() && !tokio::fs::try_exists(&dir).await.unwrap_or(false) {
            let limits = limits.clone();
            let d = dir.clone();
            tokio::task::spawn_blocking(move || -> Result<(), StoreError> {
                let tmp = d.with_extension(format!("{}.partial", uuid::Uuid::new_v4().simple()));
                crate::io::archive::extract_archive(
                    &blob,
                    &tmp,
                    &limits,
                    &crate::progress::NoProgress,
                )
                .map_err(|e| {
                    let _ = std::fs::remove_dir_all(&tmp);
                    StoreError::Internal(format!("cannot extract {}: {e}", blob.display()))
                })?;
                std::fs::rename(&tmp, &d).map_err(io(&d))
            })
            .await
            .map_err(|e| StoreError::Internal(format!("extraction crashed: {e}")))??;
        }
        Ok(dir)
    }

    /// Copies a finished stage's outputs (`jobs/<id>/<stage>/`) to the object store, replacing
    /// whatever an earlier attempt left there. Without an object store there is nothing to do.
    pub async fn push_stage(&self, id: &str, stage: &str) -> Result<(), StoreError> {
        let Some(r) = &self.remote else {
            return Ok(());
        };
        let base = format!("jobs/{id}/{stage}");
        r.delete_prefix(&base).await?;
        let dir = self.job_dir(id).join(stage);
        for (rel, path) in files_under(&dir)? {
            r.put_file(&path, &format!("{base}/{rel}")).await?;
        }
        Ok(())
    }

    /// Brings the outputs of a job's finished `stages` from the object store into the local
    /// job folder where this machine lacks them or holds another size (a job resumed on
    /// another machine). Without an object store there is nothing to do.
    pub async fn pull_stages(&self, id: &str, stages: &[String]) -> Result<u64, StoreError> {
        let Some(r) = &self.remote else {
            return Ok(0);
        };
        let mut fetched = 0;
        for stage in stages {
            let base = format!("jobs/{id}/{stage}");
            let dir = self.job_dir(id).join(stage);
            for (rel, size) in r.list(&base).await? {
                let local = dir.join(&rel);
                let have = tokio::fs::metadata(&local).await.map(|m| m.len()).ok();
                if have != Some(size) {
                    r.get_file(&format!("{base}/{rel}"), &local).await?;
                    fetched += 1;
                }
            }
        }
        Ok(fetched)
    }

    /// Free bytes on the filesystem holding the data directory.
    pub fn free_bytes(&self) -> Result<u64, StoreError> {
        free_bytes(&self.root).map_err(io(&self.root))
    }
}

/// Every file under `dir` as (path relative to `dir` with `/` separators, full path).
fn files_under(dir: &Path) -> Result<Vec<(String, PathBuf)>, StoreError> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for entry in std::fs::read_dir(&d).map_err(io(&d))? {
            let entry = entry.map_err(io(&d))?;
            let path = entry.path();
            let ft = entry.file_type().map_err(io(&path))?;
            if ft.is_dir() {
                todo.push(path);
            } else if ft.is_file()
                && let Ok(rel) = path.strip_prefix(dir)
            {
                let rel: Vec<String> = rel
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect();
                out.push((rel.join("/"), path));
            }
        }
    }
    out.sort();
    Ok(out)
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
        write_hello_world(&store).await;
        assemble_hello_world(&store).await;
        assert!(store.free_bytes().expect("statvfs") > 0);
    }

    fn body(b: &'static [u8]) -> impl Stream<Item = Result<bytes::Bytes, std::io::Error>> + Unpin {
        futures::stream::iter(vec![Ok(bytes::Bytes::from_static(b))])
    }

    /// Writes upload "u" as parts "hello " and "world" (out of order, parts of at most 16
    /// bytes), and checks that a longer third part is refused.
    async fn write_hello_world(store: &BlobStore) {
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
    }

    /// Assembles the parts of [`write_hello_world`] into `a.xyz` and checks the blob.
    async fn assemble_hello_world(store: &BlobStore) {
        let (size, sha) = store.assemble("u", "a.xyz", 2).await.expect("assemble");
        assert_eq!(size, 11);
        assert_eq!(sha, hex::encode(Sha256::digest(b"hello world")));
        assert_eq!(
            std::fs::read(store.upload_blob("u", "a.xyz")).expect("blob"),
            b"hello world"
        );
    }

    /// Two "machines" (data directories) sharing one object store: what one stores, the other
    /// fetches; deletions reach the store.
    #[tokio::test]
    async fn an_object_store_carries_uploads_and_stage_outputs_between_machines() {
        let dir = tempfile::tempdir().expect("tempdir");
        let url = format!("file://{}", dir.path().join("bucket").display());
        let a = BlobStore::open_with(&dir.path().join("a"), Some(&url)).expect("store a");
        let b = BlobStore::open_with(&dir.path().join("b"), Some(&url)).expect("store b");
        assert_eq!(a.kind(), "file");
        let remote = a.remote().expect("remote").clone();

        write_hello_world(&a).await;
        let parts = remote.list("uploads/u/parts").await.expect("list");
        assert_eq!(parts, vec![("0".to_string(), 6), ("1".to_string(), 5)]);
        assert!(
            !a.upload_dir("u").join("parts").exists(),
            "parts stay off the local disk"
        );

        assemble_hello_world(&a).await;
        a.drop_parts("u").await;
        assert!(
            remote
                .list("uploads/u/parts")
                .await
                .expect("list")
                .is_empty()
        );

        // Machine b has never seen the upload: it is fetched.
        let p = b.local_input("u", "a.xyz", None).await.expect("fetch");
        assert_eq!(std::fs::read(p).expect("read"), b"hello world");

        // Stage outputs computed on a, resumed on b.
        let stage = a.job_dir("j").join("ingest");
        std::fs::create_dir_all(stage.join("sparse")).expect("mkdir");
        std::fs::write(stage.join("report.json"), b"{}").expect("write");
        std::fs::write(stage.join("sparse").join("cameras.txt"), b"# none").expect("write");
        a.push_stage("j", "ingest").await.expect("push");
        let fetched = b
            .pull_stages("j", &["ingest".to_string()])
            .await
            .expect("pull");
        assert_eq!(fetched, 2);
        assert_eq!(
            std::fs::read(b.job_dir("j").join("ingest/sparse/cameras.txt")).expect("read"),
            b"# none"
        );
        assert_eq!(
            b.pull_stages("j", &["ingest".to_string()])
                .await
                .expect("pull"),
            0
        );

        // A stale local copy (another size) is replaced.
        std::fs::write(b.job_dir("j").join("ingest/report.json"), b"{\"old\": 1}").expect("w");
        assert_eq!(
            b.pull_stages("j", &["ingest".to_string()])
                .await
                .expect("pull"),
            1
        );

        b.remove_stages("j", &["ingest".to_string()])
            .await
            .expect("remove stage");
        assert!(remote.list("jobs/j/ingest").await.expect("list").is_empty());
        a.push_stage("j", "ingest").await.expect("push");
        a.remove_job("j").await.expect("remove job");
        assert!(remote.list("jobs/j").await.expect("list").is_empty());
        assert!(!a.job_dir("j").exists());
    }

    #[test]
    fn unknown_store_schemes_are_refused_clearly() {
        let dir = tempfile::tempdir().expect("tempdir");
        let err = BlobStore::open_with(dir.path(), Some("ftp://x/y")).expect_err("ftp");
        assert!(err.to_string().contains("unsupported scheme"), "{err}");
        let err = BlobStore::open_with(dir.path(), Some("file://relative")).expect_err("rel");
        assert!(err.to_string().contains("absolute"), "{err}");
        assert_eq!(
            BlobStore::open_with(dir.path(), Some("local"))
                .expect("local")
                .kind(),
            "local"
        );
    }
}
