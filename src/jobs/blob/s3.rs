//! [`BlobStore`] on S3-compatible object storage (SPEC §7), through the `object_store` crate.
//!
//! Objects are named `<prefix>/blobs/<first 2 hex>/<hash>`, like the embedded store's files.
//! The trait is synchronous (bakes stream into writers on the bake pool); each call blocks on
//! the async client with the runtime handle captured at construction, which is allowed on the
//! bake pool and on blocking threads (never call it from an async worker).
//! Nothing is published under a name before its hash is known and pinned: a writer buffers up
//! to 64 MiB and publishes it with one PUT; a larger blob (an 8192² result) streams 5 MiB parts
//! to a staging key while the bake writes and is copied server-side to its hash on commit, so
//! memory stays bounded. Bytes already in memory up to 64 MiB are one PUT; downloads stream part
//! by part, so no blob is ever whole in memory.

use crate::error::{Error, Result};
use crate::jobs::blob::{BlobStore, BlobWriter, PinHook};
use futures_util::StreamExt;
use object_store::aws::{AmazonS3, AmazonS3Builder};
use object_store::path::Path as ObjPath;
use object_store::{ObjectStore, PutPayload, WriteMultipart};
use std::io::{Read, Seek, Write};
use std::sync::Arc;

/// Bytes already in memory (an upload's input) up to this size are one PUT: a multipart upload
/// costs two more round trips and the server's reassembly. Larger ones go up in parts.
const PART: usize = 64 << 20;
/// A writer buffers this much in memory and publishes it with one PUT at commit; past it, parts
/// stream to a staging key while the bake writes, and commit copies them to the hash. Measured
/// at 2048² (two ~10 MB results) on 2 cores, streaming parts during the bake slowed the bake
/// more than it saved (the S3 server competes for the same cores): end to end 1.94× the
/// embedded mode with an 8 MiB buffer, 1.66× with this one (`benches/distributed.rs`).
const WRITER_BUFFER: usize = 64 << 20;
/// Parts of a blob streamed while it is written (S3's smallest part size, so uploading starts
/// as early as possible).
const STREAM_PART: usize = 5 << 20;
/// Staging objects older than this are leftovers of a crash between upload and copy.
const STAGING_MAX_AGE_SECS: u64 = 3600;

fn s3_err(e: object_store::Error) -> Error {
    Error::Unavailable(format!("object storage: {e}"))
}

