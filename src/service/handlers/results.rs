//! Downloads of a succeeded bake's results: horizon layers (stored, or encoded in the background
//! after their first request, which is answered 202 at once), Fourier layers and the layered
//! textures, streamed from the blob store (one `Range` at a time when asked).

#![allow(clippy::result_large_err)]

use super::*;

pub(super) fn etag_matches(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(|t| t.trim().trim_start_matches("W/"))
        .any(|t| t == "*" || t == etag)
}

/// What a download answers for the request's `Range` header (RFC 9110 §14), over a result of
/// `len` bytes whose strong ETag is `etag`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RangeAnswer {
    /// 200 with the whole body: no `Range`, one we do not serve (several ranges, another unit,
    /// a malformed one: RFC 9110 lets a server ignore it), or an `If-Range` that no longer
    /// matches.
    Full,
    /// 206 with bytes `start..end` (end exclusive).
    Part(u64, u64),
    /// 416 with `Content-Range: bytes */len`.
    Unsatisfiable,
}

/// Reads `Range` (and `If-Range`) for a result of `len` bytes: one range of bytes, `a-b`, `a-`
/// or the suffix `-n`.
pub fn range_answer(headers: &HeaderMap, len: u64, etag: &str) -> RangeAnswer {
    let Some(spec) = headers.get(header::RANGE).and_then(|v| v.to_str().ok()) else {
        return RangeAnswer::Full;
    };
    if let Some(v) = headers.get(header::IF_RANGE) {
        if v.to_str().ok().map(str::trim) != Some(etag) {
            return RangeAnswer::Full;
        }
    }
    let Some(set) = spec.trim().strip_prefix("bytes=") else { return RangeAnswer::Full };
    if set.contains(',') {
        return RangeAnswer::Full;
    }
    let Some((a, b)) = set.trim().split_once('-') else { return RangeAnswer::Full };
    let num = |t: &str| -> Option<u64> {
        (!t.is_empty() && t.bytes().all(|c| c.is_ascii_digit())).then(|| t.parse().ok())?
    };
    match (a.trim(), b.trim()) {
        ("", n) => match num(n) {
            Some(0) => RangeAnswer::Unsatisfiable,
            Some(_) if len == 0 => RangeAnswer::Unsatisfiable,
            Some(n) => RangeAnswer::Part(len - n.min(len), len),
            None => RangeAnswer::Full,
        },
        (a, "") => match num(a) {
            Some(a) if a >= len => RangeAnswer::Unsatisfiable,
            Some(a) => RangeAnswer::Part(a, len),
            None => RangeAnswer::Full,
        },
        (a, b) => match (num(a), num(b)) {
            (Some(a), Some(b)) if a > b => RangeAnswer::Full,
            (Some(a), Some(_)) if a >= len => RangeAnswer::Unsatisfiable,
            (Some(a), Some(b)) => RangeAnswer::Part(a, b.min(len - 1) + 1),
            _ => RangeAnswer::Full,
        },
    }
}

