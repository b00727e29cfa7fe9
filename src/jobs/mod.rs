//! The jobs core: the whole lifecycle of a bake (submit, get, list, cancel, results, watch,
//! recover, sweep) and the worker loop that claims bakes and runs them, on any backend.
//!
//! # Shape
//! [`Jobs`] owns its background tasks (worker loop, reaper, retention sweeper) and its private
//! state, as mini-redis's `Db` does: callers (the HTTP handlers, tests) only call methods. It
//! reaches storage only through two traits:
//! - [`repo::JobRepo`]: records, queue, claims with leases and fencing numbers, heartbeats,
//!   cancel requests, blob pins and the change feed. [`repo::EmbeddedRepo`] (redb + memory)
//!   on one machine; [`repo::PgRepo`] across many.
//! - [`blob::BlobStore`]: immutable content-addressed bytes. [`blob::FsBlobStore`] on one
//!   machine; [`blob::S3BlobStore`] across many.
//!
//! The record model is [`record`]; the pure tile plan [`tiles`]; the coordination of a tiled
//! bake (split, tiles claimed like bakes, assemble) `coordinate`. What a bake computes is not
//! this module's business: the service hands it a [`Runner`] (decode, bake, encode, store
//! through [`Blobs`]), run on the bake pool, never on the async runtime, inside `catch_unwind`.
//!
//! # Guarantees, and what each rests on (on PostgreSQL and S3 in detail: docs/service.md)
//! - An accepted bake is never lost: its input blob and `queued` record are durable before the
//!   submission is answered; a claim that stops heartbeating loses its lease and the reaper
//!   queues the bake again (embedded: the restart does).
//! - A bake's results are written once: completion names the claim's attempt and is refused
//!   when a later claim took the bake over.
//! - Identical submissions make one bake: insert-if-absent on the deduplication key (a unique
//!   index in PostgreSQL).
//! - A cancel reaches the bake wherever it runs: the flag is in the repository and every
//!   heartbeat returns it.
//! - A blob is never deleted while a writer is about to reference it: writers pin a blob's hash
//!   before publishing it, and deletion checks pins and references atomically.

pub mod blob;
mod coordinate;
pub mod record;
pub mod repo;
pub mod tiles;

pub use coordinate::{TileHook, Tiler, Tiling};

use crate::error::{Error, Result};
use crate::progress::Progress;
use blob::{BlobStore, BlobWriter};
use record::{
    now_ms, BakeFailure, BakeRecord, ListQuery, Listing, LiveProgress, Status, TileClaim,
    TileCount, TileOutcome, TileRecord,
};
use repo::{Beat, CancelResult, Claim, Counts, JobRepo, Outcome, Submitted};
use std::collections::HashMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, Semaphore};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

/// Runs one claimed bake on the bake pool: reads the input and writes results through [`Blobs`],
/// reports through the [`Progress`] (and stops when it is canceled), and returns the record with
/// its results, input description, radius and timings filled in.
pub type Runner = Arc<dyn Fn(&BakeRecord, &Progress, &Blobs) -> Result<BakeRecord> + Send + Sync>;

/// Called when a bake this node ran reaches a final status: (status, seconds, texels).
pub type FinishHook = Arc<dyn Fn(Status, f64, u64) + Send + Sync>;

/// How a bake's run on this node ended, before it becomes an [`Outcome`].
enum Ended {
    Done(Result<Box<BakeRecord>>),
    Panicked,
    /// A tile failed its last attempt.
    TileFailed(BakeFailure),
}

/// Work a worker claimed.
enum Work {
    Bake(Box<Claim>),
    Tile(Box<TileClaim>),
}

/// How the core behaves (from the service's flags).
#[derive(Clone)]
pub struct JobsConfig {
    /// This node's name in claims (`--worker-id`).
    pub worker_id: String,
    pub lease: Duration,
    pub heartbeat: Duration,
    pub max_attempts: u32,
    pub queue_capacity: usize,
    /// Bakes this node runs at once (0: this node claims nothing, `--role api`).
    pub concurrency: usize,
    pub bake_threads: usize,
    pub retention: Duration,
    pub sweep_interval: Duration,
    /// Blobs no record references are removed once older than this.
    pub orphan_age: Duration,
    /// How often an idle worker looks for work when no change notification woke it.
    pub poll: Duration,
    /// Where this node's bakes put scratch files (`sweep`'s spilled far field); `None`: the
    /// system's temporary directory.
    pub scratch_dir: Option<std::path::PathBuf>,
}

