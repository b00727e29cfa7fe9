//! HTTP handlers: validate, call the store or the queue, answer. No pixel arithmetic here; the
//! only CPU work a handler starts runs off the async workers: the cube map on a blocking thread,
//! a preview on the bake pool.

// `Problem` is the error answer itself, built at most once per request on the way out; boxing it
// would add an allocation to every error path for no gain.
#![allow(clippy::result_large_err)]

use crate::encode::CubeFormats;
use crate::error::Error;
use crate::heightmap;
use crate::jobs::repo::{CancelResult, Submitted};
use crate::params::BakeParams;
use crate::preview::{self, PreviewParams};
use crate::progress::{Progress, Stage};
use crate::service::problem::Problem;
use crate::service::store::{self, now_ms, BakeRecord, Status};
use crate::service::worker::{self, blocking, params_of};
use crate::service::{upload, AppState};
use axum::body::Body;
use axum::extract::{FromRequest, MatchedPath, Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::Json;
use futures_util::stream::Stream;
use serde_json::{json, Value};
use std::collections::HashMap;
use std::convert::Infallible;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Arc;
use std::time::Duration;

type Answer = Result<Response, Problem>;

/// The openapi document this server implements.
pub const OPENAPI_YAML: &str = include_str!("../../openapi.yaml");

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

fn stage_name(s: Stage) -> Value {
    serde_json::to_value(s).unwrap_or(Value::Null)
}

/// The bake resource (SPEC §5) for a record, with live progress when it is in flight.
pub fn resource(st: &AppState, rec: &BakeRecord) -> Value {
    let status = rec.status;
    let progress = match (rec.progress, status) {
        (Some(p), Status::Running) => {
            json!({"fraction": overall(p.stage, p.fraction), "stage": stage_name(p.stage)})
        }
        (None, Status::Running) => json!({"fraction": 0.0, "stage": "decode"}),
        (_, Status::Succeeded) => json!({"fraction": 1.0, "stage": "done"}),
        (_, s) if s.is_terminal() => json!({"fraction": 0.0, "stage": "done"}),
        _ => json!({"fraction": 0.0, "stage": "queued"}),
    };
    let mut params =
        params_of(rec).ok().and_then(|p| serde_json::to_value(p).ok()).unwrap_or_else(|| json!({}));
    if let (Some(obj), Some(r)) = (params.as_object_mut(), &rec.radius) {
        obj.insert("resolved_radius".into(), json!({"texels": r.texels, "reason": r.reason}));
    }
    let input = match &rec.input {
        Some(i) => json!({
            "width": i.width, "height": i.height, "format": i.format, "color": i.color,
            "bit_depth": i.bit_depth, "float": i.float, "content_hash": i.content_hash,
            "bytes": rec.input_bytes,
        }),
        None => json!({
            "width": rec.width, "height": rec.height, "format": rec.input_format,
            "color": null, "bit_depth": null, "float": null, "content_hash": rec.input_blob,
            "bytes": rec.input_bytes,
        }),
    };
    let base = format!("/v1/bakes/{}", rec.id);
    let mut links = json!({"self": base, "events": format!("{base}/events")});
    if status == Status::Succeeded {
        if let Some(obj) = links.as_object_mut() {
            for k in 0..3 {
                if rec.results.contains_key(&format!("fourier_{k}.png")) {
                    obj.insert(format!("fourier_{k}"), json!(format!("{base}/fourier/{k}")));
                }
            }
        }
    }
    if status == Status::Succeeded && rec.results.contains_key("horizon_0.png8") {
        if let Some(obj) = links.as_object_mut() {
            obj.insert("horizon_0".into(), json!(format!("{base}/horizon/0")));
            obj.insert("horizon_1".into(), json!(format!("{base}/horizon/1")));
            obj.insert("horizon_ktx2".into(), json!(format!("{base}/horizon.ktx2")));
            obj.insert("horizon_dds".into(), json!(format!("{base}/horizon.dds")));
        }
    }
    json!({
        "id": rec.id,
        "status": status.as_str(),
        "progress": progress,
        "params": params,
        "input": input,
        "created_at": rfc3339(rec.created_ms),
        "started_at": rec.started_ms.map(rfc3339),
        "finished_at": rec.finished_ms.map(rfc3339),
        "expires_at": rec.expires_ms(st.0.config.retention.as_millis() as u64).map(rfc3339),
        "timings_ms": rec.timings_ms,
        "error": rec.error,
        "attempts": rec.attempts,
        "worker": rec.worker,
        "links": links,
    })
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

// ---------------------------------------------------------------------------------------------
// Submission

/// Media types accepted as a raw-body upload (the bytes are sniffed anyway).
const RAW_TYPES: &[&str] =
    &["image/png", "image/tiff", "image/x-exr", "image/exr", "application/octet-stream"];

fn body_error(e: &(dyn std::error::Error + 'static), timeout: Duration) -> Problem {
    match upload::fault(e) {
        upload::BodyFault::TooLarge => Problem::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "payload_too_large",
            "the request body is larger than the server accepts (max_body_bytes)",
        ),
        upload::BodyFault::TimedOut => Problem::new(
            StatusCode::REQUEST_TIMEOUT,
            "body_timeout",
            format!(
                "the request body stalled for {}s (body_timeout_secs); send it without pauses",
                timeout.as_secs()
            ),
        ),
        upload::BodyFault::Other => Problem::new(
            StatusCode::BAD_REQUEST,
            "bad_request",
            "the request body could not be read",
        ),
    }
}

/// The bake parameters of a query string, and the keys it gave.
fn query_params(uri: &axum::http::Uri) -> Result<(BakeParams, Vec<String>), Problem> {
    let pairs: Vec<(String, String)> = match Query::<Vec<(String, String)>>::try_from_uri(uri) {
        Ok(Query(p)) => p,
        Err(_) => return Err(Problem::param("query", "the query string is malformed")),
    };
    let params = BakeParams::from_pairs(pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .map_err(Problem::from)?;
    Ok((params, pairs.into_iter().map(|(k, _)| k).collect()))
}

/// Applies the keys of a multipart `params` JSON object on top of `base` (the query's). A key
/// given in both is refused (422 naming it), as a key given twice in the query or in the JSON is:
/// one rule everywhere, since which one "wins" would be a guess about what the client meant.
fn merge_json(base: BakeParams, query_keys: &[String], text: &[u8]) -> Result<BakeParams, Problem> {
    if text.iter().all(u8::is_ascii_whitespace) {
        return Ok(base);
    }
    let given = crate::params::json_object_pairs(text).map_err(Problem::from)?;
    let mut merged = base;
    for (k, v) in &given {
        if query_keys.iter().any(|q| q == k) {
            return Err(Problem::param(
                k.clone(),
                "given both in the query string and in the `params` part",
            ));
        }
        if let Some(text) = crate::params::json_value_text(k, v).map_err(Problem::from)? {
            merged.set(k, &text).map_err(Problem::from)?;
        }
    }
    Ok(merged)
}

async fn read_multipart(st: &AppState, req: Request) -> Result<(Vec<u8>, BakeParams), Problem> {
    let (query, query_keys) = query_params(req.uri())?;
    let timeout = st.0.config.body_timeout;
    let mut mp = axum::extract::Multipart::from_request(req, st).await.map_err(|e| {
        Problem::new(
            StatusCode::BAD_REQUEST,
            "bad_request",
            format!("malformed multipart body: {}", e.body_text()),
        )
    })?;
    let mut image: Option<Vec<u8>> = None;
    let mut params: Option<BakeParams> = None;
    loop {
        let field = match mp.next_field().await {
            Ok(Some(f)) => f,
            Ok(None) => break,
            Err(e) => return Err(multipart_error(&e, timeout)),
        };
        let name = field.name().unwrap_or("").to_owned();
        match name.as_str() {
            "heightmap" => {
                if image.is_some() {
                    return Err(Problem::param("heightmap", "given more than once"));
                }
                let bytes = field.bytes().await.map_err(|e| multipart_error(&e, timeout))?;
                image = Some(bytes.to_vec());
            }
            "params" => {
                if params.is_some() {
                    return Err(Problem::param("params", "given more than once"));
                }
                let text = field.bytes().await.map_err(|e| multipart_error(&e, timeout))?;
                params = Some(merge_json(query.clone(), &query_keys, &text)?);
            }
            other => {
                return Err(Problem::param(
                    if other.is_empty() { "multipart" } else { other },
                    "unknown multipart part; expected `heightmap` and optionally `params`",
                ))
            }
        }
    }
    let image = image
        .ok_or_else(|| Problem::param("heightmap", "the multipart body has no `heightmap` part"))?;
    Ok((image, params.unwrap_or(query)))
}

fn multipart_error(e: &axum::extract::multipart::MultipartError, timeout: Duration) -> Problem {
    match upload::fault(e) {
        upload::BodyFault::Other if e.status() != StatusCode::PAYLOAD_TOO_LARGE => Problem::new(
            StatusCode::BAD_REQUEST,
            "bad_request",
            format!("malformed multipart body: {}", e.body_text()),
        ),
        upload::BodyFault::Other => body_error(&upload::BodyTooLarge(0), timeout),
        _ => body_error(e, timeout),
    }
}

async fn read_raw(st: &AppState, req: Request, ct: &str) -> Result<(Vec<u8>, BakeParams), Problem> {
    let mime = ct.split(';').next().unwrap_or("").trim().to_ascii_lowercase();
    let (params, _) = query_params(req.uri())?;
    let timeout = st.0.config.body_timeout;
    let bytes = axum::body::to_bytes(req.into_body(), usize::MAX)
        .await
        .map_err(|e| body_error(&e, timeout))?;
    // Checked after the body is read, so the client gets this answer rather than a reset.
    if !mime.is_empty() && !RAW_TYPES.contains(&mime.as_str()) {
        return Err(Error::Unsupported(format!(
            "Content-Type `{}` is not accepted; send image/png, image/tiff, image/x-exr or multipart/form-data",
            crate::service::problem::cap(&mime, 100)
        ))
        .into());
    }
    Ok((bytes.to_vec(), params))
}

fn retry_after(st: &AppState, waiting: u64) -> u64 {
    let mean = st.0.metrics.mean_duration().unwrap_or(1.0);
    let per_slot = waiting as f64 * mean / st.0.config.max_concurrent_bakes.max(1) as f64;
    per_slot.ceil().clamp(1.0, 300.0) as u64
}

/// `POST /v1/bakes`: multipart (`heightmap` + optional `params` JSON) or a raw image body with
/// the parameters in the query string.
pub async fn submit(State(st): State<AppState>, req: Request) -> Answer {
    if st.is_draining() {
        return Err(Problem::shutting_down());
    }
    let _upload =
        match tokio::time::timeout(st.0.config.upload_wait, st.0.uploads.clone().acquire_owned())
            .await
        {
            Ok(Ok(p)) => p,
            _ => {
                let mut p = Problem::new(
                    StatusCode::TOO_MANY_REQUESTS,
                    "too_many_uploads",
                    "too many uploads in progress; retry later",
                );
                p.retry_after = Some(1);
                return Err(p);
            }
        };
    let ct = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_owned();
    let (parts, body) = req.into_parts();
    let body = upload::guarded(body, st.0.config.max_body_bytes, st.0.config.body_timeout);
    let req = Request::from_parts(parts, body);
    let (bytes, params) = if ct.to_ascii_lowercase().starts_with("multipart/form-data") {
        read_multipart(&st, req).await?
    } else {
        read_raw(&st, req, &ct).await?
    };
    // Format and dimensions from the header against the limits, before any pixel allocation;
    // then, for float images only, the values (NaN, infinities, out of range), so such an input
    // is a 422 now rather than a failed bake later. Integer images cannot hold a bad value.
    let limits = st.0.config.limits;
    let channel = params.channel;
    let (bytes, (fmt, width, height)) = blocking(move || {
        let probed = heightmap::check_submission(&bytes, channel, &limits)?;
        Ok((bytes, probed))
    })
    .await?;
    let format = match fmt {
        image::ImageFormat::Png => "png",
        image::ImageFormat::Tiff => "tiff",
        _ => "exr",
    };
    let pairs: Vec<(String, String)> =
        params.to_pairs().into_iter().map(|(k, v)| (k.to_owned(), v)).collect();
    let (bytes, input_hash, key) = blocking(move || {
        let input_hash = blake3::hash(&bytes).to_hex().to_string();
        let mut h = blake3::Hasher::new();
        h.update(input_hash.as_bytes());
        for (k, v) in &pairs {
            h.update(b"\n");
            h.update(k.as_bytes());
            h.update(b"=");
            h.update(v.as_bytes());
        }
        Ok((bytes, input_hash, h.finalize().to_hex().to_string()))
    })
    .await
    .map_err(store_err)?;

    let rec = BakeRecord {
        id: new_id(),
        status: Status::Queued,
        dedup_key: key,
        params: params.to_pairs().into_iter().map(|(k, v)| (k.to_owned(), v)).collect(),
        input_blob: input_hash,
        input_format: format.into(),
        input_bytes: bytes.len() as u64,
        width,
        height,
        input: None,
        radius: None,
        created_ms: now_ms(),
        started_ms: None,
        finished_ms: None,
        requested_ms: None,
        timings_ms: None,
        error: None,
        results: Default::default(),
        attempts: 0,
        progress: None,
        worker: None,
    };
    let (status, rec) = match st.0.jobs.submit(bytes, rec).await.map_err(store_err)? {
        Submitted::Created(rec) => {
            st.0.metrics.submitted(false);
            (StatusCode::ACCEPTED, rec)
        }
        Submitted::Existing(rec) => {
            st.0.metrics.submitted(true);
            (StatusCode::OK, rec)
        }
        Submitted::QueueFull { waiting } => {
            return Err(Problem::queue_full(st.0.config.queue_capacity, retry_after(&st, waiting)))
        }
    };
    let mut res = json_response(status, &resource(&st, &rec));
    if let Ok(v) = HeaderValue::from_str(&format!("/v1/bakes/{}", rec.id)) {
        res.headers_mut().insert(header::LOCATION, v);
    }
    Ok(res)
}

// ---------------------------------------------------------------------------------------------
// Reading and managing bakes

/// `GET /v1/bakes?limit=&cursor=&status=&order=`: `status` is one status or a comma list,
/// `order` is `asc` (oldest first, the default) or `desc` (newest first); the answer carries
/// `total`, how many bakes match the filter in all.
pub async fn list(State(st): State<AppState>, Query(q): Query<Vec<(String, String)>>) -> Answer {
    let q = query_map(q, &["limit", "cursor", "status", "order"])?;
    let limit = match q.get("limit") {
        None => 50,
        Some(v) => match v.parse::<usize>() {
            Ok(n) if (1..=1000).contains(&n) => n,
            _ => {
                return Err(Problem::param(
                    "limit",
                    format!("`{v}` is not a whole number from 1 to 1000"),
                ))
            }
        },
    };
    let mut statuses = Vec::new();
    if let Some(list) = q.get("status") {
        for s in list.split(',') {
            let s = Status::parse(s.trim()).map_err(Problem::from)?;
            if !statuses.contains(&s) {
                statuses.push(s);
            }
        }
    }
    let newest_first = match q.get("order").map(String::as_str) {
        None | Some("asc") => false,
        Some("desc") => true,
        Some(v) => return Err(Problem::param("order", format!("`{v}` is not one of asc, desc"))),
    };
    let cursor = q.get("cursor").cloned();
    // One rule for every malformed cursor: a cursor is a bake id (20 lowercase hex digits), as
    // `next.cursor` returns it; a well-formed id of a removed bake still pages on after it.
    if let Some(c) = &cursor {
        if c.len() != 20 || !c.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)) {
            return Err(Problem::param("cursor", "not a cursor returned by this API"));
        }
    }
    let query = store::ListQuery { statuses: statuses.clone(), cursor, limit, newest_first };
    let page = st.0.jobs.list(&query).await.map_err(store_err)?;
    let items: Vec<Value> = page.items.iter().map(|r| resource(&st, r)).collect();
    let next = page.next.map(|c| {
        let mut link = format!("/v1/bakes?limit={limit}&cursor={c}");
        if !statuses.is_empty() {
            let names: Vec<&str> = statuses.iter().map(|s| s.as_str()).collect();
            link.push_str(&format!("&status={}", names.join(",")));
        }
        if newest_first {
            link.push_str("&order=desc");
        }
        json!({"cursor": c, "href": link})
    });
    Ok(json_response(StatusCode::OK, &json!({"items": items, "next": next, "total": page.total})))
}

/// `GET /v1/bakes/{id}`.
pub async fn get_bake(State(st): State<AppState>, Path(id): Path<String>) -> Answer {
    let rec = load(&st, &id).await?;
    Ok(json_response(StatusCode::OK, &resource(&st, &rec)))
}

/// `DELETE /v1/bakes/{id}`: cancels a queued bake (200, now `canceled`), asks a running one to
/// stop (202, it turns `canceled` within a band of rows), removes a finished one and its
/// results (204).
pub async fn delete_bake(State(st): State<AppState>, Path(id): Path<String>) -> Answer {
    if id.is_empty() || id.len() > 64 {
        return Err(Problem::bake_not_found(&id));
    }
    match st.0.jobs.cancel(&id).await.map_err(store_err)? {
        CancelResult::NotFound => Err(Problem::bake_not_found(&id)),
        CancelResult::Finished(_) => Ok(StatusCode::NO_CONTENT.into_response()),
        CancelResult::Canceled(rec) => Ok(json_response(StatusCode::OK, &resource(&st, &rec))),
        // Running: its worker records `canceled` when the kernel stops (within a band of rows
        // here, within a heartbeat on another machine).
        CancelResult::Requested(_) => {
            let rec = load(&st, &id).await?;
            Ok(json_response(StatusCode::ACCEPTED, &resource(&st, &rec)))
        }
    }
}

/// Removes finished bakes past their retention, then orphaned blobs (see
/// [`crate::jobs::Jobs::sweep`]); returns how many bakes were removed.
///
/// # Errors
/// Store failures.
pub async fn sweep(st: &AppState) -> crate::Result<usize> {
    st.0.jobs.sweep().await
}

// ---------------------------------------------------------------------------------------------
// Progress events

async fn snapshot(st: &AppState, id: &str) -> Option<(Status, Value)> {
    let rec = st.0.jobs.get(id).await.ok().flatten()?;
    let res = resource(st, &rec);
    let status = res.get("status").and_then(Value::as_str).and_then(|s| Status::parse(s).ok())?;
    Some((status, res))
}

struct Watch {
    st: AppState,
    id: String,
    rx: tokio::sync::broadcast::Receiver<String>,
    closing: tokio_util::sync::CancellationToken,
    last: Option<String>,
    first: bool,
    done: bool,
    /// Sequence number of the next event (the SSE `id:` field).
    seq: u64,
}

impl Watch {
    /// The next event with its `id:`; the first one also carries `retry:` (how long a client
    /// waits before reconnecting after the stream ends without `done`, e.g. a network cut).
    fn event(&mut self, name: &str, data: String) -> Event {
        let mut ev = Event::default().event(name).data(data).id(self.seq.to_string());
        if self.seq == 0 {
            ev = ev.retry(Duration::from_millis(2000));
        }
        self.seq += 1;
        ev
    }
}

/// `GET /v1/bakes/{id}/events`: `progress` events while the bake is in flight, then one `done`
/// event carrying the final resource (or `deleted`), then the stream ends. Every stream ends
/// with `done`: on shutdown too, carrying the resource as it stands (still queued or running,
/// it finishes after the restart), so a client never waits on a stream that silently stopped.
pub async fn events(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, Problem> {
    load(&st, &id).await?;
    let rx = st.0.jobs.watch();
    let closing = st.0.jobs.closing();
    let w = Watch { st, id, rx, closing, last: None, first: true, done: false, seq: 0 };
    let stream = futures_util::stream::unfold(w, |mut w| async move {
        if w.done {
            return None;
        }
        loop {
            let mut closing = false;
            if !w.first {
                tokio::select! {
                    _ = w.closing.cancelled() => closing = true,
                    _ = tokio::time::sleep(Duration::from_millis(250)) => {}
                    _ = w.rx.recv() => {}
                }
            }
            w.first = false;
            match snapshot(&w.st, &w.id).await {
                None => {
                    w.done = true;
                    let ev = w.event("deleted", json!({"id": w.id}).to_string());
                    return Some((Ok(ev), w));
                }
                Some((status, res)) if status.is_terminal() || closing => {
                    w.done = true;
                    let ev = w.event("done", res.to_string());
                    return Some((Ok(ev), w));
                }
                Some((status, res)) => {
                    let text =
                        json!({"id": w.id, "status": status.as_str(), "progress": res["progress"]})
                            .to_string();
                    if w.last.as_ref() != Some(&text) {
                        w.last = Some(text.clone());
                        let ev = w.event("progress", text);
                        return Some((Ok(ev), w));
                    }
                }
            }
        }
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

// ---------------------------------------------------------------------------------------------
// Results

fn etag_matches(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(|t| t.trim().trim_start_matches("W/"))
        .any(|t| t == "*" || t == etag)
}

/// Answers with immutable bytes: strong ETag = the content hash, 304 on If-None-Match.
async fn blob_response(
    st: &AppState,
    headers: &HeaderMap,
    hash: &str,
    content_type: &'static str,
    filename: &str,
) -> Answer {
    let etag = format!("\"{hash}\"");
    let mut res = if etag_matches(headers, &etag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        let blobs = st.0.jobs.blob_store().clone();
        let key = hash.to_owned();
        let (len, reader) =
            blocking(move || blobs.open(&key)).await.map_err(store_err)?.ok_or_else(|| {
                Problem::internal(&format!("result blob {hash} is missing from the blob store"))
            })?;
        let mut r = Response::new(stream_body(reader));
        r.headers_mut().insert(header::CONTENT_LENGTH, HeaderValue::from(len));
        r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
        if let Ok(v) = HeaderValue::from_str(&format!("inline; filename=\"{filename}\"")) {
            r.headers_mut().insert(header::CONTENT_DISPOSITION, v);
        }
        r
    };
    cache_headers(&mut res, &etag, IMMUTABLE_CACHE);
    Ok(res)
}

/// A body read from `reader` on a blocking thread, 64 KiB at a time with at most a few chunks
/// in flight: a download never holds a whole result in memory, whichever store it comes from.
fn stream_body(mut reader: Box<dyn std::io::Read + Send>) -> Body {
    let (tx, rx) = tokio::sync::mpsc::channel::<std::io::Result<bytes::Bytes>>(4);
    tokio::task::spawn_blocking(move || {
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            match reader.read(&mut buf) {
                Ok(0) => return,
                Ok(n) => {
                    if tx.blocking_send(Ok(bytes::Bytes::copy_from_slice(&buf[..n]))).is_err() {
                        return; // the client went away
                    }
                }
                Err(e) => {
                    let _ = tx.blocking_send(Err(e));
                    return;
                }
            }
        }
    });
    Body::from_stream(tokio_stream::wrappers::ReceiverStream::new(rx))
}

/// Results never change once written: clients may keep them for a year.
const IMMUTABLE_CACHE: &str = "private, max-age=31536000, immutable";

/// A succeeded bake, or the 404/409 that says why there is no result.
async fn finished(st: &AppState, id: &str) -> Result<BakeRecord, Problem> {
    let rec = load(st, id).await?;
    let status = resource(st, &rec)["status"].as_str().unwrap_or("queued").to_owned();
    if rec.status != Status::Succeeded {
        return Err(Problem::not_ready(id, &status));
    }
    Ok(rec)
}

/// `GET /v1/bakes/{id}/horizon/{layer}?format=png8|png16|exr[&exr_precision=half|float]`.
pub async fn horizon_layer(
    State(st): State<AppState>,
    Path((id, layer)): Path<(String, String)>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let q = known_query(q, &["format", "exr_precision"])?;
    let layer: u8 = match layer.as_str() {
        "0" => 0,
        "1" => 1,
        _ => return Err(Problem::param("layer", format!("`{layer}` is not 0 or 1"))),
    };
    let format = q.get("format").map(String::as_str).unwrap_or("png8");
    let (content_type, ext) = match format {
        "png8" | "png16" => ("image/png", "png"),
        "exr" => ("image/x-exr", "exr"),
        _ => {
            return Err(Problem::param(
                "format",
                format!("`{format}` is not one of png8, png16, exr"),
            ))
        }
    };
    let rec = finished(&st, &id).await?;
    if !params_of(&rec).is_ok_and(|p| p.outputs.horizon) {
        return Err(not_produced(&id, "horizon"));
    }
    let half = match q.get("exr_precision") {
        None => false,
        Some(_) if ext != "exr" => {
            return Err(Problem::param("exr_precision", "applies only with format=exr"))
        }
        Some(v) => {
            crate::encode::exr::ExrPrecision::parse("exr_precision", v)?
                == crate::encode::exr::ExrPrecision::Half
        }
    };
    let name = if half {
        format!("horizon_{layer}.half.exr")
    } else if ext == "exr" {
        format!("horizon_{layer}.exr")
    } else {
        format!("horizon_{layer}.{format}")
    };
    let hash = result_hash(&st, rec, &name).await?;
    blob_response(&st, &headers, &hash, content_type, &format!("horizon_{layer}.{ext}")).await
}

/// The blob of result `name` of a succeeded bake: stored already, or encoded now (on the preview
/// pool, once however many requests ask at the same time) and kept for the next request.
async fn result_hash(st: &AppState, rec: BakeRecord, name: &str) -> Result<String, Problem> {
    if let Some(h) = rec.results.get(name) {
        return Ok(h.clone());
    }
    let id = rec.id.clone();
    let group = worker::result_group(name)
        .ok_or_else(|| Problem::internal(&format!("bake {id} has no result {name}")))?;
    let key = format!("{id}/{}", group[0]);
    let lock = {
        let mut m = st.0.encoding.lock().unwrap_or_else(|e| e.into_inner());
        m.entry(key.clone()).or_default().clone()
    };
    let answer = async {
        let _one_at_a_time = lock.lock().await;
        // Whoever held the lock before may have stored it.
        let rec = load(st, &id).await?;
        if let Some(h) = rec.results.get(name) {
            return Ok(h.clone());
        }
        let wanted = name.to_owned();
        let encoded = on_pool(st, &format!("encoding {name} of {id}"), move |job| {
            worker::encode_on_request(job, &rec, &wanted, &Progress::new())
        })
        .await?;
        encoded.ok_or_else(|| Problem::bake_not_found(&id))
    }
    .await;
    {
        // The last one out removes the entry (the map holds one reference, this call another).
        let mut m = st.0.encoding.lock().unwrap_or_else(|e| e.into_inner());
        if m.get(&key).is_some_and(|l| Arc::strong_count(l) <= 2) {
            m.remove(&key);
        }
    }
    answer
}

fn not_produced(id: &str, what: &str) -> Problem {
    Problem::new(
        StatusCode::CONFLICT,
        "result_not_requested",
        format!("bake `{id}` did not compute `{what}`; submit it with outputs including {what}"),
    )
}

/// `GET /v1/bakes/{id}/fourier/{layer}`: `fourier_{layer}.png` as the CLI writes it (layer 0:
/// RGBA band coefficients, 1: the constant term, 2: the extra bands of 7 or 9 terms).
pub async fn fourier_layer(
    State(st): State<AppState>,
    Path((id, layer)): Path<(String, String)>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    known_query(q, &[])?;
    let layer: u8 = match layer.as_str() {
        "0" => 0,
        "1" => 1,
        "2" => 2,
        _ => return Err(Problem::param("layer", format!("`{layer}` is not 0, 1 or 2"))),
    };
    let rec = finished(&st, &id).await?;
    let name = format!("fourier_{layer}.png");
    let Some(hash) = rec.results.get(&name) else {
        return Err(not_produced(
            &id,
            if layer == 2 { "fourier (7 or 9 terms)" } else { "fourier" },
        ));
    };
    blob_response(&st, &headers, hash, "image/png", &name).await
}

async fn horizon_texture(
    st: AppState,
    id: String,
    q: Vec<(String, String)>,
    headers: HeaderMap,
    name: &'static str,
    content_type: &'static str,
) -> Answer {
    known_query(q, &[])?;
    let rec = finished(&st, &id).await?;
    if !params_of(&rec).is_ok_and(|p| p.outputs.horizon) {
        return Err(not_produced(&id, "horizon"));
    }
    let hash = result_hash(&st, rec, name).await?;
    blob_response(&st, &headers, &hash, content_type, name).await
}

/// `GET /v1/bakes/{id}/horizon.ktx2`: both layers as one 2-layer RGBA8 UNORM array texture.
pub async fn horizon_ktx2(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    horizon_texture(st, id, q, headers, "horizon.ktx2", KTX2_TYPE).await
}

/// `GET /v1/bakes/{id}/horizon.dds`: both layers as one DX10 2-element RGBA8 UNORM array.
pub async fn horizon_dds(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    horizon_texture(st, id, q, headers, "horizon.dds", DDS_TYPE).await
}

const KTX2_TYPE: &str = "image/ktx2";
const DDS_TYPE: &str = "image/vnd-ms.dds";

fn cube_size(st: &AppState, q: &HashMap<String, String>) -> Result<usize, Problem> {
    let max = st.0.config.max_cubemap_size as usize;
    match q.get("size") {
        None => Ok(16),
        Some(v) => match v.parse::<usize>() {
            Ok(n) if (1..=max).contains(&n) => Ok(n),
            _ => {
                Err(Problem::param("size", format!("`{v}` is not a whole number from 1 to {max}")))
            }
        },
    }
}

/// An ETag for a response that is a pure function of `parts` and of this build's code (cube
/// maps, previews), known before computing anything, so a revalidation (304) costs nothing.
fn derived_etag(parts: &[&str]) -> String {
    let mut h = blake3::Hasher::new();
    h.update(env!("CARGO_PKG_VERSION").as_bytes());
    for p in parts {
        h.update(b"\0");
        h.update(p.as_bytes());
    }
    format!("\"{}\"", &h.finalize().to_hex()[..32])
}

/// Adds `ETag` and `Cache-Control` to a response.
fn cache_headers(res: &mut Response, etag: &str, cache_control: &'static str) {
    if let Ok(v) = HeaderValue::from_str(etag) {
        res.headers_mut().insert(header::ETAG, v);
    }
    res.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static(cache_control));
}

/// Cube maps depend only on the size and the format: cacheable by anyone for a day, and
/// revalidated by the derived ETag without re-encoding.
const CUBE_CACHE: &str = "public, max-age=86400";

/// Encodes a cube-map file (the CLI's own function) and answers it with a derived ETag; a
/// matching `If-None-Match` is answered 304 before anything is computed.
async fn cube_answer(
    headers: &HeaderMap,
    size: usize,
    formats: CubeFormats,
    pick: usize,
    content_type: &'static str,
) -> Answer {
    let etag = derived_etag(&[
        "cube",
        &size.to_string(),
        &format!("{}{}{}", formats.png8, formats.ktx2, formats.dds),
        &pick.to_string(),
    ]);
    if etag_matches(headers, &etag) {
        let mut res = StatusCode::NOT_MODIFIED.into_response();
        cache_headers(&mut res, &etag, CUBE_CACHE);
        return Ok(res);
    }
    let file = blocking(move || {
        let mut files = crate::encode::cube_files(size, formats)?;
        if pick >= files.len() {
            return Err(Error::Internal("cube map file missing".into()));
        }
        Ok(files.swap_remove(pick))
    })
    .await
    .map_err(store_err)?;
    let mut res = Response::new(Body::from(file.bytes));
    res.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    if let Ok(v) = HeaderValue::from_str(&format!("inline; filename=\"{}\"", file.name)) {
        res.headers_mut().insert(header::CONTENT_DISPOSITION, v);
    }
    cache_headers(&mut res, &etag, CUBE_CACHE);
    Ok(res)
}

/// `GET /v1/cubemap/{face}?size=N`: one face of the channel-factor cube map, RGBA8 UNORM PNG.
pub async fn cubemap_face(
    State(st): State<AppState>,
    Path(face): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let q = known_query(q, &["size"])?;
    let face: usize = match face.parse::<usize>() {
        Ok(f) if f < 6 && face.len() == 1 => f,
        _ => return Err(Problem::param("face", format!("`{face}` is not a face index 0..5"))),
    };
    let size = cube_size(&st, &q)?;
    let formats = CubeFormats { png8: true, ktx2: false, dds: false };
    cube_answer(&headers, size, formats, face, "image/png").await
}

/// `GET /v1/cubemap.ktx2?size=N`: the six faces as one RGBA8 SNORM cube map.
pub async fn cubemap_ktx2(
    State(st): State<AppState>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let q = known_query(q, &["size"])?;
    let size = cube_size(&st, &q)?;
    cube_answer(&headers, size, CubeFormats { png8: false, ktx2: true, dds: false }, 0, KTX2_TYPE)
        .await
}

/// `GET /v1/cubemap.dds?size=N`: the six faces as one RGBA8 SNORM DDS cube map.
pub async fn cubemap_dds(
    State(st): State<AppState>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let q = known_query(q, &["size"])?;
    let size = cube_size(&st, &q)?;
    cube_answer(&headers, size, CubeFormats { png8: false, ktx2: false, dds: true }, 0, DDS_TYPE)
        .await
}

/// Runs `f` on the preview pool (never the async workers, and never behind a long bake: the
/// work a request waits for), panics caught, the result sent back over a oneshot; `what` names
/// the work in the 500 a panic becomes.
async fn on_pool<T, F>(st: &AppState, what: &str, f: F) -> Result<T, Problem>
where
    T: Send + 'static,
    F: FnOnce(&AppState) -> crate::Result<T> + Send + 'static,
{
    let (tx, rx) = tokio::sync::oneshot::channel();
    let pool_state = st.clone();
    st.0.preview_pool.spawn(move || {
        let _ = tx.send(catch_unwind(AssertUnwindSafe(|| f(&pool_state))));
    });
    match rx.await {
        Ok(Ok(r)) => r.map_err(Problem::from),
        Ok(Err(_)) | Err(_) => Err(Problem::internal(&format!("{what} panicked"))),
    }
}

/// `GET /v1/bakes/{id}/heights`: the heights the bake used, in texels (channel picked,
/// `height_scale` applied), little-endian f32, row 0 first, with the size in `x-width` and
/// `x-height`. A browser decodes 16-bit PNGs to 8 bits, so this is how a viewer rebuilds the
/// server's normals exactly. The input is stored from submission on, so any status has them.
pub async fn heights(
    State(st): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Answer {
    let rec = load(&st, &id).await?;
    let params = params_of(&rec).map_err(store_err)?;
    // The bytes are a function of the input and of these two parameters only.
    let etag = format!(
        "\"{}\"",
        blake3::hash(
            format!("heights|{}|{:?}|{}", rec.input_blob, params.channel, params.height_scale)
                .as_bytes()
        )
        .to_hex()
    );
    let mut res = if etag_matches(&headers, &etag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        let (w, h, bytes) = on_pool(&st, &format!("the heights of bake {id}"), move |st| {
            let map = worker::decode_input(
                st.0.jobs.blob_store().as_ref(),
                &rec,
                &params,
                &st.0.config.limits,
            )?
            .0;
            let (w, h) = (map.width, map.height);
            let bytes: Vec<u8> =
                map.into_scaled(params.height_scale).iter().flat_map(|v| v.to_le_bytes()).collect();
            Ok((w, h, bytes))
        })
        .await?;
        let mut r = Response::new(Body::from(bytes));
        let hs = r.headers_mut();
        hs.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/octet-stream"));
        hs.insert("x-width", HeaderValue::from(w));
        hs.insert("x-height", HeaderValue::from(h));
        if let Ok(v) = HeaderValue::from_str(&format!("inline; filename=\"heights_{id}.f32\"")) {
            hs.insert(header::CONTENT_DISPOSITION, v);
        }
        r
    };
    cache_headers(&mut res, &etag, IMMUTABLE_CACHE);
    Ok(res)
}

/// Cancels a preview render when its request future is dropped (the client went away), so the
/// pool does not keep computing an image nobody will read.
struct CancelOnDrop(Progress);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.cancel();
    }
}

/// `GET /v1/bakes/{id}/preview?…`: the lit surface (SPEC §3.5 parameters; `contact_sheet=N` for
/// the contact sheet) rendered from the bake's stored input with its resolved parameters, as PNG.
///
/// Rendering is CPU work, so it runs on the preview pool (never the async workers, and not the
/// bake pool, where it would wait for a running bake to finish); `preview_threads` bounds its CPU
/// use, and the renderer's own limits (`MAX_SIZE`, `MAX_TILES`, `MAX_PIXELS`) cap the cost of one
/// request.
pub async fn preview(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let mut pp = PreviewParams::default();
    let mut seen = std::collections::HashSet::new();
    for (k, v) in &q {
        if !seen.insert(k.as_str()) {
            return Err(Problem::param(k.clone(), "given more than once"));
        }
        pp.set(k, v).map_err(Problem::from)?;
    }
    let rec = finished(&st, &id).await?;
    // A preview is a pure function of the input, the bake's parameters and the query: its ETag
    // is known before rendering, so a revalidation is a 304 with no render.
    let mut query: Vec<String> = q.iter().map(|(k, v)| format!("{k}={v}")).collect();
    query.sort();
    let bake_params: Vec<String> = rec.params.iter().map(|(k, v)| format!("{k}={v}")).collect();
    let etag =
        derived_etag(&["preview", &rec.input_blob, &bake_params.join("&"), &query.join("&")]);
    const PREVIEW_CACHE: &str = "private, max-age=86400";
    if etag_matches(&headers, &etag) {
        let mut res = StatusCode::NOT_MODIFIED.into_response();
        cache_headers(&mut res, &etag, PREVIEW_CACHE);
        return Ok(res);
    }
    let params = params_of(&rec).map_err(store_err)?;
    let progress = Progress::new();
    let _cancel = CancelOnDrop(progress.clone());
    let png = on_pool(&st, &format!("the preview of bake {id}"), move |st| {
        let map = worker::decode_input(
            st.0.jobs.blob_store().as_ref(),
            &rec,
            &params,
            &st.0.config.limits,
        )?
        .0;
        preview::render_baking(&map, &params, &pp, &progress)?.to_png()
    })
    .await?;
    let mut r = Response::new(Body::from(png));
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
    if let Ok(v) = HeaderValue::from_str(&format!("inline; filename=\"preview_{id}.png\"")) {
        r.headers_mut().insert(header::CONTENT_DISPOSITION, v);
    }
    cache_headers(&mut r, &etag, PREVIEW_CACHE);
    Ok(r)
}

// ---------------------------------------------------------------------------------------------
// Operations

/// `GET /healthz`: the process is alive.
pub async fn healthz() -> Response {
    json_response(StatusCode::OK, &json!({"status": "ok"}))
}

/// `GET /readyz`: 200 while accepting work, 503 while draining.
pub async fn readyz(State(st): State<AppState>) -> Answer {
    if st.is_draining() {
        return Err(Problem::shutting_down());
    }
    // Ready means the stores answer too: with PostgreSQL away this is 503, so a load
    // balancer stops sending work here until it is back.
    let c = st.0.jobs.counts().await.map_err(store_err)?;
    Ok(json_response(
        StatusCode::OK,
        &json!({
            "status": "ready",
            "role": match st.0.config.role {
                super::config::Role::All => "all",
                super::config::Role::Api => "api",
                super::config::Role::Worker => "worker",
            },
            "queue_depth": c.queued,
            "queue_capacity": st.0.config.queue_capacity,
            "running": c.running,
            "running_here": st.0.jobs.running_here(),
        }),
    ))
}

/// `GET /metrics`: Prometheus text.
pub async fn metrics(State(st): State<AppState>) -> Answer {
    let c = st.0.jobs.counts().await.map_err(store_err)?;
    let stored: Vec<(Status, u64)> = Status::ALL.iter().map(|s| (*s, c.of(*s))).collect();
    let (waiting, running) = (c.queued as usize, c.running as usize);
    let text = st.0.metrics.render(&stored, waiting, running);
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4; charset=utf-8")], text).into_response())
}

/// `GET /openapi.yaml`.
pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/yaml")], OPENAPI_YAML).into_response()
}

/// Unknown routes.
pub async fn fallback() -> Problem {
    Problem::new(StatusCode::NOT_FOUND, "route_not_found", "no such route; see /openapi.yaml")
}

// ---------------------------------------------------------------------------------------------
// Middleware

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// 414 for a request target over `max_uri_bytes`, 431 for headers over `max_header_bytes`,
/// both problem+json, before routing (so before any extractor echoes a part of them).
pub async fn head_limits(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let target = req.uri().path_and_query().map_or(0, |pq| pq.as_str().len());
    if target > st.0.config.max_uri_bytes {
        return Problem::new(
            StatusCode::URI_TOO_LONG,
            "uri_too_long",
            format!(
                "the request target is {target} bytes; at most {} are accepted (max_uri_bytes)",
                st.0.config.max_uri_bytes
            ),
        )
        .into_response();
    }
    let headers: usize = req.headers().iter().map(|(k, v)| k.as_str().len() + v.len() + 4).sum();
    if headers > st.0.config.max_header_bytes {
        return Problem::new(
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            "headers_too_large",
            format!(
                "the request headers are {headers} bytes; at most {} are accepted \
                 (max_header_bytes)",
                st.0.config.max_header_bytes
            ),
        )
        .into_response();
    }
    next.run(req).await
}

/// Bearer-token check on /v1 routes when an API key is configured.
pub async fn auth(State(st): State<AppState>, req: Request, next: Next) -> Response {
    if let Some(key) = &st.0.config.api_key {
        // RFC 9110 §11.1: the auth scheme is case-insensitive (`bearer`, `BEARER`), and the
        // credentials follow after one or more spaces.
        let ok = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.split_once(' '))
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .is_some_and(|(_, t)| constant_time_eq(t.trim().as_bytes(), key.as_bytes()));
        if !ok {
            return Problem::new(
                StatusCode::UNAUTHORIZED,
                "unauthorized",
                "this route needs `Authorization: Bearer <api key>`",
            )
            .into_response();
        }
    }
    next.run(req).await
}