/// Answers with immutable bytes: strong ETag = the content hash, 304 on If-None-Match, and a
/// single `Range` answered 206 with only those bytes read from the blob store (416 when it
/// lies past the end), so a client can resume a large EXR.
pub(super) async fn blob_response(
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
        let missing =
            || Problem::internal(&format!("result blob {hash} is missing from the blob store"));
        let (len, reader) =
            blocking(move || blobs.open(&key)).await.map_err(store_err)?.ok_or_else(missing)?;
        let mut r = match range_answer(headers, len, &etag) {
            RangeAnswer::Full => {
                let mut r = Response::new(stream_body(reader));
                r.headers_mut().insert(header::CONTENT_LENGTH, HeaderValue::from(len));
                r
            }
            RangeAnswer::Part(start, end) => {
                drop(reader);
                let blobs = st.0.jobs.blob_store().clone();
                let key = hash.to_owned();
                let reader = blocking(move || blobs.open_range(&key, start, end))
                    .await
                    .map_err(store_err)?
                    .ok_or_else(missing)?;
                let mut r = Response::new(stream_body(reader));
                *r.status_mut() = StatusCode::PARTIAL_CONTENT;
                r.headers_mut().insert(header::CONTENT_LENGTH, HeaderValue::from(end - start));
                if let Ok(v) = HeaderValue::from_str(&format!("bytes {start}-{}/{len}", end - 1)) {
                    r.headers_mut().insert(header::CONTENT_RANGE, v);
                }
                r
            }
            RangeAnswer::Unsatisfiable => {
                drop(reader);
                let mut r = Problem::new(
                    StatusCode::RANGE_NOT_SATISFIABLE,
                    "range_not_satisfiable",
                    format!(
                        "the range `{}` lies outside the {len} bytes of this result",
                        headers.get(header::RANGE).and_then(|v| v.to_str().ok()).unwrap_or("")
                    ),
                )
                .into_response();
                if let Ok(v) = HeaderValue::from_str(&format!("bytes */{len}")) {
                    r.headers_mut().insert(header::CONTENT_RANGE, v);
                }
                r.headers_mut().insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
                return Ok(r);
            }
        };
        r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
        if let Ok(v) = HeaderValue::from_str(&format!("inline; filename=\"{filename}\"")) {
            r.headers_mut().insert(header::CONTENT_DISPOSITION, v);
        }
        r
    };
    res.headers_mut().insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    cache_headers(&mut res, &etag, IMMUTABLE_CACHE);
    Ok(res)
}

