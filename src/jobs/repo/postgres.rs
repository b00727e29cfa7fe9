//! The job repository on PostgreSQL, for API and worker processes on many machines (SPEC §7).
//!
//! One row per bake: the record as JSON plus the columns the lifecycle needs in SQL (status,
//! dedup key, worker, attempt, lease, cancel flag, progress). The columns are the truth; the
//! JSON's copies of status and attempts are rewritten with them.
//! - **Claims** take the oldest queued row with `FOR UPDATE SKIP LOCKED`, so workers never wait
//!   on each other, and stamp `attempt + 1` (the fencing number) and a lease from the
//!   database's clock (`now()`), so node clocks do not matter.
//! - **Heartbeats** extend the lease and store progress only while status, worker and attempt
//!   still match; they return `cancel_requested`. **Completion** re-checks the same under
//!   `FOR UPDATE`, so a worker that lost its lease writes nothing.
//! - **The reaper** runs under a transaction-level advisory lock (one node at a time): expired
//!   leases go back to `queued`, or `failed` (`worker_lost`) after `max_attempts`.
//! - **Dedup** is a unique index on the key over queued, running and succeeded rows, and
//!   `INSERT … ON CONFLICT DO NOTHING`: two API nodes cannot both insert.
//! - **Changes** are `pg_notify('horizon_changes', id)` inside the changing transaction (sent on
//!   commit); every node LISTENs and re-broadcasts, with the caller's slow polling as fallback.
//! - **Blobs**: `blob_refs` (bake → hash) is maintained with the records; a writer pins a hash
//!   (`blob_pins`) before publishing it. Pinning and deleting take the same advisory lock per
//!   hash, and a delete re-checks pins and references under it, so a blob a writer is about to
//!   reference is never deleted.
//! - **A stalled node holds no lock for long**: every session has a server-side
//!   `idle_in_transaction_session_timeout` of half the lease ([`idle_in_transaction_ms`]), so a
//!   process frozen inside a transaction (its heartbeat's row lock, the reaper's lock) has its
//!   session ended and its locks freed before its lease runs out, and the reaper can give its
//!   work back (SPEC §7).
//! - **Migrations** run at start under a session advisory lock, numbered in `horizon_schema`.

use crate::error::{Error, Result};
use crate::jobs::blob::BlobStore;
use crate::jobs::record::{
    now_ms, BakeFailure, BakeRecord, ListQuery, Listing, LiveProgress, Status,
};
use crate::jobs::record::{TileClaim, TileOutcome, TileRecord};
use crate::jobs::repo::{Beat, CancelResult, Claim, Counts, JobRepo, Outcome, Submitted};
use sqlx::postgres::{PgListener, PgPool, PgPoolOptions, PgRow};
use sqlx::{Postgres, Row, Transaction};
use std::collections::HashSet;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::broadcast;

const CHANNEL: &str = "horizon_changes";
/// Advisory lock keys (arbitrary constants of this application).
const MIGRATE_LOCK: i64 = 0x686f_7269_7a6f_6e01;
const REAPER_LOCK: i64 = 0x686f_7269_7a6f_6e02;
const PIN_TTL_SECS: f64 = 3600.0;

/// Schema versions, applied in order, each once.
const MIGRATIONS: &[&str] = &[
    r"
CREATE TABLE bakes (
    id text PRIMARY KEY,
    status text NOT NULL,
    dedup_key text NOT NULL,
    record jsonb NOT NULL,
    worker text,
    attempt integer NOT NULL DEFAULT 0,
    lease_until timestamptz,
    cancel_requested boolean NOT NULL DEFAULT false,
    progress jsonb
);
CREATE UNIQUE INDEX bakes_dedup_live ON bakes (dedup_key)
    WHERE status IN ('queued', 'running', 'succeeded');
CREATE INDEX bakes_queued ON bakes (id) WHERE status = 'queued';
CREATE INDEX bakes_leases ON bakes (lease_until) WHERE status = 'running';
CREATE TABLE blob_refs (
    bake_id text NOT NULL REFERENCES bakes (id) ON DELETE CASCADE,
    hash text NOT NULL,
    PRIMARY KEY (bake_id, hash)
);
CREATE INDEX blob_refs_hash ON blob_refs (hash);
CREATE TABLE blob_pins (
    hash text NOT NULL,
    owner text NOT NULL,
    pinned_until timestamptz NOT NULL,
    PRIMARY KEY (hash, owner)
);
",
    r"
CREATE TABLE tiles (
    bake_id text NOT NULL REFERENCES bakes (id) ON DELETE CASCADE,
    idx integer NOT NULL,
    status text NOT NULL,
    record jsonb NOT NULL,
    worker text,
    attempt integer NOT NULL DEFAULT 0,
    lease_until timestamptz,
    cancel_requested boolean NOT NULL DEFAULT false,
    PRIMARY KEY (bake_id, idx)
);
CREATE INDEX tiles_queued ON tiles (bake_id, idx) WHERE status = 'queued';
CREATE INDEX tiles_leases ON tiles (lease_until) WHERE status = 'running';
",
];

