//! What a submission may say and what its refusals say: parameter combinations that make no
//! sense, a parameter given twice, unknown keys listed against the known ones, the body limit
//! stated, echoed input capped, and float inputs checked when they are submitted (422 or 415,
//! nothing queued). Regression tests from tests/edges.rs (issue 25's sharp edges) and
//! tests/service_defects.rs (issue 14's service defects), each written to fail before its fix.

use crate::support::*;
use axum::body::Body;
use axum::http::Request;
use horizon_bake::service;
use serde_json::Value;
use tower::ServiceExt;

fn multipart_submit(
    png: &[u8],
    query: &str,
    params: &str,
) -> axum::http::Request<axum::body::Body> {
    let b = "XbOuNdArY";
    let mut body = Vec::new();
    body.extend_from_slice(
        format!(
            "--{b}\r\ncontent-disposition: form-data; name=\"heightmap\"; filename=\"h.png\"\r\n\
             content-type: image/png\r\n\r\n"
        )
        .as_bytes(),
    );
    body.extend_from_slice(png);
    body.extend_from_slice(
        format!(
            "\r\n--{b}\r\ncontent-disposition: form-data; name=\"params\"\r\n\r\n{params}\r\n--{b}--\r\n"
        )
        .as_bytes(),
    );
    axum::http::Request::post(format!("/v1/bakes{query}"))
        .header("content-type", format!("multipart/form-data; boundary={b}"))
        .body(axum::body::Body::from(body))
        .unwrap()
}

