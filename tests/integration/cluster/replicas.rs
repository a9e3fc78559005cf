//! Three replicas behind a real HAProxy, routed by shard over REST and gRPC;
//! a replica restarted with a different map; the shard maps and cluster
//! flags a replica refuses before it opens a port.

use crate::common;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{Server, free_ports, grpc_request, http_client};
use mcapi_cluster::haproxy::{runtime_command, set_owner};
use mcapi_server::api::grpc::pb;
use mcapi_shards::{ReplicaName, ShardMap, shard_key, shard_of_id};
use serde_json::json;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use super::{
    call, haproxy_or_skip, mcapi, meta, owner_of, plan, start_replica, start_router, stay, stderr,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_replicas_behind_haproxy_route_by_shard() {
    if !haproxy_or_skip("three_replicas_behind_haproxy_route_by_shard") {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let map_path = dir.path().join("shards.map");
    let map = plan(&map_path, 3);
    let names = ["mcapi-0", "mcapi-1", "mcapi-2"];
    let mut replicas = Vec::new();
    for name in names {
        replicas.push(start_replica(dir.path(), &map_path, name, &["--store", "memory"]).await);
    }
    let pairs: Vec<(&str, &Server)> = names.iter().copied().zip(replicas.iter()).collect();
    let router = start_router(dir.path(), &map_path, &pairs).await;
    let client = http_client();
    let by_name = |n: &str| &replicas[names.iter().position(|x| *x == n).expect("known")];

    // REST creates go round-robin; each replica mints in a shard it owns.
    let mut ids = Vec::new();
    let mut created_on = std::collections::BTreeMap::<String, usize>::new();
    for _ in 0..12 {
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::POST,
            &format!("{}/v1/sessions", router.base()),
            Some(json!({"model": {"preset": "hallway"}})),
        )
        .await;
        assert_eq!(status, 201, "{body}");
        let id = body["id"].as_str().expect("id").to_string();
        let replica = replica.expect("x-mcapi-replica on a create");
        assert_eq!(
            owner_of(&map, &id),
            replica,
            "{id} minted outside its replica's shards"
        );
        *created_on.entry(replica).or_default() += 1;
        ids.push(id);
    }
    assert_eq!(
        created_on.len(),
        3,
        "creates reach every replica: {created_on:?}"
    );

    // gRPC creates too, without session metadata: round-robin.
    let mut grpc = router.grpc().await;
    let mut grpc_on = std::collections::BTreeSet::new();
    for _ in 0..6 {
        let reply = grpc
            .create_session(grpc_request(
                pb::CreateSessionRequest {
                    model: Some(pb::Model::preset("hallway")),
                    ..Default::default()
                },
                None,
                None,
            ))
            .await
            .expect("gRPC create through the router");
        let replica = meta(reply.metadata(), "x-mcapi-replica").expect("replica metadata");
        let id = reply.into_inner().id;
        assert_eq!(owner_of(&map, &id), replica);
        grpc_on.insert(replica);
        ids.push(id);
    }
    assert!(grpc_on.len() >= 2, "gRPC creates spread: {grpc_on:?}");

    // Every session, over both transports through the router, reaches its owner.
    for (k, id) in ids.iter().enumerate() {
        let owner = owner_of(&map, id);
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::POST,
            &format!("{}/v1/sessions/{id}/observations", router.base()),
            Some(json!({"state": 25})),
        )
        .await;
        assert_eq!(
            (status, replica.as_deref()),
            (200, Some(owner.as_str())),
            "{id}: {body}"
        );
        // Two requests in a row for one session: round-robin would send
        // them to two different replicas, so both reaching the owner shows
        // the routing by shard (the creates above ran in the same rotation,
        // which one request per session could match by chance).
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::GET,
            &format!("{}/v1/sessions/{id}/history?limit=1", router.base()),
            None,
        )
        .await;
        assert_eq!(
            (status, replica.as_deref()),
            (200, Some(owner.as_str())),
            "{id}: {body}"
        );
        let reply = grpc
            .observe(grpc_request(
                pb::ObserveRequest {
                    session_id: id.clone(),
                    observations: vec![stay("")],
                },
                None,
                Some(id),
            ))
            .await
            .unwrap_or_else(|s| panic!("gRPC observe {id} (#{k}): {s:?}"));
        assert_eq!(
            meta(reply.metadata(), "x-mcapi-replica").as_deref(),
            Some(owner.as_str())
        );
        assert_eq!(reply.into_inner().steps[0].tick, 1);
        // Again right after: the routing is by metadata, not the rotation.
        let reply = grpc
            .get_history(grpc_request(
                pb::GetHistoryRequest {
                    session_id: id.clone(),
                    limit: Some(1),
                },
                None,
                Some(id),
            ))
            .await
            .unwrap_or_else(|s| panic!("gRPC history {id} (#{k}): {s:?}"));
        assert_eq!(meta(reply.metadata(), "x-mcapi-replica"), Some(owner));
    }

    // A bidirectional stream through the router, on its session's owner.
    let id = &ids[0];
    let (tx, rx) = mpsc::channel(4);
    let mut req = tonic::Request::new(ReceiverStream::new(rx));
    req.metadata_mut()
        .insert("x-mcapi-session", id.parse().expect("ascii"));
    let mut steps = grpc.interact(req).await.expect("interact").into_inner();
    for tick in 2..=4 {
        tx.send(stay(id)).await.expect("send");
        let step = steps.message().await.expect("step").expect("a step");
        assert_eq!(step.tick, tick);
    }
    drop(tx);

    // Metadata naming another session than the message: INVALID_ARGUMENT.
    let e = grpc
        .get_session(grpc_request(
            pb::GetSessionRequest {
                session_id: ids[0].clone(),
            },
            None,
            Some(&ids[1]),
        ))
        .await
        .expect_err("mismatch");
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");

    // A replica asked directly for a shard it does not own: 421 / UNAVAILABLE naming the owner.
    let owner = owner_of(&map, id);
    let other = names.iter().find(|n| **n != owner).expect("another");
    let wrong = by_name(other);
    let (status, replica, owner_header, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{id}", wrong.base()),
        None,
    )
    .await;
    assert_eq!(status, 421, "{body}");
    assert_eq!(body["code"], "wrong_replica");
    assert!(
        body["message"]
            .as_str()
            .expect("message")
            .contains(&format!("`{owner}`")),
        "{body}"
    );
    assert_eq!(owner_header.as_deref(), Some(owner.as_str()));
    assert_eq!(replica.as_deref(), Some(*other));
    let e = wrong
        .grpc_client()
        .await
        .get_session(grpc_request(
            pb::GetSessionRequest {
                session_id: id.clone(),
            },
            None,
            Some(id),
        ))
        .await
        .expect_err("misdirected");
    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
    assert_eq!(meta(e.metadata(), "x-mcapi-owner"), Some(owner.clone()));
    assert_eq!(
        meta(e.metadata(), "x-mcapi-error-code").as_deref(),
        Some("wrong_replica")
    );

    // Flip the session's shard to another replica live (Runtime API, no
    // reload): the router sends it there at once, and that replica, the
    // authority, refuses with 421 naming the owner of its map.
    let shard = shard_of_id(id).expect("shard");
    let to = ReplicaName::parse(other).expect("name");
    set_owner(&router.socket, &router.map_path, shard, &to).expect("set map");
    let shown = runtime_command(
        &router.socket,
        &format!("show map {}", router.map_path.display()),
    )
    .expect("show map");
    assert!(
        shown.contains(&format!("{} {other}", shard_key(shard))),
        "the live map has the flip: {}",
        shown.lines().take(3).collect::<Vec<_>>().join(" | ")
    );
    let (status, replica, owner_header, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{id}", router.base()),
        None,
    )
    .await;
    assert_eq!((status, replica.as_deref()), (421, Some(*other)), "{body}");
    assert_eq!(owner_header.as_deref(), Some(owner.as_str()));
    let e = grpc
        .get_session(grpc_request(
            pb::GetSessionRequest {
                session_id: id.clone(),
            },
            None,
            Some(id),
        ))
        .await
        .expect_err("flipped");
    assert_eq!(e.code(), Code::Unavailable);
    assert_eq!(
        meta(e.metadata(), "x-mcapi-replica").as_deref(),
        Some(*other)
    );
    // Only that shard moved: a session of another shard still reaches its owner.
    let steady = ids
        .iter()
        .find(|i| shard_of_id(i) != Some(shard))
        .expect("another session");
    let (status, replica, _, _) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{steady}", router.base()),
        None,
    )
    .await;
    assert_eq!((status, replica), (200, Some(owner_of(&map, steady))));
    // Flipped back, the session is served again by its owner.
    set_owner(
        &router.socket,
        &router.map_path,
        shard,
        &ReplicaName::parse(&owner).expect("name"),
    )
    .expect("set map back");
    let (status, replica, _, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{id}", router.base()),
        None,
    )
    .await;
    assert_eq!(
        (status, replica.as_deref()),
        (200, Some(owner.as_str())),
        "{body}"
    );
    assert_eq!(body["tick"], 4);
    // The Runtime API refuses a key the map does not have.
    assert!(
        set_owner(&router.socket, Path::new("/nonexistent.map"), 0, &to).is_err(),
        "an unknown map is refused"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_replica_keeps_but_does_not_serve_shards_it_lost() {
    let dir = tempfile::tempdir().expect("tempdir");
    let v1 = dir.path().join("v1.map");
    let map = plan(&v1, 2);
    let mut server = start_replica(dir.path(), &v1, "mcapi-0", &[]).await;
    let client = http_client();
    let mut ids = Vec::new();
    for _ in 0..6 {
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::POST,
            &format!("{}/v1/sessions", server.base()),
            Some(json!({"model": {"preset": "hallway"}})),
        )
        .await;
        assert_eq!(
            (status, replica.as_deref()),
            (201, Some("mcapi-0")),
            "{body}"
        );
        ids.push(body["id"].as_str().expect("id").to_string());
    }
    assert!(ids.iter().all(|id| owner_of(&map, id) == "mcapi-0"));
    server.terminate();

    // Epoch 2 gives the first session's shard to mcapi-1.
    let lost = shard_of_id(&ids[0]).expect("shard");
    let mut owners = map.owners();
    owners[usize::from(lost)] = ReplicaName::parse("mcapi-1").expect("name");
    let v2 = dir.path().join("v2.map");
    std::fs::write(
        &v2,
        ShardMap::from_owners(2, &owners).expect("map").to_text(),
    )
    .expect("write");
    let mut server = start_replica(dir.path(), &v2, "mcapi-0", &[]).await;
    let (status, _, owner, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{}", server.base(), ids[0]),
        None,
    )
    .await;
    assert_eq!((status, owner.as_deref()), (421, Some("mcapi-1")), "{body}");
    assert!(
        body["message"]
            .as_str()
            .expect("message")
            .contains("epoch 2"),
        "{body}"
    );
    for id in ids.iter().filter(|i| shard_of_id(i) != Some(lost)) {
        let (status, _, _, body) = call(
            &client,
            reqwest::Method::GET,
            &format!("{}/v1/sessions/{id}", server.base()),
            None,
        )
        .await;
        assert_eq!(status, 200, "{body}");
    }
    let (_, _, _, page) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions", server.base()),
        None,
    )
    .await;
    let listed: Vec<&str> = page["sessions"]
        .as_array()
        .expect("sessions")
        .iter()
        .filter_map(|s| s["id"].as_str())
        .collect();
    assert!(
        !listed.contains(&ids[0].as_str()),
        "a lost shard's session is not listed"
    );
    let events = common::log_events(
        &server.log_text(),
        "stored sessions of shards this replica does not own are kept in the store, not served",
    );
    let kept = ids.iter().filter(|i| shard_of_id(i) == Some(lost)).count();
    assert_eq!(events.len(), 1, "{}", server.log_text());
    assert_eq!(events[0]["sessions"], kept);
    server.terminate();

    // Back on the epoch-1 map, the kept session is served again, intact.
    let server = start_replica(dir.path(), &v1, "mcapi-0", &[]).await;
    let (status, _, _, body) = call(
        &client,
        reqwest::Method::GET,
        &format!("{}/v1/sessions/{}", server.base(), ids[0]),
        None,
    )
    .await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["id"], ids[0].as_str());
}