fn pg_err(e: sqlx::Error) -> Error {
    match e {
        // SQLSTATE classes 08 (connection), 53 (resources), 57 (operator intervention: a
        // shutdown or restart terminating sessions), and 25P03 (this session sat in a
        // transaction past `idle_in_transaction_session_timeout`, so the server ended it): the
        // database is away, or we stalled, not our bug.
        sqlx::Error::Database(d)
            if d.code().is_some_and(|c| {
                c == "25P03" || ["08", "53", "57"].iter().any(|k| c.starts_with(k))
            }) =>
        {
            Error::Unavailable(format!("database: {d}"))
        }
        sqlx::Error::Database(d) => Error::Internal(format!("database: {d}")),
        sqlx::Error::RowNotFound | sqlx::Error::ColumnDecode { .. } | sqlx::Error::Decode(_) => {
            Error::Internal(format!("database: {e}"))
        }
        // Connection refused, reset, pool timeouts: the database is away, not our bug.
        other => Error::Unavailable(format!("database: {other}")),
    }
}

fn json_err(e: serde_json::Error) -> Error {
    Error::Internal(format!("corrupt bake record: {e}"))
}

const TILE_COLUMNS: &str = "bake_id, idx, status, record, worker, attempt";

fn tile_of(row: &PgRow) -> Result<TileRecord> {
    let json: serde_json::Value = row.try_get("record").map_err(pg_err)?;
    let mut t: TileRecord = serde_json::from_value(json).map_err(json_err)?;
    let status: String = row.try_get("status").map_err(pg_err)?;
    t.status = Status::parse(&status).map_err(|_| Error::Internal(format!("status {status}")))?;
    t.attempts = row.try_get::<i32, _>("attempt").map_err(pg_err)?.max(0) as u32;
    t.worker = row.try_get("worker").map_err(pg_err)?;
    Ok(t)
}

/// Writes a tile's JSON and columns (the lease and cancel flag end unless it is running).
async fn write_tile(tx: &mut Transaction<'_, Postgres>, t: &TileRecord) -> Result<()> {
    sqlx::query(
        "UPDATE tiles SET status = $3, record = $4, worker = $5, attempt = $6, \
         lease_until = CASE WHEN $3 = 'running' THEN lease_until END, \
         cancel_requested = CASE WHEN $3 = 'running' THEN cancel_requested ELSE false END \
         WHERE bake_id = $1 AND idx = $2",
    )
    .bind(&t.bake_id)
    .bind(t.index as i32)
    .bind(t.status.as_str())
    .bind(serde_json::to_value(t).map_err(json_err)?)
    .bind(&t.worker)
    .bind(t.attempts as i32)
    .execute(&mut **tx)
    .await
    .map_err(pg_err)?;
    Ok(())
}

async fn cancel_tiles_tx(tx: &mut Transaction<'_, Postgres>, id: &str) -> Result<()> {
    sqlx::query(
        "UPDATE tiles SET status = 'canceled', \
         record = record || jsonb_build_object('status', 'canceled') \
         WHERE bake_id = $1 AND status = 'queued'",
    )
    .bind(id)
    .execute(&mut **tx)
    .await
    .map_err(pg_err)?;
    sqlx::query(
        "UPDATE tiles SET cancel_requested = true WHERE bake_id = $1 AND status = 'running'",
    )
    .bind(id)
    .execute(&mut **tx)
    .await
    .map_err(pg_err)?;
    Ok(())
}

/// The server-side `idle_in_transaction_session_timeout` of every session, in milliseconds: half
/// the lease (at least a second).
///
/// A process that stalls (SIGSTOP, a frozen VM, a long pause) inside one of its transactions
/// would otherwise hold that transaction's locks for as long as it stalls: its heartbeat's row
/// lock on the bake (the reaper's `FOR UPDATE SKIP LOCKED` skips it for ever, so the bake stays
/// `running`), a tile's row lock, the reaper's advisory lock. The server ends such a session
/// (rolling its transaction back) once it has been idle that long, which a frozen client cannot
/// prevent, so its locks are free before its lease runs out. Every transaction here runs its
/// statements back to back (a blob deletion waits for one object store call inside its own),
/// so a live node never comes near it; if one does, its statement fails as
/// [`Error::Unavailable`] and is retried like a database outage.
pub fn idle_in_transaction_ms(lease: Duration) -> u128 {
    (lease / 2).max(Duration::from_secs(1)).as_millis()
}

/// The `application_name` of node `name`'s sessions (PostgreSQL keeps 63 bytes of it).
pub fn application_name(name: &str) -> String {
    let mut s = format!("horizon-bake {name}");
    while s.len() > 63 {
        s.pop();
    }
    s
}

/// [`JobRepo`] on PostgreSQL.
pub struct PgRepo {
    pool: PgPool,
    changes: broadcast::Sender<String>,
}

const COLUMNS: &str = "id, status, record, worker, attempt, progress";

fn record_of(row: &PgRow) -> Result<BakeRecord> {
    let json: serde_json::Value = row.try_get("record").map_err(pg_err)?;
    let mut rec: BakeRecord = serde_json::from_value(json).map_err(json_err)?;
    let status: String = row.try_get("status").map_err(pg_err)?;
    rec.status = Status::parse(&status).map_err(|_| Error::Internal(format!("status {status}")))?;
    rec.attempts = row.try_get::<i32, _>("attempt").map_err(pg_err)?.max(0) as u32;
    rec.worker = row.try_get("worker").map_err(pg_err)?;
    let progress: Option<serde_json::Value> = row.try_get("progress").map_err(pg_err)?;
    rec.progress = progress.and_then(|p| serde_json::from_value(p).ok());
    Ok(rec)
}