/// A body read from `reader` on a blocking thread, 64 KiB at a time with at most a few chunks
/// in flight: a download never holds a whole result in memory, whichever store it comes from.
pub(super) fn stream_body(mut reader: Box<dyn std::io::Read + Send>) -> Body {
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
pub(super) const IMMUTABLE_CACHE: &str = "private, max-age=31536000, immutable";

/// A succeeded bake, or the 404/409 that says why there is no result.
pub(super) async fn finished(st: &AppState, id: &str) -> Result<BakeRecord, Problem> {
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
    match result_or_encode(&st, rec, &name).await? {
        Found::Stored(hash) => {
            blob_response(&st, &headers, &hash, content_type, &download_name(&name)).await
        }
        Found::Encoding(answer) => Ok(answer),
    }
}

/// The file name a download of result `name` is offered under (`Content-Disposition`): the
/// CLI's name, with the precision added where the CLI's names would collide in one folder:
/// `horizon_0.png` (8-bit, as `bake --format png8` writes it), `horizon_0_16.png` (16-bit),
/// `horizon_0.exr` (float), `horizon_0_half.exr` (half), `horizon.ktx2`, `fourier_0.png`.
pub fn download_name(name: &str) -> String {
    if let Some(stem) = name.strip_suffix(".png8") {
        format!("{stem}.png")
    } else if let Some(stem) = name.strip_suffix(".png16") {
        format!("{stem}_16.png")
    } else if let Some(stem) = name.strip_suffix(".half.exr") {
        format!("{stem}_half.exr")
    } else {
        name.to_owned()
    }
}

/// An encode of a result group started by a download ([`result_or_encode`]), running in the
/// background on the preview pool. Keyed in [`crate::service::Shared::encodes`] by
/// `{bake id}/{first result name of the group}`: any variant [`job::result_group`] knows goes
/// through it unchanged.
#[derive(Debug, Clone)]
pub struct EncodeJob {
    /// The bake.
    pub id: String,
    /// The first result of the group being encoded (`horizon_0.png16`, `horizon_0.exr`, …).
    pub result: String,
    /// The re-bake's and the encode's progress.
    pub progress: Progress,
    pub started: std::time::Instant,
    /// How long it should take: the bake's own decode + bake + encode time.
    pub estimate: Duration,
    /// Set when it failed: the next request for it answers this problem (once), and the one
    /// after starts again.
    pub failed: Option<Problem>,
}

impl EncodeJob {
    /// Overall fraction done, as a bake's progress is reported.
    pub fn fraction(&self) -> f64 {
        overall(self.progress.stage(), self.progress.fraction())
    }

    /// Seconds a client should wait before asking again.
    fn retry_after(&self) -> u64 {
        let left = self.estimate.saturating_sub(self.started.elapsed()).as_secs_f64();
        left.ceil().clamp(1.0, 30.0) as u64
    }
}

/// What a download finds: the stored blob, or a 202 for a result being encoded.
pub(super) enum Found {
    Stored(String),
    Encoding(Response),
}

/// The results of bake `id` being encoded in the background now (first result name of each
/// group), for its resource and its events.
pub fn encoding_of(st: &AppState, id: &str) -> Vec<EncodeJob> {
    let m = st.0.encodes.lock().unwrap_or_else(|e| e.into_inner());
    let mut v: Vec<EncodeJob> =
        m.values().filter(|j| j.id == id && j.failed.is_none()).cloned().collect();
    v.sort_by(|a, b| a.result.cmp(&b.result));
    v
}

/// The blob of result `name` of a succeeded bake when it is stored; otherwise its encode is
/// started in the background (once, however many requests ask; on the preview pool) and the
/// request is answered 202 Accepted with `Retry-After` at once: a download never waits for a
/// re-bake. The same request, repeated, answers the file once it is stored. A failed encode is
/// answered once with its problem, and started again by the next request.
pub(super) async fn result_or_encode(
    st: &AppState,
    rec: BakeRecord,
    name: &str,
) -> Result<Found, Problem> {
    if let Some(h) = rec.results.get(name) {
        return Ok(Found::Stored(h.clone()));
    }
    let id = rec.id.clone();
    let group = job::result_group(name)
        .ok_or_else(|| Problem::internal(&format!("bake {id} has no result {name}")))?;
    let key = format!("{id}/{}", group[0]);
    // Running (or just failed) already?
    if let Some(found) = encode_state(st, &key)? {
        return Ok(found);
    }
    // Not running: it may have been stored since `rec` was read.
    let rec = load(st, &id).await?;
    if let Some(h) = rec.results.get(name) {
        return Ok(Found::Stored(h.clone()));
    }
    let job = {
        let mut m = st.0.encodes.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(running) = m.get(&key) {
            // Another request started it in between.
            return Ok(Found::Encoding(encoding_response(running)));
        }
        let t = rec.timings_ms.as_ref();
        let ms = t.map_or(1000.0, |t| t.decode + t.bake + t.encode);
        let job = EncodeJob {
            id: id.clone(),
            result: group[0].to_owned(),
            progress: Progress::new(),
            started: std::time::Instant::now(),
            estimate: Duration::from_secs_f64(ms.max(0.0) / 1000.0),
            failed: None,
        };
        m.insert(key.clone(), job.clone());
        job
    };
    let answer = encoding_response(&job);
    let bg = st.clone();
    let wanted = name.to_owned();
    tokio::spawn(async move {
        let progress = job.progress.clone();
        let what = format!("encoding {wanted} of {}", job.id);
        let r = previews::run_on(&bg, previews::Pool::Encode, &what, move |pool| {
            // In the background, for a request already answered 202: it waits its turn.
            let admit = heightmap::budget::Admit { budget: &pool.0.decode_budget, wait: None };
            job::encode_on_request(
                &pool.0.jobs,
                &pool.0.config.limits,
                Some(admit),
                &rec,
                &wanted,
                &progress,
                &|| pool.0.metrics.encoded_on_request(),
            )
        })
        .await;
        let mut m = bg.0.encodes.lock().unwrap_or_else(|e| e.into_inner());
        match r {
            // Stored and recorded (or the bake was removed meanwhile): requests find it in the
            // record from now on.
            Ok(_) => {
                m.remove(&key);
            }
            Err(p) => {
                tracing::warn!(bake = %job.id, result = %job.result, code = p.code, "on-request encode failed");
                if let Some(j) = m.get_mut(&key) {
                    j.failed = Some(p);
                }
            }
        }
    });
    Ok(Found::Encoding(answer))
}

/// The state of the encode `key`: running (a 202), failed (its problem, once; a failure older
/// than a minute is forgotten instead), or none.
fn encode_state(st: &AppState, key: &str) -> Result<Option<Found>, Problem> {
    let mut m = st.0.encodes.lock().unwrap_or_else(|e| e.into_inner());
    match m.get(key) {
        None => Ok(None),
        Some(j) if j.failed.is_none() => Ok(Some(Found::Encoding(encoding_response(j)))),
        Some(j) => {
            let stale = j.started.elapsed() > Duration::from_secs(60);
            let failed = m.remove(key).and_then(|j| j.failed);
            match failed {
                Some(p) if !stale => Err(p),
                _ => Ok(None),
            }
        }
    }
}

/// 202 Accepted for a result being encoded: `Retry-After`, and what is being done.
fn encoding_response(job: &EncodeJob) -> Response {
    let body = serde_json::json!({
        "id": job.id,
        "status": "encoding",
        "result": job.result,
        "progress": {"fraction": job.fraction(), "stage": job.progress.stage()},
        "retry_after": job.retry_after(),
        "events": format!("/v1/bakes/{}/events", job.id),
    });
    let mut r = json_response(StatusCode::ACCEPTED, &body);
    r.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(job.retry_after()));
    r.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    r
}

