//! The gRPC scenario and its driver: `Interact` over bidirectional
//! streams of one hallway session each, then `InteractBatch` streams of
//! several sessions driven as one vectorised world, closed loop; printed as
//! the gRPC table, returned as its JSON.

use std::time::Instant;

use anyhow::{Context, Result, anyhow, bail, ensure};
use serde_json::{Value, json};
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::{Channel, Endpoint};

use mcapi_proto as pb;
use mcapi_proto::SESSION_METADATA;
use mcapi_proto::agents_client::AgentsClient;

use crate::args::{LoadgenArgs, Mode};
use crate::hallway::Hallway;
use crate::proc::CpuUse;
use crate::report::{cores, latency, per_request, thousands};
use crate::stats::{Phase, Summary, Tally};
use crate::window::{measure_window, server_us};

/// One stream through a phase, one observation in flight.
async fn grpc_worker(mut client: AgentsClient<Channel>, id: String, phase: Phase) -> Result<Tally> {
    let (tx, rx) = mpsc::channel(1);
    let mut request = tonic::Request::new(ReceiverStream::new(rx));
    request.metadata_mut().insert(SESSION_METADATA, id.parse()?);
    let mut steps = client.interact(request).await?.into_inner();
    let mut world = Hallway::new();
    let mut tally = Tally::default();
    while !phase.over() {
        let issued = Instant::now();
        tx.send(world.proto())
            .await
            .map_err(|_| anyhow!("the Interact stream closed"))?;
        let step = steps
            .message()
            .await?
            .ok_or_else(|| anyhow!("the server ended the Interact stream"))?;
        let done = Instant::now();
        world.advance(step.action_index as usize);
        tally.record(&phase, issued, done, Ok(()));
    }
    drop(tx);
    while steps.message().await?.is_some() {}
    Ok(tally)
}

/// One `InteractBatch` stream through a phase: its sessions as a vectorised
/// world, one message (an observation per session) in flight.
async fn grpc_batch_worker(
    mut client: AgentsClient<Channel>,
    ids: Vec<String>,
    phase: Phase,
) -> Result<Tally> {
    let (tx, rx) = mpsc::channel(1);
    let mut steps = client
        .interact_batch(ReceiverStream::new(rx))
        .await?
        .into_inner();
    let mut worlds: Vec<Hallway> = ids.iter().map(|_| Hallway::new()).collect();
    let mut tally = Tally::default();
    while !phase.over() {
        let observations = ids
            .iter()
            .zip(&worlds)
            .map(|(id, world)| pb::Observation {
                session_id: id.clone(),
                ..world.proto()
            })
            .collect();
        let issued = Instant::now();
        tx.send(pb::ObservationBatch { observations })
            .await
            .map_err(|_| anyhow!("the InteractBatch stream closed"))?;
        let reply = steps
            .message()
            .await?
            .ok_or_else(|| anyhow!("the server ended the InteractBatch stream"))?;
        let done = Instant::now();
        ensure!(
            reply.results.len() == worlds.len(),
            "{} results for {} observations",
            reply.results.len(),
            worlds.len()
        );
        for (world, result) in worlds.iter_mut().zip(reply.results) {
            match result.outcome {
                Some(pb::step_result::Outcome::Step(step)) => {
                    world.advance(step.action_index as usize);
                    tally.record(&phase, issued, done, Ok(()));
                }
                Some(pb::step_result::Outcome::Error(e)) => {
                    tally.record(
                        &phase,
                        issued,
                        done,
                        Err(format!("{}: {}", e.code, e.message)),
                    );
                }
                None => bail!("a result with neither a step nor an error"),
            }
        }
    }
    drop(tx);
    while steps.message().await?.is_some() {}
    Ok(tally)
}

/// `n` hallway sessions in `mode`, seeded 0..n.
async fn create_grpc_sessions(
    admin: &mut AgentsClient<Channel>,
    n: usize,
    mode: Mode,
) -> Result<Vec<String>> {
    let mut ids = Vec::with_capacity(n);
    for i in 0..n {
        let info = admin
            .create_session(pb::CreateSessionRequest {
                model: Some(pb::Model::preset("hallway")),
                agent: Some(pb::SessionConfig {
                    seed: Some(i as u64),
                    update_mode: mode.to_pb().into(),
                    ..Default::default()
                }),
                ..Default::default()
            })
            .await?
            .into_inner();
        ids.push(info.id);
    }
    Ok(ids)
}

/// One row of the gRPC table.
struct GrpcRow {
    mode: Mode,
    method: &'static str,
    streams: usize,
    batch: usize,
    summary: Summary,
    cpu: CpuUse,
}

/// One HTTP/2 connection to `target`: a URL (`http://host:port`), or
/// `unix:PATH` for the server's Unix socket (`mcapi serve --grpc-socket`).
async fn connect(target: &str) -> Result<Channel> {
    let Some(path) = target.strip_prefix("unix:") else {
        return Ok(Endpoint::from_shared(target.to_string())?
            .tcp_nodelay(true)
            .connect()
            .await?);
    };
    let path = path.to_string();
    // The URI is never dialled: the connector opens the socket. It gives
    // the requests their `:authority`.
    let channel = Endpoint::from_static("http://localhost")
        .connect_with_connector(tower::service_fn(move |_: tonic::transport::Uri| {
            let path = path.clone();
            async move {
                let stream = tokio::net::UnixStream::connect(path).await?;
                Ok::<_, std::io::Error>(hyper_util::rt::TokioIo::new(stream))
            }
        }))
        .await?;
    Ok(channel)
}

