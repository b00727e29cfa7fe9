//! The record model: what is persisted about a bake and about each tile of a tiled bake,
//! whichever backend keeps it, and the listing types. Every other part of `jobs` (the
//! repositories, the coordination, the plan's consumers) imports these; this module imports
//! only the pure tile plan, so no import runs back.

use crate::error::{Error, Result};
use crate::heightmap::InputInfo;
use crate::jobs::tiles::{TileGeom, TilePlan};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
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
    pub tiles: Option<TileCount>,
}

/// Progress as a worker reports it: the stage and the fraction of that stage done.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LiveProgress {
    pub stage: crate::progress::Stage,
    pub fraction: f64,
    /// A tiled bake's tiles done out of total (SPEC §7.1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tiles: Option<TileCount>,
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

/// What the split step hands every tile beside its input: the whole map's values the kernels
/// need so that a tile computes what the untiled bake computes (SPEC §7.1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileContext {
    pub plan: TilePlan,
    /// The whole map's scaled height range (lo, hi), in texels.
    pub range: (f32, f32),
    /// The radius resolved on the whole map, and why.
    pub radius: u32,
    pub radius_reason: String,
    /// The input as the split decoded it (reported with the bake).
    #[serde(default)]
    pub input: Option<crate::heightmap::InputInfo>,
    /// How long the split took, ms (the bake's `decode` timing).
    #[serde(default)]
    pub split_ms: f64,
    /// The whole map's decode statistics (`heightmap::stream::MapStats::to_json`: hole fill,
    /// nodata, georeferencing), which turn a tile's raw heights into the whole decode's crop;
    /// null when the tile heights are stored already filled.
    #[serde(default)]
    pub stats: serde_json::Value,
}

/// One tile as the repository keeps it: a unit of work with its own status, attempt (the
/// fencing number of its claims) and results.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileRecord {
    pub bake_id: String,
    pub index: u32,
    pub status: Status,
    /// How many times a worker claimed this tile; the fencing number of the current claim.
    pub attempts: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub worker: Option<String>,
    /// Blob of the window's heights (written by the split step).
    pub input_blob: String,
    /// The tile's geometry and the whole map's context, as the split step wrote them.
    pub context: TileContext,
    /// Result name → blob hash, once succeeded.
    #[serde(default)]
    pub results: BTreeMap<String, String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<BakeFailure>,
}

impl TileRecord {
    /// A queued tile.
    pub fn new(bake_id: &str, index: u32, input_blob: String, context: TileContext) -> Self {
        TileRecord {
            bake_id: bake_id.to_owned(),
            index,
            status: Status::Queued,
            attempts: 0,
            worker: None,
            input_blob,
            context,
            results: BTreeMap::new(),
            error: None,
        }
    }

    /// The tile's geometry.
    pub fn geom(&self) -> TileGeom {
        self.context.plan.tile(self.index)
    }

    /// Every blob this tile references.
    pub fn blobs(&self) -> impl Iterator<Item = &str> {
        std::iter::once(self.input_blob.as_str()).chain(self.results.values().map(String::as_str))
    }
}

/// How many tiles of a bake are done, out of how many (the bake resource's `tiles`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileCount {
    pub done: u32,
    pub total: u32,
}

/// A worker's hold on a running tile; `attempt` is the fencing number.
#[derive(Debug, Clone)]
pub struct TileClaim {
    pub bake_id: String,
    pub index: u32,
    pub attempt: u32,
    pub worker: String,
    pub tile: TileRecord,
}

impl TileClaim {
    /// Who owns the blobs this claim writes until its tile references them.
    pub fn owner(&self) -> String {
        format!("{}/{}/tile{}/{}", self.worker, self.bake_id, self.index, self.attempt)
    }
}

/// How a claimed tile ended.
#[derive(Debug, Clone)]
pub enum TileOutcome {
    /// Its results (name → blob).
    Succeeded(BTreeMap<String, String>),
    /// Retried while attempts remain (`max_attempts`), then `failed`.
    Failed(BakeFailure),
    Canceled,
    /// Handed back unfinished (shutdown, lease lost to the store): `queued` again.
    Released,
}

impl TileOutcome {
    /// The tile `current` (claimed by `claim`) becomes with this outcome, and the blobs it now
    /// references. Both backends apply it.
    pub fn apply(self, current: TileRecord, claim: &TileClaim, max_attempts: u32) -> TileRecord {
        let mut t = current;
        match self {
            TileOutcome::Succeeded(results) => {
                t.status = Status::Succeeded;
                t.results = results;
                t.error = None;
            }
            TileOutcome::Failed(f) if claim.attempt < max_attempts => {
                t.status = Status::Queued;
                t.error = Some(f);
                t.worker = None;
            }
            TileOutcome::Failed(f) => {
                t.status = Status::Failed;
                t.error = Some(f);
            }
            TileOutcome::Canceled => t.status = Status::Canceled,
            TileOutcome::Released => {
                t.status = Status::Queued;
                t.worker = None;
            }
        }
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::Edge;

    #[test]
    fn failed_tiles_are_retried_until_the_last_attempt() {
        let plan = TilePlan::new(8, 8, 4, 2, Edge::Wrap).unwrap();
        let ctx = TileContext {
            plan,
            range: (0.0, 1.0),
            radius: 1,
            radius_reason: String::new(),
            input: None,
            split_ms: 0.0,
            stats: serde_json::Value::Null,
        };
        let mut t = TileRecord::new("b", 1, "h".into(), ctx);
        t.status = Status::Running;
        let claim = |attempt| TileClaim {
            bake_id: "b".into(),
            index: 1,
            attempt,
            worker: "w".into(),
            tile: t.clone(),
        };
        let f = BakeFailure { code: "x".into(), message: "y".into() };
        let again = TileOutcome::Failed(f.clone()).apply(t.clone(), &claim(2), 3);
        assert_eq!(again.status, Status::Queued);
        let failed = TileOutcome::Failed(f).apply(t.clone(), &claim(3), 3);
        assert_eq!(failed.status, Status::Failed);
    }
}