/// `reduce=point` means nothing to Lengyel's splat: a 422 naming `reduce`, however the two keys
/// arrive, while the ray methods take it.
#[tokio::test]
async fn point_reduction_with_lengyel_is_refused() {
    let (st, _dir) = idle_state(|_| {});
    let app = horizon_bake::service::app(st);
    let png = terrain_png16(16, 16, 3);
    for q in ["?reduce=point", "?method=lengyel&reduce=point"] {
        let (s, _, v) = oneshot_with_headers(&app, raw_submit(&png, q)).await;
        assert_eq!(s, 422, "{q}: {v}");
        assert_eq!(v["field"], "reduce", "{q}: {v}");
        assert!(v["detail"].as_str().unwrap().contains("lengyel"), "{v}");
    }
    let (s, _, v) = oneshot_with_headers(
        &app,
        multipart_submit(&png, "?reduce=point", r#"{"method":"lengyel"}"#),
    )
    .await;
    assert_eq!((s, v["field"].as_str()), (422, Some("reduce")), "{v}");
    let (s, _, v) = oneshot_with_headers(
        &app,
        multipart_submit(&png, "?reduce=point", r#"{"method":"exact"}"#),
    )
    .await;
    assert_eq!(s, 202, "{v}");
    let (s, _, v) =
        oneshot_with_headers(&app, raw_submit(&png, "?method=march&reduce=point")).await;
    assert_eq!(s, 202, "{v}");
}

/// A 413 states the limit; an unknown key lists every key a submission takes (the bake
/// parameters from the library's own list, `formats` and `exr_precision`), in the query and in
/// a `params` part alike.
#[tokio::test]
async fn errors_state_the_limit_and_the_known_keys() {
    let (st, _dir) = idle_state(|c| c.max_body_bytes = 3000);
    let app = horizon_bake::service::app(st);
    let big = noise_png8(64, 64, 1);
    assert!(big.len() > 3000);
    let (s, _, v) = oneshot_with_headers(&app, raw_submit(&big, "")).await;
    assert_eq!(s, 413, "{v}");
    assert!(v["detail"].as_str().unwrap().contains("3000 bytes"), "{v}");

    let (st, _dir) = idle_state(|_| {});
    let app = horizon_bake::service::app(st);
    let png = terrain_png16(16, 16, 3);
    for req in [raw_submit(&png, "?radiuss=4"), multipart_submit(&png, "", r#"{"radiuss": 4}"#)] {
        let (s, _, v) = oneshot_with_headers(&app, req).await;
        assert_eq!((s, v["field"].as_str()), (422, Some("radiuss")), "{v}");
        let detail = v["detail"].as_str().unwrap();
        let delivery = ["formats", "exr_precision"];
        let texture = horizon_bake::encode::texture::OPTION_KEYS;
        for k in horizon_bake::params::PARAM_NAMES.iter().chain(&delivery).chain(&texture) {
            assert!(detail.contains(&format!(" {k}")), "`{k}` missing from: {detail}");
        }
    }
    // The list is the setter's truth: each listed name is a parameter it knows.
    for k in horizon_bake::params::PARAM_NAMES {
        let mut p = horizon_bake::params::BakeParams::default();
        if let Err(e) = p.set(k, "?") {
            assert!(!e.to_string().contains("unknown parameter"), "{k}: {e}");
        }
    }
    // application/octet-stream is accepted (and documented below).
    let req = axum::http::Request::post("/v1/bakes")
        .header("content-type", "application/octet-stream")
        .body(axum::body::Body::from(png.clone()))
        .unwrap();
    assert_eq!(oneshot_with_headers(&app, req).await.0, 202);
}

/// One rule for a parameter given twice: 422 naming it, whether both are in the query, in two
/// `params` parts, or one in the query and one in the JSON part.
#[tokio::test]
async fn duplicate_parameters_are_a_422_naming_the_key_everywhere() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let png = terrain_png16(8, 8, 31);
    let (s, p) = oneshot(&app, raw_submit(&png, "?radius=21&radius=22")).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("radius")), "{p}");

    let multipart = |query: &str, parts: &[&str]| {
        let boundary = "XyZ";
        let mut body = Vec::new();
        body.extend_from_slice(
            format!(
                "--{boundary}\r\ncontent-disposition: form-data; name=\"heightmap\"; \
                 filename=\"h.png\"\r\ncontent-type: image/png\r\n\r\n"
            )
            .as_bytes(),
        );
        body.extend_from_slice(&png);
        for part in parts {
            body.extend_from_slice(
                format!(
                    "\r\n--{boundary}\r\ncontent-disposition: form-data; name=\"params\"\r\n\r\n{part}"
                )
                .as_bytes(),
            );
        }
        body.extend_from_slice(format!("\r\n--{boundary}--\r\n").as_bytes());
        Request::post(format!("/v1/bakes{query}"))
            .header("content-type", format!("multipart/form-data; boundary={boundary}"))
            .body(Body::from(body))
            .unwrap()
    };
    let (s, p) = oneshot(&app, multipart("", &[r#"{"radius": 21}"#, r#"{"bins": 32}"#])).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("params")), "{p}");
    let (s, p) = oneshot(&app, multipart("?radius=21", &[r#"{"radius": 21}"#])).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("radius")), "{p}");
    let (s, p) = oneshot(&app, multipart("", &[r#"{"radius": 21, "radius": 22}"#])).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("radius")), "{p}");
    // Different keys from the query and the JSON part are merged.
    let (s, v) = oneshot(&app, multipart("?radius=21", &[r#"{"bins": 48}"#])).await;
    assert_eq!(s, 202, "{v}");
    assert_eq!(
        (&v["params"]["radius"], &v["params"]["bins"]),
        (&Value::from(21), &Value::from(48)),
        "{v}"
    );
}

/// A huge unknown key is named, but not echoed in full: the answer stays small.
#[tokio::test]
async fn echoed_input_in_errors_is_capped() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    // 12,000 characters: under max_uri_bytes (16 KiB), so it reaches the parameter parser.
    let key = "k".repeat(12_000);
    for uri in [
        format!("/v1/bakes?{key}=1"),
        format!("/v1/cubemap/0?size={key}"),
        format!("/v1/bakes?status={key}"),
    ] {
        let res = app.clone().oneshot(Request::get(&uri).body(Body::empty()).unwrap()).await;
        let res = res.unwrap();
        assert_eq!(res.status(), 422);
        let body = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
        assert!(body.len() < 2048, "{} bytes answered to {}…", body.len(), &uri[..30]);
    }
    let (s, _) = oneshot(&app, raw_submit(&terrain_png16(4, 4, 1), &format!("?{key}=1"))).await;
    assert_eq!(s, 422);
}

fn tiff_of<C: tiff::encoder::colortype::ColorType>(w: u32, h: u32, data: &[C::Inner]) -> Vec<u8>
where
    [C::Inner]: tiff::encoder::TiffValue,
{
    let mut out = std::io::Cursor::new(Vec::new());
    tiff::encoder::TiffEncoder::new(&mut out).unwrap().write_image::<C>(w, h, data).unwrap();
    out.into_inner()
}

fn exr_of(w: usize, h: usize, samples: exr::prelude::FlatSamples) -> Vec<u8> {
    use exr::prelude::*;
    let list: SmallVec<[AnyChannel<FlatSamples>; 4]> =
        std::iter::once(AnyChannel::new("Y", samples)).collect();
    let layer = Layer::new(
        (w, h),
        LayerAttributes::named("height"),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(list),
    );
    let mut out = std::io::Cursor::new(Vec::new());
    Image::from_layer(layer).write().to_buffered(&mut out).unwrap();
    out.into_inner()
}

/// A little-endian baseline TIFF of one gray 16-bit float (half) sample per texel, all `v`:
/// written by hand, as the `tiff` crate's encoder has no half-float colour type.
fn half_float_tiff(w: u16, h: u16, v: f32) -> Vec<u8> {
    // f32 → f16 for normal values (v = 0.5 here): sign, rebased exponent, top 10 mantissa bits.
    let b = v.to_bits();
    let half =
        (((b >> 16) & 0x8000) | ((((b >> 23) & 0xff) - 112) << 10) | ((b >> 13) & 0x3ff)) as u16;
    let entries: [(u16, u16, u32); 10] = [
        (256, 3, w as u32),                // ImageWidth
        (257, 3, h as u32),                // ImageLength
        (258, 3, 16),                      // BitsPerSample
        (259, 3, 1),                       // Compression: none
        (262, 3, 1),                       // Photometric: BlackIsZero
        (273, 4, 8 + 2 + 10 * 12 + 4),     // StripOffsets
        (277, 3, 1),                       // SamplesPerPixel
        (278, 3, h as u32),                // RowsPerStrip
        (279, 4, 2 * w as u32 * h as u32), // StripByteCounts
        (339, 3, 3),                       // SampleFormat: IEEE float
    ];
    let mut out = b"II".to_vec();
    out.extend_from_slice(&42u16.to_le_bytes());
    out.extend_from_slice(&8u32.to_le_bytes());
    out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, ty, value) in entries {
        out.extend_from_slice(&tag.to_le_bytes());
        out.extend_from_slice(&ty.to_le_bytes());
        out.extend_from_slice(&1u32.to_le_bytes());
        out.extend_from_slice(&value.to_le_bytes());
    }
    out.extend_from_slice(&0u32.to_le_bytes());
    for _ in 0..w as usize * h as usize {
        out.extend_from_slice(&half.to_le_bytes());
    }
    out
}

/// Float inputs are checked when they are submitted: NaN/Inf and out-of-range heights are a 422
/// (blaming the input), unsupported sample formats a 415; nothing is queued for them.
#[tokio::test]
async fn float_inputs_are_checked_at_submission() {
    use tiff::encoder::colortype::{Gray32, Gray32Float};
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let mut nan = vec![0.5f32; 16];
    nan[5] = f32::NAN;
    let mut inf = vec![0.5f32; 16];
    inf[9] = f32::INFINITY;
    let mut huge = vec![0.5f32; 16];
    huge[3] = 3.0e38;
    huge[4] = -3.0e38;
    let cases: Vec<(&str, Vec<u8>, u16, &str)> = vec![
        ("tiff nan", tiff_of::<Gray32Float>(4, 4, &nan), 422, "invalid_input"),
        ("tiff inf", tiff_of::<Gray32Float>(4, 4, &inf), 422, "invalid_input"),
        ("tiff 3e38", tiff_of::<Gray32Float>(4, 4, &huge), 422, "invalid_input"),
        (
            "exr nan",
            exr_of(4, 4, exr::prelude::FlatSamples::F32(nan.clone())),
            422,
            "invalid_input",
        ),
        ("tiff u32", tiff_of::<Gray32>(4, 4, &[7u32; 16]), 415, "unsupported_media_type"),
        ("tiff f16", half_float_tiff(4, 4, 0.5), 415, "unsupported_media_type"),
    ];
    for (what, bytes, status, code) in cases {
        let (s, p) = oneshot(&app, raw_submit(&bytes, "")).await;
        assert_eq!((s.as_u16(), p["code"].as_str()), (status, Some(code)), "{what}: {p}");
        if what == "tiff f16" {
            // Refused for its sample format, not as an unreadable file.
            let detail = p["detail"].as_str().unwrap();
            assert!(detail.contains("16-bit"), "{what}: {detail}");
        }
        if code == "invalid_input" {
            let detail = p["detail"].as_str().unwrap();
            assert!(!detail.contains("height_scale"), "{what} blames height_scale: {detail}");
        }
    }
    let (s, v) = oneshot(&app, Request::get("/v1/bakes").body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
    assert_eq!(v["items"].as_array().unwrap().len(), 0, "a rejected input was queued: {v}");
}
