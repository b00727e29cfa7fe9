//! Work that decodes a bake's input on the preview pool: the CPU preview and the heights a
//! viewer needs. Never on the bake pool, so it never waits for a running bake.

#![allow(clippy::result_large_err)]

use super::*;

/// The pools a request's CPU work runs on, apart from the bake pool.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Pool {
    /// Previews, shadows, profiles, rendered images, heights: a request someone waits for,
    /// under `--preview-timeout-secs`.
    Preview,
    /// On-request encodes, which run in the background of the request that asked.
    Encode,
}

/// Runs `f` on the preview pool under its deadline (see [`run_on`]).
pub(super) async fn on_pool<T, F>(st: &AppState, what: &str, f: F) -> Result<T, Problem>
where
    T: Send + 'static,
    F: FnOnce(&AppState) -> crate::Result<T> + Send + 'static,
{
    run_on(st, Pool::Preview, what, f).await
}

/// Runs `f` on `pool` (never the async workers, and never behind a long bake: the work a
/// request waits for), panics caught, the result sent back over a oneshot; `what` names the
/// work in the 500 a panic becomes. A pool takes [`crate::service::POOL_QUEUE`] requests per
/// thread at once (a 503 with Retry-After beyond: each holds a decoded map). On the preview
/// pool the answer is a 503 `preview_timeout` once `--preview-timeout-secs` pass; the caller's
/// [`CancelOnDrop`] then stops the computation at its next row, and its slot is free when it
/// has stopped.
pub(super) async fn run_on<T, F>(st: &AppState, pool: Pool, what: &str, f: F) -> Result<T, Problem>
where
    T: Send + 'static,
    F: FnOnce(&AppState) -> crate::Result<T> + Send + 'static,
{
    let (threads, slots) = match pool {
        Pool::Preview => (&st.0.preview_pool, &st.0.preview_slots),
        Pool::Encode => (&st.0.encode_pool, &st.0.encode_slots),
    };
    let Ok(slot) = slots.clone().try_acquire_owned() else {
        let mut p = Problem::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "pool_busy",
            format!("too many requests are computing on the {pool:?} pool; retry shortly")
                .to_lowercase(),
        );
        p.retry_after = Some(1);
        return Err(p);
    };
    let (tx, rx) = tokio::sync::oneshot::channel();
    let pool_state = st.clone();
    threads.spawn(move || {
        let _slot = slot;
        let _ = tx.send(catch_unwind(AssertUnwindSafe(|| f(&pool_state))));
    });
    let answer = async {
        match rx.await {
            Ok(Ok(r)) => r.map_err(Problem::from),
            Ok(Err(_)) | Err(_) => Err(Problem::internal(&format!("{what} panicked"))),
        }
    };
    if pool == Pool::Encode {
        return answer.await;
    }
    let limit = st.0.config.preview_timeout;
    tokio::time::timeout(limit, answer).await.unwrap_or_else(|_| {
        Err(Problem::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "preview_timeout",
            format!(
                "{what} took longer than the server allows ({}s, --preview-timeout-secs); ask \
                 for a smaller size or fewer steps",
                limit.as_secs()
            ),
        ))
    })
}

