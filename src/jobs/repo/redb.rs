//! The embedded repository's record table: bake records and the deduplication index in one redb
//! file in the data directory ([`RedbStore`]). A commit is durable before the caller answers,
//! which is what lets a restart re-queue every bake that was accepted. The job lifecycle
//! (claims, leases, cancel, changes) is [`super::JobRepo`]'s; [`super::EmbeddedRepo`] is built
//! on this table.

use crate::error::{Error, Result};
use crate::jobs::record::{BakeRecord, ListQuery, Listing, Page, Status};
use redb::{ReadableDatabase, ReadableTable, TableDefinition};
use std::path::Path;

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

const BAKES: TableDefinition<&str, &[u8]> = TableDefinition::new("bakes");
const DEDUP: TableDefinition<&str, &str> = TableDefinition::new("dedup");

fn db_err(e: impl std::fmt::Display) -> Error {
    Error::Internal(format!("bake store: {e}"))
}

/// A redb failure as the bake's error: a full disk under `bakes.redb` is
/// [`Error::StorageFull`] (507, retried once space is freed), anything else internal.
fn redb_err<E: std::error::Error + 'static>(e: E) -> Error {
    let mut source: Option<&(dyn std::error::Error + 'static)> = Some(&e);
    while let Some(s) = source {
        if let Some(io) = s.downcast_ref::<std::io::Error>() {
            if crate::error::is_storage_full(io) {
                return Error::StorageFull {
                    store: "the bake records' disk",
                    cause: e.to_string(),
                };
            }
        }
        source = s.source();
    }
    // Some of redb's errors carry the I/O error only in their text.
    if e.to_string().contains("(os error 28)") {
        return Error::StorageFull { store: "the bake records' disk", cause: e.to_string() };
    }
    db_err(e)
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
        let tx = self.db.begin_write().map_err(redb_err)?;
        {
            let mut bakes = tx.open_table(BAKES).map_err(db_err)?;
            bakes.insert(rec.id.as_str(), bytes.as_slice()).map_err(redb_err)?;
            let mut dedup = tx.open_table(DEDUP).map_err(db_err)?;
            dedup.insert(rec.dedup_key.as_str(), rec.id.as_str()).map_err(redb_err)?;
        }
        tx.commit().map_err(redb_err)
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
        let tx = self.db.begin_write().map_err(redb_err)?;
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
        tx.commit().map_err(redb_err)?;
        Ok(existed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

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
}
