//! Content-addressed blobs: immutable bytes (inputs and encoded results) named by the BLAKE3 of
//! their content. [`FsBlobStore`] keeps them in a directory on one machine, [`S3BlobStore`] in
//! S3-compatible object storage across many. A result streamed out of a bake goes through a
//! [`BlobWriter`] (hashed as it is written, named on commit), so it is never whole in memory.
//!
//! The traits are synchronous: both implementations block (on disk, or on the async client),
//! so callers run them on a blocking thread or on the bake pool, never on an async worker.

pub mod fs;
pub mod s3;

pub use fs::FsBlobStore;
pub use s3::{S3BlobStore, S3Config};

use crate::error::{Error, Result};

/// A blob written piece by piece (a result streamed out of a bake), so its bytes never need to
/// be in memory at once; it is named by its hash when committed.
pub trait BlobWriter: std::io::Write + Send {
    /// Makes the bytes written so far durable under their hash and returns the hash. Dropping a
    /// writer without committing discards what it wrote.
    ///
    /// # Errors
    /// The backend's failure.
    fn commit(self: Box<Self>, pin: PinHook<'_>) -> Result<String>;
}

/// Immutable content-addressed bytes.
pub trait BlobStore: Send + Sync + 'static {
    /// A writer for a new blob (see [`BlobWriter`]).
    ///
    /// # Errors
    /// The backend's failure.
    fn writer(&self) -> Result<Box<dyn BlobWriter>>;
    /// Stores `bytes` and returns their hash (hex BLAKE3). Idempotent; durable on return.
    /// `pin` is called with the hash before the bytes are published (see [`PinHook`]).
    ///
    /// # Errors
    /// The backend's failure.
    fn put(&self, bytes: &[u8], pin: PinHook<'_>) -> Result<String>;
    /// The bytes stored under `hash`.
    ///
    /// # Errors
    /// The backend's failure.
    fn get(&self, hash: &str) -> Result<Option<Vec<u8>>>;
    /// Whether `hash` is stored.
    ///
    /// # Errors
    /// The backend's failure.
    fn contains(&self, hash: &str) -> Result<bool>;
    /// Removes `hash` (no error when absent).
    ///
    /// # Errors
    /// The backend's failure.
    fn delete(&self, hash: &str) -> Result<()>;
    /// Whether a new blob can be written now (`/readyz`): a store on a local disk writes and
    /// removes a small probe file, so a full disk is seen before a submission fails on it and
    /// again once space is freed. Remote stores answer for themselves on each request.
    ///
    /// # Errors
    /// [`Error::StorageFull`] when there is no space; the backend's other failures.
    fn check_writable(&self) -> Result<()> {
        Ok(())
    }
    /// Every stored hash with its age in seconds (for sweeping orphans).
    ///
    /// # Errors
    /// The backend's failure.
    fn list(&self) -> Result<Vec<(String, u64)>>;
    /// A reader over the bytes stored under `hash` and their length, for streaming a download
    /// without holding it in memory.
    ///
    /// # Errors
    /// The backend's failure.
    fn open(&self, hash: &str) -> Result<Option<(u64, Box<dyn std::io::Read + Send>)>>;
    /// A reader over bytes `start..end` of the blob under `hash` (a `Range` download), with
    /// `start <= end <= len`. The default reads and discards the first `start` bytes; stores
    /// that can seek or ask for a range override it.
    ///
    /// # Errors
    /// The backend's failure.
    fn open_range(
        &self,
        hash: &str,
        start: u64,
        end: u64,
    ) -> Result<Option<Box<dyn std::io::Read + Send>>> {
        use std::io::Read;
        let Some((_, mut r)) = self.open(hash)? else { return Ok(None) };
        std::io::copy(&mut (&mut r).take(start), &mut std::io::sink())?;
        Ok(Some(Box::new(r.take(end.saturating_sub(start)))))
    }
}

/// Reads `len` bytes from byte `start` of the blob `hash` (a ranged read: S3 a ranged GET, the
/// file store a seek), what `encode::assemble::TileRows` pulls tile results with.
///
/// # Errors
/// [`Error::Internal`] when the blob is missing; the backend's failure.
pub fn read_range(store: &dyn BlobStore, hash: &str, start: u64, len: usize) -> Result<Vec<u8>> {
    use std::io::Read;
    let mut r = store
        .open_range(hash, start, start + len as u64)?
        .ok_or_else(|| Error::Internal(format!("blob {hash} is missing")))?;
    let mut out = vec![0u8; len];
    r.read_exact(&mut out)?;
    Ok(out)
}

/// A blob read as `Read + Seek` through ranged reads of [`BlobStore::open_range`], a window of
/// [`BlobSeekReader::WINDOW`] bytes at a time: a TIFF decoder seeks to its IFD and its strips
/// without the blob ever being in memory or on local disk whole.
pub struct BlobSeekReader {
    store: std::sync::Arc<dyn BlobStore>,
    hash: String,
    len: u64,
    pos: u64,
    buf: Vec<u8>,
    buf_at: u64,
}

impl BlobSeekReader {
    /// Bytes fetched per ranged read.
    pub const WINDOW: usize = 4 << 20;

    /// A reader over the blob `hash` of `store`, `None` when it is not stored.
    ///
    /// # Errors
    /// The backend's failure.
    pub fn open(store: std::sync::Arc<dyn BlobStore>, hash: &str) -> Result<Option<Self>> {
        let Some((len, _)) = store.open(hash)? else { return Ok(None) };
        Ok(Some(BlobSeekReader {
            store,
            hash: hash.to_string(),
            len,
            pos: 0,
            buf: Vec::new(),
            buf_at: 0,
        }))
    }

    /// The blob's length in bytes.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether the blob is empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl std::io::Read for BlobSeekReader {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        if self.pos >= self.len || out.is_empty() {
            return Ok(0);
        }
        let end = self.buf_at + self.buf.len() as u64;
        if self.pos < self.buf_at || self.pos >= end {
            let n = (Self::WINDOW as u64).min(self.len - self.pos) as usize;
            self.buf =
                read_range(&*self.store, &self.hash, self.pos, n).map_err(std::io::Error::other)?;
            self.buf_at = self.pos;
        }
        let off = (self.pos - self.buf_at) as usize;
        let n = out.len().min(self.buf.len() - off);
        out[..n].copy_from_slice(&self.buf[off..off + n]);
        self.pos += n as u64;
        Ok(n)
    }
}

impl std::io::Seek for BlobSeekReader {
    fn seek(&mut self, to: std::io::SeekFrom) -> std::io::Result<u64> {
        let pos = match to {
            std::io::SeekFrom::Start(p) => Some(p),
            std::io::SeekFrom::End(d) => self.len.checked_add_signed(d),
            std::io::SeekFrom::Current(d) => self.pos.checked_add_signed(d),
        };
        let pos = pos.ok_or_else(|| {
            std::io::Error::new(std::io::ErrorKind::InvalidInput, "seek before the blob's start")
        })?;
        self.pos = pos;
        Ok(pos)
    }
}

/// Called with a blob's hash after its bytes are hashed and before they become visible under
/// that hash: the jobs core pins the hash there, so a concurrent sweep cannot remove the blob
/// between its write and the commit of the record that references it.
pub type PinHook<'a> = &'a (dyn Fn(&str) -> Result<()> + Sync);