/// A bake this node runs.
#[derive(Clone)]
struct LocalRun {
    progress: Progress,
    /// Set by shutdown: the cancellation means "hand it back", not "the owner canceled it".
    requeue: Arc<AtomicBool>,
    /// A tiled bake's tiles done / total, for its heartbeats and resource.
    tiles: Arc<Mutex<Option<TileCount>>>,
}

impl LocalRun {
    fn new(scratch_dir: Option<std::path::PathBuf>) -> Self {
        LocalRun {
            progress: Progress::with_scratch_dir(scratch_dir),
            requeue: Arc::new(AtomicBool::new(false)),
            tiles: Default::default(),
        }
    }

    fn live(&self) -> LiveProgress {
        let tiles = *self.tiles.lock().unwrap_or_else(|e| e.into_inner());
        LiveProgress { tiles, ..LiveProgress::of(&self.progress) }
    }
}

struct Inner {
    repo: Arc<dyn JobRepo>,
    blobs: Arc<dyn BlobStore>,
    cfg: JobsConfig,
    runner: Runner,
    on_finish: Option<FinishHook>,
    pool: rayon::ThreadPool,
    local: Mutex<HashMap<String, LocalRun>>,
    slots: Arc<Semaphore>,
    /// Tiles this node runs beyond its bake slots ([`TILE_AHEAD`]).
    tiles_ahead: Arc<Semaphore>,
    /// Stops claiming.
    stop: CancellationToken,
    /// Ends background loops and watchers.
    closing: CancellationToken,
    tracker: TaskTracker,
    /// The reaper and the retention sweeper: [`Jobs::drain`] waits for them to stop, so a
    /// sweep in flight finishes removing a bake's blobs rather than leaving them behind.
    housekeeping: TaskTracker,
    /// Local fan-out of the repository's change feed (and of local progress).
    changes: broadcast::Sender<String>,
    rt: tokio::runtime::Handle,
    tiling: std::sync::OnceLock<Tiling>,
}

/// The jobs core. Cheap to clone.
#[derive(Clone)]
pub struct Jobs(Arc<Inner>);

/// Blob access for one owner: every hash written through it is pinned for that owner before it
/// is published, so it survives until the owner's record references it.
#[derive(Clone)]
pub struct Blobs {
    store: Arc<dyn BlobStore>,
    repo: Arc<dyn JobRepo>,
    owner: String,
    rt: tokio::runtime::Handle,
}

impl Blobs {
    fn pin(&self, hash: &str) -> Result<()> {
        // Called on the bake pool or a blocking thread, never on an async worker.
        self.rt.block_on(self.repo.pin_blob(hash, &self.owner))
    }

    /// Stores `bytes`; returns their hash.
    ///
    /// # Errors
    /// The store's or the repository's failure.
    pub fn put(&self, bytes: &[u8]) -> Result<String> {
        self.store.put(bytes, &|h| self.pin(h))
    }

    /// A writer for a blob streamed piece by piece.
    ///
    /// # Errors
    /// The store's failure.
    pub fn writer(&self) -> Result<PinnedWriter> {
        Ok(PinnedWriter { inner: self.store.writer()?, blobs: self.clone() })
    }

    /// The bytes of `hash`.
    ///
    /// # Errors
    /// The store's failure.
    pub fn get(&self, hash: &str) -> Result<Option<Vec<u8>>> {
        self.store.get(hash)
    }

    /// Who pins what this handle writes.
    pub fn owner(&self) -> &str {
        &self.owner
    }
}

/// A [`BlobWriter`] that pins its hash (see [`Blobs`]).
pub struct PinnedWriter {
    inner: Box<dyn BlobWriter>,
    blobs: Blobs,
}

