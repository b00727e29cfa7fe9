//! Submission, listing, reading and cancelling bakes: `POST /v1/bakes`, `GET /v1/bakes`,
//! `GET` and `DELETE /v1/bakes/{id}`. Each parses, calls the jobs core, and answers.

#![allow(clippy::result_large_err)]

use super::*;

/// Media types accepted as a raw-body upload (the bytes are sniffed anyway).
pub(super) const RAW_TYPES: &[&str] =
    &["image/png", "image/tiff", "image/x-exr", "image/exr", "application/octet-stream"];

/// The 413 of a body larger than `--max-body-bytes`, stating the limit.
fn too_large(max_bytes: u64) -> Problem {
    Problem::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "payload_too_large",
        format!(
            "the request body is larger than the server accepts: at most {max_bytes} bytes \
             ({:.1} MiB, the server's --max-body-bytes)",
            max_bytes as f64 / (1024.0 * 1024.0)
        ),
    )
}

/// The answer to a body that could not be read: too large (the detail states the limit, so a
/// client knows what to send), stalled, or broken.
pub(super) fn body_error(
    e: &(dyn std::error::Error + 'static),
    timeout: Duration,
    max_bytes: u64,
) -> Problem {
    match upload::fault(e) {
        upload::BodyFault::TooLarge => too_large(max_bytes),
        upload::BodyFault::TimedOut => Problem::new(
            StatusCode::REQUEST_TIMEOUT,
            "body_timeout",
            format!(
                "the request body stalled for {}s (body_timeout_secs); send it without pauses",
                timeout.as_secs()
            ),
        ),
        upload::BodyFault::TooSlow => Problem::new(
            StatusCode::REQUEST_TIMEOUT,
            "body_too_slow",
            format!(
                "the request body arrived slower than the server's minimum upload rate over {}s \
                 (--min-upload-rate); send it at a steady pace",
                upload::RATE_WINDOW.as_secs()
            ),
        ),
        upload::BodyFault::Other => Problem::new(
            StatusCode::BAD_REQUEST,
            "bad_request",
            "the request body could not be read",
        ),
    }
}

/// What a submission asks besides the bake's parameters: which result formats to encode with
/// the bake (`formats`, the CLI's `--format` list, default `png8`), at which EXR precision
/// (`exr_precision`, the CLI's `--exr-precision`) and, for `ktx2`/`dds`, which texture variant
/// (SPEC §8's options, [`crate::encode::texture::OPTION_KEYS`], as the CLI's flags and the
/// texture routes' query). They are not bake parameters: the same input and parameters are the
/// same bake whatever formats were asked, and a format or variant not asked is encoded on its
/// first request.
#[derive(Debug, Clone, Default)]
pub(super) struct Delivery {
    formats: Option<String>,
    exr_precision: Option<String>,
    /// The texture options given, in order (each key at most once).
    texture: Vec<(String, String)>,
}

/// The submission keys that are not bake parameters: `formats`, `exr_precision` and the
/// texture options (SPEC §5, §8).
const DELIVERY_KEYS: [&str; 9] = [
    "formats",
    "exr_precision",
    "texture_precision",
    "mips",
    "mip_filter",
    "supercompression",
    "zstd_level",
    "texture_layout",
    "dds_header",
];

/// Every key a submission accepts: the bake parameters ([`crate::params::PARAM_NAMES`], the
/// list [`BakeParams::set`] is tested against) and the delivery keys. The unknown-key message is
/// built from it, so it lists what the server really takes.
pub fn submission_keys() -> Vec<&'static str> {
    crate::params::PARAM_NAMES.iter().chain(DELIVERY_KEYS.iter()).copied().collect()
}

/// A 422 naming `key` unless a submission accepts it.
fn known_submission_key(key: &str) -> Result<(), Problem> {
    if crate::params::PARAM_NAMES.contains(&key) || DELIVERY_KEYS.contains(&key) {
        return Ok(());
    }
    Err(Problem::param(
        key,
        format!("unknown parameter; known ones are {}", submission_keys().join(", ")),
    ))
}

