//! The bake record, its embedded record table, and content-addressed blobs.
//!
//! - [`BakeRecord`]: everything persisted about one bake, whichever backend keeps it.
//! - [`BakeStore`]: the embedded backend's record table and deduplication index.
//!   [`RedbStore`] keeps them in one redb file in the data directory; a commit is durable before
//!   the caller answers, which is what lets a restart re-queue every bake that was accepted.
//!   The job lifecycle (claims, leases, cancel, changes) is [`crate::jobs::repo::JobRepo`]'s;
//!   the embedded repository is built on this table.
//! - [`BlobStore`]: immutable, content-addressed bytes (inputs and encoded results), named by the
//!   BLAKE3 of their content. [`FsBlobStore`] writes each to a temporary file, fsyncs it and
//!   renames it into place, so a crash leaves either the whole file or nothing. A result
//!   streamed out of a bake goes through a [`BlobWriter`] (hashed as it is written, named on
//!   commit), so it is never whole in memory.
//!
//! The traits are synchronous: both implementations block on disk, so callers run them on a
//! blocking thread or on the bake pool, never on an async worker.

use crate::error::{Error, Result};
use crate::heightmap::InputInfo;
use redb::{ReadableDatabase, ReadableTable, TableDefinition};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

/// Lifecycle of a bake.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    Queued,
    Running,
    Succeeded,
    Failed,
    Canceled,
}

impl Status {
    /// Every status, in lifecycle order.
    pub const ALL: [Status; 5] =
        [Status::Queued, Status::Running, Status::Succeeded, Status::Failed, Status::Canceled];

    /// The API spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Queued => "queued",
            Status::Running => "running",
            Status::Succeeded => "succeeded",
            Status::Failed => "failed",
            Status::Canceled => "canceled",
        }
    }

    /// Parses the API spelling.
    ///
    /// # Errors
    /// [`Error::Param`] naming `status`.
    pub fn parse(s: &str) -> Result<Status> {
        Status::ALL.into_iter().find(|st| st.as_str() == s).ok_or_else(|| {
            Error::param(
                "status",
                format!("`{s}` is not one of queued, running, succeeded, failed, canceled"),
            )
        })
    }

    /// Whether the bake will not change any more.
    pub fn is_terminal(self) -> bool {
        matches!(self, Status::Succeeded | Status::Failed | Status::Canceled)
    }
}

/// Why a bake failed, as the API reports it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BakeFailure {
    pub code: String,
    pub message: String,
}

/// The radius a bake used and why (SPEC §3.6).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RadiusInfo {
    pub texels: u32,
    pub reason: String,
}

/// Wall-clock phases of a finished bake, in milliseconds.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Timings {
    pub queued: f64,
    pub decode: f64,
    pub bake: f64,
    pub encode: f64,
    pub store: f64,
    pub total: f64,
}