fn to_json(rec: &BakeRecord) -> Result<serde_json::Value> {
    let mut r = rec.clone();
    r.progress = None;
    serde_json::to_value(&r).map_err(json_err)
}

async fn notify(tx: &mut Transaction<'_, Postgres>, id: &str) -> Result<()> {
    sqlx::query("SELECT pg_notify($1, $2)")
        .bind(CHANNEL)
        .bind(id)
        .execute(&mut **tx)
        .await
        .map_err(pg_err)?;
    Ok(())
}

async fn add_refs(
    tx: &mut Transaction<'_, Postgres>,
    id: &str,
    hashes: &[String],
    owner: &str,
) -> Result<()> {
    for h in hashes {
        sqlx::query("INSERT INTO blob_refs (bake_id, hash) VALUES ($1, $2) ON CONFLICT DO NOTHING")
            .bind(id)
            .bind(h)
            .execute(&mut **tx)
            .await
            .map_err(pg_err)?;
    }
    sqlx::query("DELETE FROM blob_pins WHERE owner = $1 AND hash = ANY($2)")
        .bind(owner)
        .bind(hashes)
        .execute(&mut **tx)
        .await
        .map_err(pg_err)?;
    Ok(())
}

/// Writes the record's JSON and columns of an existing row.
async fn write(tx: &mut Transaction<'_, Postgres>, rec: &BakeRecord) -> Result<()> {
    let progress = rec.progress.map(|p| serde_json::to_value(p).unwrap_or_default());
    sqlx::query(
        "UPDATE bakes SET status = $2, record = $3, worker = $4, attempt = $5, progress = $6, \
         lease_until = CASE WHEN $2 = 'running' THEN lease_until END, \
         cancel_requested = CASE WHEN $2 = 'running' THEN cancel_requested ELSE false END \
         WHERE id = $1",
    )
    .bind(&rec.id)
    .bind(rec.status.as_str())
    .bind(to_json(rec)?)
    .bind(&rec.worker)
    .bind(rec.attempts as i32)
    .bind(progress)
    .execute(&mut **tx)
    .await
    .map_err(pg_err)?;
    Ok(())
}

impl PgRepo {
    /// Connects (retrying for up to `wait`), applies the schema migrations and starts listening
    /// for changes. Call inside a tokio runtime.
    ///
    /// # Errors
    /// When the database cannot be reached within `wait` or a migration fails.
    pub async fn connect(url: &str, wait: Duration, name: &str, lease: Duration) -> Result<Self> {
        let opts: sqlx::postgres::PgConnectOptions =
            url.parse().map_err(|e| Error::param("database_url", format!("{e}")))?;
        // Operators (and the tests) find a node's sessions in `pg_stat_activity` by it.
        let opts = opts
            .application_name(&application_name(name))
            .options([("idle_in_transaction_session_timeout", idle_in_transaction_ms(lease))]);
        let pool = PgPoolOptions::new()
            .max_connections(16)
            .acquire_timeout(Duration::from_secs(3))
            .connect_lazy_with(opts);
        let deadline = tokio::time::Instant::now() + wait;
        loop {
            match sqlx::query("SELECT 1").execute(&pool).await {
                Ok(_) => break,
                Err(e) if tokio::time::Instant::now() < deadline => {
                    tracing::info!(error = %e, "waiting for the database");
                    tokio::time::sleep(Duration::from_millis(250)).await;
                }
                Err(e) => {
                    return Err(Error::Unavailable(format!("cannot reach the database: {e}")))
                }
            }
        }
        migrate(&pool).await?;
        let (changes, _) = broadcast::channel(4096);
        let repo = PgRepo { pool, changes };
        repo.listen();
        Ok(repo)
    }

    /// The connection pool (tests inspect rows through it).
    pub fn pool(&self) -> &PgPool {
        &self.pool
    }

    /// Re-broadcasts `horizon_changes` notifications until the sender is dropped; reconnects
    /// after the database restarts.
    fn listen(&self) {
        let pool = self.pool.clone();
        let tx = self.changes.clone();
        tokio::spawn(async move {
            loop {
                let mut listener = match PgListener::connect_with(&pool).await {
                    Ok(l) => l,
                    Err(e) => {
                        tracing::debug!(error = %e, "LISTEN connection failed; retrying");
                        tokio::time::sleep(Duration::from_millis(500)).await;
                        continue;
                    }
                };
                if let Err(e) = listener.listen(CHANNEL).await {
                    tracing::debug!(error = %e, "LISTEN failed; retrying");
                    tokio::time::sleep(Duration::from_millis(500)).await;
                    continue;
                }
                loop {
                    match listener.try_recv().await {
                        Ok(Some(n)) => {
                            if tx.send(n.payload().to_owned()).is_err() && tx.receiver_count() == 0
                            {
                                // Nobody listens yet; keep the connection.
                            }
                        }
                        // The connection dropped: notifications may be lost, so wake everyone.
                        Ok(None) | Err(_) => {
                            let _ = tx.send(String::new());
                            tokio::time::sleep(Duration::from_millis(250)).await;
                            break;
                        }
                    }
                }
            }
        });
    }