impl Delivery {
    fn set(&mut self, key: &str, value: &str) -> Result<(), Problem> {
        let slot = match key {
            "formats" => &mut self.formats,
            "exr_precision" => &mut self.exr_precision,
            _ => {
                if self.texture.iter().any(|(k, _)| k == key) {
                    return Err(Problem::param(key, "given more than once"));
                }
                self.texture.push((key.to_owned(), value.to_owned()));
                return Ok(());
            }
        };
        if slot.is_some() {
            return Err(Problem::param(key, "given more than once"));
        }
        *slot = Some(value.to_owned());
        Ok(())
    }

    /// The formats to encode with the bake, checked as the CLI checks `--format`,
    /// `--exr-precision` and the texture flags (a texture option without `ktx2` or `dds`, or
    /// one neither container asked for takes, is a 422 naming it).
    pub(super) fn resolve(&self) -> Result<Formats, Problem> {
        let list = self.formats.as_deref().unwrap_or("png8");
        let mut f = Formats::parse(list, TexturePrecision::Unorm8).map_err(|e| match e {
            Error::Param { message, .. } => Problem::param("formats", message),
            other => Problem::from(other),
        })?;
        if let Some(p) = &self.exr_precision {
            if !f.exr {
                return Err(Problem::param("exr_precision", "applies only when formats has exr"));
            }
            f.exr_precision = ExrPrecision::parse("exr_precision", p)?;
        }
        if let Some((key, _)) = self.texture.first() {
            if !(f.ktx2 || f.dds) {
                return Err(Problem::param(
                    key.clone(),
                    "applies only when formats has ktx2 or dds",
                ));
            }
            f.texture = crate::encode::TextureOptions::from_pairs(
                self.texture.iter().map(|(k, v)| (k.as_str(), v.as_str())),
            )?;
            f.texture.check_for(f.ktx2, f.dds, false)?;
        }
        Ok(f)
    }
}

/// The bake parameters of a query string, what it asks besides them, and the keys it gave.
pub(super) fn query_params(
    uri: &axum::http::Uri,
) -> Result<(BakeParams, Delivery, Vec<String>), Problem> {
    let pairs: Vec<(String, String)> = match Query::<Vec<(String, String)>>::try_from_uri(uri) {
        Ok(Query(p)) => p,
        Err(_) => return Err(Problem::param("query", "the query string is malformed")),
    };
    for (k, _) in &pairs {
        known_submission_key(k)?;
    }
    let mut delivery = Delivery::default();
    for (k, v) in pairs.iter().filter(|(k, _)| DELIVERY_KEYS.contains(&k.as_str())) {
        delivery.set(k, v)?;
    }
    // Unchecked: the multipart JSON part may hold the other half of a combination; `submit`
    // checks once both are merged.
    let params = BakeParams::from_pairs_unchecked(
        pairs
            .iter()
            .filter(|(k, _)| !DELIVERY_KEYS.contains(&k.as_str()))
            .map(|(k, v)| (k.as_str(), v.as_str())),
    )
    .map_err(Problem::from)?;
    Ok((params, delivery, pairs.into_iter().map(|(k, _)| k).collect()))
}

/// Applies the keys of a multipart `params` JSON object on top of `base` (the query's). A key
/// given in both is refused (422 naming it), as a key given twice in the query or in the JSON is:
/// one rule everywhere, since which one "wins" would be a guess about what the client meant.
pub(super) fn merge_json(
    base: (BakeParams, Delivery),
    query_keys: &[String],
    text: &[u8],
) -> Result<(BakeParams, Delivery), Problem> {
    if text.iter().all(u8::is_ascii_whitespace) {
        return Ok(base);
    }
    let given = crate::params::json_object_pairs(text).map_err(Problem::from)?;
    let (mut merged, mut delivery) = base;
    for (k, v) in &given {
        known_submission_key(k)?;
        if query_keys.iter().any(|q| q == k) {
            return Err(Problem::param(
                k.clone(),
                "given both in the query string and in the `params` part",
            ));
        }
        if let Some(text) = crate::params::json_value_text(k, v).map_err(Problem::from)? {
            if DELIVERY_KEYS.contains(&k.as_str()) {
                delivery.set(k, &text)?;
            } else {
                merged.set(k, &text).map_err(Problem::from)?;
            }
        }
    }
    Ok((merged, delivery))
}