/// Everything persisted about one bake.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BakeRecord {
    /// Time-ordered id: 12 hex digits of Unix milliseconds, then 8 of noise.
    pub id: String,
    pub status: Status,
    /// BLAKE3 of the input bytes and the resolved parameter pairs.
    pub dedup_key: String,
    /// Resolved parameters as `BakeParams::to_pairs` writes them.
    pub params: Vec<(String, String)>,
    /// Blob hash of the uploaded input.
    pub input_blob: String,
    pub input_format: String,
    pub input_bytes: u64,
    pub width: u32,
    pub height: u32,
    /// The full input description, once decoded by the bake.
    pub input: Option<InputInfo>,
    pub radius: Option<RadiusInfo>,
    /// Unix milliseconds.
    pub created_ms: u64,
    pub started_ms: Option<u64>,
    pub finished_ms: Option<u64>,
    /// When an identical submission last asked for this finished bake (a deduplication hit):
    /// the retention counts from the later of this and `finished_ms`.
    #[serde(default)]
    pub requested_ms: Option<u64>,
    pub timings_ms: Option<Timings>,
    pub error: Option<BakeFailure>,
    /// Result name (`horizon_0.png8`, …) → blob hash.
    pub results: BTreeMap<String, String>,
    /// How many times a worker started this bake (restarts re-run it); the fencing number of
    /// the current claim.
    pub attempts: u32,
    /// Progress of a running bake as its worker last reported it (heartbeats).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub progress: Option<LiveProgress>,
    /// The worker running (or that last ran) this bake.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub worker: Option<String>,
    /// The result formats the submission asked to have encoded with the bake (`formats`, plus
    /// `exr_precision` when not `float`), e.g. `png8` or `png16,exr` or `png8,exr,half`; None
    /// (records from before the field) is `png8`. Not part of the dedup key.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub formats: Option<String>,
    /// Where a running bake stood when it was canceled: its resource keeps showing that
    /// fraction rather than 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stopped_at: Option<LiveProgress>,
    /// The input's georeferencing (a GeoTIFF DEM), as bake.json reports it: read at submission.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub georeferencing: Option<serde_json::Value>,
    /// A tiled bake's tiles (SPEC §7.1): done out of total, once finished (a running one's
    /// live count is in its progress).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tiles: Option<crate::jobs::tiles::TileCount>,
}

/// Progress as a worker reports it: the stage and the fraction of that stage done.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LiveProgress {
    pub stage: crate::progress::Stage,
    pub fraction: f64,
    /// A tiled bake's tiles done out of total (SPEC §7.1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tiles: Option<crate::jobs::tiles::TileCount>,
}

impl LiveProgress {
    /// A snapshot of `p`.
    pub fn of(p: &crate::progress::Progress) -> Self {
        LiveProgress { stage: p.stage(), fraction: p.fraction(), tiles: None }
    }
}

impl BakeRecord {
    /// When a finished bake's retention of `retention_ms` runs out (None while in flight).
    pub fn expires_ms(&self, retention_ms: u64) -> Option<u64> {
        if !self.status.is_terminal() {
            return None;
        }
        let last = self.finished_ms?.max(self.requested_ms.unwrap_or(0));
        Some(last.saturating_add(retention_ms))
    }

    /// Every blob this record references.
    pub fn blobs(&self) -> impl Iterator<Item = &str> {
        std::iter::once(self.input_blob.as_str()).chain(self.results.values().map(String::as_str))
    }
}

/// Unix milliseconds now.
pub fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

/// One page of a listing.
#[derive(Debug, Clone)]
pub struct Page {
    pub items: Vec<BakeRecord>,
    /// The cursor for the next page, when there is one.
    pub next: Option<String>,
}

/// What a listing asks for: any of `statuses` (all when empty), after `cursor` in the chosen
/// order, at most `limit`.
#[derive(Debug, Clone, Default)]
pub struct ListQuery {
    pub statuses: Vec<Status>,
    pub cursor: Option<String>,
    pub limit: usize,
    /// Newest first.
    pub newest_first: bool,
}

/// One page of a listing, with how many records match the filter in all.
#[derive(Debug, Clone)]
pub struct Listing {
    pub items: Vec<BakeRecord>,
    pub next: Option<String>,
    pub total: u64,
}