    async fn begin(&self) -> Result<Transaction<'static, Postgres>> {
        self.pool.begin().await.map_err(pg_err)
    }

    async fn select_for_update(
        tx: &mut Transaction<'_, Postgres>,
        id: &str,
    ) -> Result<Option<BakeRecord>> {
        let row = sqlx::query(&format!("SELECT {COLUMNS} FROM bakes WHERE id = $1 FOR UPDATE"))
            .bind(id)
            .fetch_optional(&mut **tx)
            .await
            .map_err(pg_err)?;
        row.as_ref().map(record_of).transpose()
    }
}

async fn migrate(pool: &PgPool) -> Result<()> {
    // One transaction under a transaction-level advisory lock: nodes starting together apply
    // each migration once, and a failed migration leaves nothing half-applied.
    let mut tx = pool.begin().await.map_err(pg_err)?;
    sqlx::query("SELECT pg_advisory_xact_lock($1)")
        .bind(MIGRATE_LOCK)
        .execute(&mut *tx)
        .await
        .map_err(pg_err)?;
    sqlx::query("CREATE TABLE IF NOT EXISTS horizon_schema (version integer NOT NULL)")
        .execute(&mut *tx)
        .await
        .map_err(pg_err)?;
    let current: Option<i32> = sqlx::query_scalar("SELECT max(version) FROM horizon_schema")
        .fetch_one(&mut *tx)
        .await
        .map_err(pg_err)?;
    let current = current.unwrap_or(0).max(0) as usize;
    for (i, m) in MIGRATIONS.iter().enumerate().skip(current) {
        // Statement by statement (the migrations hold no `;` inside a statement): a prepared
        // query takes one statement, and `sqlx::raw_sql`'s future is not `Send` for every
        // lifetime, which `tokio::spawn` of the server needs.
        let statements: Vec<&'static str> =
            m.split(';').map(str::trim).filter(|q| !q.is_empty()).collect();
        for q in statements {
            sqlx::query(q).execute(&mut *tx).await.map_err(pg_err)?;
        }
        sqlx::query("INSERT INTO horizon_schema (version) VALUES ($1)")
            .bind((i + 1) as i32)
            .execute(&mut *tx)
            .await
            .map_err(pg_err)?;
        tracing::info!(version = i + 1, "database schema migrated");
    }
    tx.commit().await.map_err(pg_err)
}

#[async_trait::async_trait]
impl JobRepo for PgRepo {
    async fn submit(&self, rec: BakeRecord, capacity: usize, owner: &str) -> Result<Submitted> {
        let mut tx = self.begin().await?;
        let live = format!(
            "SELECT {COLUMNS} FROM bakes WHERE dedup_key = $1 \
             AND status IN ('queued', 'running', 'succeeded') FOR UPDATE"
        );
        let existing = sqlx::query(&live)
            .bind(&rec.dedup_key)
            .fetch_optional(&mut *tx)
            .await
            .map_err(pg_err)?;
        let found = |row: Option<PgRow>| row.as_ref().map(record_of).transpose();
        let unpin = "DELETE FROM blob_pins WHERE owner = $1";
        if let Some(mut existing) = found(existing)? {
            if existing.status.is_terminal() {
                existing.requested_ms = Some(now_ms());
                write(&mut tx, &existing).await?;
            }
            sqlx::query(unpin).bind(owner).execute(&mut *tx).await.map_err(pg_err)?;
            tx.commit().await.map_err(pg_err)?;
            return Ok(Submitted::Existing(existing));
        }
        let waiting: i64 = sqlx::query_scalar("SELECT count(*) FROM bakes WHERE status = 'queued'")
            .fetch_one(&mut *tx)
            .await
            .map_err(pg_err)?;
        if waiting as usize >= capacity {
            sqlx::query(unpin).bind(owner).execute(&mut *tx).await.map_err(pg_err)?;
            tx.commit().await.map_err(pg_err)?;
            return Ok(Submitted::QueueFull { waiting: waiting as u64 });
        }
        let inserted = sqlx::query(
            "INSERT INTO bakes (id, status, dedup_key, record, attempt) VALUES ($1, 'queued', $2, $3, 0) \
             ON CONFLICT (dedup_key) WHERE status IN ('queued', 'running', 'succeeded') DO NOTHING \
             RETURNING id",
        )
        .bind(&rec.id)
        .bind(&rec.dedup_key)
        .bind(to_json(&rec)?)
        .fetch_optional(&mut *tx)
        .await
        .map_err(pg_err)?;
        if inserted.is_none() {
            // Another node inserted the same bake between our check and our insert.
            let existing = sqlx::query(&live)
                .bind(&rec.dedup_key)
                .fetch_optional(&mut *tx)
                .await
                .map_err(pg_err)?;
            sqlx::query(unpin).bind(owner).execute(&mut *tx).await.map_err(pg_err)?;
            tx.commit().await.map_err(pg_err)?;
            return match found(existing)? {
                Some(e) => Ok(Submitted::Existing(e)),
                None => Err(Error::Unavailable("a concurrent submission is settling".into())),
            };
        }
        add_refs(&mut tx, &rec.id, std::slice::from_ref(&rec.input_blob), owner).await?;
        sqlx::query(unpin).bind(owner).execute(&mut *tx).await.map_err(pg_err)?;
        notify(&mut tx, &rec.id).await?;
        tx.commit().await.map_err(pg_err)?;
        Ok(Submitted::Created(rec))
    }