/// The spool an upload for bake `id` reads into: in memory up to
/// [`upload::STREAM_UPLOAD_ABOVE`], then streamed to the blob store, pinned for the submission.
fn spool_for(st: &AppState, id: &str, expected: usize) -> upload::Spool {
    let blobs = st.0.jobs.blobs_for(format!("submit/{id}"));
    upload::Spool::new(
        expected,
        upload::STREAM_UPLOAD_ABOVE,
        Box::new(move || Ok(Box::new(blobs.writer()?) as Box<dyn upload::SpoolWriter>)),
    )
}

pub(super) async fn read_multipart(
    st: &AppState,
    req: Request,
    id: &str,
) -> Result<(upload::Upload, (BakeParams, Delivery)), Problem> {
    let (query, query_delivery, query_keys) = query_params(req.uri())?;
    let query = (query, query_delivery);
    let timeout = st.0.config.body_timeout;
    let max_bytes = st.0.config.max_body_bytes;
    // The whole request's announced length: past the threshold, the image part is spooled
    // from its first byte.
    let announced = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok()?.parse::<u64>().ok())
        .unwrap_or(0)
        .min(max_bytes) as usize;
    let mut mp = axum::extract::Multipart::from_request(req, st).await.map_err(|e| {
        Problem::new(
            StatusCode::BAD_REQUEST,
            "bad_request",
            format!("malformed multipart body: {}", e.body_text()),
        )
    })?;
    let mut image: Option<upload::Upload> = None;
    let mut params: Option<(BakeParams, Delivery)> = None;
    // A part refused mid-body is answered only once the rest of the body is read (and thrown
    // away): a server that answers and closes with bytes unread resets the connection, and the
    // client, still writing, sees a broken pipe instead of the answer. The drain costs what the
    // body limits already bound (`--max-body-bytes`, `--min-upload-rate`), no memory.
    let mut refused: Option<Problem> = None;
    loop {
        let mut field = match mp.next_field().await {
            Ok(Some(f)) => f,
            Ok(None) => break,
            Err(e) => {
                return Err(refused.unwrap_or_else(|| multipart_error(&e, timeout, max_bytes)))
            }
        };
        if refused.is_none() {
            let read = read_part(
                st,
                id,
                announced,
                &query,
                &query_keys,
                &mut field,
                &mut image,
                &mut params,
            );
            match read.await {
                Ok(()) => {}
                // The body itself failed: nothing more can be read from it.
                Err(Refusal::Body(p)) => return Err(p),
                Err(Refusal::Part(p)) => refused = Some(p),
            }
        }
        if let Some(p) = &refused {
            loop {
                match field.chunk().await {
                    Ok(Some(_)) => {}
                    Ok(None) => break,
                    Err(_) => return Err(p.clone()),
                }
            }
        }
    }
    if let Some(p) = refused {
        return Err(p);
    }
    let image = image
        .ok_or_else(|| Problem::param("heightmap", "the multipart body has no `heightmap` part"))?;
    Ok((image, params.unwrap_or(query)))
}

/// Why a part was not taken: its body could not be read (answered at once), or what it holds
/// is refused (answered once the rest of the body is drained).
enum Refusal {
    Body(Problem),
    Part(Problem),
}

impl From<Problem> for Refusal {
    fn from(p: Problem) -> Self {
        Refusal::Part(p)
    }
}

