//! Tiled bakes in the jobs core (SPEC §7.1): the [`Tiler`] the pipeline hands the core, and the
//! coordination of a tiled bake's claim. The claim splits the input into tiles (unless an
//! earlier attempt did), waits without holding a bake slot while any worker claims, leases,
//! heartbeats and completes the tiles exactly as bakes ([`Jobs::run_tile`]), then assembles
//! the results; a tile's work itself is the pipeline's (`pipeline::tiled`).

use super::*;

/// What a tiled bake (SPEC §7.1) computes, handed to the core by the service. Each step runs on
/// the bake pool; the core owns the lifecycle: the bake's claim runs [`Tiler::split`], records
/// the tiles, waits (holding no bake slot) while any worker claims, leases, heartbeats and
/// completes them exactly as bakes, then runs [`Tiler::assemble`] and records the bake.
pub trait Tiler: Send + Sync + 'static {
    /// Whether `rec` is baked in tiles.
    fn is_tiled(&self, rec: &BakeRecord) -> bool;
    /// Cuts the input into tile inputs (blobs written through `blobs`): the queued tiles.
    ///
    /// # Errors
    /// Decode, parameter and store failures; [`Error::Canceled`].
    fn split(
        &self,
        rec: &BakeRecord,
        progress: &Progress,
        blobs: &Blobs,
    ) -> Result<Vec<TileRecord>>;
    /// Bakes one tile: its results (name → blob written through `blobs`).
    ///
    /// # Errors
    /// Kernel and store failures; [`Error::Canceled`].
    fn bake_tile(
        &self,
        rec: &BakeRecord,
        tile: &TileRecord,
        progress: &Progress,
        blobs: &Blobs,
    ) -> Result<std::collections::BTreeMap<String, String>>;
    /// Assembles the bake's results from its succeeded tiles (in index order): the record with
    /// its results, input description, radius and timings filled in.
    ///
    /// # Errors
    /// Encode and store failures; [`Error::Canceled`].
    fn assemble(
        &self,
        rec: &BakeRecord,
        tiles: &[TileRecord],
        progress: &Progress,
        blobs: &Blobs,
    ) -> Result<BakeRecord>;
}

