//! The job repository: the one trait every state change of a bake goes through.
//!
//! It is shaped for several machines, so the embedded backend cannot hide a state change that a
//! networked one would miss:
//! - a submission is an insert-if-absent on the deduplication key;
//! - a worker *claims* a queued bake for a lease and gets a [`Claim`] whose `attempt` is a
//!   fencing number: every later write of that worker names it, and is refused once another
//!   claim (a higher attempt) took the bake over or the bake left `running`;
//! - heartbeats extend the lease, carry the progress, and answer whether a cancel was requested;
//! - a reaper gives bakes with expired leases back to `queued` (or fails them as `worker_lost`
//!   after `max_attempts`);
//! - blobs a writer is about to reference are pinned, and a blob is deleted only when no record
//!   references it and no live pin holds it, checked atomically with the delete;
//! - every change is announced on a broadcast channel of bake ids (SSE and idle workers wake on
//!   it on every node).
//!
//! The methods are async because a networked database is; the embedded backend runs its redb
//! transactions on blocking threads.

pub mod embedded;
pub mod postgres;
pub mod redb;

pub use embedded::EmbeddedRepo;
pub use postgres::PgRepo;

use crate::error::Result;
use crate::jobs::blob::BlobStore;
use crate::jobs::record::{BakeFailure, BakeRecord, ListQuery, Listing, LiveProgress, Status};
use crate::jobs::record::{TileClaim, TileOutcome, TileRecord};
use std::collections::HashSet;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::broadcast;

/// What a submission became.
#[derive(Debug, Clone)]
pub enum Submitted {
    /// A new bake, now `queued`.
    Created(BakeRecord),
    /// An identical bake that is queued, running or succeeded (its retention starts over).
    Existing(BakeRecord),
    /// The queue holds `waiting` bakes already.
    QueueFull { waiting: u64 },
}

/// A worker's hold on a running bake. `attempt` is the fencing number.
#[derive(Debug, Clone)]
pub struct Claim {
    pub id: String,
    pub attempt: u32,
    pub worker: String,
    /// The record as claimed (status `running`).
    pub record: BakeRecord,
}

impl Claim {
    /// Who owns the blobs this claim writes until its record references them.
    pub fn owner(&self) -> String {
        format!("{}/{}/{}", self.worker, self.id, self.attempt)
    }
}

/// A heartbeat's answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Beat {
    /// The lease is extended; `cancel` says whether someone asked the bake to stop.
    Alive { cancel: bool },
    /// The claim is stale: the lease expired and the bake was given back (or finished, or
    /// removed). The worker must stop and write nothing.
    Lost,
}

/// How a claimed bake ended.
#[derive(Debug, Clone)]
pub enum Outcome {
    /// The record with its results, input description, radius and timings filled in.
    Succeeded(Box<BakeRecord>),
    Failed(BakeFailure),
    /// Stopped on request, with the progress it had reached.
    Canceled(Option<crate::jobs::record::LiveProgress>),
    /// Handed back unfinished (shutdown): `queued` again, for any worker.
    Released,
}

impl Outcome {
    /// The record `current` (the claimed bake) becomes with this outcome, and the result blobs
    /// it now references. Both backends apply it, so they cannot disagree on a transition.
    pub fn apply(self, current: BakeRecord, claim: &Claim) -> (BakeRecord, Vec<String>) {
        let mut rec = current;
        let mut results = Vec::new();
        let now = crate::jobs::record::now_ms();
        match self {
            Outcome::Succeeded(done) => {
                let mut done = *done;
                results = done.results.values().cloned().collect();
                done.status = Status::Succeeded;
                done.attempts = claim.attempt;
                done.worker = Some(claim.worker.clone());
                done.error = None;
                done.finished_ms.get_or_insert(now);
                done.started_ms = rec.started_ms.or(done.started_ms);
                rec = done;
            }
            Outcome::Failed(f) => {
                rec.status = Status::Failed;
                rec.error = Some(f);
                rec.finished_ms = Some(now);
            }
            Outcome::Canceled(last) => {
                rec.stopped_at = last;
                rec.status = Status::Canceled;
                rec.finished_ms = Some(now);
            }
            Outcome::Released => {
                rec.status = Status::Queued;
                rec.started_ms = None;
                rec.worker = None;
            }
        }
        rec.progress = None;
        (rec, results)
    }
}

/// What a cancel request found.
#[derive(Debug, Clone)]
pub enum CancelResult {
    NotFound,
    /// Already finished (succeeded, failed or canceled): nothing to stop.
    Finished(BakeRecord),
    /// It was queued: now `canceled`.
    Canceled(BakeRecord),
    /// It is running: its worker learns it at its next heartbeat.
    Requested(BakeRecord),
}

/// How many bakes are in each status.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counts {
    pub queued: u64,
    pub running: u64,
    pub succeeded: u64,
    pub failed: u64,
    pub canceled: u64,
}

impl Counts {
    /// The count of `s`.
    pub fn of(&self, s: Status) -> u64 {
        match s {
            Status::Queued => self.queued,
            Status::Running => self.running,
            Status::Succeeded => self.succeeded,
            Status::Failed => self.failed,
            Status::Canceled => self.canceled,
        }
    }

    /// Adds one bake in status `s`.
    pub fn add(&mut self, s: Status) {
        match s {
            Status::Queued => self.queued += 1,
            Status::Running => self.running += 1,
            Status::Succeeded => self.succeeded += 1,
            Status::Failed => self.failed += 1,
            Status::Canceled => self.canceled += 1,
        }
    }
}

