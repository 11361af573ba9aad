//! Blobs in an object store (S3-compatible, or a shared folder through `file://`), for
//! deployments where API replicas and workers run on different machines.
//!
//! Keys mirror the local layout under the store's prefix:
//! ```text
//! <prefix>/uploads/<id>/parts/<n>     one object per received part
//! <prefix>/uploads/<id>/blob.<ext>    the assembled upload
//! <prefix>/jobs/<id>/<stage>/<file>   a finished stage's outputs
//! ```
//! Everything is streamed: parts and blobs go up as multipart uploads in 5 MiB pieces (aborted
//! when anything fails, so no half-written object is ever visible), downloads come down in
//! chunks. The local data directory still holds working copies (the extracted COLMAP project,
//! the stage folders a worker computes in); the store is the copy that counts.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use futures::{Stream, StreamExt, TryStreamExt};
use object_store::path::Path as Key;
use object_store::signer::Signer;
use object_store::{ObjectStore, ObjectStoreExt, WriteMultipart};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::{Body, StoreError, Tally};

/// Bytes per multipart piece (S3's smallest part, except the last, is 5 MiB).
const PIECE: usize = 5 << 20;
/// Pieces in flight at once per upload (bounds memory to about 4 × 5 MiB per transfer).
const IN_FLIGHT: usize = 4;

/// An object store and the key prefix Sylva owns in it.
#[derive(Clone)]
pub struct Remote {
    store: Arc<dyn ObjectStore>,
    signer: Option<Arc<dyn Signer>>,
    prefix: Key,
    /// What the store was opened from, credentials never included (for logs and /v1/info).
    pub url: String,
    /// `s3` or `file`.
    pub kind: &'static str,
}

impl std::fmt::Debug for Remote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Remote").field("url", &self.url).finish()
    }
}

fn os(e: object_store::Error) -> StoreError {
    StoreError::Remote(e.to_string())
}

impl Remote {
    /// Opens `url`: `s3://bucket[/prefix]` (credentials, region and endpoint from the standard
    /// `AWS_*` environment variables, e.g. `AWS_ENDPOINT_URL` and `AWS_ALLOW_HTTP=true` for a
    /// MinIO on plain HTTP) or `file:///absolute/folder` (a folder every process can see, such
    /// as an NFS mount).
    pub fn open(url: &str) -> Result<Self, StoreError> {
        let bad = |m: String| StoreError::Config(format!("--store {url:?}: {m}"));
        let (scheme, rest) = url
            .split_once("://")
            .ok_or_else(|| bad("expected s3://bucket/prefix or file:///folder".into()))?;
        match scheme {
            "s3" => {
                let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
                if bucket.is_empty() {
                    return Err(bad("the bucket name is missing".into()));
                }
                let s3 = object_store::aws::AmazonS3Builder::from_env()
                    .with_bucket_name(bucket)
                    .build()
                    .map_err(|e| bad(e.to_string()))?;
                let s3 = Arc::new(s3);
                Ok(Self {
                    store: s3.clone(),
                    signer: Some(s3),
                    prefix: Key::from(prefix.trim_matches('/')),
                    url: format!("s3://{bucket}/{}", prefix.trim_matches('/')),
                    kind: "s3",
                })
            }
            "file" => {
                let dir = PathBuf::from(rest);
                if !dir.is_absolute() {
                    return Err(bad("a file:// store needs an absolute path".into()));
                }
                std::fs::create_dir_all(&dir).map_err(|e| bad(e.to_string()))?;
                let fs = object_store::local::LocalFileSystem::new_with_prefix(&dir)
                    .map_err(|e| bad(e.to_string()))?
                    .with_automatic_cleanup(true);
                Ok(Self {
                    store: Arc::new(fs),
                    signer: None,
                    prefix: Key::default(),
                    url: url.to_string(),
                    kind: "file",
                })
            }
            other => Err(bad(format!(
                "unsupported scheme {other:?}; this build stores blobs locally (no --store), \
                 in S3-compatible storage (s3://) or in a shared folder (file://)"
            ))),
        }
    }

