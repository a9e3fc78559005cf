//! Bad input over gRPC gets the right status codes.

use mcapi_server::api::grpc::pb::observation::ActionTaken;
use mcapi_server::api::grpc::{SESSION_METADATA, pb};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use super::{Server, assert_code, create_hallway, observation, with_session};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_inputs_get_the_right_codes() {
    let server = Server::start().await;
    let mut client = server.client().await;
    let id = create_hallway(&mut client, pb::UpdateMode::Lockstep)
        .await
        .id;

    // Unknown sessions.
    let status = assert_code(
        client
            .get_session(pb::GetSessionRequest {
                session_id: "s0000.nope".into(),
            })
            .await,
        Code::NotFound,
        "s0000.nope",
    );
    assert_eq!(
        status
            .metadata()
            .get("x-mcapi-error-code")
            .and_then(|v| v.to_str().ok()),
        Some("not_found")
    );
    assert_code(
        client
            .observe(pb::ObserveRequest {
                session_id: "s0000.nope".into(),
                observations: vec![observation("", 0, None)],
            })
            .await,
        Code::NotFound,
        "not found",
    );
    assert_code(
        client
            .watch(pb::WatchRequest {
                session_id: "s0000.nope".into(),
                interval_ms: 10,
            })
            .await,
        Code::NotFound,
        "not found",
    );
    let (tx, rx) = mpsc::channel(1);
    tx.send(observation("s0000.nope", 0, None))
        .await
        .expect("send");
    let mut stream = client
        .interact(ReceiverStream::new(rx))
        .await
        .expect("interact")
        .into_inner();
    assert_code(stream.message().await, Code::NotFound, "not found");

    // Bad model JSON, unknown preset, bad configuration.
    let create = |model_json: &str, agent: Option<pb::SessionConfig>| pb::CreateSessionRequest {
        model_json: model_json.into(),
        model: None,
        agent,
    };
    assert_code(
        client.create_session(create("{not json", None)).await,
        Code::InvalidArgument,
        "model_json",
    );
    assert_code(
        client.create_session(create("", None)).await,
        Code::InvalidArgument,
        "model_json",
    );
    assert_code(
        client.create_session(create("[1, 2]", None)).await,
        Code::InvalidArgument,
        "model",
    );
    assert_code(
        client
            .create_session(create(r#"{"preset": "maze"}"#, None))
            .await,
        Code::InvalidArgument,
        "model.preset",
    );
    assert_code(
        client
            .create_session(create(
                r#"{"preset": "hallway"}"#,
                Some(pb::SessionConfig {
                    eta: Some(0.9),
                    ..Default::default()
                }),
            ))
            .await,
        Code::InvalidArgument,
        "eta",
    );
    assert_code(
        client
            .create_session(create(
                r#"{"preset": "hallway"}"#,
                Some(pb::SessionConfig {
                    update_mode: 7,
                    ..Default::default()
                }),
            ))
            .await,
        Code::InvalidArgument,
        "agent.update_mode",
    );

    // Observations: first one with a stimulus, wrong length, unknown action.
    let observe = |obs: pb::Observation| pb::ObserveRequest {
        session_id: id.clone(),
        observations: vec![obs],
    };
    assert_code(
        client
            .observe(observe(observation("", 3, Some(vec![0.0, 0.0]))))
            .await,
        Code::InvalidArgument,
        "stimulus",
    );
    client
        .observe(observe(observation("", 3, None)))
        .await
        .expect("first observation");
    let status = assert_code(
        client
            .observe(observe(observation("", 3, Some(vec![1.0, 2.0, 3.0]))))
            .await,
        Code::InvalidArgument,
        "stimulus",
    );
    assert_eq!(
        status
            .metadata()
            .get("x-mcapi-error-code")
            .and_then(|v| v.to_str().ok()),
        Some("stimulus_length")
    );
    assert_code(
        client.observe(observe(observation("", 3, None))).await,
        Code::InvalidArgument,
        "stimulus",
    );
    assert_code(
        client
            .observe(observe(pb::Observation {
                action_taken: Some(ActionTaken::ActionName("jump".into())),
                ..observation("", 3, Some(vec![0.0, 0.0]))
            }))
            .await,
        Code::InvalidArgument,
        "action_taken",
    );
    assert_code(
        client
            .observe(observe(observation("", 99, Some(vec![0.0, 0.0]))))
            .await,
        Code::InvalidArgument,
        "state 99",
    );
    assert_code(
        client
            .observe(pb::ObserveRequest {
                session_id: id.clone(),
                observations: vec![],
            })
            .await,
        Code::InvalidArgument,
        "observations",
    );
    assert_code(
        client
            .observe(observe(observation("s0000.other", 3, Some(vec![0.0, 0.0]))))
            .await,
        Code::InvalidArgument,
        "observations[0].session_id",
    );

    // Metadata and message must agree; the id is required somewhere.
    assert_code(
        client
            .get_session(with_session(
                "s0000.other",
                pb::GetSessionRequest {
                    session_id: id.clone(),
                },
            ))
            .await,
        Code::InvalidArgument,
        SESSION_METADATA,
    );
    assert_code(
        client
            .get_session(pb::GetSessionRequest {
                session_id: String::new(),
            })
            .await,
        Code::InvalidArgument,
        "session_id",
    );
    let info = client
        .get_session(with_session(
            &id,
            pb::GetSessionRequest {
                session_id: String::new(),
            },
        ))
        .await
        .expect("id from metadata")
        .into_inner();
    assert_eq!(info.id, id);

    // An error inside Interact ends the stream with its status; the earlier
    // observations stay applied.
    let (tx, rx) = mpsc::channel(4);
    let mut stream = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    tx.send(observation(&id, 3, Some(vec![0.0, 0.0])))
        .await
        .expect("send");
    let ok = stream.message().await.expect("step").expect("open");
    assert_eq!(ok.tick, info.tick + 1);
    tx.send(observation(&id, 3, Some(vec![0.0])))
        .await
        .expect("send");
    assert_code(
        stream.message().await,
        Code::InvalidArgument,
        "stimulus has 1 components, expected 2",
    );
    assert!(stream.message().await.expect("ended").is_none());
    // A message naming another session than the metadata.
    let (tx, rx) = mpsc::channel(4);
    let mut stream = client
        .interact(with_session(&id, ReceiverStream::new(rx)))
        .await
        .expect("interact")
        .into_inner();
    tx.send(observation("s0000.other", 3, Some(vec![0.0, 0.0])))
        .await
        .expect("send");
    assert_code(
        stream.message().await,
        Code::InvalidArgument,
        SESSION_METADATA,
    );

    // Values: unknown table; Watch: interval below the minimum.
    assert_code(
        client
            .get_values(pb::GetValuesRequest {
                session_id: id.clone(),
                include: vec!["w".into()],
            })
            .await,
        Code::InvalidArgument,
        "include",
    );
    assert_code(
        client
            .watch(pb::WatchRequest {
                session_id: id.clone(),
                interval_ms: 5,
            })
            .await,
        Code::InvalidArgument,
        "interval_ms",
    );
    assert_code(
        client
            .get_history(pb::GetHistoryRequest {
                session_id: id.clone(),
                limit: Some(0),
            })
            .await,
        Code::InvalidArgument,
        "`limit`: must be at least 1",
    );
    assert_code(
        client
            .list_sessions(pb::ListSessionsRequest {
                after: None,
                limit: Some(0),
            })
            .await,
        Code::InvalidArgument,
        "limit",
    );
    server.stop().await;
}