pub(super) fn not_produced(id: &str, what: &str) -> Problem {
    Problem::new(
        StatusCode::CONFLICT,
        "result_not_requested",
        format!("bake `{id}` did not compute `{what}`; submit it with outputs including {what}"),
    )
}

/// A product stored with the bake (a terrain product of SPEC §3.7, a surface map of §3.8):
/// `file` of a bake submitted with `outputs` naming `what`, served as `content_type`.
async fn stored_file(
    st: &AppState,
    id: &str,
    q: Vec<(String, String)>,
    headers: &HeaderMap,
    file: &'static str,
    what: &str,
    content_type: &'static str,
) -> Answer {
    known_query(q, &[])?;
    let rec = finished(st, id).await?;
    let Some(hash) = rec.results.get(file) else {
        return Err(not_produced(id, what));
    };
    blob_response(st, headers, hash, content_type, file).await
}

/// A surface map (SPEC §3.8) `what` of a bake, in the `format` its bake wrote it: `png` (its
/// PNG, 8- or 16-bit), `png8`, `png16`, `exr`, `ktx2` or `dds` (the 2D texture); a 409 naming
/// the format when the bake did not write it. Without `format`, its PNG, else its EXR.
async fn surface_file(
    st: &AppState,
    id: &str,
    q: Vec<(String, String)>,
    headers: &HeaderMap,
    what: &'static str,
) -> Answer {
    let mut q = q;
    let format = q.iter().position(|(k, _)| k == "format").map(|i| q.remove(i).1);
    known_query(q, &[])?;
    // Result names in the order a format looks them up: the CLI's file names, but a 16-bit
    // PNG is `{what}.png16` (the CLI writes `{what}.png` in either depth).
    let (names, content_type): (&[&str], &'static str) = match format.as_deref() {
        None => (&["png", "png16", "exr"], "image/png"),
        Some("png") => (&["png", "png16"], "image/png"),
        Some("png8") => (&["png"], "image/png"),
        Some("png16") => (&["png16"], "image/png"),
        Some("exr") => (&["exr"], EXR_TYPE),
        Some("ktx2") => (&["ktx2"], KTX2_TYPE),
        Some("dds") => (&["dds"], DDS_TYPE),
        Some(other) => {
            return Err(Problem::param(
                "format",
                format!("`{other}` is not one of png, png8, png16, exr, ktx2, dds"),
            ))
        }
    };
    let rec = finished(st, id).await?;
    for ext in names {
        let file = format!("{what}.{ext}");
        if let Some(hash) = rec.results.get(file.as_str()) {
            let content_type = if *ext == "exr" { EXR_TYPE } else { content_type };
            return blob_response(st, headers, hash, content_type, &file).await;
        }
    }
    let Some(ext) = format else {
        return Err(not_produced(id, what));
    };
    Err(Problem::new(
        StatusCode::CONFLICT,
        "result_not_requested",
        format!(
            "bake `{id}` did not write its {what} as {ext}; submit it with outputs including \
             {what} and formats including {}",
            if ext == "png" { "png8 or png16" } else { ext.as_str() }
        ),
    ))
}