/// Reads one part of a multipart submission into `image` or `params`.
#[allow(clippy::too_many_arguments)]
async fn read_part(
    st: &AppState,
    id: &str,
    announced: usize,
    query: &(BakeParams, Delivery),
    query_keys: &[String],
    field: &mut axum::extract::multipart::Field<'_>,
    image: &mut Option<upload::Upload>,
    params: &mut Option<(BakeParams, Delivery)>,
) -> Result<(), Refusal> {
    let timeout = st.0.config.body_timeout;
    let max_bytes = st.0.config.max_body_bytes;
    let name = field.name().unwrap_or("").to_owned();
    match name.as_str() {
        "heightmap" => {
            if image.is_some() {
                return Err(Problem::param("heightmap", "given more than once").into());
            }
            // Read piece by piece: a large image goes to the blob store as it arrives.
            let mut spool = spool_for(st, id, announced);
            while let Some(chunk) = field
                .chunk()
                .await
                .map_err(|e| Refusal::Body(multipart_error(&e, timeout, max_bytes)))?
            {
                spool.push(chunk).await.map_err(store_err)?;
            }
            *image = Some(spool.finish().await.map_err(store_err)?);
        }
        "params" => {
            if params.is_some() {
                return Err(Problem::param("params", "given more than once").into());
            }
            let mut text = Vec::new();
            while let Some(chunk) = field
                .chunk()
                .await
                .map_err(|e| Refusal::Body(multipart_error(&e, timeout, max_bytes)))?
            {
                text.extend_from_slice(&chunk);
                if text.len() > crate::params::MAX_PARAMS_BYTES {
                    return Err(Problem::new(
                        StatusCode::PAYLOAD_TOO_LARGE,
                        "payload_too_large",
                        format!(
                            "the `params` part is larger than {} bytes; a bake's parameters \
                             take a few hundred",
                            crate::params::MAX_PARAMS_BYTES
                        ),
                    )
                    .into());
                }
            }
            *params = Some(merge_json(query.clone(), query_keys, &text)?);
        }
        other => {
            return Err(Problem::param(
                if other.is_empty() { "multipart" } else { other },
                "unknown multipart part; expected `heightmap` and optionally `params`",
            )
            .into())
        }
    }
    Ok(())
}

pub(super) fn multipart_error(
    e: &axum::extract::multipart::MultipartError,
    timeout: Duration,
    max_bytes: u64,
) -> Problem {
    match upload::fault(e) {
        upload::BodyFault::Other if e.status() != StatusCode::PAYLOAD_TOO_LARGE => Problem::new(
            StatusCode::BAD_REQUEST,
            "bad_request",
            format!("malformed multipart body: {}", e.body_text()),
        ),
        upload::BodyFault::Other => body_error(&upload::BodyTooLarge(0), timeout, max_bytes),
        _ => body_error(e, timeout, max_bytes),
    }
}

pub(super) async fn read_raw(
    st: &AppState,
    req: Request,
    ct: &str,
    id: &str,
) -> Result<(upload::Upload, (BakeParams, Delivery)), Problem> {
    let mime = ct.split(';').next().unwrap_or("").trim().to_ascii_lowercase();
    let (params, delivery, _) = query_params(req.uri())?;
    let timeout = st.0.config.body_timeout;
    let announced = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok()?.parse::<u64>().ok())
        .unwrap_or(0)
        .min(st.0.config.max_body_bytes) as usize;
    use futures_util::StreamExt;
    let mut spool = spool_for(st, id, announced);
    let mut body = req.into_body().into_data_stream();
    while let Some(chunk) = body.next().await {
        let chunk = chunk.map_err(|e| body_error(&e, timeout, st.0.config.max_body_bytes))?;
        spool.push(chunk).await.map_err(store_err)?;
    }
    let bytes = spool.finish().await.map_err(store_err)?;
    // Checked after the body is read, so the client gets this answer rather than a reset.
    if !mime.is_empty() && !RAW_TYPES.contains(&mime.as_str()) {
        return Err(Error::Unsupported(format!(
            "Content-Type `{}` is not accepted; send {} or multipart/form-data",
            crate::service::problem::cap(&mime, 100),
            RAW_TYPES.join(", ")
        ))
        .into());
    }
    Ok((bytes, (params, delivery)))
}