/// Called when a tile this node ran ends: `succeeded`, `failed`, `canceled`, `released` or
/// `lost` (fenced off), the label of `horizon_tiles_total`.
pub type TileHook = Arc<dyn Fn(&'static str) + Send + Sync>;

/// The tiled-bake half of the core, set once before [`Jobs::start`].
#[derive(Clone)]
pub struct Tiling {
    pub tiler: Arc<dyn Tiler>,
    pub on_tile: Option<TileHook>,
}

impl Jobs {
    /// Whether bake `id` is no longer running (gone, finished, or given back), read from the
    /// repository: a tile that meets an error then has lost its claim, not failed.
    pub(super) async fn bake_ended(&self, id: &str) -> bool {
        match self.0.repo.get(id).await {
            Ok(None) => true,
            Ok(Some(r)) => r.status != Status::Running,
            Err(_) => false,
        }
    }

    /// Whether another claim took `claim`'s bake over (another attempt) or it ended, read from
    /// the repository: what the run meets then is the loss of its claim, even before a
    /// heartbeat has said so. An unreachable repository says no: the heartbeat decides later.
    pub(super) async fn claim_taken(&self, claim: &Claim) -> bool {
        match self.0.repo.get(&claim.id).await {
            Ok(None) => true,
            Ok(Some(r)) => r.attempts != claim.attempt || r.status != Status::Running,
            Err(_) => false,
        }
    }

    /// Removes a finished tiled bake's tiles and the blobs only they referenced.
    pub(super) async fn drop_tiles(&self, id: &str) {
        match self.0.repo.remove_tiles(id).await {
            Ok(hashes) => {
                if let Err(e) =
                    self.0.repo.delete_blobs_if_unused(hashes, self.0.blobs.clone()).await
                {
                    tracing::warn!(bake = %id, error = %e, "cannot remove tile blobs yet");
                }
            }
            Err(e) => tracing::warn!(bake = %id, error = %e, "cannot remove the tiles"),
        }
    }

    /// Runs a tiled bake's claim: split (unless an earlier attempt did), wait for the tiles
    /// without holding a bake slot, then assemble.
    pub(super) async fn coordinate(
        &self,
        claim: &Claim,
        run: &LocalRun,
        lost: &AtomicBool,
        tiler: Arc<dyn Tiler>,
        permit: tokio::sync::OwnedSemaphorePermit,
    ) -> Ended {
        let progress = run.progress.clone();
        let blobs = self.blobs_for(claim.owner());
        let rec = claim.record.clone();
        let existing = match self.0.repo.tiles(&claim.id).await {
            Ok(t) => t,
            Err(e) => return Ended::Done(Err(e)),
        };
        if existing.is_empty() {
            let (t, p, b, r) = (tiler.clone(), progress.clone(), blobs.clone(), rec.clone());
            let tiles = match self.on_pool(move || t.split(&r, &p, &b)).await {
                Some(Ok(t)) => t,
                Some(Err(e)) => return Ended::Done(Err(e)),
                None => return Ended::Panicked,
            };
            match self.0.repo.add_tiles(claim, tiles).await {
                Ok(true) => {}
                Ok(false) => {
                    lost.store(true, Ordering::SeqCst);
                    return Ended::Done(Err(Error::Canceled));
                }
                Err(e) => return Ended::Done(Err(e)),
            }
        }
        // Waiting costs no bake slot: this node's own slots bake tiles meanwhile.
        drop(permit);
        let mut wake = self.0.repo.subscribe();
        let mut reported = 0u64;
        let mut started = false;
        let tiles = loop {
            if progress.is_canceled() {
                if !run.requeue.load(Ordering::SeqCst) && !lost.load(Ordering::SeqCst) {
                    if let Err(e) = self.0.repo.cancel_tiles(&claim.id).await {
                        tracing::warn!(bake = %claim.id, error = %e, "cannot cancel the tiles");
                    }
                }
                return Ended::Done(Err(Error::Canceled));
            }
            let tiles = match self.0.repo.tiles(&claim.id).await {
                Ok(t) => t,
                Err(e) => {
                    tracing::warn!(bake = %claim.id, error = %e, "cannot read the tiles; retrying");
                    tokio::time::sleep(Duration::from_millis(250)).await;
                    continue;
                }
            };
            if tiles.is_empty() {
                // Another claim of this bake finished it and removed its tiles while this one
                // stalled (its heartbeat may not have said so yet): this claim is stale, and
                // nothing it would record counts. Otherwise something removed the tiles of a
                // running bake, and it fails rather than assembles nothing.
                if self.claim_taken(claim).await {
                    lost.store(true, Ordering::SeqCst);
                    tracing::info!(bake = %claim.id, attempt = claim.attempt,
                        "the claim is stale: the tiles went with the bake another claim finished");
                    return Ended::Done(Err(Error::Canceled));
                }
                return Ended::Done(Err(Error::Internal(format!(
                    "the tiles of bake {} are gone",
                    claim.id
                ))));
            }
            let total = tiles.len() as u64;
            let done = tiles.iter().filter(|t| t.status == Status::Succeeded).count() as u64;
            if !started {
                progress.start(crate::progress::Stage::Bake, total);
                started = true;
            }
            if done > reported {
                progress.advance(done - reported);
                reported = done;
            }
            *run.tiles.lock().unwrap_or_else(|e| e.into_inner()) =
                Some(TileCount { done: done as u32, total: total as u32 });
            if let Some(f) = tiles.iter().find(|t| t.status == Status::Failed) {
                if let Err(e) = self.0.repo.cancel_tiles(&claim.id).await {
                    tracing::warn!(bake = %claim.id, error = %e, "cannot cancel the tiles");
                }
                let g = f.geom();
                let why = f
                    .error
                    .clone()
                    .unwrap_or(BakeFailure { code: "internal".into(), message: "unknown".into() });
                return Ended::TileFailed(BakeFailure {
                    code: why.code,
                    message: format!(
                        "tile {} (column {}, row {}: texels {}..{} × {}..{}) failed after {} \
                         attempts: {}",
                        f.index,
                        g.col,
                        g.row,
                        g.interior.x,
                        g.interior.x + g.interior.w,
                        g.interior.y,
                        g.interior.y + g.interior.h,
                        f.attempts,
                        why.message
                    ),
                });
            }
            if tiles.iter().any(|t| t.status == Status::Canceled) {
                return Ended::Done(Err(Error::Canceled));
            }
            if done == total {
                break tiles;
            }
            tokio::select! {
                _ = wake.recv() => {}
                _ = tokio::time::sleep(Duration::from_millis(250)) => {}
            }
        };
        // A claim that stalled while it waited (SIGSTOP, a frozen VM) may have been taken over
        // and its bake finished by another worker: it learns so here, before it spends an
        // assembly on results nobody would record.
        if let Ok(Beat::Lost) = self.0.repo.heartbeat(claim, run.live(), self.0.cfg.lease).await {
            tracing::warn!(bake = %claim.id, attempt = claim.attempt,
                "lease lost before the assembly: the bake belongs to another worker now");
            lost.store(true, Ordering::SeqCst);
            return Ended::Done(Err(Error::Canceled));
        }
        // The assembly takes no slot either: an idle work loop holds one while it waits for
        // work, and the assembly is the last step of work already claimed.
        let count = TileCount { done: tiles.len() as u32, total: tiles.len() as u32 };
        let out = self
            .on_pool(move || {
                let mut done = tiler.assemble(&rec, &tiles, &progress, &blobs)?;
                done.tiles = Some(count);
                Ok(done)
            })
            .await;
        out.map_or(Ended::Panicked, |r| Ended::Done(r.map(Box::new)))
    }

    /// Runs one claimed tile: heartbeats its lease, bakes it on the pool, records the outcome
    /// (refused when the claim went stale meanwhile).
    pub(super) async fn run_tile(&self, claim: TileClaim) {
        let key = format!("{}/tile{}", claim.bake_id, claim.index);
        let run = LocalRun::new(self.0.cfg.scratch_dir.clone());
        self.local().insert(key.clone(), run.clone());
        let lost = Arc::new(AtomicBool::new(false));
        let beat = {
            let (repo, claim, progress, lost) =
                (self.0.repo.clone(), claim.clone(), run.progress.clone(), lost.clone());
            let (every, lease) = (self.0.cfg.heartbeat, self.0.cfg.lease);
            tokio::spawn(async move {
                loop {
                    tokio::time::sleep(every).await;
                    match repo.heartbeat_tile(&claim, lease).await {
                        Ok(Beat::Alive { cancel: true }) => progress.cancel(),
                        Ok(Beat::Alive { cancel: false }) => {}
                        Ok(Beat::Lost) => {
                            tracing::warn!(bake = %claim.bake_id, tile = claim.index,
                                attempt = claim.attempt,
                                "tile lease lost: stopping, it belongs to another worker now");
                            lost.store(true, Ordering::SeqCst);
                            progress.cancel();
                            return;
                        }
                        Err(e) => tracing::warn!(bake = %claim.bake_id, tile = claim.index,
                            error = %e, "tile heartbeat failed"),
                    }
                }
            })
        };
        let tiler = self.tiling().map(|t| t.tiler.clone());
        let bake = self.0.repo.get(&claim.bake_id).await;
        let out = match (tiler, bake) {
            (Some(tiler), Ok(Some(rec))) => {
                let blobs = self.blobs_for(claim.owner());
                let (tile, progress) = (claim.tile.clone(), run.progress.clone());
                self.on_pool(move || tiler.bake_tile(&rec, &tile, &progress, &blobs)).await
            }
            (_, Ok(None)) => Some(Err(Error::Canceled)),
            (_, Err(e)) => Some(Err(e)),
            (None, _) => Some(Err(Error::Internal("tiling is off on this node".into()))),
        };
        beat.abort();
        let outcome = match out {
            Some(Ok(results)) => TileOutcome::Succeeded(results),
            Some(Err(Error::Canceled)) if run.requeue.load(Ordering::SeqCst) => {
                TileOutcome::Released
            }
            Some(Err(Error::Canceled)) => TileOutcome::Canceled,
            Some(Err(e @ Error::Unavailable(_))) if claim.attempt < UNAVAILABLE_ATTEMPTS => {
                tracing::warn!(bake = %claim.bake_id, tile = claim.index, error = %e,
                    "store unavailable during a tile: handing it back");
                TileOutcome::Released
            }
            // What a tile meets once its bake was finished elsewhere (its blobs gone) is no
            // failure: the claim is stale, whether or not its heartbeat has said so yet.
            Some(Err(e))
                if lost.load(Ordering::SeqCst) || self.bake_ended(&claim.bake_id).await =>
            {
                lost.store(true, Ordering::SeqCst);
                tracing::info!(bake = %claim.bake_id, tile = claim.index, error = %e,
                    "the tile's bake ended elsewhere during the run: dropped");
                TileOutcome::Canceled
            }
            Some(Err(e)) => TileOutcome::Failed(failure_of(&key, &e)),
            None => {
                tracing::error!(bake = %claim.bake_id, tile = claim.index, "tile panicked");
                TileOutcome::Failed(BakeFailure {
                    code: "internal".into(),
                    message: "an internal error occurred; it has been logged".into(),
                })
            }
        };
        let label = match &outcome {
            TileOutcome::Succeeded(_) => "succeeded",
            TileOutcome::Failed(_) => "failed",
            TileOutcome::Canceled => "canceled",
            TileOutcome::Released => "released",
        };
        let recorded = if lost.load(Ordering::SeqCst) {
            false
        } else {
            let mut wait = Duration::from_millis(100);
            loop {
                match self
                    .0
                    .repo
                    .complete_tile(&claim, outcome.clone(), self.0.cfg.max_attempts)
                    .await
                {
                    Ok(done) => break done,
                    Err(e) if wait < Duration::from_secs(5) => {
                        tracing::warn!(bake = %claim.bake_id, tile = claim.index, error = %e,
                            "cannot record a tile; retrying");
                        tokio::time::sleep(wait).await;
                        wait *= 2;
                    }
                    Err(e) => {
                        tracing::warn!(bake = %claim.bake_id, tile = claim.index, error = %e,
                            "cannot record a tile; its lease will run out");
                        break false;
                    }
                }
            }
        };
        if !recorded {
            tracing::warn!(bake = %claim.bake_id, tile = claim.index, attempt = claim.attempt,
                "tile outcome refused: the claim is stale");
        }
        self.discard(&claim.owner()).await;
        if let Some(hook) = self.tiling().and_then(|t| t.on_tile.clone()) {
            // A DELETE cancels the bake's tiles in the repository, which makes the running
            // ones' claims stale too: those were stopped, not taken over by another worker.
            let label = if recorded {
                label
            } else {
                match self.0.repo.get(&claim.bake_id).await {
                    Ok(None) => "canceled",
                    Ok(Some(rec)) if rec.status == Status::Canceled => "canceled",
                    _ => "lost",
                }
            };
            hook(label);
        }
        self.local().remove(&key);
        let _ = self.0.changes.send(claim.bake_id.clone());
    }
}
