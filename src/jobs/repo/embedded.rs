//! The embedded job repository: one process, a redb file and a data directory, nothing else.
//!
//! Records live in [`RedbStore`] (durable before any answer); what only matters while this
//! process lives is in memory: the FIFO of queued ids, the claims with their progress and cancel
//! flags, and blob pins. A claim writes `running` durably, so after a crash [`JobRepo::recover`]
//! finds every accepted bake (`queued` or `running`) and queues it again in creation order: the
//! only worker that could hold a claim was this process. Leases therefore never expire here and
//! [`JobRepo::reap`] has nothing to do.
//!
//! One mutex orders the changes that must be atomic with each other: the dedup check and the
//! insert of a submission, a completion and its fencing check, and a blob deletion with the
//! reference scan and pin check that justify it (a record that references a blob commits under
//! the same mutex, so the scan cannot miss it).
//!
//! That deletion holds the mutex across its store calls, which take as long as the disk (or the
//! test's gate) does. So no runtime thread ever waits on the mutex: [`EmbeddedRepo::with_mem`]
//! takes it in place only when it is free, and otherwise waits on a blocking thread. A runtime
//! thread parked on it would stop the timers and sockets of every task scheduled there.

use crate::error::{Error, Result};
use crate::jobs::blob::BlobStore;
use crate::jobs::record::{now_ms, BakeRecord, ListQuery, Listing, LiveProgress, Status};
use crate::jobs::record::{TileClaim, TileOutcome, TileRecord};
use crate::jobs::repo::redb::{BakeStore, RedbStore};
use crate::jobs::repo::{Beat, CancelResult, Claim, Counts, JobRepo, Outcome, Submitted};
use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::path::Path;
use std::sync::{Arc, Mutex, MutexGuard, TryLockError};
use std::time::Duration;
use tokio::sync::broadcast;

/// How long a pin holds a blob whose writer never committed its record.
const PIN_TTL_MS: u64 = 3600 * 1000;

#[derive(Debug, Default)]
struct Mem {
    queue: VecDeque<String>,
    /// Claims of running bakes: attempt, progress, cancel requested.
    claims: HashMap<String, (u32, Option<LiveProgress>, bool)>,
    /// hash → owner → pinned until (Unix ms).
    pins: HashMap<String, HashMap<String, u64>>,
    /// Tiles of tiled bakes (bake id → tiles by index, each with its cancel flag). In memory:
    /// after a crash the bake is queued again and its claim splits it again.
    tiles: BTreeMap<String, Vec<(TileRecord, bool)>>,
}

/// The tile `claim` still holds: running, at the claim's attempt, by its worker (the fencing
/// check of a tile's heartbeat and of its completion); `None` once it lost the tile.
fn held_tile<'m>(mem: &'m mut Mem, claim: &TileClaim) -> Option<&'m mut (TileRecord, bool)> {
    let tiles = mem.tiles.get_mut(&claim.bake_id)?;
    tiles.iter_mut().find(|(t, _)| t.index == claim.index).filter(|(t, _)| {
        t.status == Status::Running
            && t.attempts == claim.attempt
            && t.worker.as_deref() == Some(claim.worker.as_str())
    })
}

fn cancel_tiles_in(mem: &mut Mem, id: &str) {
    if let Some(ts) = mem.tiles.get_mut(id) {
        for (t, cancel) in ts {
            match t.status {
                Status::Queued => t.status = Status::Canceled,
                Status::Running => *cancel = true,
                _ => {}
            }
        }
    }
}

/// [`JobRepo`] on redb and memory.
pub struct EmbeddedRepo {
    store: Arc<RedbStore>,
    mem: Arc<Mutex<Mem>>,
    changes: broadcast::Sender<String>,
}

impl EmbeddedRepo {
    /// Opens (or creates) the record file at `path`.
    ///
    /// # Errors
    /// When the file cannot be opened (locked by another server, corrupt), naming it.
    pub fn open(path: &Path) -> Result<Self> {
        let (changes, _) = broadcast::channel(1024);
        Ok(EmbeddedRepo {
            store: Arc::new(RedbStore::open(path)?),
            mem: Default::default(),
            changes,
        })
    }

    /// The record table (for tests that age or inspect records directly).
    pub fn store(&self) -> &RedbStore {
        &self.store
    }

    fn notify(&self, id: &str) {
        let _ = self.changes.send(id.to_owned());
    }

