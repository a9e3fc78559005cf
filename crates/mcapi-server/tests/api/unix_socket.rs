//! gRPC over a Unix socket (`--grpc-socket`) on the full server: the same
//! service as the TCP port, the socket file's life (made at start, removed
//! at stop, a stale one replaced, a live one or a regular file left alone).

use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

use mcapi_server::api::grpc::pb;
use mcapi_server::api::grpc::pb::agents_client::AgentsClient;
use mcapi_server::server::Running;
use mcapi_testkit::time_to_close;
use tokio_stream::StreamExt;
use tonic::transport::{Channel, Endpoint, Uri};

/// The full server on loopback port 0 and the memory store, with its gRPC
/// socket at `socket`.
async fn start(data: &Path, socket: &Path) -> Result<Running, String> {
    start_with(data, socket, &[]).await
}

/// [`start`] with more flags.
async fn start_with(data: &Path, socket: &Path, more: &[&str]) -> Result<Running, String> {
    let socket = socket.to_str().expect("utf-8 path");
    let mut args = vec!["--store", "memory", "--grpc-socket", socket];
    args.extend_from_slice(more);
    mcapi_testkit::try_start_in_process(data, &args).await
}

/// A gRPC client over the Unix socket at `path`.
async fn over_socket(path: &Path) -> AgentsClient<Channel> {
    let path = path.to_path_buf();
    let channel = Endpoint::from_static("http://localhost")
        .connect_with_connector(tower::service_fn(move |_: Uri| {
            let path = path.clone();
            async move {
                let stream = tokio::net::UnixStream::connect(path).await?;
                Ok::<_, std::io::Error>(hyper_util::rt::TokioIo::new(stream))
            }
        }))
        .await
        .expect("connects over the socket");
    AgentsClient::new(channel)
}

async fn hallway(client: &mut AgentsClient<Channel>) -> String {
    client
        .create_session(pb::CreateSessionRequest {
            model: Some(pb::Model::preset("hallway")),
            agent: Some(pb::SessionConfig {
                seed: Some(7),
                update_mode: pb::UpdateMode::Lockstep as i32,
                ..Default::default()
            }),
            ..Default::default()
        })
        .await
        .expect("create")
        .into_inner()
        .id
}