impl PinnedWriter {
    /// Publishes the bytes written; returns their hash.
    ///
    /// # Errors
    /// The store's or the repository's failure.
    pub fn commit(self) -> Result<String> {
        let blobs = self.blobs;
        self.inner.commit(&|h| blobs.pin(h))
    }
}

impl std::io::Write for PinnedWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.inner.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// What the API says of a failed bake or tile: the error itself when it is the input's fault,
/// a pointer to the log for ours.
fn failure_of(id: &str, e: &Error) -> BakeFailure {
    let message = match e {
        Error::Io(_) | Error::Internal(_) | Error::Unavailable(_) => {
            tracing::error!(bake = %id, code = e.code(), error = %e, "bake failed");
            "an internal error occurred; it has been logged".to_owned()
        }
        _ => {
            // The input's fault, not ours: one line so an operator can still find it.
            tracing::warn!(bake = %id, code = e.code(), error = %e, "bake failed");
            e.to_string()
        }
    };
    BakeFailure { code: e.code().to_owned(), message }
}

/// Tiles a worker runs beyond its bake slots: while one tile reads its window from the store
/// or writes its result (the bake pool waits on the network), another's kernel keeps the pool
/// busy, so a worker's cores are not idle between tiles.
pub const TILE_AHEAD: usize = 1;

/// Attempts after which a bake whose store kept failing under it (`store_unavailable`) fails
/// instead of going back to the queue once more.
const UNAVAILABLE_ATTEMPTS: u32 = 5;

/// How long [`Jobs::drain`] waits for the reaper and a retention sweep in flight: each stops
/// between bakes once closing, so this only bounds a store that has stopped answering (what is
/// left then, blobs of a removed record, the next start's orphan sweep collects).
pub const HOUSEKEEPING_GRACE: Duration = Duration::from_secs(30);

/// Runs a blocking closure off the async workers.
///
/// # Errors
/// The closure's error, or [`Error::Internal`] if it panicked.
pub async fn blocking<T, F>(f: F) -> Result<T>
where
    T: Send + 'static,
    F: FnOnce() -> Result<T> + Send + 'static,
{
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| Error::Internal(format!("blocking task failed: {e}")))?
}