    /// Runs `f` with the store and the memory state locked, on a blocking thread.
    async fn locked<T, F>(&self, f: F) -> Result<T>
    where
        T: Send + 'static,
        F: FnOnce(&RedbStore, &mut Mem) -> Result<T> + Send + 'static,
    {
        let store = self.store.clone();
        let mem = self.mem.clone();
        tokio::task::spawn_blocking(move || {
            let mut g = lock(&mem);
            f(&store, &mut g)
        })
        .await
        .map_err(|e| Error::Internal(format!("blocking task failed: {e}")))?
    }

    /// Runs `f` on the memory state: here when the mutex is free (the usual case, no thread
    /// hop), else on a blocking thread, so a long holder never parks a runtime thread.
    async fn with_mem<T, F>(&self, f: F) -> Result<T>
    where
        T: Send + 'static,
        F: FnOnce(&mut Mem) -> T + Send + 'static,
    {
        match self.mem.try_lock() {
            Ok(mut g) => return Ok(f(&mut g)),
            Err(TryLockError::Poisoned(e)) => return Ok(f(&mut e.into_inner())),
            Err(TryLockError::WouldBlock) => {}
        }
        let mem = self.mem.clone();
        tokio::task::spawn_blocking(move || f(&mut lock(&mem)))
            .await
            .map_err(|e| Error::Internal(format!("blocking task failed: {e}")))
    }

    async fn read<T, F>(&self, f: F) -> Result<T>
    where
        T: Send + 'static,
        F: FnOnce(&RedbStore) -> Result<T> + Send + 'static,
    {
        let store = self.store.clone();
        tokio::task::spawn_blocking(move || f(&store))
            .await
            .map_err(|e| Error::Internal(format!("blocking task failed: {e}")))?
    }
}

fn lock(m: &Mutex<Mem>) -> MutexGuard<'_, Mem> {
    // Plain data: a panic while holding the lock leaves it consistent.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

fn unpin(mem: &mut Mem, hashes: impl IntoIterator<Item = String>, owner: &str) {
    for h in hashes {
        if let Some(owners) = mem.pins.get_mut(&h) {
            owners.remove(owner);
            if owners.is_empty() {
                mem.pins.remove(&h);
            }
        }
    }
}

/// Every record, in id order (one pass over the table).
fn each_record(store: &RedbStore, mut f: impl FnMut(BakeRecord)) -> Result<()> {
    let mut after: Option<String> = None;
    loop {
        let page = store.list(None, after.as_deref(), 1000)?;
        for r in page.items {
            f(r);
        }
        match page.next {
            Some(n) => after = Some(n),
            None => return Ok(()),
        }
    }
}

#[async_trait::async_trait]
impl JobRepo for EmbeddedRepo {
    async fn submit(&self, rec: BakeRecord, capacity: usize, owner: &str) -> Result<Submitted> {
        let owner = owner.to_owned();
        let out = self
            .locked(move |store, mem| {
                if let Some(mut existing) = store.find_by_key(&rec.dedup_key)? {
                    if !matches!(existing.status, Status::Failed | Status::Canceled) {
                        if existing.status.is_terminal() {
                            existing.requested_ms = Some(now_ms());
                            store.put(&existing)?;
                        }
                        unpin(mem, [rec.input_blob.clone()], &owner);
                        return Ok(Submitted::Existing(existing));
                    }
                }
                if mem.queue.len() >= capacity {
                    unpin(mem, [rec.input_blob.clone()], &owner);
                    return Ok(Submitted::QueueFull { waiting: mem.queue.len() as u64 });
                }
                store.put(&rec)?;
                mem.queue.push_back(rec.id.clone());
                unpin(mem, [rec.input_blob.clone()], &owner);
                Ok(Submitted::Created(rec))
            })
            .await?;
        match &out {
            Submitted::Created(r) | Submitted::Existing(r) => self.notify(&r.id),
            Submitted::QueueFull { .. } => {}
        }
        Ok(out)
    }

    async fn get(&self, id: &str) -> Result<Option<BakeRecord>> {
        let id = id.to_owned();
        let Some(mut r) = self.read(move |store| store.get(&id)).await? else { return Ok(None) };
        if r.status == Status::Running {
            let id = r.id.clone();
            if let Some(p) = self.with_mem(move |mem| mem.claims.get(&id).map(|c| c.1)).await? {
                r.progress = p;
            }
        }
        Ok(Some(r))
    }