/// The request id: the client's `X-Request-Id` when it is a short token, else a fresh one.
fn request_id(headers: &HeaderMap) -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(1);
    let given = headers.get("x-request-id").and_then(|v| v.to_str().ok()).filter(|v| {
        !v.is_empty()
            && v.len() <= 64
            && v.bytes().all(|b| b.is_ascii_alphanumeric() || b"-_.:".contains(&b))
    });
    match given {
        Some(v) => v.to_owned(),
        None => format!("{:08x}-{}", std::process::id(), NEXT.fetch_add(1, Ordering::Relaxed)),
    }
}

/// One log line per request (method, path, status, latency, request id; the path without its
/// query and capped, so a huge or secret-bearing query string never reaches the log), the
/// `X-Request-Id` answer header, and the request counters by matched route.
pub async fn track(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let started = std::time::Instant::now();
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_owned())
        .unwrap_or_else(|| "unmatched".into());
    let method = req.method().clone();
    let path = crate::service::problem::cap(req.uri().path(), 200);
    let rid = request_id(req.headers());
    let mut res = next.run(req).await;
    let status = res.status().as_u16();
    tracing::info!(
        method = %method,
        path = %path,
        status,
        latency_ms = (started.elapsed().as_secs_f64() * 1e3 * 10.0).round() / 10.0,
        request_id = %rid,
        "request"
    );
    if let Ok(v) = HeaderValue::from_str(&rid) {
        res.headers_mut().insert("x-request-id", v);
    }
    let method = if [Method::GET, Method::POST, Method::DELETE, Method::HEAD].contains(&method) {
        method.as_str().to_owned()
    } else {
        "OTHER".into()
    };
    st.0.metrics.http(&route, &method, status);
    res
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
