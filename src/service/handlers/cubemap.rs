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

/// Bytes computed in memory, answered with their type, an inline file name, `ETag` and
/// `Cache-Control`: the one shape of every computed download (cube maps, previews, shadows,
/// SVF renderings).
pub(super) fn computed_response(
    body: Vec<u8>,
    content_type: &'static str,
    filename: &str,
    etag: &str,
    cache_control: &'static str,
) -> Response {
    let mut res = Response::new(Body::from(body));
    res.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    if let Ok(v) = HeaderValue::from_str(&format!("inline; filename=\"{filename}\"")) {
        res.headers_mut().insert(header::CONTENT_DISPOSITION, v);
    }
    cache_headers(&mut res, etag, cache_control);
    res
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
        &formats.texture.pairs().iter().map(|(k, v)| format!("{k}={v}&")).collect::<String>(),
    ]);
    if etag_matches(headers, &etag) {
        let mut res = StatusCode::NOT_MODIFIED.into_response();
        cache_headers(&mut res, &etag, CUBE_CACHE);
        return Ok(res);
    }
    st.0.metrics.rendered(Render::Cube);
    let file = blocking(move || {
        let mut files = crate::pipeline::cube_files(size, formats)?;
        if pick >= files.len() {
            return Err(Error::Internal("cube map file missing".into()));
        }
        Ok(files.swap_remove(pick))
    })
    .await
    .map_err(store_err)?;
    Ok(computed_response(file.bytes, content_type, file.name, &etag, CUBE_CACHE))
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
    let formats = CubeFormats { png8: true, ..Default::default() };
    cube_answer(&st, &headers, size, formats, face, "image/png").await
}

/// The SPEC §8 options a cube-map texture takes (`texture_precision` unorm8 or bc7, `mips`,
/// `mip_filter`, `supercompression`, `zstd_level` for KTX2, `dds_header` for DDS) from the
/// query.
fn cube_texture(
    q: &HashMap<String, String>,
    ktx2: bool,
) -> Result<crate::encode::TextureOptions, Problem> {
    let keys: &[&str] = if ktx2 {
        &["texture_precision", "mips", "mip_filter", "supercompression", "zstd_level"]
    } else {
        &["texture_precision", "mips", "mip_filter", "dds_header"]
    };
    let opts = crate::encode::TextureOptions::from_pairs(
        keys.iter().filter_map(|k| q.get(*k).map(|v| (*k, v.as_str()))),
    )?;
    opts.check_for(ktx2, !ktx2, true)?;
    Ok(opts)
}

/// `GET /v1/cubemap.ktx2?size=N`: the six faces as one RGBA8 SNORM cube map, or BC7 blocks of
/// the UNORM faces with `texture_precision=bc7` (with `mips`, `mip_filter`,
/// `supercompression`, `zstd_level` as SPEC §8 says).
pub async fn cubemap_ktx2(
    State(st): State<AppState>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let q = known_query(
        q,
        &["size", "texture_precision", "mips", "mip_filter", "supercompression", "zstd_level"],
    )?;
    let size = cube_size(&st, &q)?;
    let texture = cube_texture(&q, true)?;
    let formats = CubeFormats { ktx2: true, texture, ..Default::default() };
    cube_answer(&st, &headers, size, formats, 0, KTX2_TYPE).await
}

/// `GET /v1/cubemap.dds?size=N`: the six faces as one RGBA8 SNORM DDS cube map, or BC7 with
/// `texture_precision=bc7` (with `mips`, `mip_filter`, `dds_header`).
pub async fn cubemap_dds(
    State(st): State<AppState>,
    Query(q): Query<Vec<(String, String)>>,
    headers: HeaderMap,
) -> Answer {
    let q = known_query(q, &["size", "texture_precision", "mips", "mip_filter", "dds_header"])?;
    let size = cube_size(&st, &q)?;
    let texture = cube_texture(&q, false)?;
    let formats = CubeFormats { dds: true, texture, ..Default::default() };
    cube_answer(&st, &headers, size, formats, 0, DDS_TYPE).await
}
