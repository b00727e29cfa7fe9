//! HTTP handlers, one file per resource: validate, call the jobs core, answer. No pixel
//! arithmetic here; the only CPU work a handler starts runs off the async workers: the cube map
//! on a blocking thread, previews and on-request encodes on the preview pool.
//!
//! This module holds what several resources share (query parsing, the bake resource, loading a
//! bake, problem mapping); [`bakes`], [`events`], [`results`], [`cubemap`], [`shaders`], [`previews`]
//! and [`ops`] hold the handlers, re-exported here for the router.

// `Problem` is the error answer itself, built at most once per request on the way out; boxing it
// would add an allocation to every error path for no gain.
#![allow(clippy::result_large_err)]

use crate::encode::exr::ExrPrecision;
use crate::encode::{CubeFormats, Formats, TexturePrecision};
use crate::error::Error;
use crate::heightmap;
use crate::jobs::record::{self, now_ms, BakeRecord, Status};
use crate::jobs::repo::{CancelResult, Submitted};
use crate::params::BakeParams;
use crate::pipeline::job::{self, blocking, params_of};
use crate::preview::{self, PreviewParams};
use crate::progress::{Progress, Stage};
use crate::service::metrics::Render;
use crate::service::problem::Problem;
use crate::service::{upload, AppState};
use axum::body::Body;
use axum::extract::{FromRequest, MatchedPath, Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::Json;
use futures_util::stream::Stream;
use serde_json::Value;
use std::collections::HashMap;
use std::convert::Infallible;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::time::Duration;

pub mod bakes;
pub mod cubemap;
pub mod events;
pub mod ops;
pub mod previews;
pub mod results;
pub mod shaders;

pub use bakes::*;
pub use cubemap::*;
pub use events::*;
pub use ops::*;
pub use previews::*;
pub use results::*;
pub use shaders::*;

type Answer = Result<Response, Problem>;

/// The openapi document this server implements.
pub const OPENAPI_YAML: &str = include_str!("../../../openapi.yaml");

// ---------------------------------------------------------------------------------------------
// Small helpers

fn store_err(e: Error) -> Problem {
    Problem::from(e)
}

/// Parses query pairs, rejecting names not in `allowed` and repeated names (422 naming them).
fn query_map(
    pairs: Vec<(String, String)>,
    allowed: &[&str],
) -> Result<HashMap<String, String>, Problem> {
    let mut out = HashMap::new();
    for (k, v) in pairs {
        if !allowed.contains(&k.as_str()) {
            return Err(Problem::param(
                k,
                format!(
                    "unknown query parameter; this route accepts {}",
                    if allowed.is_empty() { "none".to_owned() } else { allowed.join(", ") }
                ),
            ));
        }
        if out.insert(k.clone(), v).is_some() {
            return Err(Problem::param(k, "given more than once"));
        }
    }
    Ok(out)
}

/// Query pairs of a GET of an immutable result: the keys in `known` are parsed (each at most
/// once), any other key is ignored, so a cache buster (`?v=123`) does not turn a download into
/// a 422.
fn known_query(
    pairs: Vec<(String, String)>,
    known: &[&str],
) -> Result<HashMap<String, String>, Problem> {
    let mut out = HashMap::new();
    for (k, v) in pairs {
        if known.contains(&k.as_str()) && out.insert(k.clone(), v).is_some() {
            return Err(Problem::param(k, "given more than once"));
        }
    }
    Ok(out)
}

/// RFC 3339 UTC time of Unix milliseconds (civil-from-days, Howard Hinnant's algorithm).
pub fn rfc3339(ms: u64) -> String {
    let secs = ms / 1000;
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        (rem % 3600) / 60,
        rem % 60,
        ms % 1000
    )
}

/// Overall progress in [0, 1] from a stage and its fraction (weights: decode 5%, bake 85%,
/// encode 7%, store 3%).
fn overall(stage: Stage, f: f64) -> f64 {
    let (start, span) = match stage {
        Stage::Queued => (0.0, 0.0),
        Stage::Decode => (0.0, 0.05),
        Stage::Bake | Stage::Fourier => (0.05, 0.85),
        Stage::Encode => (0.90, 0.07),
        Stage::Store => (0.97, 0.03),
        Stage::Done => (1.0, 0.0),
    };
    (start + span * f).clamp(0.0, 1.0)
}

/// A bake's progress as the API reports it: overall fraction and stage.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct ProgressView {
    pub fraction: f64,
    pub stage: Stage,
}

/// The resolved parameters, with the radius the bake used once it is known.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ParamsView {
    #[serde(flatten)]
    pub params: Option<BakeParams>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resolved_radius: Option<record::RadiusInfo>,
}

