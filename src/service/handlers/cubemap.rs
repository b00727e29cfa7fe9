//! The channel-factor cube map: faces and textures, computed on a blocking thread, with a derived
//! ETag so a 304 costs no computation.

#![allow(clippy::result_large_err)]

use super::*;

pub(super) fn cube_size(st: &AppState, q: &HashMap<String, String>) -> Result<usize, Problem> {
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
pub(super) fn derived_etag(parts: &[&str]) -> String {
    let mut h = blake3::Hasher::new();
    h.update(env!("CARGO_PKG_VERSION").as_bytes());
    for p in parts {
        h.update(b"\0");
        h.update(p.as_bytes());
    }
    format!("\"{}\"", &h.finalize().to_hex()[..32])
}

/// Adds `ETag` and `Cache-Control` to a response.
pub(super) fn cache_headers(res: &mut Response, etag: &str, cache_control: &'static str) {
    if let Ok(v) = HeaderValue::from_str(etag) {
        res.headers_mut().insert(header::ETAG, v);
    }
    res.headers_mut().insert(header::CACHE_CONTROL, HeaderValue::from_static(cache_control));
}

/// Cube maps depend only on the size and the format: cacheable by anyone for a day, and
/// revalidated by the derived ETag without re-encoding.
pub(super) const CUBE_CACHE: &str = "public, max-age=86400";

/// Encodes a cube-map file (the CLI's own function) and answers it with a derived ETag; a
/// matching `If-None-Match` is answered 304 before anything is computed.
pub(super) async fn cube_answer(
    st: &AppState,
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
    st.0.metrics.rendered(Render::Cube);
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
    cube_answer(&st, &headers, size, formats, face, "image/png").await
}

/// `GET /v1/cubemap.ktx2?size=N`: the six faces as one RGBA8 SNORM cube map.
pub async fn cubemap_ktx2(
    State(st): State<AppState>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let q = known_query(q, &["size"])?;
    let size = cube_size(&st, &q)?;
    cube_answer(
        &st,
        &headers,
        size,
        CubeFormats { png8: false, ktx2: true, dds: false },
        0,
        KTX2_TYPE,
    )
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
    cube_answer(
        &st,
        &headers,
        size,
        CubeFormats { png8: false, ktx2: false, dds: true },
        0,
        DDS_TYPE,
    )
    .await
}