    async fn query(&self, q: &ListQuery) -> Result<Listing> {
        let q = q.clone();
        let page = self.read(move |store| store.query(&q)).await?;
        self.with_mem(move |mem| {
            let mut page = page;
            for r in &mut page.items {
                if let Some((_, p, _)) = mem.claims.get(&r.id) {
                    r.progress = *p;
                }
            }
            page
        })
        .await
    }

    async fn claim(&self, worker: &str, _lease: Duration) -> Result<Option<Claim>> {
        let worker = worker.to_owned();
        let claim = self
            .locked(move |store, mem| {
                while let Some(id) = mem.queue.pop_front() {
                    let Some(mut rec) = store.get(&id)? else { continue };
                    if rec.status != Status::Queued {
                        continue;
                    }
                    rec.status = Status::Running;
                    rec.started_ms = Some(now_ms());
                    rec.attempts += 1;
                    rec.worker = Some(worker.clone());
                    rec.progress = None;
                    if let Err(e) = store.put(&rec) {
                        // Leave it first in line for the next try.
                        mem.queue.push_front(id);
                        return Err(e);
                    }
                    mem.claims.insert(id.clone(), (rec.attempts, None, false));
                    return Ok(Some(Claim {
                        id,
                        attempt: rec.attempts,
                        worker: worker.clone(),
                        record: rec,
                    }));
                }
                Ok(None)
            })
            .await?;
        if let Some(c) = &claim {
            self.notify(&c.id);
        }
        Ok(claim)
    }

    async fn heartbeat(
        &self,
        claim: &Claim,
        progress: LiveProgress,
        _lease: Duration,
    ) -> Result<Beat> {
        let (id, attempt) = (claim.id.clone(), claim.attempt);
        let beat = self
            .with_mem(move |mem| match mem.claims.get_mut(&id) {
                Some(c) if c.0 == attempt => {
                    let changed = c.1 != Some(progress);
                    c.1 = Some(progress);
                    (Beat::Alive { cancel: c.2 }, changed)
                }
                _ => (Beat::Lost, false),
            })
            .await?;
        if beat.1 {
            self.notify(&claim.id);
        }
        Ok(beat.0)
    }

    async fn complete(&self, claim: &Claim, outcome: Outcome) -> Result<bool> {
        let claim = claim.clone();
        let id = claim.id.clone();
        let done = self
            .locked(move |store, mem| {
                if mem.claims.get(&claim.id).map(|c| c.0) != Some(claim.attempt) {
                    return Ok(false);
                }
                let Some(current) = store.get(&claim.id)? else {
                    mem.claims.remove(&claim.id);
                    return Ok(false);
                };
                if current.status != Status::Running || current.attempts != claim.attempt {
                    mem.claims.remove(&claim.id);
                    return Ok(false);
                }
                let (rec, results) = outcome.apply(current, &claim);
                store.put(&rec)?;
                mem.claims.remove(&claim.id);
                if rec.status == Status::Queued {
                    mem.queue.push_back(rec.id.clone());
                }
                unpin(mem, results, &claim.owner());
                Ok(true)
            })
            .await?;
        self.notify(&id);
        Ok(done)
    }

    async fn request_cancel(&self, id: &str) -> Result<CancelResult> {
        let id = id.to_owned();
        let out = self
            .locked(move |store, mem| {
                let Some(mut rec) = store.get(&id)? else { return Ok(CancelResult::NotFound) };
                match rec.status {
                    Status::Queued => {
                        mem.queue.retain(|q| q != &id);
                        rec.status = Status::Canceled;
                        rec.finished_ms = Some(now_ms());
                        store.put(&rec)?;
                        Ok(CancelResult::Canceled(rec))
                    }
                    Status::Running => {
                        if let Some(c) = mem.claims.get_mut(&id) {
                            c.2 = true;
                        }
                        cancel_tiles_in(mem, &id);
                        Ok(CancelResult::Requested(rec))
                    }
                    _ => Ok(CancelResult::Finished(rec)),
                }
            })
            .await?;
        if let CancelResult::Canceled(r) | CancelResult::Requested(r) = &out {
            self.notify(&r.id);
        }
        Ok(out)
    }

    async fn reap(&self, _max_attempts: u32) -> Result<Vec<String>> {
        // One process holds every claim; they end with it, and `recover` handles a crash.
        Ok(Vec::new())
    }