/// Bake records and the deduplication index.
pub trait BakeStore: Send + Sync + 'static {
    /// A page of records for `q` and the total matching count. The provided version reads the
    /// ids in order through [`BakeStore::list`] (one pass, keeping only matching records up to
    /// the page); a database backend would answer it with an indexed query instead.
    ///
    /// # Errors
    /// The backend's failure.
    fn query(&self, q: &ListQuery) -> Result<Listing> {
        let wanted = |s: Status| q.statuses.is_empty() || q.statuses.contains(&s);
        // At most `limit + 1` records (the extra one says whether there is a next page).
        let mut page_items: std::collections::VecDeque<BakeRecord> = Default::default();
        let mut total = 0u64;
        let mut after: Option<String> = None;
        loop {
            let page = self.list(None, after.as_deref(), 1000)?;
            for r in page.items {
                if !wanted(r.status) {
                    continue;
                }
                total += 1;
                let in_range = match (&q.cursor, q.newest_first) {
                    (None, _) => true,
                    (Some(c), false) => r.id.as_str() > c.as_str(),
                    (Some(c), true) => r.id.as_str() < c.as_str(),
                };
                if !in_range {
                    continue;
                }
                if q.newest_first {
                    // Ids ascend: keep the last `limit + 1` below the cursor.
                    page_items.push_back(r);
                    if page_items.len() > q.limit + 1 {
                        page_items.pop_front();
                    }
                } else if page_items.len() <= q.limit {
                    page_items.push_back(r);
                }
            }
            match page.next {
                Some(n) => after = Some(n),
                None => break,
            }
        }
        let mut items: Vec<BakeRecord> = page_items.into();
        if q.newest_first {
            items.reverse();
        }
        let more = items.len() > q.limit;
        items.truncate(q.limit);
        let next = if more { items.last().map(|r| r.id.clone()) } else { None };
        Ok(Listing { items, next, total })
    }

    /// Inserts or replaces a record, and points its dedup key at it. Durable on return.
    ///
    /// # Errors
    /// The backend's failure, as [`Error::Internal`] or [`Error::Io`].
    fn put(&self, rec: &BakeRecord) -> Result<()>;
    /// The record with `id`.
    ///
    /// # Errors
    /// The backend's failure.
    fn get(&self, id: &str) -> Result<Option<BakeRecord>>;
    /// The record the dedup index points at for `key`.
    ///
    /// # Errors
    /// The backend's failure.
    fn find_by_key(&self, key: &str) -> Result<Option<BakeRecord>>;
    /// Records with ids strictly after `after`, in id (= creation) order, optionally only those
    /// with `status`, at most `limit` of them.
    ///
    /// # Errors
    /// The backend's failure.
    fn list(&self, status: Option<Status>, after: Option<&str>, limit: usize) -> Result<Page>;
    /// Removes a record (and its dedup entry when that points at it). Returns whether it existed.
    ///
    /// # Errors
    /// The backend's failure.
    fn delete(&self, id: &str) -> Result<bool>;
}

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

const BAKES: TableDefinition<&str, &[u8]> = TableDefinition::new("bakes");
const DEDUP: TableDefinition<&str, &str> = TableDefinition::new("dedup");

fn db_err(e: impl std::fmt::Display) -> Error {
    Error::Internal(format!("bake store: {e}"))
}

/// [`BakeStore`] on an embedded redb file.
pub struct RedbStore {
    db: redb::Database,
}

impl RedbStore {
    /// Opens (or creates) the store at `path`.
    ///
    /// # Errors
    /// When the file cannot be created or opened (e.g. another server holds it).
    pub fn open(path: &Path) -> Result<Self> {
        // The operator must learn which file is at fault (locked by a running server, corrupt),
        // so every failure here names it.
        let named = |e: &dyn std::fmt::Display| {
            Error::Io(std::io::Error::other(format!(
                "cannot open the bake store {}: {e}",
                path.display()
            )))
        };
        let db = redb::Database::create(path).map_err(|e| named(&e))?;
        // Create the tables up front so readers never see "table does not exist".
        let tx = db.begin_write().map_err(|e| named(&e))?;
        tx.open_table(BAKES).map_err(|e| named(&e))?;
        tx.open_table(DEDUP).map_err(|e| named(&e))?;
        tx.commit().map_err(|e| named(&e))?;
        Ok(RedbStore { db })
    }
}

fn decode_record(bytes: &[u8]) -> Result<BakeRecord> {
    serde_json::from_slice(bytes).map_err(|e| db_err(format!("corrupt record: {e}")))
}

