//! A shard move between two replicas in process (no socket, real stores):
//! the admin routes' refusals (403 without the admin key, 400 for a bad
//! shard, 404 for an unknown step, 409 for a step that does not fit), and
//! a whole move with observations acknowledged between the snapshot and
//! the freeze, which only the delta carries.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use futures_util::StreamExt;
use http_body_util::BodyExt;
use serde_json::Value;
use tower::ServiceExt;

use mcapi_server::api::{AppState, router};
use mcapi_server::service::{ApiKeys, Limits, ManagerOptions, SessionManager};
use mcapi_shards::moves::Manifest;
use mcapi_shards::plan::{ordinal_names, plan};
use mcapi_shards::{Placement, ReplicaName, ShardMap, shard_key, shard_of_id};
use mcapi_store::Store;

const KEY: &str = "admin-key-of-the-test";

struct Replica {
    app: axum::Router,
    manager: Arc<SessionManager>,
    store: Arc<Store>,
}

fn replica(map: &ShardMap, name: &str, dir: &std::path::Path, admin: Option<&str>) -> Replica {
    let placement = Arc::new(
        Placement::new(map.clone(), ReplicaName::parse(name).expect("name")).expect("placement"),
    );
    let store = Arc::new(Store::open(dir).expect("store"));
    let manager = Arc::new(
        SessionManager::with_options(ManagerOptions {
            placement: Some(placement),
            store: Some(Arc::clone(&store)),
            admin: ApiKeys::new(admin),
            ..ManagerOptions::new(Limits::default(), 1)
        })
        .expect("manager"),
    );
    manager.recover().expect("recover");
    let app = router(AppState {
        manager: Arc::clone(&manager),
        metrics: None,
        serving: None,
    });
    Replica {
        app,
        manager,
        store,
    }
}

async fn send(
    app: &axum::Router,
    method: &str,
    uri: &str,
    auth: Option<&str>,
    body: Option<&str>,
) -> (StatusCode, Value) {
    let mut req = Request::builder()
        .method(method)
        .uri(uri)
        .header("content-type", "application/json");
    if let Some(a) = auth {
        req = req.header("authorization", format!("Bearer {a}"));
    }
    let req = req
        .body(body.map_or_else(Body::empty, |b| Body::from(b.to_string())))
        .expect("request");
    let resp = app.clone().oneshot(req).await.expect("response");
    let (parts, body) = resp.into_parts();
    let bytes = body.collect().await.expect("body").to_bytes();
    (
        parts.status,
        serde_json::from_slice(&bytes).unwrap_or(Value::Null),
    )
}

#[tokio::test]
async fn an_unadmitted_call_is_refused_before_its_body_is_read() {
    // A body the size of the admin limit, generated lazily: refusing the
    // caller must not cost the server a gigabyte of buffering.
    use std::sync::atomic::{AtomicUsize, Ordering};
    let tmp = tempfile::tempdir().expect("tempdir");
    let names = ordinal_names("mcapi", 1).expect("names");
    let map = plan(&names, None).expect("plan").map;
    let a = replica(&map, "mcapi-0", &tmp.path().join("a"), Some(KEY));
    let shard = shard_key(map.shards_of(&names[0])[0]);
    let polled = Arc::new(AtomicUsize::new(0));
    let counter = Arc::clone(&polled);
    let chunk = axum::body::Bytes::from(vec![0u8; 1 << 20]);
    let chunks = futures_util::stream::iter(0..mcapi_server::api::admin::MAX_ADMIN_BODY >> 20).map(
        move |_| {
            counter.fetch_add(1, Ordering::SeqCst);
            Ok::<_, std::io::Error>(chunk.clone())
        },
    );
    let req = Request::builder()
        .method("POST")
        .uri(format!("/admin/shards/{shard}/import?begin=true"))
        .header("authorization", "Bearer not-the-key-at-all")
        .body(Body::from_stream(chunks))
        .expect("request");
    let resp = a.app.clone().oneshot(req).await.expect("response");
    assert_eq!(resp.status(), StatusCode::FORBIDDEN);
    assert_eq!(
        polled.load(Ordering::SeqCst),
        0,
        "no chunk of the body was read"
    );
}

const LATER: &str = r#"{"state": 26, "stimulus": [0.5, 0.25], "action_taken": 1}"#;