/// What the API says of a bake's input (the header's view until the bake decoded it).
#[derive(Debug, Clone, serde::Serialize)]
pub struct InputView {
    pub width: u32,
    pub height: u32,
    pub format: String,
    pub color: Option<String>,
    pub bit_depth: Option<u8>,
    pub float: Option<bool>,
    pub content_hash: String,
    pub bytes: u64,
}

/// The bake resource (SPEC §5; `Bake` in openapi.yaml).
#[derive(Debug, Clone, serde::Serialize)]
pub struct BakeResource {
    pub id: String,
    pub status: Status,
    pub progress: ProgressView,
    pub params: ParamsView,
    pub input: InputView,
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    pub expires_at: Option<String>,
    pub timings_ms: Option<record::Timings>,
    pub error: Option<record::BakeFailure>,
    pub attempts: u32,
    pub worker: Option<String>,
    /// Result formats: what the submission asked to encode with the bake, and what is stored
    /// (the rest is encoded on its first request).
    pub formats: FormatsView,
    /// The input's georeferencing (a GeoTIFF DEM: model, EPSG code or citation, transform,
    /// cell size, units), null for a plain image.
    pub georeferencing: Option<Value>,
    /// A tiled bake's tiles done out of total (SPEC §7.1); absent for an untiled bake.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tiles: Option<crate::jobs::record::TileCount>,
    pub links: std::collections::BTreeMap<String, String>,
}

/// The `formats` of a bake resource.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FormatsView {
    /// The submission's `formats` (with `half` when `exr_precision=half`).
    pub requested: String,
    /// Result files stored so far (`horizon_0.png8`, `horizon_0.half.exr`, `horizon.ktx2`,
    /// `fourier_0.png`, …).
    pub stored: Vec<String>,
}

impl BakeResource {
    /// The resource of `rec`, with its live progress when it is running.
    pub fn of(rec: &BakeRecord, retention_ms: u64) -> Self {
        let status = rec.status;
        let progress = match (rec.progress, status) {
            (Some(p), Status::Running) => {
                ProgressView { fraction: overall(p.stage, p.fraction), stage: p.stage }
            }
            (None, Status::Running) => ProgressView { fraction: 0.0, stage: Stage::Decode },
            (_, Status::Succeeded) => ProgressView { fraction: 1.0, stage: Stage::Done },
            // A canceled bake keeps the fraction it had reached (and the stage it stopped in).
            (_, Status::Canceled) if rec.stopped_at.is_some() => {
                let p = rec.stopped_at.unwrap_or(record::LiveProgress {
                    stage: Stage::Queued,
                    fraction: 0.0,
                    tiles: None,
                });
                ProgressView { fraction: overall(p.stage, p.fraction), stage: p.stage }
            }
            (_, s) if s.is_terminal() => ProgressView { fraction: 0.0, stage: Stage::Done },
            _ => ProgressView { fraction: 0.0, stage: Stage::Queued },
        };
        let input = match &rec.input {
            Some(i) => InputView {
                width: i.width,
                height: i.height,
                format: i.format.clone(),
                color: Some(i.color.clone()),
                bit_depth: Some(i.bit_depth),
                float: Some(i.float),
                content_hash: i.content_hash.clone(),
                bytes: rec.input_bytes,
            },
            None => InputView {
                width: rec.width,
                height: rec.height,
                format: rec.input_format.clone(),
                color: None,
                bit_depth: None,
                float: None,
                content_hash: rec.input_blob.clone(),
                bytes: rec.input_bytes,
            },
        };
        let base = format!("/v1/bakes/{}", rec.id);
        let mut links = std::collections::BTreeMap::new();
        links.insert("self".to_owned(), base.clone());
        links.insert("events".to_owned(), format!("{base}/events"));
        if status == Status::Succeeded {
            for k in 0..3 {
                if rec.results.contains_key(&format!("fourier_{k}.png")) {
                    links.insert(format!("fourier_{k}"), format!("{base}/fourier/{k}"));
                }
            }
            let outputs = params_of(rec).ok().map(|p| p.outputs);
            // The terrain products (SPEC §3.7): the GeoTIFFs; the shadow and the profile are
            // asked with their own query (sun, point), so they have no fixed link.
            if outputs.is_some_and(|o| o.angles) {
                links.insert("angles".to_owned(), format!("{base}/angles"));
            }
            if outputs.is_some_and(|o| o.svf) {
                links.insert("svf".to_owned(), format!("{base}/svf"));
            }
            if outputs.is_some_and(|o| o.horizon_distance) {
                links.insert("horizon_distance".to_owned(), format!("{base}/horizon_distance"));
            }
            if outputs.is_some_and(|o| o.openness) {
                for sign in ["openness_positive", "openness_negative"] {
                    links.insert(sign.to_owned(), format!("{base}/{sign}"));
                }
            }
            for (on, name) in [
                (outputs.is_some_and(|o| o.sun_hours), "sun_hours"),
                (outputs.is_some_and(|o| o.insolation), "insolation"),
            ] {
                if on {
                    links.insert(name.to_owned(), format!("{base}/{name}"));
                }
            }
            // The surface maps (SPEC §3.8).
            for (on, name) in [
                (outputs.is_some_and(|o| o.normal), "normal"),
                (outputs.is_some_and(|o| o.ao), "ao"),
                (outputs.is_some_and(|o| o.bent_normal), "bent_normal"),
            ] {
                if on {
                    links.insert(name.to_owned(), format!("{base}/{name}"));
                }
            }
            if outputs.is_some_and(|o| o.horizon) {
                for (k, path) in [
                    ("horizon_0", "/horizon/0"),
                    ("horizon_1", "/horizon/1"),
                    ("horizon_ktx2", "/horizon.ktx2"),
                    ("horizon_dds", "/horizon.dds"),
                ] {
                    links.insert(k.to_owned(), format!("{base}{path}"));
                }
            }
        }
        BakeResource {
            id: rec.id.clone(),
            status,
            progress,
            params: ParamsView { params: params_of(rec).ok(), resolved_radius: rec.radius.clone() },
            input,
            created_at: rfc3339(rec.created_ms),
            started_at: rec.started_ms.map(rfc3339),
            finished_at: rec.finished_ms.map(rfc3339),
            expires_at: rec.expires_ms(retention_ms).map(rfc3339),
            timings_ms: rec.timings_ms.clone(),
            error: rec.error.clone(),
            attempts: rec.attempts,
            worker: rec.worker.clone(),
            formats: FormatsView {
                requested: rec.formats.clone().unwrap_or_else(|| "png8".into()),
                stored: rec.results.keys().cloned().collect(),
            },
            georeferencing: rec.georeferencing.clone(),
            tiles: match (rec.progress, status) {
                (Some(p), Status::Running) => p.tiles.or(rec.tiles),
                _ => rec.tiles,
            },
            links,
        }
    }
}