impl BakeStore for RedbStore {
    fn put(&self, rec: &BakeRecord) -> Result<()> {
        let bytes = serde_json::to_vec(rec).map_err(db_err)?;
        let tx = self.db.begin_write().map_err(db_err)?;
        {
            let mut bakes = tx.open_table(BAKES).map_err(db_err)?;
            bakes.insert(rec.id.as_str(), bytes.as_slice()).map_err(db_err)?;
            let mut dedup = tx.open_table(DEDUP).map_err(db_err)?;
            dedup.insert(rec.dedup_key.as_str(), rec.id.as_str()).map_err(db_err)?;
        }
        tx.commit().map_err(db_err)
    }

    fn get(&self, id: &str) -> Result<Option<BakeRecord>> {
        let tx = self.db.begin_read().map_err(db_err)?;
        let bakes = tx.open_table(BAKES).map_err(db_err)?;
        let found = bakes.get(id).map_err(db_err)?;
        found.map(|g| decode_record(g.value())).transpose()
    }

    fn find_by_key(&self, key: &str) -> Result<Option<BakeRecord>> {
        let tx = self.db.begin_read().map_err(db_err)?;
        let dedup = tx.open_table(DEDUP).map_err(db_err)?;
        let Some(id) = dedup.get(key).map_err(db_err)?.map(|g| g.value().to_owned()) else {
            return Ok(None);
        };
        let bakes = tx.open_table(BAKES).map_err(db_err)?;
        let found = bakes.get(id.as_str()).map_err(db_err)?;
        found.map(|g| decode_record(g.value())).transpose()
    }

    fn list(&self, status: Option<Status>, after: Option<&str>, limit: usize) -> Result<Page> {
        let tx = self.db.begin_read().map_err(db_err)?;
        let bakes = tx.open_table(BAKES).map_err(db_err)?;
        let iter = match after {
            Some(a) => {
                bakes.range::<&str>((std::ops::Bound::Excluded(a), std::ops::Bound::Unbounded))
            }
            None => bakes.range::<&str>(..),
        }
        .map_err(db_err)?;
        let mut items = Vec::new();
        let mut next = None;
        for entry in iter {
            let (_, v) = entry.map_err(db_err)?;
            let rec = decode_record(v.value())?;
            if status.is_some_and(|s| s != rec.status) {
                continue;
            }
            if items.len() == limit {
                next = items.last().map(|r: &BakeRecord| r.id.clone());
                break;
            }
            items.push(rec);
        }
        Ok(Page { items, next })
    }

    fn delete(&self, id: &str) -> Result<bool> {
        let tx = self.db.begin_write().map_err(db_err)?;
        let existed;
        {
            let mut bakes = tx.open_table(BAKES).map_err(db_err)?;
            let old = bakes.remove(id).map_err(db_err)?.map(|g| decode_record(g.value()));
            existed = old.is_some();
            if let Some(rec) = old.transpose()? {
                let mut dedup = tx.open_table(DEDUP).map_err(db_err)?;
                let points_here = dedup
                    .get(rec.dedup_key.as_str())
                    .map_err(db_err)?
                    .is_some_and(|g| g.value() == id);
                if points_here {
                    dedup.remove(rec.dedup_key.as_str()).map_err(db_err)?;
                }
            }
        }
        tx.commit().map_err(db_err)?;
        Ok(existed)
    }
}

/// [`BlobStore`] on a directory: `<root>/<first 2 hex>/<hash>`.
pub struct FsBlobStore {
    root: PathBuf,
}