/// The ticks, actions and drives of `steps` observations of the hallway, sent one
/// message at a time on an `Interact` stream, each after the last reply.
async fn interact(
    client: &mut AgentsClient<Channel>,
    id: &str,
    steps: usize,
) -> Vec<(u64, u32, Vec<f64>)> {
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    let mut replies = client
        .interact(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .expect("interact")
        .into_inner();
    // The hallway of 50 states: food ξ = [6, 0] at 10, rest [0, 6] at 40.
    let mut state = 25usize;
    let mut out = Vec::with_capacity(steps);
    for t in 0..steps {
        let stimulus = (t > 0).then(|| pb::Stimulus {
            values: match state {
                10 => vec![6.0, 0.0],
                40 => vec![0.0, 6.0],
                _ => vec![0.0, 0.0],
            },
        });
        tx.send(pb::Observation {
            session_id: id.to_string(),
            state: state as u64,
            stimulus,
            ..Default::default()
        })
        .await
        .expect("send");
        let reply = replies.next().await.expect("a reply").expect("a step");
        let action = reply.action_index;
        state = match action {
            0 => state.saturating_sub(1),
            1 => (state + 1).min(49),
            _ => state,
        };
        out.push((reply.tick, action, reply.drive));
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_socket_serves_what_the_port_serves_and_goes_at_stop() {
    let dir = tempfile::tempdir().expect("dir");
    let socket = dir.path().join("mcapi.sock");
    let running = start(&dir.path().join("data"), &socket)
        .await
        .expect("starts");
    assert!(socket.exists(), "the socket is made at start");
    let mut unix = over_socket(&socket).await;
    let mut tcp = AgentsClient::connect(format!("http://{}", running.grpc_addr))
        .await
        .expect("connects over TCP");
    let (a, b) = (hallway(&mut unix).await, hallway(&mut tcp).await);
    let over_unix = interact(&mut unix, &a, 300).await;
    let over_tcp = interact(&mut tcp, &b, 300).await;
    assert_eq!(
        over_unix, over_tcp,
        "the same seed and observations give the same steps"
    );
    assert!(
        over_unix.iter().any(|(_, a, _)| *a == 0) && over_unix.iter().any(|(_, a, _)| *a == 1),
        "the agent moved both ways"
    );
    // Each transport sees the other's sessions: one service behind both.
    let seen = unix
        .get_session(pb::GetSessionRequest {
            session_id: b.clone(),
        })
        .await
        .expect("a session made over TCP, read over the socket")
        .into_inner();
    assert_eq!(Some(seen.tick), over_tcp.last().map(|(tick, _, _)| *tick));
    drop((unix, tcp));
    running.shutdown();
    running.wait().await.expect("stops");
    assert!(!socket.exists(), "the socket is removed at stop");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_live_socket_and_a_regular_file_are_left_alone_and_a_stale_socket_is_replaced() {
    let dir = tempfile::tempdir().expect("dir");
    let socket = dir.path().join("mcapi.sock");
    let first = start(&dir.path().join("a"), &socket).await.expect("starts");
    let refused = start(&dir.path().join("b"), &socket)
        .await
        .err()
        .expect("a second server on a live socket is refused");
    assert!(
        refused
            .to_string()
            .contains("another server is listening on it"),
        "{refused}"
    );
    // The first server still answers on its socket.
    let mut client = over_socket(&socket).await;
    hallway(&mut client).await;
    drop(client);
    first.shutdown();
    first.wait().await.expect("stops");

    // A socket left behind by a killed server: bound, never unlinked.
    drop(std::os::unix::net::UnixListener::bind(&socket).expect("a stale socket"));
    assert!(socket.exists());
    let second = start(&dir.path().join("c"), &socket)
        .await
        .expect("replaces a stale socket");
    let mut client = over_socket(&socket).await;
    hallway(&mut client).await;
    drop(client);
    second.shutdown();
    second.wait().await.expect("stops");

    // A stopping server removes its socket before it stops listening: a
    // server started meanwhile (a rolling restart) binds the path afresh,
    // and the first one's cleanup never takes that socket away.
    let third = start(&dir.path().join("e"), &socket).await.expect("starts");
    third.shutdown();
    assert!(!socket.exists(), "the socket goes as shutdown begins");
    let next = start(&dir.path().join("f"), &socket)
        .await
        .expect("the next server starts");
    third.wait().await.expect("stops");
    let mut client = over_socket(&socket).await;
    hallway(&mut client).await;
    drop(client);
    next.shutdown();
    next.wait().await.expect("stops");

    let file = dir.path().join("notes.txt");
    std::fs::write(&file, "keep me").expect("a file");
    let refused = start(&dir.path().join("d"), &file)
        .await
        .err()
        .expect("a regular file is not replaced");
    assert!(refused.contains("is not a socket"), "{refused}");
    assert_eq!(
        std::fs::read_to_string(&file).expect("still there"),
        "keep me"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_socket_has_the_ports_connection_limits_and_a_budget_of_its_own() {
    // Margins wide enough for a loaded machine: the preface is due in 3 s.
    let preface = Duration::from_secs(3);
    let dir = tempfile::tempdir().expect("dir");
    let socket = dir.path().join("mcapi.sock");
    let running = start_with(
        &dir.path().join("data"),
        &socket,
        &["--max-connections", "2", "--header-read-timeout-ms", "3000"],
    )
    .await
    .expect("starts");

    // A connection that never finishes the HTTP/2 preface is closed.
    let half = socket.clone();
    let closed = tokio::task::spawn_blocking(move || {
        let mut stream = std::os::unix::net::UnixStream::connect(half).expect("connect");
        stream
            .write_all(b"PRI * HTTP/2.0\r\n")
            .expect("half a preface");
        time_to_close(&mut stream, Duration::from_secs(20))
    })
    .await
    .expect("joins")
    .expect("the socket closes a connection without a preface");
    assert!(
        closed >= preface * 8 / 10 && closed < preface * 2,
        "closed after {closed:?}, expected about {preface:?}"
    );
    tokio::time::sleep(Duration::from_millis(200)).await;

    // Two silent connections take both of the socket's slots until the
    // preface deadline frees them: the TCP port, with a budget of its own,
    // answers meanwhile, and a third socket client waits for a slot.
    let idle: Vec<_> = (0..2)
        .map(|_| std::os::unix::net::UnixStream::connect(&socket).expect("connect"))
        .collect();
    let held = Instant::now();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut tcp = AgentsClient::connect(format!("http://{}", running.grpc_addr))
        .await
        .expect("connects over TCP");
    hallway(&mut tcp).await;
    let tcp_done = held.elapsed();
    assert!(
        tcp_done < preface * 2 / 3,
        "the TCP port answered {tcp_done:?} after the socket's slots were taken: it waited for them"
    );
    let mut late = over_socket(&socket).await;
    hallway(&mut late).await;
    let served = held.elapsed();
    assert!(
        served >= preface * 8 / 10,
        "a third socket client was served {served:?} after both slots were taken, before one was free"
    );
    drop((idle, late, tcp));
    running.shutdown();
    running.wait().await.expect("stops");
}