    async fn get(&self, id: &str) -> Result<Option<BakeRecord>> {
        let row = sqlx::query(&format!("SELECT {COLUMNS} FROM bakes WHERE id = $1"))
            .bind(id)
            .fetch_optional(&self.pool)
            .await
            .map_err(pg_err)?;
        row.as_ref().map(record_of).transpose()
    }

    async fn query(&self, q: &ListQuery) -> Result<Listing> {
        let statuses: Vec<String> = q.statuses.iter().map(|s| s.as_str().to_owned()).collect();
        let (cmp, order) = if q.newest_first { ("<", "DESC") } else { (">", "ASC") };
        let rows = sqlx::query(&format!(
            "SELECT {COLUMNS} FROM bakes WHERE (cardinality($1::text[]) = 0 OR status = ANY($1)) \
             AND ($2::text IS NULL OR id {cmp} $2) ORDER BY id {order} LIMIT $3"
        ))
        .bind(&statuses)
        .bind(&q.cursor)
        .bind(q.limit as i64 + 1)
        .fetch_all(&self.pool)
        .await
        .map_err(pg_err)?;
        let total: i64 = sqlx::query_scalar(
            "SELECT count(*) FROM bakes WHERE cardinality($1::text[]) = 0 OR status = ANY($1)",
        )
        .bind(&statuses)
        .fetch_one(&self.pool)
        .await
        .map_err(pg_err)?;
        let mut items = rows.iter().map(record_of).collect::<Result<Vec<_>>>()?;
        let more = items.len() > q.limit;
        items.truncate(q.limit);
        let next = if more { items.last().map(|r| r.id.clone()) } else { None };
        Ok(Listing { items, next, total: total as u64 })
    }

    async fn claim(&self, worker: &str, lease: Duration) -> Result<Option<Claim>> {
        let mut tx = self.begin().await?;
        let row = sqlx::query(&format!(
            "UPDATE bakes SET status = 'running', worker = $1, attempt = attempt + 1, \
             lease_until = now() + make_interval(secs => $2), cancel_requested = false, \
             progress = NULL, \
             record = record || jsonb_build_object('started_ms', \
                 (extract(epoch FROM clock_timestamp()) * 1000)::bigint) \
             WHERE id = (SELECT id FROM bakes WHERE status = 'queued' ORDER BY id \
                 LIMIT 1 FOR UPDATE SKIP LOCKED) \
             RETURNING {COLUMNS}"
        ))
        .bind(worker)
        .bind(lease.as_secs_f64())
        .fetch_optional(&mut *tx)
        .await
        .map_err(pg_err)?;
        let Some(row) = row else {
            tx.commit().await.map_err(pg_err)?;
            return Ok(None);
        };
        let rec = record_of(&row)?;
        notify(&mut tx, &rec.id).await?;
        tx.commit().await.map_err(pg_err)?;
        Ok(Some(Claim {
            id: rec.id.clone(),
            attempt: rec.attempts,
            worker: worker.to_owned(),
            record: rec,
        }))
    }

    async fn heartbeat(
        &self,
        claim: &Claim,
        progress: LiveProgress,
        lease: Duration,
    ) -> Result<Beat> {
        let mut tx = self.begin().await?;
        let cancel: Option<bool> = sqlx::query_scalar(
            "UPDATE bakes SET lease_until = now() + make_interval(secs => $4), progress = $5 \
             WHERE id = $1 AND attempt = $2 AND worker = $3 AND status = 'running' \
             RETURNING cancel_requested",
        )
        .bind(&claim.id)
        .bind(claim.attempt as i32)
        .bind(&claim.worker)
        .bind(lease.as_secs_f64())
        .bind(serde_json::to_value(progress).map_err(json_err)?)
        .fetch_optional(&mut *tx)
        .await
        .map_err(pg_err)?;
        if cancel.is_some() {
            notify(&mut tx, &claim.id).await?;
        }
        tx.commit().await.map_err(pg_err)?;
        Ok(match cancel {
            Some(cancel) => Beat::Alive { cancel },
            None => Beat::Lost,
        })
    }

    async fn complete(&self, claim: &Claim, outcome: Outcome) -> Result<bool> {
        let mut tx = self.begin().await?;
        let Some(current) = Self::select_for_update(&mut tx, &claim.id).await? else {
            return Ok(false);
        };
        if current.status != Status::Running
            || current.attempts != claim.attempt
            || current.worker.as_deref() != Some(claim.worker.as_str())
        {
            return Ok(false);
        }
        let (rec, results) = outcome.apply(current, claim);
        write(&mut tx, &rec).await?;
        add_refs(&mut tx, &rec.id, &results, &claim.owner()).await?;
        notify(&mut tx, &rec.id).await?;
        tx.commit().await.map_err(pg_err)?;
        Ok(true)
    }

    async fn request_cancel(&self, id: &str) -> Result<CancelResult> {
        let mut tx = self.begin().await?;
        let Some(mut rec) = Self::select_for_update(&mut tx, id).await? else {
            return Ok(CancelResult::NotFound);
        };
        let out = match rec.status {
            Status::Queued => {
                rec.status = Status::Canceled;
                rec.finished_ms = Some(now_ms());
                write(&mut tx, &rec).await?;
                CancelResult::Canceled(rec)
            }
            Status::Running => {
                sqlx::query("UPDATE bakes SET cancel_requested = true WHERE id = $1")
                    .bind(id)
                    .execute(&mut *tx)
                    .await
                    .map_err(pg_err)?;
                cancel_tiles_tx(&mut tx, id).await?;
                CancelResult::Requested(rec)
            }
            _ => CancelResult::Finished(rec),
        };
        if !matches!(out, CancelResult::Finished(_)) {
            notify(&mut tx, id).await?;
        }
        tx.commit().await.map_err(pg_err)?;
        Ok(out)
    }