pub(crate) async fn grpc_scenario(args: &LoadgenArgs, pid: Option<u32>) -> Result<Value> {
    let mut channels = Vec::with_capacity(args.grpc_connections);
    for _ in 0..args.grpc_connections {
        channels.push(
            connect(&args.grpc)
                .await
                .with_context(|| format!("connecting to {}", args.grpc))?,
        );
    }
    let mut admin = AgentsClient::new(channels[0].clone());
    let batch = usize::from(args.grpc_batch);
    let mut rows = Vec::new();
    for &mode in &args.modes {
        eprintln!(
            "grpc: Interact, {} {} streams over {} connections",
            args.grpc_streams,
            mode.as_str(),
            args.grpc_connections
        );
        let ids = create_grpc_sessions(&mut admin, args.grpc_streams, mode).await?;
        let phase = Phase::new(args);
        let mut set = JoinSet::new();
        for (i, id) in ids.iter().enumerate() {
            let client = AgentsClient::new(channels[i % channels.len()].clone());
            set.spawn(grpc_worker(client, id.clone(), phase));
        }
        rows.push(grpc_row(mode, "Interact", args.grpc_streams, 1, set, phase, pid).await?);
        delete_grpc_sessions(&mut admin, ids).await?;
        if batch <= 1 {
            continue;
        }
        let streams = args.grpc_streams.div_ceil(batch);
        eprintln!(
            "grpc: InteractBatch, {} {} sessions in {streams} streams of up to {batch}",
            args.grpc_streams,
            mode.as_str(),
        );
        let ids = create_grpc_sessions(&mut admin, args.grpc_streams, mode).await?;
        let phase = Phase::new(args);
        let mut set = JoinSet::new();
        for (i, chunk) in ids.chunks(batch).enumerate() {
            let client = AgentsClient::new(channels[i % channels.len()].clone());
            set.spawn(grpc_batch_worker(client, chunk.to_vec(), phase));
        }
        rows.push(grpc_row(mode, "InteractBatch", streams, batch, set, phase, pid).await?);
        delete_grpc_sessions(&mut admin, ids).await?;
    }
    println!("## gRPC: Interact and InteractBatch (closed loop)\n");
    println!(
        "{} hallway sessions over {} HTTP/2 connections: `Interact` with one stream per \
         session, `InteractBatch` with streams of up to {batch} sessions (one observation \
         each per message); each stream waits for its reply before sending again.\n",
        args.grpc_streams, args.grpc_connections
    );
    println!(
        "| mode | method | streams × batch | observations/s | p50 / p99 / max | \
         server CPU µs/obs | CPU: server / loadgen / other |"
    );
    println!("|---|---|---|---|---|---|---|");
    let mut out = Vec::with_capacity(rows.len());
    for r in rows {
        let (s, cpu) = (&r.summary, r.cpu);
        out.push(json!({
            "mode": r.mode.as_str(),
            "method": r.method,
            "streams": r.streams,
            "batch": r.batch,
            "connections": args.grpc_connections,
            "summary": s.json(),
            "cpu_server": cpu.server,
            "cpu_loadgen": cpu.loadgen,
            "cpu_other": cpu.other,
            "server_cpu_us_per_observation": server_us(cpu, s.rate),
        }));
        println!(
            "| {} | {} | {} × {} | {} | {} / {} / {} | {} | {} |",
            r.mode.as_str(),
            r.method,
            r.streams,
            r.batch,
            thousands(s.rate),
            latency(s.p50),
            latency(s.p99),
            latency(s.max),
            per_request(cpu, s.rate),
            cores(cpu),
        );
    }
    println!();
    Ok(Value::Array(out))
}

/// Waits for a phase's workers and measures it.
async fn grpc_row(
    mode: Mode,
    method: &'static str,
    streams: usize,
    batch: usize,
    mut set: JoinSet<Result<Tally>>,
    phase: Phase,
    pid: Option<u32>,
) -> Result<GrpcRow> {
    let cpu = measure_window(phase, pid, None).await.cpu;
    let mut tally = Tally::default();
    while let Some(joined) = set.join_next().await {
        tally.merge(joined??);
    }
    let summary = tally.summary(&phase);
    eprintln!("  {:.0} observations/s", summary.rate);
    if let Some(e) = &summary.first_error {
        bail!(
            "{method}: {} observations failed, the first: {e}",
            summary.errors
        );
    }
    Ok(GrpcRow {
        mode,
        method,
        streams,
        batch,
        summary,
        cpu,
    })
}

async fn delete_grpc_sessions(admin: &mut AgentsClient<Channel>, ids: Vec<String>) -> Result<()> {
    for id in ids {
        admin
            .delete_session(pb::DeleteSessionRequest { session_id: id })
            .await?;
    }
    Ok(())
}