fn valid_hash(hash: &str) -> bool {
    hash.len() == 64 && hash.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

impl FsBlobStore {
    /// Opens (or creates) a blob directory; removes temporary files a crash left behind.
    ///
    /// # Errors
    /// When the directory cannot be created or read.
    pub fn open(root: &Path) -> Result<Self> {
        std::fs::create_dir_all(root.join("tmp"))?;
        for entry in std::fs::read_dir(root.join("tmp"))? {
            let _ = std::fs::remove_file(entry?.path());
        }
        Ok(FsBlobStore { root: root.to_path_buf() })
    }

    fn path(&self, hash: &str) -> Result<PathBuf> {
        if !valid_hash(hash) {
            return Err(Error::Internal(format!("malformed blob hash `{hash}`")));
        }
        Ok(self.root.join(&hash[..2]).join(hash))
    }
}

/// [`BlobWriter`] of [`FsBlobStore`]: a temporary file in `tmp/`, hashed as it is written,
/// fsynced and renamed to its hash on commit (the same durability as [`BlobStore::put`]).
struct FsBlobWriter {
    tmp: tempfile::NamedTempFile,
    hasher: blake3::Hasher,
    store: FsBlobStore,
}

impl std::io::Write for FsBlobWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.tmp.write(buf)?;
        self.hasher.update(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.tmp.flush()
    }
}

impl BlobWriter for FsBlobWriter {
    fn commit(self: Box<Self>, pin: PinHook<'_>) -> Result<String> {
        let FsBlobWriter { mut tmp, hasher, store } = *self;
        tmp.flush()?;
        let hash = hasher.finalize().to_hex().to_string();
        let dest = store.path(&hash)?;
        pin(&hash)?;
        if dest.exists() {
            // Already stored (content-addressed); the temporary file is removed on drop.
            return Ok(hash);
        }
        let dir = dest.parent().map(Path::to_path_buf).unwrap_or_else(|| store.root.clone());
        std::fs::create_dir_all(&dir)?;
        tmp.as_file().sync_all()?;
        tmp.persist(&dest).map_err(|e| Error::Io(e.error))?;
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(hash)
    }
}

impl BlobStore for FsBlobStore {
    fn writer(&self) -> Result<Box<dyn BlobWriter>> {
        Ok(Box::new(FsBlobWriter {
            tmp: tempfile::NamedTempFile::new_in(self.root.join("tmp"))?,
            hasher: blake3::Hasher::new(),
            store: FsBlobStore { root: self.root.clone() },
        }))
    }

    fn put(&self, bytes: &[u8], pin: PinHook<'_>) -> Result<String> {
        let hash = blake3::hash(bytes).to_hex().to_string();
        let dest = self.path(&hash)?;
        pin(&hash)?;
        if dest.exists() {
            return Ok(hash);
        }
        let dir = dest.parent().map(Path::to_path_buf).unwrap_or_else(|| self.root.clone());
        std::fs::create_dir_all(&dir)?;
        let mut tmp = tempfile::NamedTempFile::new_in(self.root.join("tmp"))?;
        tmp.write_all(bytes)?;
        tmp.as_file().sync_all()?;
        tmp.persist(&dest).map_err(|e| Error::Io(e.error))?;
        // Make the rename itself durable.
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(hash)
    }