/// Bake records, the queue, leases, cancel flags, blob pins and the change feed.
#[async_trait::async_trait]
pub trait JobRepo: Send + Sync + 'static {
    /// Inserts `rec` (status `queued`) unless a queued, running or succeeded bake has the same
    /// `dedup_key`; a succeeded one has its retention extended (`requested_ms`). Refuses when
    /// `capacity` bakes are queued already. Unpins the input blob pinned by `owner`.
    async fn submit(&self, rec: BakeRecord, capacity: usize, owner: &str) -> Result<Submitted>;
    /// The record with `id`.
    async fn get(&self, id: &str) -> Result<Option<BakeRecord>>;
    /// A page of records and the total matching count.
    async fn query(&self, q: &ListQuery) -> Result<Listing>;
    /// Takes the oldest queued bake for `worker` for `lease`: status `running`, attempt + 1.
    async fn claim(&self, worker: &str, lease: Duration) -> Result<Option<Claim>>;
    /// Extends the lease and stores the progress; see [`Beat`].
    async fn heartbeat(
        &self,
        claim: &Claim,
        progress: LiveProgress,
        lease: Duration,
    ) -> Result<Beat>;
    /// Records how the claimed bake ended, unless the claim is stale (returns false then and
    /// writes nothing). Unpins the blobs `claim.owner()` pinned.
    async fn complete(&self, claim: &Claim, outcome: Outcome) -> Result<bool>;
    /// Cancels a queued bake, or asks a running one to stop.
    async fn request_cancel(&self, id: &str) -> Result<CancelResult>;
    /// Gives bakes whose lease expired back to `queued`, or fails them (`worker_lost`) once
    /// they were claimed `max_attempts` times. One node at a time. Returns the ids touched.
    async fn reap(&self, max_attempts: u32) -> Result<Vec<String>>;
    /// At start: what this backend must do for bakes a previous run left (the embedded one puts
    /// every `running` bake back to `queued`; a shared database leaves them to the reaper).
    /// Returns how many bakes are queued.
    async fn recover(&self) -> Result<usize>;
    /// Adds results encoded on request to a succeeded bake; false when it is gone. Unpins
    /// `owner`'s pins of them.
    async fn add_results(
        &self,
        id: &str,
        results: &[(String, String)],
        owner: &str,
    ) -> Result<bool>;
    /// Removes a finished record; returns it (None when absent or not finished).
    async fn remove(&self, id: &str) -> Result<Option<BakeRecord>>;
    /// Ids of finished bakes whose retention ran out at `now_ms`.
    async fn expired(&self, now_ms: u64, retention_ms: u64) -> Result<Vec<String>>;
    /// How many bakes are in each status.
    async fn counts(&self) -> Result<Counts>;
    /// Keeps `hash` from being deleted until `owner`'s record references it (or an hour).
    async fn pin_blob(&self, hash: &str, owner: &str) -> Result<()>;
    /// Drops every pin `owner` holds and returns their hashes: a run whose outcome was refused
    /// (its claim stale) hands what it wrote to [`JobRepo::delete_blobs_if_unused`] instead of
    /// leaving it pinned for an hour.
    async fn release_pins(&self, owner: &str) -> Result<Vec<String>>;
    /// Deletes each of `hashes` from `blobs` that no record references and no live pin holds,
    /// atomically with respect to pins and references. Returns how many were deleted.
    async fn delete_blobs_if_unused(
        &self,
        hashes: Vec<String>,
        blobs: Arc<dyn BlobStore>,
    ) -> Result<usize>;
    /// Every blob some record references.
    async fn referenced_blobs(&self) -> Result<HashSet<String>>;
    /// Whether the backend answers (readiness).
    async fn ping(&self) -> Result<()>;

    // Tiled bakes (SPEC §7.1): each tile is claimed, leased, heartbeated and fenced like a bake.
    // A tile change is announced under its bake's id.

    /// Adds the tiles of the bake `claim` holds (those not already there from an earlier
    /// attempt keep their state), unless the claim is stale (false). References their input
    /// blobs and unpins `claim.owner()`'s pins of them.
    async fn add_tiles(&self, claim: &Claim, tiles: Vec<TileRecord>) -> Result<bool>;
    /// The tiles of bake `id`, by index.
    async fn tiles(&self, id: &str) -> Result<Vec<TileRecord>>;
    /// Takes the first queued tile of a running, uncanceled bake for `worker` for `lease`:
    /// status `running`, attempt + 1 (its fencing number).
    async fn claim_tile(&self, worker: &str, lease: Duration) -> Result<Option<TileClaim>>;
    /// Extends the tile's lease; `cancel` when the tile or its bake was asked to stop or the
    /// bake is no longer running; `Lost` when the claim is stale.
    async fn heartbeat_tile(&self, claim: &TileClaim, lease: Duration) -> Result<Beat>;
    /// Records how the claimed tile ended ([`TileOutcome::apply`]), unless the claim is stale
    /// (false, nothing written): a worker that lost its lease cannot replace the results of the
    /// claim that took over. References the result blobs and unpins `claim.owner()`'s pins.
    async fn complete_tile(
        &self,
        claim: &TileClaim,
        outcome: TileOutcome,
        max_attempts: u32,
    ) -> Result<bool>;
    /// Stops every tile of bake `id`: queued ones become `canceled`, running ones are asked to
    /// stop (their workers learn it at their next heartbeat).
    async fn cancel_tiles(&self, id: &str) -> Result<()>;
    /// Removes the tiles of bake `id` and their references; returns the blobs they referenced
    /// (for [`JobRepo::delete_blobs_if_unused`]).
    async fn remove_tiles(&self, id: &str) -> Result<Vec<String>>;
    /// Ids of bakes as they change, on every node.
    fn subscribe(&self) -> broadcast::Receiver<String>;
}