    /// The key of a path relative to the data directory's layout (`uploads/...`, `jobs/...`).
    pub fn key(&self, rel: &str) -> Key {
        let mut k = self.prefix.clone();
        for part in rel.split('/').filter(|p| !p.is_empty()) {
            k = k.clone().join(part);
        }
        k
    }

    /// Streams `body` into the object `rel`, hashing as it goes; nothing is left behind when
    /// it fails or exceeds `limit` bytes.
    pub async fn put_stream(
        &self,
        rel: &str,
        mut body: impl Body,
        limit: u64,
    ) -> Result<(u64, String), StoreError> {
        let upload = self.store.put_multipart(&self.key(rel)).await.map_err(os)?;
        let mut w = WriteMultipart::new_with_chunk_size(upload, PIECE);
        let mut tally = Tally::default();
        let result = async {
            while let Some(chunk) = body.next().await {
                let chunk = tally.take(chunk, limit)?;
                w.wait_for_capacity(IN_FLIGHT).await.map_err(os)?;
                w.put(chunk);
            }
            Ok(())
        }
        .await;
        match result {
            Ok(()) => {
                w.finish().await.map_err(os)?;
                Ok(tally.finish())
            }
            Err(e) => {
                let _ = w.abort().await;
                Err(e)
            }
        }
    }

    /// Concatenates the objects `parts` into the object `dest`, and also into the local file
    /// `copy` (written to a temporary name and renamed), returning size and SHA-256.
    pub async fn concat(
        &self,
        parts: &[String],
        dest: &str,
        copy: &Path,
    ) -> Result<(u64, String), StoreError> {
        if let Some(dir) = copy.parent() {
            tokio::fs::create_dir_all(dir)
                .await
                .map_err(super::io(dir))?;
        }
        let tmp = copy.with_extension(format!("{}.assembling", uuid::Uuid::new_v4().simple()));
        let upload = self
            .store
            .put_multipart(&self.key(dest))
            .await
            .map_err(os)?;
        let mut w = WriteMultipart::new_with_chunk_size(upload, PIECE);
        let mut tally = Tally::default();
        let result = async {
            let mut file = tokio::fs::File::create(&tmp)
                .await
                .map_err(super::io(&tmp))?;
            for rel in parts {
                let mut stream = self.get_stream(rel).await?;
                while let Some(chunk) = stream.next().await {
                    let chunk = chunk.map_err(os)?;
                    tally.add(&chunk);
                    file.write_all(&chunk).await.map_err(super::io(&tmp))?;
                    w.wait_for_capacity(IN_FLIGHT).await.map_err(os)?;
                    w.put(chunk);
                }
            }
            file.sync_all().await.map_err(super::io(&tmp))?;
            Ok(())
        }
        .await;
        match result {
            Ok(()) => {
                w.finish().await.map_err(os)?;
                tokio::fs::rename(&tmp, copy)
                    .await
                    .map_err(super::io(copy))?;
                Ok(tally.finish())
            }
            Err(e) => {
                let _ = w.abort().await;
                let _ = tokio::fs::remove_file(&tmp).await;
                Err(e)
            }
        }
    }

    /// The object `rel`, as it comes down.
    async fn get_stream(
        &self,
        rel: &str,
    ) -> Result<futures::stream::BoxStream<'static, object_store::Result<bytes::Bytes>>, StoreError>
    {
        Ok(self
            .store
            .get(&self.key(rel))
            .await
            .map_err(os)?
            .into_stream())
    }

    /// Uploads the local file `src` as the object `rel`.
    pub async fn put_file(&self, src: &Path, rel: &str) -> Result<(), StoreError> {
        let mut file = tokio::fs::File::open(src).await.map_err(super::io(src))?;
        let upload = self.store.put_multipart(&self.key(rel)).await.map_err(os)?;
        let mut w = WriteMultipart::new_with_chunk_size(upload, PIECE);
        let result = async {
            let mut buf = vec![0u8; 1 << 20];
            loop {
                let k = file.read(&mut buf).await.map_err(super::io(src))?;
                if k == 0 {
                    break;
                }
                w.wait_for_capacity(IN_FLIGHT).await.map_err(os)?;
                w.write(&buf[..k]);
            }
            Ok(())
        }
        .await;
        match result {
            Ok(()) => w.finish().await.map(|_| ()).map_err(os),
            Err(e) => {
                let _ = w.abort().await;
                Err(e)
            }
        }
    }