    async fn reap(&self, max_attempts: u32) -> Result<Vec<String>> {
        let mut tx = self.begin().await?;
        let mine: bool = sqlx::query_scalar("SELECT pg_try_advisory_xact_lock($1)")
            .bind(REAPER_LOCK)
            .fetch_one(&mut *tx)
            .await
            .map_err(pg_err)?;
        if !mine {
            return Ok(Vec::new());
        }
        let rows = sqlx::query(&format!(
            "SELECT {COLUMNS} FROM bakes WHERE status = 'running' AND lease_until < now() \
             FOR UPDATE SKIP LOCKED"
        ))
        .fetch_all(&mut *tx)
        .await
        .map_err(pg_err)?;
        let mut ids = Vec::new();
        for row in &rows {
            let mut rec = record_of(row)?;
            if rec.attempts >= max_attempts {
                rec.status = Status::Failed;
                rec.finished_ms = Some(now_ms());
                rec.error = Some(BakeFailure {
                    code: "worker_lost".into(),
                    message: format!(
                        "the worker running this bake stopped answering, {} times",
                        rec.attempts
                    ),
                });
            } else {
                rec.status = Status::Queued;
                rec.started_ms = None;
            }
            rec.worker = None;
            rec.progress = None;
            write(&mut tx, &rec).await?;
            notify(&mut tx, &rec.id).await?;
            ids.push(rec.id);
        }
        let rows = sqlx::query(&format!(
            "SELECT {TILE_COLUMNS} FROM tiles WHERE status = 'running' AND lease_until < now() \
             FOR UPDATE SKIP LOCKED"
        ))
        .fetch_all(&mut *tx)
        .await
        .map_err(pg_err)?;
        for row in &rows {
            let mut t = tile_of(row)?;
            if t.attempts >= max_attempts {
                t.status = Status::Failed;
                t.error = Some(BakeFailure {
                    code: "worker_lost".into(),
                    message: format!(
                        "the worker running this tile stopped answering, {} times",
                        t.attempts
                    ),
                });
            } else {
                t.status = Status::Queued;
            }
            t.worker = None;
            write_tile(&mut tx, &t).await?;
            notify(&mut tx, &t.bake_id).await?;
            ids.push(format!("{}/tile{}", t.bake_id, t.index));
        }
        tx.commit().await.map_err(pg_err)?;
        Ok(ids)
    }

    async fn recover(&self) -> Result<usize> {
        // Running bakes may belong to live workers on other machines: the reaper decides.
        let n: i64 = sqlx::query_scalar("SELECT count(*) FROM bakes WHERE status = 'queued'")
            .fetch_one(&self.pool)
            .await
            .map_err(pg_err)?;
        Ok(n as usize)
    }

    async fn add_results(
        &self,
        id: &str,
        results: &[(String, String)],
        owner: &str,
    ) -> Result<bool> {
        let mut tx = self.begin().await?;
        let hashes: Vec<String> = results.iter().map(|(_, h)| h.clone()).collect();
        let rec = Self::select_for_update(&mut tx, id).await?;
        let Some(mut rec) = rec.filter(|r| r.status == Status::Succeeded) else {
            sqlx::query("DELETE FROM blob_pins WHERE owner = $1")
                .bind(owner)
                .execute(&mut *tx)
                .await
                .map_err(pg_err)?;
            tx.commit().await.map_err(pg_err)?;
            return Ok(false);
        };
        for (n, h) in results {
            rec.results.insert(n.clone(), h.clone());
        }
        write(&mut tx, &rec).await?;
        add_refs(&mut tx, id, &hashes, owner).await?;
        notify(&mut tx, id).await?;
        tx.commit().await.map_err(pg_err)?;
        Ok(true)
    }

    async fn remove(&self, id: &str) -> Result<Option<BakeRecord>> {
        let mut tx = self.begin().await?;
        let row = sqlx::query(&format!(
            "DELETE FROM bakes WHERE id = $1 AND status IN ('succeeded', 'failed', 'canceled') \
             RETURNING {COLUMNS}"
        ))
        .bind(id)
        .fetch_optional(&mut *tx)
        .await
        .map_err(pg_err)?;
        let rec = row.as_ref().map(record_of).transpose()?;
        if rec.is_some() {
            notify(&mut tx, id).await?;
        }
        tx.commit().await.map_err(pg_err)?;
        Ok(rec)
    }

    async fn expired(&self, now: u64, retention_ms: u64) -> Result<Vec<String>> {
        sqlx::query_scalar(
            "SELECT id FROM bakes WHERE status IN ('succeeded', 'failed', 'canceled') \
             AND greatest(coalesce((record->>'finished_ms')::bigint, 0), \
                          coalesce((record->>'requested_ms')::bigint, 0)) + $2 <= $1",
        )
        .bind(now as i64)
        .bind(retention_ms as i64)
        .fetch_all(&self.pool)
        .await
        .map_err(pg_err)
    }

