//! The bake records: a deduplicated submission renews the retention (and the resource says when
//! it expires), listing newest first with several statuses and a total, malformed cursors a 422.
//! Regression tests from tests/service_defects.rs (issue 14's service defects), each written to
//! fail before its fix.

use crate::support::*;
use axum::body::Body;
use axum::http::{Request, StatusCode};
use horizon_bake::service::{self, handlers};
use serde_json::Value;
use std::time::Duration;

/// A deduplicated submission (answered 200) renews the bake's retention, and the resource says
/// when it expires.
#[tokio::test]
async fn dedup_hit_extends_retention_and_shows_expires_at() {
    let (st, repo, _dir) = idle_state_with_repo(|c| c.retention = Duration::from_secs(3600));
    let app = service::app(st.clone());
    let png = terrain_png16(8, 8, 21);
    let (s, v) = oneshot(&app, raw_submit(&png, "")).await;
    assert_eq!(s, 202);
    assert!(v["expires_at"].is_null(), "a queued bake does not expire: {v}");
    let id = v["id"].as_str().unwrap().to_owned();
    // Make it a bake that finished two hours ago: past the retention.
    use horizon_bake::jobs::repo::redb::BakeStore;
    let mut rec = repo.store().get(&id).unwrap().unwrap();
    rec.status = horizon_bake::jobs::record::Status::Succeeded;
    let two_hours_ago = horizon_bake::jobs::record::now_ms() - 2 * 3600 * 1000;
    rec.finished_ms = Some(two_hours_ago);
    repo.store().put(&rec).unwrap();
    let (s, v) =
        oneshot(&app, Request::get(format!("/v1/bakes/{id}")).body(Body::empty()).unwrap()).await;
    assert_eq!(s, 200);
    assert_eq!(v["expires_at"], handlers::rfc3339(two_hours_ago + 3600 * 1000));

    let (s, v) = oneshot(&app, raw_submit(&png, "")).await;
    assert_eq!((s, v["id"].as_str().unwrap()), (StatusCode::OK, id.as_str()));
    let renewed = v["expires_at"].as_str().unwrap().to_owned();
    assert!(renewed > handlers::rfc3339(horizon_bake::jobs::record::now_ms()), "{renewed}");
    let removed = handlers::sweep(&st).await;
    assert_eq!(removed.unwrap(), 0, "the sweep removed a bake that was just asked for again");
    assert!(repo.store().get(&id).unwrap().is_some());
}

/// Listing: newest first on request, several statuses in one filter, and the total count.
#[tokio::test]
async fn listing_newest_first_several_statuses_and_total() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let mut ids = Vec::new();
    for seed in 0..3 {
        let (s, v) = oneshot(&app, raw_submit(&terrain_png16(6, 6, 100 + seed), "")).await;
        assert_eq!(s, 202);
        ids.push(v["id"].as_str().unwrap().to_owned());
        // Ids are time-ordered to the millisecond.
        tokio::time::sleep(Duration::from_millis(3)).await;
    }
    let (s, _) = oneshot(
        &app,
        Request::delete(format!("/v1/bakes/{}", ids[1])).body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 200);
    let get = |uri: String| Request::get(uri).body(Body::empty()).unwrap();
    let id_list = |v: &Value| -> Vec<String> {
        v["items"]
            .as_array()
            .unwrap()
            .iter()
            .map(|i| i["id"].as_str().unwrap().to_owned())
            .collect()
    };
    let (s, v) = oneshot(&app, get("/v1/bakes?order=desc&limit=2".into())).await;
    assert_eq!(s, 200, "{v}");
    assert_eq!(id_list(&v), [ids[2].clone(), ids[1].clone()]);
    assert_eq!(v["total"], 3);
    let href = v["next"]["href"].as_str().unwrap().to_owned();
    assert!(href.contains("order=desc"), "{href}");
    let (_, v) = oneshot(&app, get(href)).await;
    assert_eq!(id_list(&v), [ids[0].clone()]);
    assert!(v["next"].is_null());
    let (_, v) = oneshot(&app, get("/v1/bakes?status=canceled".into())).await;
    assert_eq!((id_list(&v), &v["total"]), (vec![ids[1].clone()], &Value::from(1)));
    let (_, v) = oneshot(&app, get("/v1/bakes?status=queued,canceled&limit=1".into())).await;
    assert_eq!((id_list(&v), &v["total"]), (vec![ids[0].clone()], &Value::from(3)));
    let (s, p) = oneshot(&app, get("/v1/bakes?order=sideways".into())).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("order")));
    let (s, p) = oneshot(&app, get("/v1/bakes?status=queued,done".into())).await;
    assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("status")));
}

/// Every malformed cursor is one answer: 422 naming `cursor`.
#[tokio::test]
async fn invalid_cursors_are_all_422() {
    let (st, _dir) = idle_state(|_| {});
    let app = service::app(st);
    let long = "0".repeat(65);
    for cursor in ["zzz", "", long.as_str(), "0123456789abcdef012", "ZZZZZZZZZZZZZZZZZZZZ"] {
        let (s, p) = oneshot(
            &app,
            Request::get(format!("/v1/bakes?cursor={cursor}")).body(Body::empty()).unwrap(),
        )
        .await;
        assert_eq!((s.as_u16(), p["field"].as_str()), (422, Some("cursor")), "{cursor}: {p}");
    }
    // A well-formed cursor that names no bake is fine: the page after it.
    let (s, v) = oneshot(
        &app,
        Request::get("/v1/bakes?cursor=0123456789abcdef0123").body(Body::empty()).unwrap(),
    )
    .await;
    assert_eq!(s, 200, "{v}");
}