#[tokio::test]
async fn admin_routes_refuse_what_does_not_fit() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let names = ordinal_names("mcapi", 2).expect("names");
    let map = plan(&names, None).expect("plan").map;
    let a = replica(&map, "mcapi-0", &tmp.path().join("a"), Some(KEY));
    let closed = replica(&map, "mcapi-1", &tmp.path().join("b"), None);
    let mine = shard_key(map.shards_of(&names[0])[0]);
    let theirs = shard_key(map.shards_of(&names[1])[0]);
    let status = format!("/admin/shards/{mine}");
    for (app, auth) in [
        (&a.app, None),
        (&a.app, Some("not-the-key-at-all")),
        (&closed.app, Some(KEY)),
    ] {
        let (code, body) = send(app, "GET", &status, auth, None).await;
        assert_eq!(code, StatusCode::FORBIDDEN, "{body}");
        assert_eq!(body["code"], "forbidden");
        assert!(!body.to_string().contains(KEY), "the key is not echoed");
    }
    // The key is checked before anything of the request is parsed; a query
    // that does not parse is then a JSON 400.
    let bad_query = format!("/admin/shards/{mine}/activate?epoch=abc");
    let (code, body) = send(&a.app, "POST", &bad_query, None, None).await;
    assert_eq!(
        (code, body["code"].as_str()),
        (StatusCode::FORBIDDEN, Some("forbidden")),
        "{body}"
    );
    let (code, body) = send(&a.app, "POST", &bad_query, Some(KEY), None).await;
    assert_eq!(
        (code, body["code"].as_str()),
        (StatusCode::BAD_REQUEST, Some("bad_request")),
        "{body}"
    );
    let (code, body) = send(&a.app, "GET", &status, Some(KEY), None).await;
    assert_eq!(code, StatusCode::OK, "{body}");
    assert_eq!(body["state"], "owned");
    assert_eq!(body["epoch"], 1);
    for bad in ["s0400", "s00a", "S0001", "x"] {
        let (code, body) = send(
            &a.app,
            "GET",
            &format!("/admin/shards/{bad}"),
            Some(KEY),
            None,
        )
        .await;
        assert_eq!(code, StatusCode::BAD_REQUEST, "{bad}: {body}");
    }
    let (code, body) = send(
        &a.app,
        "POST",
        &format!("{status}/explode"),
        Some(KEY),
        None,
    )
    .await;
    assert_eq!(code, StatusCode::NOT_FOUND, "{body}");
    // Steps out of order: 409, nothing done.
    for (uri, why) in [
        (
            format!("/admin/shards/{theirs}/freeze"),
            "freeze a foreign shard",
        ),
        (
            format!("/admin/shards/{theirs}/export"),
            "export a foreign shard",
        ),
        (
            format!("{status}/activate?epoch=2"),
            "activate an owned shard",
        ),
        (
            format!("{status}/import?begin=true"),
            "import an owned shard",
        ),
        (
            format!("/admin/shards/{theirs}/thaw"),
            "thaw a foreign shard",
        ),
    ] {
        let (code, body) = send(&a.app, "POST", &uri, Some(KEY), None).await;
        assert_eq!(code, StatusCode::CONFLICT, "{why}: {body}");
        assert_eq!(body["code"], "move_conflict", "{why}");
    }
    let (code, body) = send(
        &a.app,
        "POST",
        &format!("{status}/import"),
        Some(KEY),
        Some("\u{1}\u{2}"),
    )
    .await;
    assert_eq!(
        code,
        StatusCode::BAD_REQUEST,
        "shard data that does not decode: {body}"
    );
    let (code, _) = send(
        &a.app,
        "POST",
        &format!("{status}/release?epoch=0&owner=mcapi-1"),
        Some(KEY),
        None,
    )
    .await;
    assert_eq!(code, StatusCode::BAD_REQUEST, "epoch 0");
    let (_, body) = send(&a.app, "GET", &status, Some(KEY), None).await;
    assert_eq!(body["state"], "owned", "nothing changed");
}

