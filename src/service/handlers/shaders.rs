//! The shader includes (SPEC §8): `GET /v1/shaders` lists them, `GET /v1/shaders/{file}` answers
//! one as text with a strong ETag (the BLAKE3 of its text) and `Cache-Control: no-cache`, so a
//! client revalidates (a 304 costs nothing) and never keeps an include older than the server's
//! viewer. Like `/openapi.yaml` they hold no data and sit outside the API key: the web page's
//! viewer fetches the GLSL one before anyone could have typed a key.

#![allow(clippy::result_large_err)]

use super::*;
use crate::shaders::{self, ShaderFile};

/// The `GET /v1/shaders` answer.
#[derive(Debug, serde::Serialize)]
pub struct ShaderList {
    pub files: Vec<ShaderEntry>,
}

/// One file of [`ShaderList`].
#[derive(Debug, serde::Serialize)]
pub struct ShaderEntry {
    #[serde(flatten)]
    pub file: ShaderFile,
    pub bytes: usize,
    pub etag: String,
    pub href: String,
}

fn etag_of(f: &ShaderFile) -> String {
    format!("\"{}\"", &blake3::hash(f.text.as_bytes()).to_hex()[..32])
}

const SHADER_CACHE: &str = "no-cache";

/// `GET /v1/shaders`: every shipped shader file.
pub async fn shaders_list() -> Json<ShaderList> {
    Json(ShaderList {
        files: shaders::FILES
            .iter()
            .map(|f| ShaderEntry {
                file: *f,
                bytes: f.text.len(),
                etag: etag_of(f),
                href: format!("/v1/shaders/{}", f.name),
            })
            .collect(),
    })
}

/// `GET /v1/shaders/{file}`: one shader file as `text/plain`; 404 `shader_not_found` for a name
/// not in the list.
pub async fn shader_file(Path(name): Path<String>, headers: HeaderMap) -> Answer {
    let Some(f) = shaders::find(&name) else {
        return Err(Problem::new(
            StatusCode::NOT_FOUND,
            "shader_not_found",
            format!(
                "no shader file `{name}`; GET /v1/shaders lists them ({})",
                shaders::FILES.iter().map(|f| f.name).collect::<Vec<_>>().join(", ")
            ),
        ));
    };
    let etag = etag_of(f);
    let mut res = if etag_matches(&headers, &etag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        let mut r = Response::new(Body::from(f.text));
        r.headers_mut()
            .insert(header::CONTENT_TYPE, HeaderValue::from_static("text/plain; charset=utf-8"));
        if let Ok(v) = HeaderValue::from_str(&format!("inline; filename=\"{}\"", f.name)) {
            r.headers_mut().insert(header::CONTENT_DISPOSITION, v);
        }
        r
    };
    cache_headers(&mut res, &etag, SHADER_CACHE);
    Ok(res)
}