    async fn recover(&self) -> Result<usize> {
        self.locked(|store, mem| {
            let mut unfinished = Vec::new();
            each_record(store, |r| {
                if !r.status.is_terminal() {
                    unfinished.push(r);
                }
            })?;
            mem.queue.clear();
            mem.claims.clear();
            mem.tiles.clear();
            for mut r in unfinished {
                if r.status == Status::Running {
                    r.status = Status::Queued;
                    r.started_ms = None;
                    r.progress = None;
                    store.put(&r)?;
                }
                mem.queue.push_back(r.id);
            }
            Ok(mem.queue.len())
        })
        .await
    }

    async fn add_results(
        &self,
        id: &str,
        results: &[(String, String)],
        owner: &str,
    ) -> Result<bool> {
        let id = id.to_owned();
        let results = results.to_vec();
        let owner = owner.to_owned();
        let nid = id.clone();
        let added = self
            .locked(move |store, mem| {
                let hashes = results.iter().map(|(_, h)| h.clone());
                let Some(mut rec) = store.get(&id)? else {
                    unpin(mem, hashes, &owner);
                    return Ok(false);
                };
                if rec.status != Status::Succeeded {
                    unpin(mem, hashes, &owner);
                    return Ok(false);
                }
                for (n, h) in &results {
                    rec.results.insert(n.clone(), h.clone());
                }
                store.put(&rec)?;
                unpin(mem, hashes, &owner);
                Ok(true)
            })
            .await?;
        if added {
            self.notify(&nid);
        }
        Ok(added)
    }

    async fn remove(&self, id: &str) -> Result<Option<BakeRecord>> {
        let id = id.to_owned();
        let nid = id.clone();
        let out = self
            .locked(move |store, _| {
                let Some(rec) = store.get(&id)? else { return Ok(None) };
                if !rec.status.is_terminal() {
                    return Ok(None);
                }
                store.delete(&id)?;
                Ok(Some(rec))
            })
            .await?;
        if out.is_some() {
            self.notify(&nid);
        }
        Ok(out)
    }

    async fn expired(&self, now: u64, retention_ms: u64) -> Result<Vec<String>> {
        self.read(move |store| {
            let mut out = Vec::new();
            each_record(store, |r| {
                if r.expires_ms(retention_ms).is_some_and(|e| e <= now) {
                    out.push(r.id);
                }
            })?;
            Ok(out)
        })
        .await
    }

    async fn counts(&self) -> Result<Counts> {
        self.read(|store| {
            let mut c = Counts::default();
            each_record(store, |r| c.add(r.status))?;
            Ok(c)
        })
        .await
    }

    async fn pin_blob(&self, hash: &str, owner: &str) -> Result<()> {
        let (hash, owner) = (hash.to_owned(), owner.to_owned());
        self.with_mem(move |mem| {
            mem.pins.entry(hash).or_default().insert(owner, now_ms() + PIN_TTL_MS);
        })
        .await
    }

    async fn release_pins(&self, owner: &str) -> Result<Vec<String>> {
        let owner = owner.to_owned();
        self.with_mem(move |mem| {
            let held: Vec<String> = mem
                .pins
                .iter()
                .filter(|(_, o)| o.contains_key(&owner))
                .map(|(h, _)| h.clone())
                .collect();
            unpin(mem, held.clone(), &owner);
            held
        })
        .await
    }

    async fn delete_blobs_if_unused(
        &self,
        hashes: Vec<String>,
        blobs: Arc<dyn BlobStore>,
    ) -> Result<usize> {
        if hashes.is_empty() {
            return Ok(0);
        }
        self.locked(move |store, mem| {
            let now = now_ms();
            let mut used = HashSet::new();
            each_record(store, |r| used.extend(r.blobs().map(str::to_owned)))?;
            for ts in mem.tiles.values() {
                used.extend(ts.iter().flat_map(|(t, _)| t.blobs().map(str::to_owned)));
            }
            let mut deleted = 0;
            for hash in hashes {
                if let Some(owners) = mem.pins.get_mut(&hash) {
                    owners.retain(|_, until| *until > now);
                    if !owners.is_empty() {
                        continue;
                    }
                    mem.pins.remove(&hash);
                }
                if used.contains(&hash) {
                    continue;
                }
                blobs.delete(&hash)?;
                deleted += 1;
            }
            Ok(deleted)
        })
        .await
    }

