//! RFC 9457 problem+json answers: the one shape every failure of the HTTP API takes.
//!
//! [`Problem`] is built from the library's [`crate::Error`] (whose variant decides the status,
//! SPEC §5) or from a service condition (unknown bake, not ready, queue full, shutting down,
//! unauthorised). Each carries a stable machine-readable `code`; parameter errors also carry the
//! `field`. 5xx bodies never include the underlying message: it is logged once here and the
//! client gets a generic sentence. Responses that axum or tower produce on their own (404 of an
//! unknown route, 405, 413 from the body limit) are rewritten into the same shape by
//! [`normalize`], so a client only ever parses one error format.

use crate::error::{Error, LimitError};
use axum::body::Body;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

/// The media type of every error body.
pub const PROBLEM_JSON: &str = "application/problem+json";

/// One problem+json answer.
#[derive(Debug, Clone, Serialize)]
pub struct Problem {
    #[serde(rename = "type")]
    pub kind: String,
    pub title: String,
    pub status: u16,
    pub detail: String,
    /// Stable machine-readable code.
    pub code: &'static str,
    /// The parameter at fault, as the API spells it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// Seconds for `Retry-After` (429, 503).
    #[serde(skip)]
    pub retry_after: Option<u64>,
}

/// Longest `field` echoed back, in characters.
pub const MAX_FIELD_CHARS: usize = 64;
/// Longest `detail`, in characters: details quote the client's input, and a 65,000-character
/// query key must not come back twice in a 130 KB answer.
pub const MAX_DETAIL_CHARS: usize = 600;

/// `s` cut to at most `max` characters, with `…` marking the cut.
pub fn cap(s: &str, max: usize) -> String {
    match s.char_indices().nth(max) {
        None => s.to_owned(),
        Some((end, _)) => format!("{}…", &s[..end]),
    }
}

impl Problem {
    /// A problem with `status`, `code` and a human-readable `detail` (capped in length).
    pub fn new(status: StatusCode, code: &'static str, detail: impl Into<String>) -> Self {
        Problem {
            kind: format!("urn:horizon-bake:problem:{code}"),
            title: status.canonical_reason().unwrap_or("Error").to_string(),
            status: status.as_u16(),
            detail: cap(&detail.into(), MAX_DETAIL_CHARS),
            code,
            field: None,
            retry_after: None,
        }
    }

    /// A 422 parameter error naming `field`.
    pub fn param(field: impl Into<String>, detail: impl Into<String>) -> Self {
        let field = cap(&field.into(), MAX_FIELD_CHARS);
        let mut p = Problem::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_parameter",
            format!("invalid parameter `{field}`: {}", detail.into()),
        );
        p.field = Some(field);
        p
    }

    /// 404 for an unknown bake id.
    pub fn bake_not_found(id: &str) -> Self {
        Problem::new(StatusCode::NOT_FOUND, "bake_not_found", format!("no bake with id `{id}`"))
    }

    /// 409: the bake has no such result (yet).
    pub fn not_ready(id: &str, status: &str) -> Self {
        Problem::new(
            StatusCode::CONFLICT,
            "result_not_ready",
            format!("bake `{id}` is {status}; results exist only once it has succeeded"),
        )
    }

    /// 429 with `Retry-After`.
    pub fn queue_full(capacity: usize, retry_after: u64) -> Self {
        let mut p = Problem::new(
            StatusCode::TOO_MANY_REQUESTS,
            "queue_full",
            format!("the bake queue is full ({capacity} waiting); retry later"),
        );
        p.retry_after = Some(retry_after.max(1));
        p
    }

    /// 503 while draining for shutdown.
    pub fn shutting_down() -> Self {
        let mut p = Problem::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "shutting_down",
            "the server is shutting down and accepts no new work",
        );
        p.retry_after = Some(5);
        p
    }

    /// 500 with a sanitised body; `cause` is logged, never sent.
    pub fn internal(cause: &dyn std::fmt::Display) -> Self {
        tracing::error!(%cause, "internal error");
        Problem::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            "an internal error occurred; it has been logged",
        )
    }

    /// The HTTP status.
    pub fn status(&self) -> StatusCode {
        StatusCode::from_u16(self.status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR)
    }
}