/// The bake resource (SPEC §5) of a record, as JSON.
pub fn resource(st: &AppState, rec: &BakeRecord) -> Value {
    let r = BakeResource::of(rec, st.0.config.retention.as_millis() as u64);
    let mut v = serde_json::to_value(r).unwrap_or(Value::Null);
    // Results a download started encoding in the background, with their progress.
    let encoding: Vec<Value> = results::encoding_of(st, &rec.id)
        .iter()
        .map(|j| serde_json::json!({"result": j.result, "fraction": j.fraction()}))
        .collect();
    if let Some(f) = v.get_mut("formats").and_then(Value::as_object_mut) {
        f.insert("encoding".to_owned(), Value::Array(encoding));
    }
    v
}

async fn load(st: &AppState, id: &str) -> Result<BakeRecord, Problem> {
    if id.is_empty() || id.len() > 64 {
        return Err(Problem::bake_not_found(id));
    }
    st.0.jobs.get(id).await.map_err(store_err)?.ok_or_else(|| Problem::bake_not_found(id))
}

fn json_response(status: StatusCode, body: &Value) -> Response {
    (status, Json(body)).into_response()
}

fn new_id() -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let mut h = blake3::Hasher::new();
    h.update(&n.to_le_bytes());
    h.update(&nanos.to_le_bytes());
    h.update(&std::process::id().to_le_bytes());
    let noise = h.finalize();
    format!("{:012x}{}", now_ms() & 0xffff_ffff_ffff, &noise.to_hex()[..8])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rfc3339_known_instants() {
        assert_eq!(rfc3339(0), "1970-01-01T00:00:00.000Z");
        assert_eq!(rfc3339(951_782_400_123), "2000-02-29T00:00:00.123Z");
        assert_eq!(rfc3339(1_795_000_000_000), "2026-11-18T11:06:40.000Z");
    }

    #[test]
    fn etag_lists_and_wildcards() {
        let mut h = HeaderMap::new();
        h.insert(header::IF_NONE_MATCH, HeaderValue::from_static("\"a\", W/\"b\""));
        assert!(etag_matches(&h, "\"b\""));
        assert!(!etag_matches(&h, "\"c\""));
        h.insert(header::IF_NONE_MATCH, HeaderValue::from_static("*"));
        assert!(etag_matches(&h, "\"c\""));
    }

    #[test]
    fn overall_progress_is_monotonic_across_stages() {
        let seq = [
            overall(Stage::Queued, 0.0),
            overall(Stage::Decode, 1.0),
            overall(Stage::Bake, 0.5),
            overall(Stage::Bake, 1.0),
            overall(Stage::Encode, 1.0),
            overall(Stage::Store, 1.0),
            overall(Stage::Done, 1.0),
        ];
        assert!(seq.windows(2).all(|w| w[0] <= w[1]), "{seq:?}");
        assert_eq!(seq[6], 1.0);
    }
}