pub(super) fn retry_after(st: &AppState, waiting: u64) -> u64 {
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
    // A client that waits for `100 Continue` has sent nothing yet: a body announced larger than
    // the limit is refused at once, before hyper would send the 100 (it does when the body is
    // first read), so the client never starts sending it. Without the expectation the body is
    // read and discarded before the 413 (see `app`), or the client would see a reset.
    let announced = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok()?.trim().parse::<u64>().ok());
    let expects_continue = req
        .headers()
        .get(header::EXPECT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.trim().eq_ignore_ascii_case("100-continue"));
    if expects_continue && announced.is_some_and(|n| n > st.0.config.max_body_bytes) {
        return Err(too_large(st.0.config.max_body_bytes));
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
    let c = &st.0.config;
    let bounds = upload::Bounds {
        limit: c.max_body_bytes,
        idle: c.body_timeout,
        min_rate: c.min_upload_rate,
    };
    let body = upload::guarded(body, bounds);
    let req = Request::from_parts(parts, body);
    // The id is chosen first: a large upload is stored (pinned for it) while it arrives.
    let id = new_id();
    let (upload, (params, delivery)) = if ct.to_ascii_lowercase().starts_with("multipart/form-data")
    {
        read_multipart(&st, req, &id).await?
    } else {
        read_raw(&st, req, &ct, &id).await?
    };
    // Rules joining several parameters (bins against method and outputs), once all are merged.
    // (Those a DEM's defaults may change wait for them: the decode checks again.)
    params.check_before_input().map_err(Problem::from)?;
    let formats = delivery.resolve()?;
    if !(params.outputs.horizon || params.outputs.surface()) && formats != Formats::default() {
        // As the CLI: a format of horizon layers or surface maps that a bake of neither (a
        // Fourier-only or terrain bake) would never write.
        return Err(Problem::param(
            "formats",
            "applies to horizon layers and surface maps, and `outputs` includes neither",
        ));
    }
    // Format and dimensions from the header against the limits, before any pixel allocation;
    // then, for float images only, the values (NaN, infinities, out of range), so such an input
    // is a 422 now rather than a failed bake later. Integer images cannot hold a bad value.
    // A DEM's defaults (SPEC §2: cell size, height_scale, edge, curvature) are resolved here,
    // so the stored parameters, the dedup key and the bake resource show what will be baked.
    let limits = st.0.config.limits;
    // The bytes when in memory, or the stored blob (hash, length) of a large upload.
    let (bytes, stored, params, ((fmt, width, height), georef)) = match upload {
        upload::Upload::Memory(bytes) => {
            let (budget, wait, tiles) =
                (st.0.decode_budget.clone(), st.0.config.upload_wait, st.0.config.tiles);
            blocking(move || {
                let mut params = params;
                let (_, w, h) = heightmap::probe(&bytes, &limits)?;
                let probed = if tiles.tiles(w, h) {
                    heightmap::check_submission_streamed(&bytes, &mut params, &limits)?
                } else {
                    // Reserved from the process's decode budget before the decode allocates,
                    // given back when it returns.
                    let admit = heightmap::budget::Admit { budget: &budget, wait: Some(wait) };
                    heightmap::check_submission_for_in(&bytes, &mut params, &limits, Some(admit))?
                };
                crate::bake::fit_method(&mut params, w, h, tiles.tiles(w, h))?;
                Ok((Some(bytes), None, params, probed))
            })
            .await?
        }
        upload::Upload::Stored { hash, len } => {
            // Too large to hold: its header (format, dimensions, georeferencing and the DEM
            // defaults) is read from the store by ranged reads; its values are checked by the
            // decode when the bake runs.
            let (store, tiles) = (st.0.jobs.blob_store().clone(), st.0.config.tiles);
            blocking(move || {
                let mut params = params;
                let r = crate::jobs::blob::BlobSeekReader::open(store, &hash)?
                    .ok_or_else(|| Error::Internal("the stored upload is gone".into()))?;
                let ((f, w, h), georef) = heightmap::stream::probe_for(r, &mut params, &limits)?;
                crate::bake::fit_method(&mut params, w, h, tiles.tiles(w, h))?;
                let f = match f {
                    "png" => image::ImageFormat::Png,
                    "tiff" => image::ImageFormat::Tiff,
                    _ => image::ImageFormat::OpenExr,
                };
                Ok((None, Some((hash, len)), params, ((f, w, h), georef)))
            })
            .await?
        }
    };
    let format = match fmt {
        image::ImageFormat::Png => "png",
        image::ImageFormat::Tiff => "tiff",
        _ => "exr",
    };
    // A map above --tile-above is baked in tiles (SPEC §7.1): refuse now what tiles cannot do.
    crate::pipeline::tiled::check(&params, &formats, width, height, &st.0.config.tiles)?;
    // Its tiles are cut by the streamed decode: refuse now (415/422) an encoding it cannot
    // stream (OpenEXR, interlaced PNG, planar TIFF) rather than fail the bake at its split.
    let (bytes, stored) = if st.0.config.tiles.tiles(width, height) {
        let store = st.0.jobs.blob_store().clone();
        let channel = params.decode_channel();
        blocking(move || {
            match (&bytes, &stored) {
                (Some(b), _) => {
                    heightmap::stream::check_streamable(std::io::Cursor::new(b), channel, &limits)?
                }
                (None, Some((hash, _))) => {
                    let r = crate::jobs::blob::BlobSeekReader::open(store, hash)?
                        .ok_or_else(|| Error::Internal("the stored upload is gone".into()))?;
                    heightmap::stream::check_streamable(r, channel, &limits)?
                }
                (None, None) => {}
            }
            Ok((bytes, stored))
        })
        .await?
    } else {
        (bytes, stored)
    };
    let mut pairs: Vec<(String, String)> =
        params.to_pairs().into_iter().map(|(k, v)| (k.to_owned(), v)).collect();
    if params.outputs.surface() && (formats.ktx2 || formats.dds || formats.png16 || formats.exr) {
        // The surface maps' textures, 16-bit PNGs and EXRs are written by the bake itself (the
        // horizon layers' variants are encoded on request instead), so a bake that wrote other
        // ones, or none, is not this one.
        let texture =
            serde_json::to_string(&formats).map_err(|e| Error::Internal(e.to_string()))?;
        pairs.push(("surface_textures".to_owned(), texture));
    }
    let (bytes, input_hash, input_bytes, key) = blocking(move || {
        let (input_hash, len) = match (&bytes, stored) {
            (Some(b), _) => (blake3::hash(b).to_hex().to_string(), b.len() as u64),
            (None, Some(s)) => s,
            (None, None) => return Err(Error::Internal("an upload with no bytes".into())),
        };
        let mut h = blake3::Hasher::new();
        h.update(input_hash.as_bytes());
        for (k, v) in &pairs {
            h.update(b"\n");
            h.update(k.as_bytes());
            h.update(b"=");
            h.update(v.as_bytes());
        }
        Ok((bytes, input_hash, len, h.finalize().to_hex().to_string()))
    })
    .await
    .map_err(store_err)?;

    let rec = BakeRecord {
        id,
        status: Status::Queued,
        dedup_key: key,
        params: params.to_pairs().into_iter().map(|(k, v)| (k.to_owned(), v)).collect(),
        input_blob: input_hash,
        input_format: format.into(),
        input_bytes,
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
        formats: Some(job::formats_field(&formats)),
        stopped_at: None,
        georeferencing: georef.and_then(|g| serde_json::to_value(g).ok()),
        tiles: None,
    };
    let submitted = match bytes {
        Some(bytes) => st.0.jobs.submit(bytes, rec).await,
        None => st.0.jobs.submit_stored(rec).await,
    };
    let (status, rec) = match submitted.map_err(store_err)? {
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
    let query = record::ListQuery { statuses: statuses.clone(), cursor, limit, newest_first };
    let page = st.0.jobs.list(&query).await.map_err(store_err)?;
    let retention = st.0.config.retention.as_millis() as u64;
    let items: Vec<BakeResource> =
        page.items.iter().map(|r| BakeResource::of(r, retention)).collect();
    let next = page.next.map(|cursor| {
        let c = &cursor;
        let mut link = format!("/v1/bakes?limit={limit}&cursor={c}");
        if !statuses.is_empty() {
            let names: Vec<&str> = statuses.iter().map(|s| s.as_str()).collect();
            link.push_str(&format!("&status={}", names.join(",")));
        }
        if newest_first {
            link.push_str("&order=desc");
        }
        NextPage { cursor: cursor.clone(), href: link }
    });
    Ok((StatusCode::OK, Json(BakePage { items, next, total: page.total })).into_response())
}

/// One page of `GET /v1/bakes`.
#[derive(serde::Serialize)]
pub struct BakePage {
    pub items: Vec<BakeResource>,
    pub next: Option<NextPage>,
    /// Bakes matching the filter, in all pages.
    pub total: u64,
}

/// Where the next page is.
#[derive(serde::Serialize)]
pub struct NextPage {
    pub cursor: String,
    pub href: String,
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