impl From<Error> for Problem {
    fn from(e: Error) -> Self {
        let code = e.code();
        match &e {
            Error::Unsupported(_) => {
                Problem::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, code, e.to_string())
            }
            Error::Limits(LimitError::Bytes { .. }) => {
                Problem::new(StatusCode::PAYLOAD_TOO_LARGE, code, e.to_string())
            }
            Error::Limits(_) | Error::Decode(_) | Error::InvalidInput(_) => {
                Problem::new(StatusCode::UNPROCESSABLE_ENTITY, code, e.to_string())
            }
            Error::Param { field, message } => Problem::param(field.clone(), message.clone()),
            Error::Canceled => Problem::new(StatusCode::CONFLICT, code, "the bake was canceled"),
            Error::Io(_) | Error::Internal(_) => Problem::internal(&e),
            Error::StorageFull { store, cause } => {
                tracing::error!(%store, %cause, "storage full");
                Problem::new(
                    StatusCode::INSUFFICIENT_STORAGE,
                    code,
                    format!(
                        "the server cannot store this: {store} is full; nothing stored was lost, \
                         retry once the operator has freed space"
                    ),
                )
            }
            Error::MemoryBusy { .. } => {
                // Decodes finish in seconds (an 8192² float TIFF decodes in about one), and each
                // frees its share of the budget when it does.
                let mut p = Problem::new(StatusCode::SERVICE_UNAVAILABLE, code, e.to_string());
                p.retry_after = Some(2);
                p
            }
            Error::Unavailable(cause) => {
                tracing::warn!(%cause, "backing store unavailable");
                let mut p = Problem::new(
                    StatusCode::SERVICE_UNAVAILABLE,
                    code,
                    "the bake store is unavailable right now; retry shortly",
                );
                p.retry_after = Some(2);
                p
            }
        }
    }
}

impl IntoResponse for Problem {
    fn into_response(self) -> Response {
        let status = self.status();
        let body = serde_json::to_vec(&self).unwrap_or_else(|_| b"{}".to_vec());
        let mut res = Response::new(Body::from(body));
        *res.status_mut() = status;
        res.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
        if let Some(secs) = self.retry_after {
            res.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(secs));
        }
        if status == StatusCode::UNAUTHORIZED {
            res.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        res
    }
}

/// Middleware: rewrites any 4xx/5xx response that is not already problem+json (axum's own 404,
/// 405, 413 from the body limit, a rejected extractor) into problem+json with a stable code,
/// keeping the status and the `Allow` header.
pub async fn normalize(res: Response) -> Response {
    let status = res.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return res;
    }
    let is_problem = res
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with(PROBLEM_JSON));
    if is_problem {
        return res;
    }
    let p = match status {
        StatusCode::NOT_FOUND => {
            Problem::new(status, "route_not_found", "no such route; see /openapi.yaml")
        }
        StatusCode::METHOD_NOT_ALLOWED => Problem::new(
            status,
            "method_not_allowed",
            "this route does not accept that method; see the Allow header",
        ),
        StatusCode::PAYLOAD_TOO_LARGE => Problem::new(
            status,
            "payload_too_large",
            "the request body is larger than the server accepts (max_body_bytes)",
        ),
        StatusCode::UNSUPPORTED_MEDIA_TYPE => Problem::new(
            status,
            "unsupported_media_type",
            "unsupported Content-Type; send image/png, image/tiff, image/x-exr or multipart/form-data",
        ),
        s if s.is_server_error() => {
            tracing::error!(status = s.as_u16(), "unexpected server error response");
            Problem::new(s, "internal", "an internal error occurred; it has been logged")
        }
        s => Problem::new(s, "bad_request", "the request could not be understood"),
    };
    let allow = res.headers().get(header::ALLOW).cloned();
    let mut out = p.into_response();
    if let Some(a) = allow {
        out.headers_mut().insert(header::ALLOW, a);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn library_errors_map_to_spec_statuses() {
        let cases: Vec<(Error, u16, &str)> = vec![
            (Error::Unsupported("jpeg".into()), 415, "unsupported_media_type"),
            (
                Error::Limits(LimitError::Bytes { bytes: 10, max_bytes: 5 }),
                413,
                "payload_too_large",
            ),
            (
                Error::Limits(LimitError::Dimensions { width: 9, height: 9, max_dim: 4 }),
                422,
                "dimensions_too_large",
            ),
            (
                Error::Limits(LimitError::DecodeBytes { estimate: 9, max_decode_bytes: 4 }),
                422,
                "dimensions_too_large",
            ),
            (Error::MemoryBusy { needed: 9, in_use: 4, budget: 10 }, 503, "decode_memory_busy"),
            (Error::Decode("truncated".into()), 422, "decode_failed"),
            (Error::InvalidInput("NaN".into()), 422, "invalid_input"),
            (Error::param("bins", "bad"), 422, "invalid_parameter"),
            (Error::Internal("secret path /x".into()), 500, "internal"),
        ];
        for (e, status, code) in cases {
            let p = Problem::from(e);
            assert_eq!((p.status, p.code), (status, code));
            assert!(!p.detail.contains("secret"), "5xx detail leaks: {}", p.detail);
        }
        assert_eq!(Problem::from(Error::param("bins", "bad")).field.as_deref(), Some("bins"));
    }
}