    async fn counts(&self) -> Result<Counts> {
        let rows = sqlx::query("SELECT status, count(*) AS n FROM bakes GROUP BY status")
            .fetch_all(&self.pool)
            .await
            .map_err(pg_err)?;
        let mut c = Counts::default();
        for row in rows {
            let s: String = row.try_get("status").map_err(pg_err)?;
            let n: i64 = row.try_get("n").map_err(pg_err)?;
            match Status::parse(&s) {
                Ok(Status::Queued) => c.queued = n as u64,
                Ok(Status::Running) => c.running = n as u64,
                Ok(Status::Succeeded) => c.succeeded = n as u64,
                Ok(Status::Failed) => c.failed = n as u64,
                Ok(Status::Canceled) => c.canceled = n as u64,
                Err(_) => {}
            }
        }
        Ok(c)
    }

    async fn pin_blob(&self, hash: &str, owner: &str) -> Result<()> {
        let mut tx = self.begin().await?;
        sqlx::query("SELECT pg_advisory_xact_lock(hashtextextended($1, 0))")
            .bind(hash)
            .execute(&mut *tx)
            .await
            .map_err(pg_err)?;
        sqlx::query(
            "INSERT INTO blob_pins (hash, owner, pinned_until) \
             VALUES ($1, $2, now() + make_interval(secs => $3)) \
             ON CONFLICT (hash, owner) DO UPDATE SET pinned_until = EXCLUDED.pinned_until",
        )
        .bind(hash)
        .bind(owner)
        .bind(PIN_TTL_SECS)
        .execute(&mut *tx)
        .await
        .map_err(pg_err)?;
        tx.commit().await.map_err(pg_err)
    }

    async fn release_pins(&self, owner: &str) -> Result<Vec<String>> {
        sqlx::query_scalar("DELETE FROM blob_pins WHERE owner = $1 RETURNING hash")
            .bind(owner)
            .fetch_all(&self.pool)
            .await
            .map_err(pg_err)
    }

    async fn delete_blobs_if_unused(
        &self,
        hashes: Vec<String>,
        blobs: Arc<dyn BlobStore>,
    ) -> Result<usize> {
        let mut deleted = 0;
        for hash in hashes {
            let mut tx = self.begin().await?;
            sqlx::query("SELECT pg_advisory_xact_lock(hashtextextended($1, 0))")
                .bind(&hash)
                .execute(&mut *tx)
                .await
                .map_err(pg_err)?;
            let held: bool = sqlx::query_scalar(
                "SELECT EXISTS (SELECT 1 FROM blob_refs WHERE hash = $1) \
                 OR EXISTS (SELECT 1 FROM blob_pins WHERE hash = $1 AND pinned_until > now())",
            )
            .bind(&hash)
            .fetch_one(&mut *tx)
            .await
            .map_err(pg_err)?;
            if held {
                continue;
            }
            // Deleted while the lock is held: a writer pinning this hash waits for our commit,
            // then writes the blob again.
            let (b, h) = (blobs.clone(), hash.clone());
            crate::jobs::blocking(move || b.delete(&h)).await?;
            sqlx::query("DELETE FROM blob_pins WHERE hash = $1")
                .bind(&hash)
                .execute(&mut *tx)
                .await
                .map_err(pg_err)?;
            tx.commit().await.map_err(pg_err)?;
            deleted += 1;
        }
        Ok(deleted)
    }

    async fn referenced_blobs(&self) -> Result<HashSet<String>> {
        let v: Vec<String> = sqlx::query_scalar("SELECT DISTINCT hash FROM blob_refs")
            .fetch_all(&self.pool)
            .await
            .map_err(pg_err)?;
        Ok(v.into_iter().collect())
    }

    async fn ping(&self) -> Result<()> {
        sqlx::query("SELECT 1").execute(&self.pool).await.map_err(pg_err)?;
        Ok(())
    }

    fn subscribe(&self) -> broadcast::Receiver<String> {
        self.changes.subscribe()
    }

    async fn add_tiles(&self, claim: &Claim, tiles: Vec<TileRecord>) -> Result<bool> {
        let mut tx = self.begin().await?;
        let Some(current) = Self::select_for_update(&mut tx, &claim.id).await? else {
            return Ok(false);
        };
        if current.status != Status::Running
            || current.attempts != claim.attempt
            || current.worker.as_deref() != Some(claim.worker.as_str())
        {
            return Ok(false);
        }
        let hashes: Vec<String> = tiles.iter().map(|t| t.input_blob.clone()).collect();
        for t in &tiles {
            sqlx::query(
                "INSERT INTO tiles (bake_id, idx, status, record, attempt) \
                 VALUES ($1, $2, 'queued', $3, 0) ON CONFLICT (bake_id, idx) DO NOTHING",
            )
            .bind(&t.bake_id)
            .bind(t.index as i32)
            .bind(serde_json::to_value(t).map_err(json_err)?)
            .execute(&mut *tx)
            .await
            .map_err(pg_err)?;
        }
        add_refs(&mut tx, &claim.id, &hashes, &claim.owner()).await?;
        notify(&mut tx, &claim.id).await?;
        tx.commit().await.map_err(pg_err)?;
        Ok(true)
    }

