//! Downloads of a succeeded bake's results: horizon layers (stored, or encoded on their first
//! request), Fourier layers and the layered textures, streamed from the blob store.

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

/// Answers with immutable bytes: strong ETag = the content hash, 304 on If-None-Match.
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
    let hash = result_hash(&st, rec, &name).await?;
    blob_response(&st, &headers, &hash, content_type, &format!("horizon_{layer}.{ext}")).await
}

/// The blob of result `name` of a succeeded bake: stored already, or encoded now (on the preview
/// pool, once however many requests ask at the same time) and kept for the next request.
pub(super) async fn result_hash(
    st: &AppState,
    rec: BakeRecord,
    name: &str,
) -> Result<String, Problem> {
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

pub(super) fn not_produced(id: &str, what: &str) -> Problem {
    Problem::new(
        StatusCode::CONFLICT,
        "result_not_requested",
        format!("bake `{id}` did not compute `{what}`; submit it with outputs including {what}"),
    )
}

/// A stored terrain product (SPEC §3.7): `file` of a bake submitted with `outputs` naming `what`.
async fn terrain_product(
    st: &AppState,
    id: &str,
    q: Vec<(String, String)>,
    headers: &HeaderMap,
    file: &'static str,
    what: &str,
) -> Answer {
    known_query(q, &[])?;
    let rec = finished(st, id).await?;
    let Some(hash) = rec.results.get(file) else {
        return Err(not_produced(id, what));
    };
    blob_response(st, headers, hash, "image/tiff", file).await
}

/// `GET /v1/bakes/{id}/angles`: `angles.tif`, one GeoTIFF band per bin (SPEC §3.7).
pub async fn angles(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    terrain_product(&st, &id, q, &headers, "angles.tif", "angles").await
}

/// `GET /v1/bakes/{id}/svf`: `svf.tif`, the sky-view factor (SPEC §3.7).
pub async fn svf(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    terrain_product(&st, &id, q, &headers, "svf.tif", "svf").await
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
    let result = worker::texture_result_name(ext, &opts, layer);
    let hash = result_hash(&st, rec, &result).await?;
    let file = match layer {
        Some(i) => format!("horizon_{i}.{ext}"),
        None => name.to_owned(),
    };
    blob_response(&st, &headers, &hash, content_type, &file).await
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
pub(super) const DDS_TYPE: &str = "image/vnd-ms.dds";