impl Jobs {
    /// The core over `repo` and `blobs`. Call inside a tokio runtime; nothing runs until
    /// [`Jobs::start`].
    ///
    /// # Errors
    /// When the bake pool cannot start.
    pub fn new(
        repo: Arc<dyn JobRepo>,
        blobs: Arc<dyn BlobStore>,
        cfg: JobsConfig,
        runner: Runner,
        on_finish: Option<FinishHook>,
    ) -> Result<Self> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(cfg.bake_threads)
            .thread_name(|i| format!("bake-{i}"))
            .panic_handler(|_| tracing::error!("a bake thread panicked outside a job"))
            .build()
            .map_err(|e| Error::Internal(format!("cannot start the bake pool: {e}")))?;
        let rt = tokio::runtime::Handle::try_current()
            .map_err(|_| Error::Internal("the jobs core needs a tokio runtime".into()))?;
        let (changes, _) = broadcast::channel(1024);
        Ok(Jobs(Arc::new(Inner {
            slots: Arc::new(Semaphore::new(cfg.concurrency.max(1))),
            tiles_ahead: Arc::new(Semaphore::new(TILE_AHEAD)),
            repo,
            blobs,
            cfg,
            runner,
            on_finish,
            pool,
            local: Default::default(),
            stop: CancellationToken::new(),
            closing: CancellationToken::new(),
            tracker: TaskTracker::new(),
            housekeeping: TaskTracker::new(),
            changes,
            rt,
            tiling: std::sync::OnceLock::new(),
        })))
    }

    /// Turns tiled bakes on (call before [`Jobs::start`]; later calls are ignored).
    pub fn set_tiling(&self, tiling: Tiling) {
        let _ = self.0.tiling.set(tiling);
    }

    fn tiling(&self) -> Option<&Tiling> {
        self.0.tiling.get()
    }

    /// Runs `f` on the bake pool inside `catch_unwind`; None when it panicked.
    async fn on_pool<T, F>(&self, f: F) -> Option<Result<T>>
    where
        T: Send + 'static,
        F: FnOnce() -> Result<T> + Send + 'static,
    {
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.0.pool.spawn(move || {
            let out = catch_unwind(AssertUnwindSafe(f));
            let _ = tx.send(out);
        });
        match rx.await {
            Ok(Ok(r)) => Some(r),
            _ => None,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &JobsConfig {
        &self.0.cfg
    }

    /// The repository (tests and metrics read it directly).
    pub fn repo(&self) -> &Arc<dyn JobRepo> {
        &self.0.repo
    }

    /// The blob store, for reading results.
    pub fn blob_store(&self) -> &Arc<dyn BlobStore> {
        &self.0.blobs
    }

    /// Blob access that pins for `owner`.
    pub fn blobs_for(&self, owner: impl Into<String>) -> Blobs {
        Blobs {
            store: self.0.blobs.clone(),
            repo: self.0.repo.clone(),
            owner: owner.into(),
            rt: self.0.rt.clone(),
        }
    }

    /// Recovers what a previous run left, then starts the worker loop (unless this node runs
    /// no bakes), the reaper, the retention sweeper and the change forwarding. Returns how many
    /// bakes are queued.
    ///
    /// # Errors
    /// When the repository cannot be read.
    pub async fn start(&self) -> Result<usize> {
        let queued = self.0.repo.recover().await?;
        if queued > 0 {
            tracing::info!(count = queued, "bakes waiting in the queue");
        }
        let fwd = self.clone();
        tokio::spawn(async move { fwd.forward_changes().await });
        if self.0.cfg.concurrency > 0 {
            let (w, slots) = (self.clone(), self.0.slots.clone());
            tokio::spawn(async move { w.claim_loop(slots, true).await });
            if self.tiling().is_some() {
                let (t, ahead) = (self.clone(), self.0.tiles_ahead.clone());
                tokio::spawn(async move { t.claim_loop(ahead, false).await });
            }
        }
        let r = self.clone();
        self.0.housekeeping.spawn(async move { r.reap_loop().await });
        let s = self.clone();
        self.0.housekeeping.spawn(async move { s.sweep_loop().await });
        Ok(queued)
    }

    async fn forward_changes(&self) {
        let mut rx = self.0.repo.subscribe();
        loop {
            tokio::select! {
                _ = self.0.closing.cancelled() => return,
                got = rx.recv() => match got {
                    Ok(id) => { let _ = self.0.changes.send(id); }
                    Err(broadcast::error::RecvError::Lagged(_)) => {}
                    Err(broadcast::error::RecvError::Closed) => return,
                }
            }
        }
    }

    /// Ids of bakes as they change (anywhere, for a shared repository).
    pub fn watch(&self) -> broadcast::Receiver<String> {
        self.0.changes.subscribe()
    }

    /// Resolves when the core shuts down (long-lived responses end then).
    pub fn closing(&self) -> CancellationToken {
        self.0.closing.clone()
    }

    /// Stores the input, then inserts the bake unless an identical one exists.
    ///
    /// # Errors
    /// Store and repository failures.
    pub async fn submit(&self, input: Vec<u8>, rec: BakeRecord) -> Result<Submitted> {
        let owner = format!("submit/{}", rec.id);
        let blobs = self.blobs_for(owner.clone());
        let hash = blocking(move || blobs.put(&input)).await?;
        if hash != rec.input_blob {
            return Err(Error::Internal("the input's hash changed while it was stored".into()));
        }
        self.0.repo.submit(rec, self.0.cfg.queue_capacity, &owner).await
    }

    /// [`Jobs::submit`] for an input already stored as blob `rec.input_blob` through
    /// `blobs_for("submit/{id}")` (a large upload streamed to the store as it arrived).
    ///
    /// # Errors
    /// Repository failures; [`Error::Internal`] when the blob is not stored.
    pub async fn submit_stored(&self, rec: BakeRecord) -> Result<Submitted> {
        let owner = format!("submit/{}", rec.id);
        let store = self.0.blobs.clone();
        let hash = rec.input_blob.clone();
        if !blocking(move || store.contains(&hash)).await? {
            return Err(Error::Internal("the stored input is missing".into()));
        }
        self.0.repo.submit(rec, self.0.cfg.queue_capacity, &owner).await
    }

    /// A bake, with the live progress when this node runs it.
    ///
    /// # Errors
    /// Repository failures.
    pub async fn get(&self, id: &str) -> Result<Option<BakeRecord>> {
        let rec = self.0.repo.get(id).await?;
        Ok(rec.map(|r| self.overlay(r)))
    }

    fn overlay(&self, mut r: BakeRecord) -> BakeRecord {
        if r.status == Status::Running {
            if let Some(l) = self.local().get(&r.id) {
                r.progress = Some(l.live());
            }
        }
        r
    }

    fn local(&self) -> std::sync::MutexGuard<'_, HashMap<String, LocalRun>> {
        self.0.local.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A page of bakes.
    ///
    /// # Errors
    /// Repository failures.
    pub async fn list(&self, q: &ListQuery) -> Result<Listing> {
        let mut page = self.0.repo.query(q).await?;
        page.items = page.items.into_iter().map(|r| self.overlay(r)).collect();
        Ok(page)
    }

    /// Bakes per status.
    ///
    /// # Errors
    /// Repository failures.
    pub async fn counts(&self) -> Result<Counts> {
        self.0.repo.counts().await
    }

    /// Bakes this node is running.
    pub fn running_here(&self) -> usize {
        self.local().len()
    }

    /// Cancels a queued bake, stops a running one (here at once, elsewhere at its worker's next
    /// heartbeat), or removes a finished one with its unreferenced blobs.
    ///
    /// # Errors
    /// Repository and store failures.
    pub async fn cancel(&self, id: &str) -> Result<CancelResult> {
        let out = self.0.repo.request_cancel(id).await?;
        match &out {
            CancelResult::Requested(_) => {
                // The bake and every tile of it this node runs.
                let tile_prefix = format!("{id}/tile");
                for (k, l) in self.local().iter() {
                    if k == id || k.starts_with(&tile_prefix) {
                        l.progress.cancel();
                    }
                }
            }
            CancelResult::Canceled(_) => {
                if let Some(f) = &self.0.on_finish {
                    f(Status::Canceled, 0.0, 0);
                }
            }
            CancelResult::Finished(_) => {
                self.remove(id).await?;
            }
            CancelResult::NotFound => {}
        }
        Ok(out)
    }

    /// Removes a finished bake and every blob of it nothing else references.
    ///
    /// # Errors
    /// Repository and store failures.
    pub async fn remove(&self, id: &str) -> Result<bool> {
        let Some(rec) = self.0.repo.remove(id).await? else { return Ok(false) };
        let hashes: Vec<String> = rec.blobs().map(str::to_owned).collect();
        self.0.repo.delete_blobs_if_unused(hashes, self.0.blobs.clone()).await?;
        Ok(true)
    }

    /// Adds results encoded on request (pinned by `owner`) to a succeeded bake.
    ///
    /// # Errors
    /// Repository failures.
    pub async fn add_results(
        &self,
        id: &str,
        results: &[(String, String)],
        owner: &str,
    ) -> Result<bool> {
        let added = self.0.repo.add_results(id, results, owner).await?;
        if !added {
            // The bake went away during the encode: its new blobs are nobody's.
            let hashes = results.iter().map(|(_, h)| h.clone()).collect();
            self.0.repo.delete_blobs_if_unused(hashes, self.0.blobs.clone()).await?;
        }
        Ok(added)
    }

    /// Removes finished bakes past their retention, then blobs no record references that are
    /// older than `orphan_age`. Returns how many bakes were removed. Once the core is closing
    /// ([`Jobs::drain`]) it stops between bakes: each bake it started is removed whole, its
    /// record and then its blobs, and the rest wait for the next start.
    ///
    /// # Errors
    /// Repository and store failures.
    pub async fn sweep(&self) -> Result<usize> {
        let retention = self.0.cfg.retention.as_millis() as u64;
        let mut removed = 0;
        for id in self.0.repo.expired(now_ms(), retention).await? {
            if self.0.closing.is_cancelled() {
                return Ok(removed);
            }
            if self.remove(&id).await? {
                removed += 1;
            }
        }
        if self.0.closing.is_cancelled() {
            return Ok(removed);
        }
        let blobs = self.0.blobs.clone();
        let listed = blocking(move || blobs.list()).await?;
        let referenced = self.0.repo.referenced_blobs().await?;
        let min_age = self.0.cfg.orphan_age.as_secs();
        let orphans: Vec<String> = listed
            .into_iter()
            .filter(|(h, age)| *age >= min_age && !referenced.contains(h))
            .map(|(h, _)| h)
            .collect();
        let n = self.0.repo.delete_blobs_if_unused(orphans, self.0.blobs.clone()).await?;
        if n > 0 {
            tracing::info!(blobs = n, "removed blobs no bake references");
        }
        Ok(removed)
    }

    async fn sweep_loop(&self) {
        loop {
            tokio::select! {
                _ = self.0.closing.cancelled() => return,
                _ = tokio::time::sleep(self.0.cfg.sweep_interval) => {}
            }
            match self.sweep().await {
                Ok(0) => {}
                Ok(n) => tracing::info!(removed = n, "retention sweep"),
                Err(e) => tracing::error!(error = %e, "retention sweep failed"),
            }
        }
    }

    async fn reap_loop(&self) {
        let every = (self.0.cfg.lease / 2).max(Duration::from_millis(100));
        loop {
            tokio::select! {
                _ = self.0.closing.cancelled() => return,
                _ = tokio::time::sleep(every) => {}
            }
            match self.0.repo.reap(self.0.cfg.max_attempts).await {
                Ok(ids) if !ids.is_empty() => {
                    tracing::warn!(bakes = ?ids, "leases expired: bakes given back or failed");
                }
                Ok(_) => {}
                Err(e) => tracing::warn!(error = %e, "reaper failed"),
            }
        }
    }

    /// Claims work while `slots` has a permit free, until [`Jobs::drain`]: tiles of running
    /// bakes first (they finish started work), then, with `bakes`, new bakes. The bake slots
    /// run one such loop, the tiles beyond them ([`TILE_AHEAD`]) another, tiles only.
    async fn claim_loop(&self, slots: Arc<Semaphore>, bakes: bool) {
        let mut wake = self.0.repo.subscribe();
        loop {
            let permit = tokio::select! {
                p = slots.clone().acquire_owned() => match p { Ok(p) => p, Err(_) => return },
                _ = self.0.stop.cancelled() => return,
            };
            let work = loop {
                if self.0.stop.is_cancelled() {
                    return;
                }
                if self.tiling().is_some() {
                    match self.0.repo.claim_tile(&self.0.cfg.worker_id, self.0.cfg.lease).await {
                        Ok(Some(t)) => break Work::Tile(Box::new(t)),
                        Ok(None) => {}
                        Err(e) => tracing::warn!(error = %e, "cannot claim a tile; retrying"),
                    }
                }
                if bakes {
                    match self.0.repo.claim(&self.0.cfg.worker_id, self.0.cfg.lease).await {
                        Ok(Some(c)) => break Work::Bake(Box::new(c)),
                        Ok(None) => {}
                        Err(e) => tracing::warn!(error = %e, "cannot claim a bake; retrying"),
                    }
                }
                tokio::select! {
                    _ = self.0.stop.cancelled() => return,
                    _ = wake.recv() => {}
                    _ = tokio::time::sleep(self.0.cfg.poll) => {}
                }
            };
            let me = self.clone();
            self.0.tracker.spawn(async move {
                match work {
                    Work::Bake(claim) => me.run_claim(*claim, permit).await,
                    Work::Tile(tile) => {
                        me.run_tile(*tile).await;
                        drop(permit);
                    }
                }
            });
        }
    }

    async fn run_claim(&self, claim: Claim, permit: tokio::sync::OwnedSemaphorePermit) {
        let id = claim.id.clone();
        let run = LocalRun::new(self.0.cfg.scratch_dir.clone());
        self.local().insert(id.clone(), run.clone());
        let _ = self.0.changes.send(id.clone());
        let lost = Arc::new(AtomicBool::new(false));
        let beat = {
            let (repo, claim, run, lost) =
                (self.0.repo.clone(), claim.clone(), run.clone(), lost.clone());
            let (every, lease) = (self.0.cfg.heartbeat, self.0.cfg.lease);
            tokio::spawn(async move {
                loop {
                    tokio::time::sleep(every).await;
                    match repo.heartbeat(&claim, run.live(), lease).await {
                        Ok(Beat::Alive { cancel: true }) => run.progress.cancel(),
                        Ok(Beat::Alive { cancel: false }) => {}
                        Ok(Beat::Lost) => {
                            tracing::warn!(bake = %claim.id, attempt = claim.attempt,
                                "lease lost: stopping, the bake belongs to another worker now");
                            lost.store(true, Ordering::SeqCst);
                            run.progress.cancel();
                            return;
                        }
                        Err(e) => tracing::warn!(bake = %claim.id, error = %e, "heartbeat failed"),
                    }
                }
            })
        };

        let started = Instant::now();
        let tiler = self.tiling().map(|t| t.tiler.clone()).filter(|t| t.is_tiled(&claim.record));
        let tiled = tiler.is_some();
        let (ended, permit) = match tiler {
            Some(tiler) => (self.coordinate(&claim, &run, &lost, tiler, permit).await, None),
            None => {
                let runner = self.0.runner.clone();
                let blobs = self.blobs_for(claim.owner());
                let (record, progress) = (claim.record.clone(), run.progress.clone());
                let out = self.on_pool(move || runner(&record, &progress, &blobs)).await;
                (out.map_or(Ended::Panicked, |r| Ended::Done(r.map(Box::new))), Some(permit))
            }
        };
        beat.abort();
        let seconds = started.elapsed().as_secs_f64();
        let texels = claim.record.width as u64 * claim.record.height as u64;

        // An error met after another claim took the bake over is the loss of this claim, even
        // before a heartbeat has said so: the record shows another attempt (or an end).
        if matches!(&ended, Ended::Done(Err(e)) if !matches!(e, Error::Canceled))
            && !lost.load(Ordering::SeqCst)
            && self.claim_taken(&claim).await
        {
            lost.store(true, Ordering::SeqCst);
        }
        let outcome = match ended {
            Ended::Done(Ok(rec)) => Outcome::Succeeded(rec),
            Ended::Done(Err(Error::Canceled)) if run.requeue.load(Ordering::SeqCst) => {
                Outcome::Released
            }
            Ended::Done(Err(Error::Canceled)) => Outcome::Canceled(Some(run.live())),
            // The store went away mid-bake (a result blob could not be pinned or written): not
            // the bake's fault. It goes back to the queue, to be baked again once the store is
            // back (recording that waits for it too), a bounded number of times.
            Ended::Done(Err(e @ Error::Unavailable(_))) if claim.attempt < UNAVAILABLE_ATTEMPTS => {
                tracing::warn!(bake = %id, attempt = claim.attempt, error = %e,
                    "store unavailable during the bake: handing it back to the queue");
                Outcome::Released
            }
            // Fenced off meanwhile: what this run met (its tiles gone with the bake another
            // worker finished, say) is no failure of the bake, and its outcome is not recorded.
            Ended::Done(Err(e)) if lost.load(Ordering::SeqCst) => {
                tracing::info!(bake = %id, error = %e,
                    "lost the claim during the run: another worker has the bake; dropped");
                Outcome::Released
            }
            Ended::Done(Err(e)) => Outcome::Failed(failure_of(&id, &e)),
            Ended::TileFailed(f) => {
                tracing::warn!(bake = %id, code = %f.code, error = %f.message, "tiled bake failed");
                Outcome::Failed(f)
            }
            Ended::Panicked => {
                tracing::error!(bake = %id, "bake panicked");
                Outcome::Failed(BakeFailure {
                    code: "internal".into(),
                    message: "an internal error occurred; it has been logged".into(),
                })
            }
        };
        let status = match &outcome {
            Outcome::Succeeded(_) => Status::Succeeded,
            Outcome::Failed(_) => Status::Failed,
            Outcome::Canceled(_) => Status::Canceled,
            Outcome::Released => Status::Queued,
        };
        // Fenced off (lost, or the outcome refused): whatever this run produced, the claim that
        // took over decides.
        let recorded = !lost.load(Ordering::SeqCst) && self.complete(&claim, outcome).await;
        // What the run wrote and its record does not reference (all of it when the outcome was
        // refused or is not a success: a canceled bake's Fourier files, say) is nobody's now.
        self.discard(&claim.owner()).await;
        if recorded && status.is_terminal() {
            if let Some(f) = &self.0.on_finish {
                f(status, seconds, texels);
            }
            if tiled {
                // The tiles' blobs were intermediate: the bake's results are assembled.
                self.drop_tiles(&id).await;
            }
        }
        drop(permit);
        self.local().remove(&id);
        let _ = self.0.changes.send(id);
    }

    /// Deletes the blobs a finished run (claim owner `owner`) still pins, unless a record
    /// references them or another writer pins them: what a refused, canceled or failed outcome
    /// wrote (a deterministic bake's results are often the same blobs as the winning claim's,
    /// which that claim keeps). A recorded success has no pins left. Before, they stayed pinned
    /// for an hour and then waited for the orphan sweep; a failure here still leaves them to it.
    pub(crate) async fn discard(&self, owner: &str) {
        let out = match self.0.repo.release_pins(owner).await {
            Ok(held) if held.is_empty() => Ok(0),
            Ok(held) => self.0.repo.delete_blobs_if_unused(held, self.0.blobs.clone()).await,
            Err(e) => Err(e),
        };
        match out {
            Ok(0) => {}
            Ok(n) => tracing::info!(
                owner,
                blobs = n,
                "removed the blobs of a run its record does not keep"
            ),
            Err(e) => tracing::warn!(owner, error = %e,
                "cannot remove the blobs of a finished run: left to the orphan sweep"),
        }
    }

    /// Records an outcome, retrying while the repository is unreachable (until the claim is
    /// found stale: then another worker has the bake). Returns whether it was recorded.
    async fn complete(&self, claim: &Claim, outcome: Outcome) -> bool {
        let mut wait = Duration::from_millis(100);
        loop {
            match self.0.repo.complete(claim, outcome.clone()).await {
                Ok(true) => return true,
                Ok(false) => {
                    tracing::warn!(bake = %claim.id, attempt = claim.attempt,
                        "outcome refused: the claim is stale");
                    return false;
                }
                Err(e) => {
                    tracing::warn!(bake = %claim.id, error = %e, "cannot record an outcome; retrying");
                    if self.0.closing.is_cancelled() && wait > Duration::from_secs(5) {
                        // Shutting down with the repository gone: the lease runs out and the
                        // reaper gives the bake to another worker.
                        return false;
                    }
                    tokio::time::sleep(wait).await;
                    wait = (wait * 2).min(Duration::from_secs(5));
                }
            }
        }
    }

    /// Stops claiming, lets running bakes finish within `grace`, hands the others back to the
    /// queue, then ends the background loops, waiting (within [`HOUSEKEEPING_GRACE`]) for a
    /// retention sweep or a reap in flight to finish the bake it is on.
    pub async fn drain(&self, grace: Duration) {
        self.0.stop.cancel();
        self.0.tracker.close();
        if tokio::time::timeout(grace, self.0.tracker.wait()).await.is_err() {
            let runs: Vec<LocalRun> = self.local().values().cloned().collect();
            tracing::warn!(count = runs.len(), "grace period over: handing running bakes back");
            for r in runs {
                r.requeue.store(true, Ordering::SeqCst);
                r.progress.cancel();
            }
            self.0.tracker.wait().await;
        }
        self.0.closing.cancel();
        self.0.housekeeping.close();
        if tokio::time::timeout(HOUSEKEEPING_GRACE, self.0.housekeeping.wait()).await.is_err() {
            tracing::warn!(
                "a retention sweep or reap still running at shutdown: left to the next start"
            );
        }
    }

    /// Runs `f` to completion from a thread outside the runtime (the bake or preview pool, a
    /// blocking thread); never call it from an async worker.
    pub fn block_on<F: std::future::Future>(&self, f: F) -> F::Output {
        self.0.rt.block_on(f)
    }

    /// Whether the repository answers.
    pub async fn ping(&self) -> Result<()> {
        self.0.repo.ping().await
    }
}