    async fn tiles(&self, id: &str) -> Result<Vec<TileRecord>> {
        let rows = sqlx::query(&format!(
            "SELECT {TILE_COLUMNS} FROM tiles WHERE bake_id = $1 ORDER BY idx"
        ))
        .bind(id)
        .fetch_all(&self.pool)
        .await
        .map_err(pg_err)?;
        rows.iter().map(tile_of).collect()
    }

    async fn claim_tile(&self, worker: &str, lease: Duration) -> Result<Option<TileClaim>> {
        let mut tx = self.begin().await?;
        let row = sqlx::query(&format!(
            "UPDATE tiles SET status = 'running', worker = $1, attempt = attempt + 1, \
             lease_until = now() + make_interval(secs => $2), cancel_requested = false \
             WHERE (bake_id, idx) = (SELECT t.bake_id, t.idx FROM tiles t \
                 JOIN bakes b ON b.id = t.bake_id \
                 WHERE t.status = 'queued' AND b.status = 'running' AND NOT b.cancel_requested \
                 ORDER BY t.bake_id, t.idx LIMIT 1 FOR UPDATE OF t SKIP LOCKED) \
             RETURNING {TILE_COLUMNS}"
        ))
        .bind(worker)
        .bind(lease.as_secs_f64())
        .fetch_optional(&mut *tx)
        .await
        .map_err(pg_err)?;
        let Some(row) = row else {
            tx.commit().await.map_err(pg_err)?;
            return Ok(None);
        };
        let t = tile_of(&row)?;
        notify(&mut tx, &t.bake_id).await?;
        tx.commit().await.map_err(pg_err)?;
        Ok(Some(TileClaim {
            bake_id: t.bake_id.clone(),
            index: t.index,
            attempt: t.attempts,
            worker: worker.to_owned(),
            tile: t,
        }))
    }

    async fn heartbeat_tile(&self, claim: &TileClaim, lease: Duration) -> Result<Beat> {
        let cancel: Option<bool> = sqlx::query_scalar(
            "UPDATE tiles t SET lease_until = now() + make_interval(secs => $5) \
             WHERE bake_id = $1 AND idx = $2 AND attempt = $3 AND worker = $4 \
             AND status = 'running' \
             RETURNING t.cancel_requested OR NOT EXISTS (SELECT 1 FROM bakes b \
                 WHERE b.id = t.bake_id AND b.status = 'running' AND NOT b.cancel_requested)",
        )
        .bind(&claim.bake_id)
        .bind(claim.index as i32)
        .bind(claim.attempt as i32)
        .bind(&claim.worker)
        .bind(lease.as_secs_f64())
        .fetch_optional(&self.pool)
        .await
        .map_err(pg_err)?;
        Ok(match cancel {
            Some(cancel) => Beat::Alive { cancel },
            None => Beat::Lost,
        })
    }

    async fn complete_tile(
        &self,
        claim: &TileClaim,
        outcome: TileOutcome,
        max_attempts: u32,
    ) -> Result<bool> {
        let mut tx = self.begin().await?;
        let row = sqlx::query(&format!(
            "SELECT {TILE_COLUMNS} FROM tiles WHERE bake_id = $1 AND idx = $2 FOR UPDATE"
        ))
        .bind(&claim.bake_id)
        .bind(claim.index as i32)
        .fetch_optional(&mut *tx)
        .await
        .map_err(pg_err)?;
        let Some(current) = row.as_ref().map(tile_of).transpose()? else { return Ok(false) };
        if current.status != Status::Running
            || current.attempts != claim.attempt
            || current.worker.as_deref() != Some(claim.worker.as_str())
        {
            return Ok(false);
        }
        let t = outcome.apply(current, claim, max_attempts);
        write_tile(&mut tx, &t).await?;
        let results: Vec<String> = t.results.values().cloned().collect();
        add_refs(&mut tx, &t.bake_id, &results, &claim.owner()).await?;
        notify(&mut tx, &t.bake_id).await?;
        tx.commit().await.map_err(pg_err)?;
        Ok(true)
    }

    async fn cancel_tiles(&self, id: &str) -> Result<()> {
        let mut tx = self.begin().await?;
        cancel_tiles_tx(&mut tx, id).await?;
        notify(&mut tx, id).await?;
        tx.commit().await.map_err(pg_err)
    }

    async fn remove_tiles(&self, id: &str) -> Result<Vec<String>> {
        let mut tx = self.begin().await?;
        let rows =
            sqlx::query(&format!("DELETE FROM tiles WHERE bake_id = $1 RETURNING {TILE_COLUMNS}"))
                .bind(id)
                .fetch_all(&mut *tx)
                .await
                .map_err(pg_err)?;
        let mut hashes: Vec<String> = Vec::new();
        for row in &rows {
            hashes.extend(tile_of(row)?.blobs().map(str::to_owned));
        }
        // The bake's own blobs (input, results) stay referenced.
        let own: HashSet<String> = match Self::select_for_update(&mut tx, id).await? {
            Some(r) => r.blobs().map(str::to_owned).collect(),
            None => HashSet::new(),
        };
        hashes.retain(|h| !own.contains(h));
        sqlx::query("DELETE FROM blob_refs WHERE bake_id = $1 AND hash = ANY($2)")
            .bind(id)
            .bind(&hashes)
            .execute(&mut *tx)
            .await
            .map_err(pg_err)?;
        tx.commit().await.map_err(pg_err)?;
        Ok(hashes)
    }
}
