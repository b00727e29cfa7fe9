//! Work that decodes a bake's input on the preview pool: the CPU preview and the heights a
//! viewer needs. Never on the bake pool, so it never waits for a running bake.

#![allow(clippy::result_large_err)]

use super::*;

/// Runs `f` on the preview pool (never the async workers, and never behind a long bake: the
/// work a request waits for), panics caught, the result sent back over a oneshot; `what` names
/// the work in the 500 a panic becomes.
pub(super) async fn on_pool<T, F>(st: &AppState, what: &str, f: F) -> Result<T, Problem>
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
    let progress = Progress::new();
    let _cancel = CancelOnDrop(progress.clone());
    st.0.metrics.rendered(Render::Preview);
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