fn valid_hash(hash: &str) -> bool {
    hash.len() == 64 && hash.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

/// Where and how to reach the bucket.
#[derive(Debug, Clone)]
pub struct S3Config {
    pub endpoint: String,
    pub bucket: String,
    pub region: String,
    pub prefix: String,
    pub access_key: Option<String>,
    pub secret_key: Option<String>,
}

/// [`BlobStore`] on an S3 bucket.
pub struct S3BlobStore {
    s3: Arc<AmazonS3>,
    prefix: String,
    rt: tokio::runtime::Handle,
    spool: std::path::PathBuf,
}

impl S3BlobStore {
    /// A store on the bucket of `cfg`, spooling writers in `spool`. Call inside a tokio
    /// runtime; checks that the bucket answers.
    ///
    /// # Errors
    /// A bad configuration (422-style [`Error::Param`]) or an unreachable bucket.
    pub async fn connect(cfg: &S3Config, spool: &std::path::Path) -> Result<Self> {
        let mut b = AmazonS3Builder::new()
            .with_endpoint(&cfg.endpoint)
            .with_bucket_name(&cfg.bucket)
            .with_region(&cfg.region)
            .with_allow_http(true)
            .with_virtual_hosted_style_request(false);
        if let Some(k) = &cfg.access_key {
            b = b.with_access_key_id(k);
        }
        if let Some(s) = &cfg.secret_key {
            b = b.with_secret_access_key(s);
        }
        let s3 = b.build().map_err(|e| Error::param("s3", e.to_string()))?;
        std::fs::create_dir_all(spool).map_err(|e| {
            Error::Io(std::io::Error::new(
                e.kind(),
                format!("cannot create the spool directory {}: {e}", spool.display()),
            ))
        })?;
        let store = S3BlobStore {
            s3: Arc::new(s3),
            prefix: cfg.prefix.trim_matches('/').to_owned(),
            rt: tokio::runtime::Handle::current(),
            spool: spool.to_path_buf(),
        };
        // Fail at start, not at the first upload: list one key of the bucket.
        let probe = store.root();
        let mut list = store.s3.list(Some(&probe));
        if let Some(Err(e)) = list.next().await {
            return Err(Error::Unavailable(format!(
                "cannot reach bucket `{}` at {}: {e}",
                cfg.bucket, cfg.endpoint
            )));
        }
        Ok(store)
    }

    fn root(&self) -> ObjPath {
        if self.prefix.is_empty() {
            ObjPath::from("blobs")
        } else {
            ObjPath::from(format!("{}/blobs", self.prefix))
        }
    }

    fn staging_root(&self) -> ObjPath {
        if self.prefix.is_empty() {
            ObjPath::from("staging")
        } else {
            ObjPath::from(format!("{}/staging", self.prefix))
        }
    }

    fn staging_key(&self) -> ObjPath {
        let mut noise = [0u8; 12];
        let t = crate::jobs::record::now_ms();
        let h = blake3::hash(
            format!("{t}/{}/{:?}", std::process::id(), std::thread::current().id()).as_bytes(),
        );
        noise.copy_from_slice(&h.as_bytes()[..12]);
        let name: String = noise.iter().map(|b| format!("{b:02x}")).collect();
        self.staging_root().child(format!("{t}-{name}"))
    }

    fn path(&self, hash: &str) -> Result<ObjPath> {
        if !valid_hash(hash) {
            return Err(Error::Internal(format!("malformed blob hash `{hash}`")));
        }
        Ok(self.root().child(&hash[..2]).child(hash))
    }

    fn exists(&self, path: &ObjPath) -> Result<bool> {
        match self.rt.block_on(self.s3.head(path)) {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(s3_err(e)),
        }
    }

    /// Uploads `len` bytes of `file` from its start under `path`.
    fn upload(&self, path: &ObjPath, file: &mut std::fs::File, len: u64) -> Result<()> {
        file.rewind()?;
        if len as usize <= PART {
            let mut buf = Vec::with_capacity(len as usize);
            file.read_to_end(&mut buf)?;
            self.rt.block_on(self.s3.put(path, PutPayload::from(buf))).map_err(s3_err)?;
            return Ok(());
        }
        let upload = self.rt.block_on(self.s3.put_multipart(path)).map_err(s3_err)?;
        // `WriteMultipart::write` spawns each part's upload as a tokio task: on the bake pool
        // that needs the runtime entered, not only `block_on`.
        let _rt = self.rt.enter();
        let mut w = WriteMultipart::new_with_chunk_size(upload, STREAM_PART);
        let mut buf = vec![0u8; STREAM_PART];
        loop {
            let n = file.read(&mut buf)?;
            if n == 0 {
                break;
            }
            // At most two parts in flight: memory stays bounded whatever the blob's size.
            self.rt.block_on(w.wait_for_capacity(2)).map_err(s3_err)?;
            w.write(&buf[..n]);
        }
        self.rt.block_on(w.finish()).map_err(s3_err)?;
        Ok(())
    }
}

/// A blob being written. Up to [`WRITER_BUFFER`] bytes are buffered; a larger blob streams its parts to
/// a staging key as they are produced (overlapping the bake that writes them), and on commit,
/// once its hash is known and pinned, is copied server-side to its final name and the staging
/// object removed. A small blob is one PUT at commit.
struct S3Writer {
    hasher: blake3::Hasher,
    buf: Vec<u8>,
    staging: Option<(ObjPath, WriteMultipart)>,
    store: S3BlobStore,
}

impl S3Writer {
    fn start_staging(&mut self) -> std::io::Result<()> {
        let key = self.store.staging_key();
        let upload = self
            .store
            .rt
            .block_on(self.store.s3.put_multipart(&key))
            .map_err(std::io::Error::other)?;
        let _rt = self.store.rt.enter();
        let mut w = WriteMultipart::new_with_chunk_size(upload, STREAM_PART);
        w.write(&self.buf);
        self.buf = Vec::new();
        self.staging = Some((key, w));
        Ok(())
    }
}

impl Write for S3Writer {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        self.hasher.update(data);
        match &mut self.staging {
            None => {
                self.buf.extend_from_slice(data);
                if self.buf.len() > WRITER_BUFFER {
                    self.start_staging()?;
                }
            }
            Some((_, w)) => {
                // At most two parts in flight: memory stays bounded whatever the blob's size.
                self.store.rt.block_on(w.wait_for_capacity(2)).map_err(std::io::Error::other)?;
                let _rt = self.store.rt.enter();
                w.write(data);
            }
        }
        Ok(data.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Drop for S3Writer {
    fn drop(&mut self) {
        // Dropped without commit (a failed or canceled bake): abandon the staged parts.
        if let Some((_, w)) = self.staging.take() {
            self.store.rt.spawn(async move {
                let _ = w.abort().await;
            });
        }
    }
}

impl BlobWriter for S3Writer {
    fn commit(mut self: Box<Self>, pin: PinHook<'_>) -> Result<String> {
        let hash = self.hasher.finalize().to_hex().to_string();
        let path = self.store.path(&hash)?;
        pin(&hash)?;
        let store = &self.store;
        match self.staging.take() {
            None => {
                // Pinned: nobody deletes it now, so an existing object can be kept as it is.
                if !store.exists(&path)? {
                    let bytes = std::mem::take(&mut self.buf);
                    store
                        .rt
                        .block_on(store.s3.put(&path, PutPayload::from(bytes)))
                        .map_err(s3_err)?;
                }
            }
            Some((key, w)) => {
                store.rt.block_on(w.finish()).map_err(s3_err)?;
                let published = if store.exists(&path)? {
                    Ok(())
                } else {
                    store.rt.block_on(store.s3.copy(&key, &path)).map_err(s3_err)
                };
                let _ = store.rt.block_on(store.s3.delete(&key));
                published?;
            }
        }
        Ok(hash)
    }
}

/// Streams an object's parts as a blocking reader.
struct S3Reader {
    rt: tokio::runtime::Handle,
    stream: futures_util::stream::BoxStream<'static, object_store::Result<bytes::Bytes>>,
    buf: bytes::Bytes,
}

impl Read for S3Reader {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        while self.buf.is_empty() {
            match self.rt.block_on(self.stream.next()) {
                Some(Ok(b)) => self.buf = b,
                Some(Err(e)) => return Err(std::io::Error::other(e)),
                None => return Ok(0),
            }
        }
        let n = out.len().min(self.buf.len());
        out[..n].copy_from_slice(&self.buf[..n]);
        self.buf = self.buf.slice(n..);
        Ok(n)
    }
}

impl BlobStore for S3BlobStore {
    fn writer(&self) -> Result<Box<dyn BlobWriter>> {
        Ok(Box::new(S3Writer {
            hasher: blake3::Hasher::new(),
            buf: Vec::new(),
            staging: None,
            store: S3BlobStore {
                s3: self.s3.clone(),
                prefix: self.prefix.clone(),
                rt: self.rt.clone(),
                spool: self.spool.clone(),
            },
        }))
    }

    fn put(&self, bytes: &[u8], pin: PinHook<'_>) -> Result<String> {
        let hash = blake3::hash(bytes).to_hex().to_string();
        let path = self.path(&hash)?;
        pin(&hash)?;
        if !self.exists(&path)? {
            if bytes.len() <= PART {
                self.rt
                    .block_on(self.s3.put(&path, PutPayload::from(bytes.to_vec())))
                    .map_err(s3_err)?;
            } else {
                let mut tmp = tempfile::tempfile_in(&self.spool)?;
                tmp.write_all(bytes)?;
                self.upload(&path, &mut tmp, bytes.len() as u64)?;
            }
        }
        Ok(hash)
    }

    fn get(&self, hash: &str) -> Result<Option<Vec<u8>>> {
        let path = self.path(hash)?;
        let got = match self.rt.block_on(self.s3.get(&path)) {
            Ok(g) => g,
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(s3_err(e)),
        };
        let bytes = self.rt.block_on(got.bytes()).map_err(s3_err)?;
        Ok(Some(bytes.to_vec()))
    }

    fn contains(&self, hash: &str) -> Result<bool> {
        self.exists(&self.path(hash)?)
    }

    fn delete(&self, hash: &str) -> Result<()> {
        match self.rt.block_on(self.s3.delete(&self.path(hash)?)) {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(s3_err(e)),
        }
    }

    fn list(&self) -> Result<Vec<(String, u64)>> {
        let now = crate::jobs::record::now_ms() as i64 / 1000;
        let root = self.root();
        let metas: Vec<object_store::ObjectMeta> = self
            .rt
            .block_on(self.s3.list(Some(&root)).collect::<Vec<_>>())
            .into_iter()
            .collect::<object_store::Result<_>>()
            .map_err(s3_err)?;
        // Staging objects are never referenced: one left by a crash between its upload and its
        // copy is removed here, on the sweep's schedule, once it is surely not being copied.
        let staging = self.staging_root();
        for m in
            self.rt.block_on(self.s3.list(Some(&staging)).collect::<Vec<_>>()).into_iter().flatten()
        {
            if (now - m.last_modified.timestamp()).max(0) as u64 > STAGING_MAX_AGE_SECS {
                let _ = self.rt.block_on(self.s3.delete(&m.location));
            }
        }
        Ok(metas
            .into_iter()
            .filter_map(|m| {
                let name = m.location.filename()?.to_owned();
                valid_hash(&name).then(|| (name, (now - m.last_modified.timestamp()).max(0) as u64))
            })
            .collect())
    }

    fn open(&self, hash: &str) -> Result<Option<(u64, Box<dyn Read + Send>)>> {
        let path = self.path(hash)?;
        let got = match self.rt.block_on(self.s3.get(&path)) {
            Ok(g) => g,
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(s3_err(e)),
        };
        let len = got.meta.size;
        let reader =
            S3Reader { rt: self.rt.clone(), stream: got.into_stream(), buf: bytes::Bytes::new() };
        Ok(Some((len, Box::new(reader))))
    }

    fn open_range(&self, hash: &str, start: u64, end: u64) -> Result<Option<Box<dyn Read + Send>>> {
        if start >= end {
            return Ok(Some(Box::new(std::io::empty())));
        }
        let path = self.path(hash)?;
        let opts = object_store::GetOptions {
            range: Some(object_store::GetRange::Bounded(start..end)),
            ..Default::default()
        };
        let got = match self.rt.block_on(self.s3.get_opts(&path, opts)) {
            Ok(g) => g,
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(s3_err(e)),
        };
        let reader =
            S3Reader { rt: self.rt.clone(), stream: got.into_stream(), buf: bytes::Bytes::new() };
        Ok(Some(Box::new(reader)))
    }
}