/// `GET /v1/bakes/{id}/normal`: `normal.png`, the tangent-space normal map (SPEC §3.8);
/// `format=ktx2|dds` its texture.
pub async fn normal(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    surface_file(&st, &id, q, &headers, "normal").await
}

/// `GET /v1/bakes/{id}/ao`: `ao.png`, the ambient occlusion (SPEC §3.8); `format=ktx2|dds`
/// its texture.
pub async fn ao(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    surface_file(&st, &id, q, &headers, "ao").await
}

/// `GET /v1/bakes/{id}/bent_normal`: `bent_normal.png` (SPEC §3.8); `format=ktx2|dds` its
/// texture.
pub async fn bent_normal(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    surface_file(&st, &id, q, &headers, "bent_normal").await
}

/// `GET /v1/bakes/{id}/angles`: `angles.tif`, one GeoTIFF band per bin (SPEC §3.7).
pub async fn angles(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    stored_file(&st, &id, q, &headers, "angles.tif", "angles", "image/tiff").await
}

/// `GET /v1/bakes/{id}/horizon_distance`: `horizon_distance.tif`, one GeoTIFF band per bin
/// (SPEC §3.7).
pub async fn horizon_distance(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    stored_file(&st, &id, q, &headers, "horizon_distance.tif", "horizon_distance", "image/tiff")
        .await
}

/// `GET /v1/bakes/{id}/openness_positive`: `openness_positive.tif` (SPEC §3.7).
pub async fn openness_positive(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let file = "openness_positive.tif";
    stored_file(&st, &id, q, &headers, file, "openness", "image/tiff").await
}

/// `GET /v1/bakes/{id}/openness_negative`: `openness_negative.tif` (SPEC §3.7).
pub async fn openness_negative(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let file = "openness_negative.tif";
    stored_file(&st, &id, q, &headers, file, "openness", "image/tiff").await
}

/// `GET /v1/bakes/{id}/sun_hours`: `sun_hours.tif` (SPEC §3.7).
pub async fn sun_hours(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    stored_file(&st, &id, q, &headers, "sun_hours.tif", "sun_hours", "image/tiff").await
}

/// `GET /v1/bakes/{id}/insolation`: `insolation.tif` (SPEC §3.7).
pub async fn insolation(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    stored_file(&st, &id, q, &headers, "insolation.tif", "insolation", "image/tiff").await
}

/// `GET /v1/bakes/{id}/svf`: `svf.tif`, the sky-view factor (SPEC §3.7); `format=png` renders
/// it as an 8-bit grey + alpha PNG for a browser ([`crate::pipeline::svf_png`], on the preview
/// pool), its strong ETag derived from the stored file's.
pub async fn svf(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let mut q = q;
    let format = take_terrain_format(&mut q)?;
    if !format {
        return stored_file(&st, &id, q, &headers, "svf.tif", "svf", "image/tiff").await;
    }
    known_query(q, &[])?;
    let rec = finished(&st, &id).await?;
    let Some(hash) = rec.results.get("svf.tif").cloned() else {
        return Err(not_produced(&id, "svf"));
    };
    if rec.tiles.is_some() {
        // Rendering reads the whole file into memory, which a tiled bake never does.
        return Err(crate::Error::param(
            "format",
            "this bake was baked in tiles (its map is above --tile-above): its svf is served as \
             the GeoTIFF only (format=geotiff), never rendered whole",
        )
        .into());
    }
    let etag = derived_etag(&["svf.png", &hash]);
    if etag_matches(&headers, &etag) {
        let mut res = StatusCode::NOT_MODIFIED.into_response();
        cache_headers(&mut res, &etag, IMMUTABLE_CACHE);
        return Ok(res);
    }
    let png = previews::on_pool(&st, &format!("the svf image of bake {id}"), move |st| {
        let tif = st.0.jobs.blob_store().get(&hash)?.ok_or_else(|| {
            crate::Error::Internal(format!("result blob {hash} is missing from the blob store"))
        })?;
        crate::pipeline::svf_png(&tif)
    })
    .await?;
    Ok(computed_response(png, "image/png", &format!("svf_{id}.png"), &etag, IMMUTABLE_CACHE))
}