    fn get(&self, hash: &str) -> Result<Option<Vec<u8>>> {
        match std::fs::read(self.path(hash)?) {
            Ok(b) => Ok(Some(b)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn contains(&self, hash: &str) -> Result<bool> {
        Ok(self.path(hash)?.exists())
    }

    fn open(&self, hash: &str) -> Result<Option<(u64, Box<dyn std::io::Read + Send>)>> {
        match std::fs::File::open(self.path(hash)?) {
            Ok(f) => {
                let len = f.metadata()?.len();
                Ok(Some((len, Box::new(f))))
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn open_range(
        &self,
        hash: &str,
        start: u64,
        end: u64,
    ) -> Result<Option<Box<dyn std::io::Read + Send>>> {
        use std::io::{Read, Seek};
        match std::fs::File::open(self.path(hash)?) {
            Ok(mut f) => {
                f.seek(std::io::SeekFrom::Start(start))?;
                Ok(Some(Box::new(f.take(end.saturating_sub(start)))))
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn delete(&self, hash: &str) -> Result<()> {
        match std::fs::remove_file(self.path(hash)?) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e.into()),
        }
    }

    fn list(&self) -> Result<Vec<(String, u64)>> {
        let mut out = Vec::new();
        let now = SystemTime::now();
        for dir in std::fs::read_dir(&self.root)? {
            let dir = dir?;
            let name = dir.file_name();
            if name.len() != 2 || !dir.file_type()?.is_dir() {
                continue;
            }
            for f in std::fs::read_dir(dir.path())? {
                let f = f?;
                let hash = f.file_name().to_string_lossy().into_owned();
                if !valid_hash(&hash) {
                    continue;
                }
                let age = f
                    .metadata()
                    .and_then(|m| m.modified())
                    .ok()
                    .and_then(|m| now.duration_since(m).ok())
                    .map(|d| d.as_secs())
                    .unwrap_or(0);
                out.push((hash, age));
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(id: &str, key: &str, status: Status) -> BakeRecord {
        BakeRecord {
            id: id.into(),
            status,
            dedup_key: key.into(),
            params: vec![("radius".into(), "16".into())],
            input_blob: "0".repeat(64),
            input_format: "png".into(),
            input_bytes: 10,
            width: 4,
            height: 4,
            input: None,
            radius: None,
            created_ms: 1,
            started_ms: None,
            finished_ms: None,
            requested_ms: None,
            timings_ms: None,
            error: None,
            results: BTreeMap::new(),
            attempts: 0,
            progress: None,
            worker: None,
            formats: None,
            stopped_at: None,
            georeferencing: None,
            tiles: None,
        }
    }

    #[test]
    fn redb_round_trips_lists_and_survives_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bakes.redb");
        {
            let s = RedbStore::open(&path).unwrap();
            for (i, st) in [Status::Queued, Status::Succeeded, Status::Queued].iter().enumerate() {
                s.put(&rec(&format!("id{i}"), &format!("k{i}"), *st)).unwrap();
            }
            let page = s.list(None, None, 2).unwrap();
            assert_eq!(
                page.items.iter().map(|r| r.id.as_str()).collect::<Vec<_>>(),
                ["id0", "id1"]
            );
            assert_eq!(page.next.as_deref(), Some("id1"));
            let page = s.list(None, page.next.as_deref(), 2).unwrap();
            assert_eq!(page.items.len(), 1);
            assert_eq!(page.next, None);
            let queued = s.list(Some(Status::Queued), None, 10).unwrap();
            assert_eq!(
                queued.items.iter().map(|r| r.id.as_str()).collect::<Vec<_>>(),
                ["id0", "id2"]
            );
        }
        let s = RedbStore::open(&path).unwrap();
        assert_eq!(s.get("id1").unwrap().unwrap().status, Status::Succeeded);
        assert_eq!(s.find_by_key("k2").unwrap().unwrap().id, "id2");
        assert!(s.delete("id2").unwrap());
        assert!(!s.delete("id2").unwrap());
        assert!(s.find_by_key("k2").unwrap().is_none());
        assert!(s.get("nope").unwrap().is_none());
    }

    #[test]
    fn blobs_are_content_addressed_and_atomic() {
        let dir = tempfile::tempdir().unwrap();
        let b = FsBlobStore::open(dir.path()).unwrap();
        let h = b.put(b"hello", &|_| Ok(())).unwrap();
        assert_eq!(h, blake3::hash(b"hello").to_hex().to_string());
        assert_eq!(b.put(b"hello", &|_| Ok(())).unwrap(), h);
        assert_eq!(b.get(&h).unwrap().unwrap(), b"hello");
        assert_eq!(b.list().unwrap().len(), 1);
        assert!(std::fs::read_dir(dir.path().join("tmp")).unwrap().next().is_none());
        b.delete(&h).unwrap();
        assert!(!b.contains(&h).unwrap());
        assert!(b.get(&h).unwrap().is_none());
        assert!(b.get("../../etc/passwd").is_err());
    }
}
