//! Streams stop cleanly: a dropped stream leaves the session usable, `Watch`
//! sends snapshots until the session is deleted, shutdown ends open
//! streams.

use std::time::Duration;

use mcapi_server::api::grpc::pb;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use super::{
    START, Server, assert_code, create_hallway, hallway_move, hallway_stimulus, observation,
    with_session,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dropped_stream_leaves_the_session_usable() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;

    let (tx, rx) = mpsc::channel(4);
    let mut steps = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    let mut s = START;
    for t in 0..20 {
        let xi = (t > 0).then(|| hallway_stimulus(s));
        tx.send(observation(&id, s, xi)).await.expect("send");
        let step = steps.message().await.expect("step").expect("open");
        s = hallway_move(s, step.action_index);
    }
    // Cancel mid-stream: drop the response stream (RST_STREAM) with the
    // request stream still open.
    drop(steps);

    let info = client
        .get_session(pb::GetSessionRequest {
            session_id: id.clone(),
        })
        .await
        .expect("get")
        .into_inner();
    assert_eq!(info.tick, 19);
    drop(tx);
    let steps = client
        .observe(with_session(
            &id,
            pb::ObserveRequest {
                session_id: id.clone(),
                observations: vec![observation("", s, Some(hallway_stimulus(s)))],
            },
        ))
        .await
        .expect("unary observe after the stream was cancelled")
        .into_inner()
        .steps;
    assert_eq!(steps.len(), 1);
    assert_eq!(steps[0].tick, 20);

    // A new stream continues the same session.
    let (tx, rx) = mpsc::channel(4);
    let mut steps2 = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact again")
        .into_inner();
    let s = hallway_move(s, steps[0].action_index);
    tx.send(observation(&id, s, Some(hallway_stimulus(s))))
        .await
        .expect("send");
    assert_eq!(
        steps2.message().await.expect("step").expect("open").tick,
        21
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_sends_snapshots_until_the_session_is_deleted() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    let mut snapshots = client
        .watch(with_session(
            &id,
            pb::WatchRequest {
                session_id: id.clone(),
                interval_ms: 10,
            },
        ))
        .await
        .expect("watch")
        .into_inner();
    let first = snapshots.message().await.expect("snapshot").expect("open");
    assert_eq!(
        (first.id.as_str(), first.tick, first.state),
        (id.as_str(), 0, None)
    );
    client
        .observe(pb::ObserveRequest {
            session_id: id.clone(),
            observations: vec![observation("", 7, None)],
        })
        .await
        .expect("observe");
    // A later snapshot shows the observation.
    let mut seen = false;
    for _ in 0..50 {
        let snap = snapshots.message().await.expect("snapshot").expect("open");
        if snap.state == Some(7) {
            seen = true;
            break;
        }
    }
    assert!(seen, "no snapshot showed state 7");
    client
        .delete_session(pb::DeleteSessionRequest {
            session_id: id.clone(),
        })
        .await
        .expect("delete");
    // Snapshots already buffered may arrive first; then NOT_FOUND ends it.
    let end = loop {
        match snapshots.message().await {
            Ok(Some(_)) => continue,
            other => break other,
        }
    };
    assert_code(end, Code::NotFound, &id);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_streams() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;
    let (tx, rx) = mpsc::channel(4);
    let mut interact = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    tx.send(observation(&id, START, None)).await.expect("send");
    interact.message().await.expect("step").expect("open");
    let mut watch = client
        .watch(pb::WatchRequest {
            session_id: id.clone(),
            interval_ms: 1000,
        })
        .await
        .expect("watch")
        .into_inner();
    watch.message().await.expect("snapshot").expect("open");

    let took = server.stop().await;
    assert!(took < Duration::from_secs(5), "shutdown took {took:?}");
    assert_code(interact.message().await, Code::Unavailable, "shutting down");
    assert_code(watch.message().await, Code::Unavailable, "shutting down");
    drop(tx);
}