/// An import answers 400 `{code, message}` for bytes that are not exactly
/// one shard's data (64 MiB of zeros used to read as an empty shard, 200
/// `{"sessions": 0}`, and left the shard `importing`), and the shard stays
/// as it was.
#[tokio::test]
async fn an_import_of_bytes_that_are_not_exactly_shard_data_changes_nothing() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let names = ordinal_names("mcapi", 2).expect("names");
    let map = plan(&names, None).expect("plan").map;
    let a = replica(&map, "mcapi-0", &tmp.path().join("a"), Some(KEY));
    let theirs = shard_key(map.shards_of(&names[1])[0]);
    let status = format!("/admin/shards/{theirs}");
    let mut valid_then_more =
        postcard::to_allocvec(&mcapi_shards::moves::ShardData::default()).expect("encode");
    valid_then_more.push(7);
    for (what, bytes) in [
        ("64 MiB of zeros", vec![0u8; 64 << 20]),
        ("empty shard data and one byte more", valid_then_more),
        ("bytes that do not decode", vec![0xff; 9]),
    ] {
        let req = Request::builder()
            .method("POST")
            .uri(format!("{status}/import?begin=true"))
            .header("authorization", format!("Bearer {KEY}"))
            .header("content-type", "application/octet-stream")
            .body(Body::from(bytes))
            .expect("request");
        let resp = a.app.clone().oneshot(req).await.expect("response");
        let code = resp.status();
        let bytes = resp.into_body().collect().await.expect("body").to_bytes();
        let body: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        assert_eq!(code, StatusCode::BAD_REQUEST, "{what}: {body}");
        assert_eq!(body["code"], "bad_request", "{what}: {body}");
        assert!(
            body["message"]
                .as_str()
                .is_some_and(|m| m.contains("does not decode")),
            "{what}: {body}"
        );
        assert_eq!(body.as_object().map(|o| o.len()), Some(2), "{body}");
        let (_, shard) = send(&a.app, "GET", &status, Some(KEY), None).await;
        assert_eq!(shard["state"], "foreign", "{what}: the shard is as it was");
    }
}