    /// Downloads the object `rel` to the local file `dest` (temporary name, sync, rename).
    pub async fn get_file(&self, rel: &str, dest: &Path) -> Result<u64, StoreError> {
        if let Some(dir) = dest.parent() {
            tokio::fs::create_dir_all(dir)
                .await
                .map_err(super::io(dir))?;
        }
        let tmp = dest.with_extension(format!("{}.fetching", uuid::Uuid::new_v4().simple()));
        let result = async {
            let mut stream = self.get_stream(rel).await?;
            let mut file = tokio::fs::File::create(&tmp)
                .await
                .map_err(super::io(&tmp))?;
            let mut size = 0u64;
            while let Some(chunk) = stream.next().await {
                let chunk = chunk.map_err(os)?;
                size += chunk.len() as u64;
                file.write_all(&chunk).await.map_err(super::io(&tmp))?;
            }
            file.sync_all().await.map_err(super::io(&tmp))?;
            Ok(size)
        }
        .await;
        match result {
            Ok(size) => {
                tokio::fs::rename(&tmp, dest)
                    .await
                    .map_err(super::io(dest))?;
                Ok(size)
            }
            Err(e) => {
                let _ = tokio::fs::remove_file(&tmp).await;
                Err(e)
            }
        }
    }

    /// Objects under `rel/` as (path relative to `rel`, size in bytes).
    pub async fn list(&self, rel: &str) -> Result<Vec<(String, u64)>, StoreError> {
        let base = self.key(rel);
        let metas: Vec<_> = self
            .store
            .list(Some(&base))
            .try_collect()
            .await
            .map_err(os)?;
        Ok(metas
            .into_iter()
            .filter_map(|m| {
                let sub: Vec<String> = m
                    .location
                    .prefix_match(&base)?
                    .map(|p| p.as_ref().to_string())
                    .collect();
                Some((sub.join("/"), m.size))
            })
            .collect())
    }

    /// Deletes every object under `rel/` (nothing there is not an error).
    pub async fn delete_prefix(&self, rel: &str) -> Result<(), StoreError> {
        let base = self.key(rel);
        let keys = self.store.list(Some(&base)).map_ok(|m| m.location).boxed();
        let mut deleted = self.store.delete_stream(keys);
        while let Some(r) = deleted.next().await {
            match r {
                Ok(_) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(os(e)),
            }
        }
        Ok(())
    }

    /// Deletes one object (a missing one is not an error).
    pub async fn delete(&self, rel: &str) -> Result<(), StoreError> {
        match self.store.delete(&self.key(rel)).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(os(e)),
        }
    }

    /// Checks that the store answers (a HEAD of a key that need not exist).
    pub async fn ping(&self) -> Result<(), StoreError> {
        match self.store.head(&self.key("readyz-probe")).await {
            Ok(_) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(os(e)),
        }
    }

    /// A presigned GET URL for the object `rel`, valid for `ttl`, where the store can sign.
    pub async fn presigned_get(&self, rel: &str, ttl: Duration) -> Option<String> {
        let signer = self.signer.as_ref()?;
        match signer
            .signed_url(object_store::signer::Method::GET, &self.key(rel), ttl)
            .await
        {
            Ok(u) => Some(u.to_string()),
            Err(e) => {
                tracing::warn!(error = %e, "presigning failed; serving through the API");
                None
            }
        }
    }

    /// The bytes `start..start+len` of the object `rel` as a stream.
    pub async fn get_range_stream(
        &self,
        rel: &str,
        start: u64,
        len: u64,
    ) -> Result<impl Stream<Item = Result<bytes::Bytes, std::io::Error>> + use<>, StoreError> {
        let opts = object_store::GetOptions {
            range: Some(object_store::GetRange::Bounded(start..start + len)),
            ..Default::default()
        };
        let r = self
            .store
            .get_opts(&self.key(rel), opts)
            .await
            .map_err(|e| match e {
                object_store::Error::NotFound { .. } => StoreError::NotFound(rel.to_string()),
                e => os(e),
            })?;
        Ok(r.into_stream().map_err(std::io::Error::other))
    }
}