/// Takes `format` (`geotiff`, the default, or `png`) out of a terrain route's query: `true` for
/// `png`.
pub(super) fn take_terrain_format(q: &mut Vec<(String, String)>) -> Result<bool, Problem> {
    let mut png = None;
    let mut err = None;
    q.retain(|(k, v)| {
        if k != "format" {
            return true;
        }
        if png.is_some() {
            err = Some(Problem::param("format", "given more than once"));
        }
        match v.as_str() {
            "geotiff" => png = Some(false),
            "png" => png = Some(true),
            _ => err = Some(Problem::param("format", format!("`{v}` is not geotiff or png"))),
        }
        false
    });
    match err {
        Some(e) => Err(e),
        None => Ok(png.unwrap_or(false)),
    }
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

pub(super) async fn horizon_texture(
    st: AppState,
    id: String,
    q: Vec<(String, String)>,
    headers: HeaderMap,
    name: &'static str,
    content_type: &'static str,
) -> Answer {
    let mut keys = crate::encode::texture::OPTION_KEYS.to_vec();
    keys.push("layer");
    let mut q = known_query(q, &keys)?;
    let (ext, is_ktx2) = if name.ends_with(".ktx2") { ("ktx2", true) } else { ("dds", false) };
    // SPEC §8 delivery options: each variant is one more result of the same bake.
    let layer = q.remove("layer");
    let opts = crate::encode::TextureOptions::from_pairs(
        keys.iter().filter_map(|k| q.get(*k).map(|v| (*k, v.as_str()))),
    )?;
    opts.check_for(is_ktx2, !is_ktx2, false)?;
    let separate = opts.layout == crate::encode::TextureLayout::Separate;
    let layer = match (layer, separate) {
        (None, false) => None,
        (Some(_), false) => {
            return Err(Problem::param("layer", "applies only with texture_layout=separate"))
        }
        (None, true) => {
            return Err(Problem::param("layer", "texture_layout=separate needs layer=0, 1, …"))
        }
        (Some(v), true) => {
            let n = if opts.precision == crate::encode::TexturePrecision::Bc5 { 4 } else { 2 };
            match v.parse::<usize>() {
                Ok(i) if i < n && v.len() == 1 => Some(i),
                _ => {
                    return Err(Problem::param(
                        "layer",
                        format!("`{v}` is not a layer 0..{}", n - 1),
                    ))
                }
            }
        }
    };
    let rec = finished(&st, &id).await?;
    if !params_of(&rec).is_ok_and(|p| p.outputs.horizon) {
        return Err(not_produced(&id, "horizon"));
    }
    let result = job::texture_result_name(ext, &opts, layer);
    let file = match layer {
        Some(i) => format!("horizon_{i}.{ext}"),
        None => name.to_owned(),
    };
    match result_or_encode(&st, rec, &result).await? {
        Found::Stored(hash) => blob_response(&st, &headers, &hash, content_type, &file).await,
        Found::Encoding(answer) => Ok(answer),
    }
}

/// `GET /v1/bakes/{id}/horizon.ktx2`: both layers as one 2-layer RGBA8 UNORM array texture, or
/// the variant the SPEC §8 query parameters ask for (`texture_precision`, `mips`, `mip_filter`,
/// `supercompression`, `zstd_level`, `texture_layout` with `layer`).
pub async fn horizon_ktx2(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    horizon_texture(st, id, q, headers, "horizon.ktx2", KTX2_TYPE).await
}

/// `GET /v1/bakes/{id}/horizon.dds`: both layers as one DX10 2-element RGBA8 UNORM array, or
/// the variant the SPEC §8 query parameters ask for (as `.ktx2`, with `dds_header` instead of
/// supercompression).
pub async fn horizon_dds(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    horizon_texture(st, id, q, headers, "horizon.dds", DDS_TYPE).await
}

pub(super) const KTX2_TYPE: &str = "image/ktx2";
pub(super) const EXR_TYPE: &str = "image/x-exr";
pub(super) const DDS_TYPE: &str = "image/vnd-ms.dds";