/// The bake's stored input decoded on a pool thread (its `channel`, unscaled), with its decode
/// reserved from the process's budget for as long as the map lives.
fn decode_stored(
    st: &AppState,
    rec: &crate::jobs::record::BakeRecord,
    params: &crate::params::BakeParams,
) -> crate::Result<(
    crate::heightmap::HeightMap,
    crate::heightmap::InputInfo,
    crate::heightmap::budget::Reservation,
)> {
    job::decode_input(
        st.0.jobs.blob_store().as_ref(),
        rec,
        params,
        &st.0.config.limits,
        Some(st.admit()),
    )
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
            format!(
                "heights|{}|{:?}|{}",
                rec.input_blob,
                params.decode_channel(),
                params.height_scale
            )
            .as_bytes()
        )
        .to_hex()
    );
    let mut res = if etag_matches(&headers, &etag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        let (w, h, bytes) = on_pool(&st, &format!("the heights of bake {id}"), move |st| {
            let (map, _, _held) = decode_stored(st, &rec, &params)?;
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
pub(super) struct CancelOnDrop(Progress);

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
    let progress = Progress::with_scratch_dir(st.0.jobs.config().scratch_dir.clone());
    let _cancel = CancelOnDrop(progress.clone());
    st.0.metrics.rendered(Render::Preview);
    let png = on_pool(&st, &format!("the preview of bake {id}"), move |st| {
        let (map, _, _held) = decode_stored(st, &rec, &params)?;
        preview::render_baking(&map, &params, &pp, &progress)?.to_png()
    })
    .await?;
    Ok(computed_response(png, "image/png", &format!("preview_{id}.png"), &etag, PREVIEW_CACHE))
}

/// `GET /v1/bakes/{id}/shadow?…`: the sun shadow (SPEC §3.7) of the bake's stored input with its
/// resolved parameters, as a uint8 GeoTIFF, for `sun_azimuth` + `sun_elevation` or `sun_time` +
/// `latitude` + `longitude` (NREL SPA); `format=png` for an 8-bit grey + alpha PNG a browser
/// shows (lit 255, shadow 0, holes transparent). Computed on request on the preview pool, like a preview;
/// its strong ETag is known before computing.
pub async fn shadow(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    const KEYS: &[&str] = &["sun_azimuth", "sun_elevation", "sun_time", "latitude", "longitude"];
    let mut q = q;
    let as_png = results::take_terrain_format(&mut q)?;
    let q = known_query(q, KEYS)?;
    let rec = finished(&st, &id).await?;
    let params = params_of(&rec).map_err(store_err)?;
    let get = |k: &str| q.get(k).map(String::as_str);
    let sun = crate::terrain::sun::SunQuery::parse(
        get("sun_azimuth"),
        get("sun_elevation"),
        get("sun_time"),
        get("latitude"),
        get("longitude"),
        params.azimuth_from,
    )
    .map_err(Problem::from)?;
    let bake_params: Vec<String> = rec.params.iter().map(|(k, v)| format!("{k}={v}")).collect();
    let etag = derived_etag(&[
        "shadow",
        &rec.input_blob,
        &bake_params.join("&"),
        &format!("{sun:?}|{as_png}"),
    ]);
    const SHADOW_CACHE: &str = "private, max-age=86400";
    if etag_matches(&headers, &etag) {
        let mut res = StatusCode::NOT_MODIFIED.into_response();
        cache_headers(&mut res, &etag, SHADOW_CACHE);
        return Ok(res);
    }
    let progress = Progress::with_scratch_dir(st.0.jobs.config().scratch_dir.clone());
    let _cancel = CancelOnDrop(progress.clone());
    let tif = on_pool(&st, &format!("the shadow of bake {id}"), move |st| {
        let mut params = params;
        let (map, _, _held) = decode_stored(st, &rec, &params)?;
        crate::heightmap::georef::apply_dem_defaults(&mut params, map.terrain.georef.as_ref())?;
        if as_png {
            crate::pipeline::shadow_png(&map, &params, &sun, &progress)
        } else {
            crate::pipeline::shadow_tif(&map, &params, &sun, &progress)
        }
    })
    .await?;
    let (ct, ext) = if as_png { ("image/png", "png") } else { ("image/tiff", "tif") };
    Ok(computed_response(tif, ct, &format!("shadow_{id}.{ext}"), &etag, SHADOW_CACHE))
}

/// `GET /v1/bakes/{id}/profile?x=&y=` (texel column and row) or `?easting=&northing=` (map
/// coordinates in the CRS): the exact horizon profile (SPEC §3.7) at `bins` azimuths (default
/// 360), as JSON, or CSV with `Accept: text/csv`. Computed on the preview pool.
pub async fn profile(
    State(st): State<AppState>,
    Path(id): Path<String>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let q = known_query(q, &["x", "y", "easting", "northing", "bins"])?;
    let num = |k: &str| -> Result<Option<f64>, Problem> {
        q.get(k).map(|v| crate::params::parse_f64(k, v).map_err(Problem::from)).transpose()
    };
    let bins = match q.get("bins") {
        Some(b) => crate::params::parse_u32("bins", b).map_err(Problem::from)?,
        None => 360,
    };
    if !(1..=3600).contains(&bins) {
        return Err(Problem::param("bins", "must be between 1 and 3600"));
    }
    let at = match (num("x")?, num("y")?, num("easting")?, num("northing")?) {
        (Some(x), Some(y), None, None) => (x, y, false),
        (None, None, Some(e), Some(n)) => (e, n, true),
        _ => return Err(Problem::param("x", "give x and y, or easting and northing")),
    };
    let csv = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.contains("text/csv"));
    let rec = finished(&st, &id).await?;
    let params = params_of(&rec).map_err(store_err)?;
    let (text, ct) = on_pool(&st, &format!("the profile of bake {id}"), move |st| {
        let mut params = params;
        let (map, _, _held) = decode_stored(st, &rec, &params)?;
        crate::heightmap::georef::apply_dem_defaults(&mut params, map.terrain.georef.as_ref())?;
        let (x, y) = if at.2 {
            let t = map.terrain.georef.as_ref().and_then(|g| g.transform()).ok_or_else(|| {
                crate::Error::param("easting", "the input has no georeferencing; use x and y")
            })?;
            ((at.0 - t[0]) / t[1] - 0.5, (at.1 - t[3]) / t[5] - 0.5)
        } else {
            (at.0, at.1)
        };
        let (xr, yr) = (x.round(), y.round());
        if xr < 0.0 || yr < 0.0 || xr >= map.width as f64 || yr >= map.height as f64 {
            return Err(crate::Error::param(
                if at.2 { "easting" } else { "x" },
                format!("({x}, {y}) is outside the {}×{} map", map.width, map.height),
            ));
        }
        let p =
            crate::bake::horizon_profile(&map, &params, xr as usize, yr as usize, bins as usize)?;
        Ok(if csv {
            (crate::terrain::profile::to_csv(&p), "text/csv")
        } else {
            let v = serde_json::json!({
                "x": xr, "y": yr, "azimuth_from": params.azimuth_from,
                "profile": p.iter().map(|(a, e)| serde_json::json!({"azimuth": a, "elevation": e}))
                    .collect::<Vec<_>>(),
            });
            (v.to_string(), "application/json")
        })
    })
    .await?;
    let mut r = Response::new(Body::from(text));
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(ct));
    Ok(r)
}