#[tokio::test]
async fn a_shard_moves_whole_with_what_was_acknowledged_before_the_freeze() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let names = ordinal_names("mcapi", 2).expect("names");
    let base = plan(&names, None).expect("plan").map;
    // mcapi-0 owns one shard only, so every session it creates is there.
    let shard = base.shards_of(&names[0])[0];
    let owners: Vec<ReplicaName> = (0..1024u16)
        .map(|s| {
            if s == shard {
                names[0].clone()
            } else {
                names[1].clone()
            }
        })
        .collect();
    let map = ShardMap::from_owners(1, &owners).expect("map");
    let a = replica(&map, "mcapi-0", &tmp.path().join("a"), Some(KEY));
    let b = replica(&map, "mcapi-1", &tmp.path().join("b"), Some(KEY));
    let mut ids = Vec::new();
    for _ in 0..6 {
        let (code, body) = send(
            &a.app,
            "POST",
            "/v1/sessions",
            None,
            Some(r#"{"model": {"preset": "hallway"}}"#),
        )
        .await;
        assert_eq!(code, StatusCode::CREATED, "{body}");
        let id = body["id"].as_str().expect("id").to_string();
        assert_eq!(shard_of_id(&id), Some(shard));
        let (code, body) = send(
            &a.app,
            "POST",
            &format!("/v1/sessions/{id}/observations"),
            None,
            Some(r#"{"state": 25}"#),
        )
        .await;
        assert_eq!(code, StatusCode::OK, "{body}");
        ids.push(id);
    }
    // 1-2: the snapshot, imported.
    let snapshot = a.manager.export_shard(shard, None).expect("snapshot");
    assert_eq!(snapshot.sessions.len(), 6);
    let manifest = snapshot.manifest(&Manifest::default());
    b.manager
        .import_shard(shard, snapshot, true)
        .await
        .expect("import");
    // Acknowledged after the snapshot: one more observation on two
    // sessions, one session deleted, one created.
    for id in &ids[..2] {
        let (code, body) = send(
            &a.app,
            "POST",
            &format!("/v1/sessions/{id}/observations"),
            None,
            Some(LATER),
        )
        .await;
        assert_eq!(code, StatusCode::OK, "{body}");
    }
    let (code, _) = send(
        &a.app,
        "DELETE",
        &format!("/v1/sessions/{}", ids[5]),
        None,
        None,
    )
    .await;
    assert_eq!(code, StatusCode::NO_CONTENT);
    let gone = ids.pop().expect("an id");
    let (_, body) = send(
        &a.app,
        "POST",
        "/v1/sessions",
        None,
        Some(r#"{"model": {"preset": "hallway"}}"#),
    )
    .await;
    ids.push(body["id"].as_str().expect("id").to_string());
    // 3: frozen: refused with 503, nothing done.
    a.manager
        .freeze_shard(shard, mcapi_server::service::shards::DEFAULT_FREEZE_LEASE)
        .await
        .expect("freeze");
    let (code, body) = send(
        &a.app,
        "POST",
        &format!("/v1/sessions/{}/observations", ids[0]),
        None,
        Some(LATER),
    )
    .await;
    assert_eq!(code, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["code"], "shard_moving");
    let (code, _) = send(
        &a.app,
        "POST",
        "/v1/sessions",
        None,
        Some(r#"{"model": {"preset": "hallway"}}"#),
    )
    .await;
    assert_eq!(
        code,
        StatusCode::SERVICE_UNAVAILABLE,
        "no shard open for creates"
    );
    // 4: the delta carries exactly what changed.
    let delta = a
        .manager
        .export_shard(shard, Some(&manifest))
        .expect("delta");
    assert_eq!(delta.deleted, vec![gone.clone()]);
    assert_eq!(delta.sessions.len(), 3, "two tails and one new session");
    b.manager
        .import_shard(shard, delta, false)
        .await
        .expect("delta import");
    // 6-7: served by the target at epoch 2, refused by the source.
    assert_eq!(b.manager.activate_shard(shard, 2).expect("activate"), 6);
    a.manager
        .release_shard(shard, &names[1], 2)
        .await
        .expect("release");
    for (k, id) in ids.iter().enumerate() {
        let (code, body) = send(&b.app, "GET", &format!("/v1/sessions/{id}"), None, None).await;
        assert_eq!(code, StatusCode::OK, "{id}: {body}");
        let want = if k < 2 { 1 } else { 0 };
        assert_eq!(
            body["tick"], want,
            "{id}: the delta's observation is there, once"
        );
        let (code, body) = send(&a.app, "GET", &format!("/v1/sessions/{id}"), None, None).await;
        assert_eq!(code, StatusCode::MISDIRECTED_REQUEST, "{body}");
        assert_eq!(body["code"], "wrong_replica");
    }
    let (code, _) = send(&b.app, "GET", &format!("/v1/sessions/{gone}"), None, None).await;
    assert_eq!(
        code,
        StatusCode::NOT_FOUND,
        "the deleted session stays deleted"
    );
    // The source's store no longer holds the shard; an older epoch is refused.
    let prefix = format!("{}.", shard_key(shard));
    assert!(
        a.store
            .sessions_with_prefix(&prefix)
            .expect("read")
            .is_empty()
    );
    assert_eq!(
        b.store.sessions_with_prefix(&prefix).expect("read").len(),
        6
    );
    let (code, body) = send(
        &b.app,
        "POST",
        &format!(
            "/admin/shards/{}/release?epoch=2&owner=mcapi-0",
            shard_key(shard)
        ),
        Some(KEY),
        None,
    )
    .await;
    assert_eq!(code, StatusCode::CONFLICT, "{body}");
    // The moved sessions take observations on the target.
    let (code, body) = send(
        &b.app,
        "POST",
        &format!("/v1/sessions/{}/observations", ids[0]),
        None,
        Some(LATER),
    )
    .await;
    assert_eq!(code, StatusCode::OK, "{body}");
    assert_eq!(body["tick"], 2);
}

/// A group moves with its shard: its members' records name it, so the
/// target serves the group (and steps it) once the shard is active there,
/// and the source refuses it as it refuses the members.
#[tokio::test]
async fn a_group_moves_with_its_shard() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let names = ordinal_names("mcapi", 2).expect("names");
    let base = plan(&names, None).expect("plan").map;
    let shard = base.shards_of(&names[0])[0];
    let owners: Vec<ReplicaName> = (0..1024u16)
        .map(|s| {
            if s == shard {
                names[0].clone()
            } else {
                names[1].clone()
            }
        })
        .collect();
    let map = ShardMap::from_owners(1, &owners).expect("map");
    let a = replica(&map, "mcapi-0", &tmp.path().join("a"), Some(KEY));
    let b = replica(&map, "mcapi-1", &tmp.path().join("b"), Some(KEY));
    let (code, group) = send(
        &a.app,
        "POST",
        "/v1/groups",
        None,
        Some(r#"{"model": {"preset": "hallway"}, "n": 3, "seed": 11}"#),
    )
    .await;
    assert_eq!(code, StatusCode::CREATED, "{group}");
    let id = group["id"].as_str().expect("id").to_string();
    assert_eq!(
        shard_of_id(&id),
        Some(shard),
        "the group's id names its shard"
    );
    let steps = format!("/v1/groups/{id}/steps");
    let (code, body) = send(
        &a.app,
        "POST",
        &steps,
        None,
        Some(r#"{"states": [25, 25, 25]}"#),
    )
    .await;
    assert_eq!(code, StatusCode::OK, "{body}");
    let snapshot = a.manager.export_shard(shard, None).expect("snapshot");
    assert_eq!(snapshot.sessions.len(), 3);
    let manifest = snapshot.manifest(&Manifest::default());
    b.manager
        .import_shard(shard, snapshot, true)
        .await
        .expect("import");
    a.manager
        .freeze_shard(shard, mcapi_server::service::shards::DEFAULT_FREEZE_LEASE)
        .await
        .expect("freeze");
    let (code, body) = send(&a.app, "GET", &format!("/v1/groups/{id}"), None, None).await;
    assert_eq!(code, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["code"], "shard_moving");
    let delta = a
        .manager
        .export_shard(shard, Some(&manifest))
        .expect("delta");
    b.manager
        .import_shard(shard, delta, false)
        .await
        .expect("delta import");
    assert_eq!(b.manager.activate_shard(shard, 2).expect("activate"), 3);
    a.manager
        .release_shard(shard, &names[1], 2)
        .await
        .expect("release");
    assert_eq!(a.manager.groups_len(), 0, "the source forgot the group");
    let (code, moved) = send(&b.app, "GET", &format!("/v1/groups/{id}"), None, None).await;
    assert_eq!(code, StatusCode::OK, "{moved}");
    assert_eq!(moved, group, "the same group, members and seed");
    let (code, body) = send(&a.app, "GET", &format!("/v1/groups/{id}"), None, None).await;
    assert_eq!(code, StatusCode::MISDIRECTED_REQUEST, "{body}");
    assert_eq!(body["code"], "wrong_replica");
    let (code, body) = send(
        &b.app,
        "POST",
        &steps,
        None,
        Some(r#"{"states": [24, 25, 26], "stimuli": [[0, 0], [0, 0], [0, 0]]}"#),
    )
    .await;
    assert_eq!(code, StatusCode::OK, "{body}");
    assert_eq!(body["ticks"], serde_json::json!([1, 1, 1]));
}

/// A freeze holds a lease: a mover that never commits leaves the shard
/// refusing writes only until the lease ends, after which the source
/// serves it again by itself and refuses the late commit (the target must
/// not serve a shard whose source took writes after the copy); a lease
/// out of bounds is refused before anything is frozen; a commit in time
/// gives the shard away at the new epoch for good.
#[tokio::test]
async fn a_freeze_ends_with_its_lease_and_a_late_commit_is_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let names = ordinal_names("mcapi", 2).expect("names");
    let base = plan(&names, None).expect("plan").map;
    let shard = base.shards_of(&names[0])[0];
    let owners: Vec<ReplicaName> = (0..1024u16)
        .map(|s| names[usize::from(s != shard)].clone())
        .collect();
    let map = ShardMap::from_owners(1, &owners).expect("map");
    let a = replica(&map, "mcapi-0", &tmp.path().join("a"), Some(KEY));
    let key = shard_key(shard);
    let (code, body) = send(
        &a.app,
        "POST",
        "/v1/sessions",
        None,
        Some(r#"{"model": {"preset": "hallway"}}"#),
    )
    .await;
    assert_eq!(code, StatusCode::CREATED, "{body}");
    let id = body["id"].as_str().expect("id").to_string();
    let observe = format!("/v1/sessions/{id}/observations");

    // Bounds, with the value and the limits in the message.
    for bad in ["0", "99", "600001", "18446744073709551615"] {
        let (code, body) = send(
            &a.app,
            "POST",
            &format!("/admin/shards/{key}/freeze?lease_ms={bad}"),
            Some(KEY),
            None,
        )
        .await;
        assert_eq!(code, StatusCode::BAD_REQUEST, "{bad}: {body}");
        let msg = body["message"].as_str().expect("message");
        assert!(
            msg.contains("lease_ms") && msg.contains("between 100 and 600000") && msg.contains(bad),
            "{msg}"
        );
    }
    let (code, body) = send(&a.app, "POST", &observe, None, Some(r#"{"state": 25}"#)).await;
    assert_eq!(code, StatusCode::OK, "nothing was frozen: {body}");

    // A short lease, no commit.
    let (code, frozen) = send(
        &a.app,
        "POST",
        &format!("/admin/shards/{key}/freeze?lease_ms=300"),
        Some(KEY),
        None,
    )
    .await;
    assert_eq!(code, StatusCode::OK, "{frozen}");
    assert_eq!(frozen["state"], "frozen");
    let lease = frozen["lease_ms"].as_u64().expect("lease_ms");
    assert!((1..=300).contains(&lease), "{frozen}");
    let token = frozen["freeze_token"].as_u64().expect("token");
    let (code, body) = send(&a.app, "POST", &observe, None, Some(LATER)).await;
    assert_eq!(code, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["code"], "shard_moving");
    let (code, all) = send(&a.app, "GET", "/admin/shards", Some(KEY), None).await;
    assert_eq!(code, StatusCode::OK, "{all}");
    assert_eq!(all["shards"][usize::from(shard)]["state"], "frozen");
    assert!(
        all["shards"][usize::from(shard)]["lease_ms"].is_u64(),
        "{all}"
    );
    assert_eq!(all["shards"][usize::from(shard)]["sessions"], 1);

    tokio::time::sleep(std::time::Duration::from_millis(450)).await;
    let (code, body) = send(&a.app, "POST", &observe, None, Some(LATER)).await;
    assert_eq!(code, StatusCode::OK, "served again after the lease: {body}");
    assert_eq!(body["tick"], 1, "{body}");
    let (code, status) = send(
        &a.app,
        "GET",
        &format!("/admin/shards/{key}"),
        Some(KEY),
        None,
    )
    .await;
    assert_eq!(code, StatusCode::OK);
    assert_eq!(status["state"], "owned", "{status}");
    assert!(status.get("lease_ms").is_none(), "{status}");

    // The commit of that freeze comes too late: refused, nothing changed.
    let commit = format!("/admin/shards/{key}/commit?epoch=2&owner=mcapi-1&token={token}");
    let (code, body) = send(&a.app, "POST", &commit, Some(KEY), None).await;
    assert_eq!(code, StatusCode::CONFLICT, "{body}");
    assert_eq!(body["code"], "move_conflict");
    let msg = body["message"].as_str().expect("message");
    assert!(
        msg.contains("the lease of its freeze (300 ms) expired"),
        "{msg}"
    );
    assert_eq!(a.manager.shard_status(shard).expect("status").epoch, 1);
    let (code, body) = send(&a.app, "POST", &observe, None, Some(LATER)).await;
    assert_eq!(code, StatusCode::OK, "still served here: {body}");

    // A fresh freeze commits in time: 421 naming the new owner from then
    // on, at the new epoch; the lease's end changes nothing any more.
    let (code, frozen) = send(
        &a.app,
        "POST",
        &format!("/admin/shards/{key}/freeze?lease_ms=300"),
        Some(KEY),
        None,
    )
    .await;
    assert_eq!(code, StatusCode::OK, "{frozen}");
    let token2 = frozen["freeze_token"].as_u64().expect("token");
    assert_ne!(token2, token, "a new freeze, a new token");
    let stale = format!("/admin/shards/{key}/commit?epoch=2&owner=mcapi-1&token={token}");
    let (code, body) = send(&a.app, "POST", &stale, Some(KEY), None).await;
    assert_eq!(code, StatusCode::CONFLICT, "the old freeze's token: {body}");
    let commit = format!("/admin/shards/{key}/commit?epoch=2&owner=mcapi-1&token={token2}");
    let (code, body) = send(&a.app, "POST", &commit, Some(KEY), None).await;
    assert_eq!(code, StatusCode::OK, "{body}");
    assert_eq!(body["state"], "foreign");
    assert_eq!(body["owner"], "mcapi-1");
    assert_eq!(body["epoch"], 2);
    tokio::time::sleep(std::time::Duration::from_millis(450)).await;
    let (code, body) = send(&a.app, "POST", &observe, None, Some(LATER)).await;
    assert_eq!(code, StatusCode::MISDIRECTED_REQUEST, "{body}");
    assert_eq!(body["code"], "wrong_replica");
}
