//! `mcapi cluster local` whole: a killed replica started again by the
//! supervisor with every session intact, SIGTERM leaving no process behind,
//! and the flags it refuses before starting anything.

use crate::common;

use std::time::{Duration, Instant};

use common::{check_session, free_ports, grpc_request, http_client};
use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_shards::ShardMap;

use super::{
    LocalCluster, call, create_walks, haproxy_or_skip, mcapi, meta, owner_of, plan, process_exists,
    stderr,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cluster_local_restarts_a_killed_replica_and_stops_everything() {
    if !haproxy_or_skip("cluster_local_restarts_a_killed_replica_and_stops_everything") {
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let started = Instant::now();
    let mut cluster = LocalCluster::start(tmp.path(), &["--replicas", "3"], "first");
    let up_in = started.elapsed();
    let state = cluster.state();
    let names: Vec<String> = state["processes"]
        .as_array()
        .expect("processes")
        .iter()
        .map(|p| p["name"].as_str().expect("name").to_string())
        .collect();
    assert_eq!(
        names,
        ["mcapi-0", "mcapi-1", "mcapi-2", "haproxy"],
        "{state}"
    );
    assert_eq!(
        state["supervisor"].as_u64(),
        Some(u64::from(cluster.child.id()))
    );
    let map = ShardMap::read(&cluster.dir.join("shards.map")).expect("the cluster's map");
    for want in [
        format!("REST  http://127.0.0.1:{}", cluster.http),
        format!("gRPC  http://127.0.0.1:{}", cluster.grpc),
        "mcapi-2".to_string(),
    ] {
        assert!(
            cluster.out().contains(&want),
            "banner lacks {want:?}:\n{}",
            cluster.out()
        );
    }

    // Sessions created and driven through the router, over both transports.
    let client = http_client();
    let base = cluster.base();
    let mut grpc = AgentsClient::connect(format!("http://127.0.0.1:{}", cluster.grpc))
        .await
        .expect("gRPC through the router");
    let mut walks = create_walks(&client, &base, &mut grpc, 18, 6).await;
    for w in &mut walks {
        for _ in 0..5 {
            w.step(&client, &base, &mut grpc).await;
        }
    }
    let mut on: std::collections::BTreeMap<String, usize> = Default::default();
    for w in &walks {
        *on.entry(owner_of(&map, &w.id)).or_default() += 1;
    }
    assert_eq!(on.len(), 3, "sessions on every replica: {on:?}");

    // SIGKILL the replica of the first session; the supervisor starts it again.
    let victim = owner_of(&map, &walks[0].id);
    let old_pid = cluster.pid(&victim).expect("the victim runs");
    let killed_at = Instant::now();
    common::signal(u32::try_from(old_pid).expect("a pid"), "-KILL");
    let deadline = killed_at + Duration::from_secs(60);
    let new_pid = loop {
        if let Some(pid) = cluster.pid(&victim)
            && pid != old_pid
        {
            break pid;
        }
        assert!(
            Instant::now() < deadline,
            "{victim} not started again within 60 s:\n{}",
            cluster.err()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let restarted_in = killed_at.elapsed();
    let entry = cluster.state()["processes"]
        .as_array()
        .expect("processes")
        .iter()
        .find(|p| p["name"] == victim.as_str())
        .cloned()
        .expect("victim entry");
    assert_eq!(entry["restarts"], 1, "{entry}");
    assert!(!process_exists(old_pid), "the killed replica is reaped");
    // Served again through the router, over both transports, once it has
    // recovered (the router may answer 503 meanwhile, as it does to any
    // client, which retries).
    let probe = &walks[0].id;
    let (mut attempts, mut rest_back, mut grpc_back) = (0, None, None);
    loop {
        attempts += 1;
        let (status, replica, _, body) = call(
            &client,
            reqwest::Method::GET,
            &format!("{base}/v1/sessions/{probe}"),
            None,
        )
        .await;
        let grpc_ok = grpc
            .get_session(grpc_request(
                pb::GetSessionRequest {
                    session_id: probe.clone(),
                },
                None,
                Some(probe),
            ))
            .await;
        let grpc_replica = grpc_ok
            .as_ref()
            .ok()
            .and_then(|r| meta(r.metadata(), "x-mcapi-replica"));
        if status == 200 && rest_back.is_none() {
            rest_back = Some(killed_at.elapsed());
        }
        if grpc_ok.is_ok() && grpc_back.is_none() {
            grpc_back = Some(killed_at.elapsed());
        }
        if status == 200 && grpc_ok.is_ok() {
            assert_eq!(replica.as_deref(), Some(victim.as_str()));
            assert_eq!(grpc_replica.as_deref(), Some(victim.as_str()));
            break;
        }
        assert!(
            Instant::now() < deadline,
            "{probe} not served again within 60 s of the kill: REST {status} {body}; gRPC {:?}",
            grpc_ok.err()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let served_in = killed_at.elapsed();
    let log = cluster.err();
    let logged = |event: &str| {
        log.lines()
            .any(|l| l.contains(event) && l.contains(victim.as_str()))
    };
    assert!(
        logged("exited; starting it again after a backoff") && logged("started again"),
        "the restart is logged:\n{log}"
    );
    // Every session bit-equal to a replay of its acknowledged observations,
    // and writable: the killed replica's through its new process.
    for w in &mut walks {
        check_session(&client, &base, None, &w.id, &w.params, &w.applied, &w.id).await;
        w.step(&client, &base, &mut grpc).await;
    }
    drop(grpc);

    // SIGTERM: replicas drained, then the router; no process left.
    let mut pids: Vec<u64> = names.iter().filter_map(|n| cluster.pid(n)).collect();
    assert_eq!(pids.len(), 4);
    assert!(pids.contains(&new_pid));
    pids.push(u64::from(cluster.child.id()));
    let (status, stop_in) = cluster.terminate();
    assert!(status.success(), "exit {status}:\n{}", cluster.err());
    for pid in &pids {
        assert!(
            !process_exists(*pid),
            "pid {pid} still exists after shutdown"
        );
    }
    assert!(
        std::net::TcpStream::connect(("127.0.0.1", cluster.http)).is_err(),
        "the router's port is closed"
    );
    assert!(
        !cluster.dir.join("cluster.json").exists(),
        "the state file goes with the cluster"
    );
    let log = cluster.err();
    assert!(log.contains("every process stopped"), "{log}");
    drop(cluster);

    // Started again on the same directory (its map, no --replicas): the
    // sessions are all there.
    let cluster = LocalCluster::start(tmp.path(), &[], "second");
    assert_eq!(
        ShardMap::read(&cluster.dir.join("shards.map"))
            .expect("map")
            .to_text(),
        map.to_text(),
        "the map is reused"
    );
    let base = cluster.base();
    for w in &walks {
        check_session(&client, &base, None, &w.id, &w.params, &w.applied, &w.id).await;
    }
    let mut cluster = cluster;
    let (status, _) = cluster.terminate();
    assert!(status.success(), "{}", cluster.err());
    eprintln!(
        "cluster local: up in {:.1} s; killed replica started again in {:.2} s, served through the router in {:.2} s ({attempts} attempts; REST from {:.2} s, gRPC from {:.2} s); stopped in {:.2} s",
        up_in.as_secs_f64(),
        restarted_in.as_secs_f64(),
        served_in.as_secs_f64(),
        rest_back.unwrap_or_default().as_secs_f64(),
        grpc_back.unwrap_or_default().as_secs_f64(),
        stop_in.as_secs_f64()
    );
}

#[test]
fn cluster_local_refuses_bad_flags_before_starting_anything() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("c");
    let data_s = data.to_str().expect("utf-8").to_string();
    let (http, grpc) = free_ports();
    let local = |extra: &[&str]| {
        let mut args = vec![
            "cluster".to_string(),
            "local".into(),
            "--data-dir".into(),
            data_s.clone(),
            "--grpc".into(),
            format!("127.0.0.1:{grpc}"),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let started = Instant::now();
        let out = mcapi(&refs);
        assert!(!out.status.success(), "{extra:?} was accepted");
        assert!(started.elapsed() < Duration::from_secs(20));
        assert!(
            !data.join("cluster.json").exists() && !data.join("logs").exists(),
            "{extra:?}: nothing started"
        );
        stderr(&out)
    };
    let http_flag = format!("127.0.0.1:{http}");
    for n in ["0", "65", "-1", "three"] {
        let e = local(&[&format!("--replicas={n}"), "--http", &http_flag]);
        assert!(e.contains("--replicas"), "{n}: {e}");
    }
    let e = local(&["--replicas", "0", "--http", &http_flag]);
    assert!(e.contains("1..=64"), "{e}");
    let busy = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    let busy_addr = busy.local_addr().expect("addr").to_string();
    let e = local(&["--http", &busy_addr]);
    assert!(
        e.contains(&format!("--http {busy_addr} is not free")),
        "{e}"
    );
    let e = local(&["--http", &format!("127.0.0.1:{grpc}")]);
    assert!(e.contains("--http and --grpc must differ"), "{e}");
    let e = local(&["--http", &http_flag, "--haproxy", "/nonexistent/haproxy"]);
    assert!(
        e.contains("--haproxy /nonexistent/haproxy: no such file"),
        "{e}"
    );
    let e = local(&["--http", &http_flag, "--", "--replica", "x"]);
    assert!(e.contains("`--replica` is set by `cluster local`"), "{e}");
    for (flag, arg) in [
        ("--ready-timeout-secs", "0"),
        ("--drain-timeout-secs", "301"),
    ] {
        let e = local(&["--http", &http_flag, flag, arg]);
        assert!(e.contains(flag), "{e}");
    }
    // A directory whose map has 2 replicas is not started with 3 (the
    // haproxy given is any file: the map is checked before it runs).
    std::fs::create_dir_all(&data).expect("mkdir");
    plan(&data.join("shards.map"), 2);
    let e = local(&[
        "--http",
        &http_flag,
        "--replicas",
        "3",
        "--haproxy",
        "/bin/true",
    ]);
    assert!(
        e.contains("has 2 replicas (mcapi-0, mcapi-1), not 3"),
        "{e}"
    );
}