#[test]
fn absurd_shard_maps_and_cluster_flags_are_refused_before_any_port_opens() {
    let dir = tempfile::tempdir().expect("tempdir");
    let good = dir.path().join("good.map");
    let map = plan(&good, 2);
    let text = map.to_text();
    let write = |name: &str, body: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, body).expect("write");
        p
    };
    let dup = write("dup.map", format!("{text}s0002 mcapi-0\n").as_bytes());
    let missing = write(
        "missing.map",
        text.lines()
            .filter(|l| !l.starts_with("s01"))
            .collect::<Vec<_>>()
            .join("\n")
            .as_bytes(),
    );
    let epoch = write(
        "epoch.map",
        text.replace("epoch 1", "epoch zero").as_bytes(),
    );
    let huge = write("huge.map", &vec![b'#'; 8 << 20]);
    let binary = write("binary.map", &[0xff; 64]);
    let (http, grpc) = free_ports();
    let serve = |extra: &[&str]| {
        let mut args = vec![
            "serve".to_string(),
            "--store".into(),
            "memory".into(),
            "--http".into(),
            format!("127.0.0.1:{http}"),
            "--grpc".into(),
            format!("127.0.0.1:{grpc}"),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let started = Instant::now();
        let out = mcapi(&refs);
        assert!(!out.status.success(), "{extra:?} was accepted");
        assert!(started.elapsed() < Duration::from_secs(20));
        stderr(&out)
    };
    let p = |p: &PathBuf| p.to_str().expect("utf-8").to_string();
    for (file, want) in [
        (
            &dup,
            "line 1027: shard s0002 is assigned again (first on line 5)",
        ),
        (
            &missing,
            "256 of the 1024 shards have no owner: s0100, s0101",
        ),
        (&epoch, "line 2: the epoch `zero` is not a whole number"),
        (&huge, "larger than 262144 bytes"),
        (&binary, "not UTF-8"),
        (&dir.path().join("absent.map"), "absent.map"),
    ] {
        let e = serve(&["--shard-map", &p(file), "--replica", "mcapi-0"]);
        assert!(e.contains(want), "{}: want {want:?} in {e}", file.display());
        assert!(!e.contains("binding"), "refused before binding: {e}");
    }
    let e = serve(&["--shard-map", &p(&good), "--replica", "mcapi-7"]);
    assert!(
        e.contains("`mcapi-7` owns no shard") && e.contains("mcapi-0, mcapi-1"),
        "{e}"
    );
    let e = serve(&["--shard-map", &p(&good), "--replica", "Not_A_Name"]);
    assert!(e.contains("only a-z, 0-9 and `-`"), "{e}");
    let e = serve(&["--shard-map", &p(&good)]);
    assert!(e.contains("--replica"), "{e}");
    let e = serve(&["--replica", "mcapi-0"]);
    assert!(e.contains("--shard-map"), "{e}");

    // plan --from: 2 -> 3 replicas moves a third, all to the new one.
    let out = mcapi(&["cluster", "plan", "--replicas", "3", "--from", &p(&good)]);
    assert!(out.status.success(), "{}", stderr(&out));
    let next = ShardMap::parse(&String::from_utf8_lossy(&out.stdout)).expect("a map on stdout");
    assert_eq!(next.epoch(), 2);
    let moved = (0..1024u16)
        .filter(|&s| next.owner(s) != map.owner(s))
        .count();
    assert!(
        stderr(&out).contains(&format!("{moved} of 1024 shards move"))
            && stderr(&out).contains(&format!("{moved} to mcapi-2")),
        "{}",
        stderr(&out)
    );
    assert!((330..=345).contains(&moved), "{moved}");
}