    async fn referenced_blobs(&self) -> Result<HashSet<String>> {
        self.locked(|store, mem| {
            let mut out = HashSet::new();
            each_record(store, |r| out.extend(r.blobs().map(str::to_owned)))?;
            for ts in mem.tiles.values() {
                out.extend(ts.iter().flat_map(|(t, _)| t.blobs().map(str::to_owned)));
            }
            Ok(out)
        })
        .await
    }

    async fn add_tiles(&self, claim: &Claim, tiles: Vec<TileRecord>) -> Result<bool> {
        let (id, attempt, owner) = (claim.id.clone(), claim.attempt, claim.owner());
        let key = id.clone();
        let added = self
            .with_mem(move |mem| {
                if mem.claims.get(&key).map(|c| c.0) != Some(attempt) {
                    return false;
                }
                let hashes: Vec<String> = tiles.iter().map(|t| t.input_blob.clone()).collect();
                let entry = mem.tiles.entry(key).or_default();
                for t in tiles {
                    if !entry.iter().any(|(e, _)| e.index == t.index) {
                        entry.push((t, false));
                    }
                }
                entry.sort_by_key(|(t, _)| t.index);
                unpin(mem, hashes, &owner);
                true
            })
            .await?;
        self.notify(&id);
        Ok(added)
    }

    async fn tiles(&self, id: &str) -> Result<Vec<TileRecord>> {
        let id = id.to_owned();
        self.with_mem(move |mem| {
            mem.tiles
                .get(&id)
                .map(|ts| ts.iter().map(|(t, _)| t.clone()).collect())
                .unwrap_or_default()
        })
        .await
    }

    async fn claim_tile(&self, worker: &str, _lease: Duration) -> Result<Option<TileClaim>> {
        let worker = worker.to_owned();
        let claim = self
            .with_mem(move |mem| {
                let Mem { claims, tiles, .. } = mem;
                let mut found = None;
                for (bid, ts) in tiles.iter_mut() {
                    if claims.get(bid).is_none_or(|c| c.2) {
                        continue;
                    }
                    if let Some((t, _)) = ts.iter_mut().find(|(t, _)| t.status == Status::Queued) {
                        t.status = Status::Running;
                        t.attempts += 1;
                        t.worker = Some(worker.clone());
                        found = Some(TileClaim {
                            bake_id: bid.clone(),
                            index: t.index,
                            attempt: t.attempts,
                            worker: worker.clone(),
                            tile: t.clone(),
                        });
                        break;
                    }
                }
                found
            })
            .await?;
        if let Some(c) = &claim {
            self.notify(&c.bake_id);
        }
        Ok(claim)
    }

    async fn heartbeat_tile(&self, claim: &TileClaim, _lease: Duration) -> Result<Beat> {
        let claim = claim.clone();
        self.with_mem(move |g| {
            let bake_stop = g.claims.get(&claim.bake_id).is_none_or(|c| c.2);
            match held_tile(g, &claim) {
                Some((_, cancel)) => Beat::Alive { cancel: *cancel || bake_stop },
                None => Beat::Lost,
            }
        })
        .await
    }

    async fn complete_tile(
        &self,
        claim: &TileClaim,
        outcome: TileOutcome,
        max_attempts: u32,
    ) -> Result<bool> {
        let c = claim.clone();
        let done = self
            .with_mem(move |g| {
                let claim = &c;
                let owner = claim.owner();
                match held_tile(g, claim) {
                    Some((t, cancel)) => {
                        *t = outcome.apply(t.clone(), claim, max_attempts);
                        *cancel = false;
                        let results: Vec<String> = t.results.values().cloned().collect();
                        unpin(g, results, &owner);
                        true
                    }
                    _ => false,
                }
            })
            .await?;
        self.notify(&claim.bake_id);
        Ok(done)
    }

    async fn cancel_tiles(&self, id: &str) -> Result<()> {
        let key = id.to_owned();
        self.with_mem(move |mem| cancel_tiles_in(mem, &key)).await?;
        self.notify(id);
        Ok(())
    }

    async fn remove_tiles(&self, id: &str) -> Result<Vec<String>> {
        let id = id.to_owned();
        let removed = self.with_mem(move |mem| mem.tiles.remove(&id).unwrap_or_default()).await?;
        Ok(removed.iter().flat_map(|(t, _)| t.blobs().map(str::to_owned)).collect())
    }

    async fn ping(&self) -> Result<()> {
        Ok(())
    }

    fn subscribe(&self) -> broadcast::Receiver<String> {
        self.changes.subscribe()
    }
}
