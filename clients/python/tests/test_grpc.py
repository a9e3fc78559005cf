"""The gRPC client against the real server: every method, parity with REST,
the Interact and Watch streams."""

from __future__ import annotations

import random
import threading
import time

import grpc
import pytest

from mcapi_client import (
    BadRequest,
    Client,
    GrpcClient,
    InvalidObservation,
    McapiError,
    NotFound,
    Observation,
    models,
)
from mcapi_client._proto.mcapi.v1 import agents_pb2 as pb
from mcapi_client._proto.mcapi.v1 import agents_pb2_grpc as pb_grpc


def test_ready(grpc_client: GrpcClient) -> None:
    assert grpc_client.ready(timeout=5)
    with GrpcClient("127.0.0.1:9") as dead:
        assert not dead.ready(timeout=0.3)


def test_create_get_list_delete(grpc_client: GrpcClient) -> None:
    info = grpc_client.create_session(
        models.hallway(), seed=12, eta=0.03, gamma=0.9, priorities=[1.0, 0.5],
        stimulus_rate=0.25, optimistic_sd=0.2, ridge=1e-5, epsilon=0.05,
        update_mode="async", history=32,
    )
    cfg = info.agent
    assert (cfg.seed, cfg.eta, cfg.gamma, cfg.priorities) == (12, 0.03, 0.9, [1.0, 0.5])
    assert (cfg.stimulus_rate, cfg.optimistic_sd, cfg.ridge, cfg.epsilon) == (0.25, 0.2, 1e-5, 0.05)
    assert (cfg.update_mode, cfg.history) == ("async", 32)
    assert info.state is None and info.tick == 0
    assert info.model.actions == ["left", "right", "stay"] and info.model.pairs == 148
    default = grpc_client.create_session("hallway")
    assert default.agent.stimulus_rate == "sample_mean"
    assert default.agent.update_mode == "lockstep"

    got = grpc_client.get_session(info.id)
    assert got == info
    ids = [s.id for s in grpc_client.iter_sessions(page_size=1)]
    assert info.id in ids and default.id in ids and ids == sorted(ids)
    page = grpc_client.list_sessions(limit=1)
    assert len(page.sessions) == 1 and page.next == page.sessions[0].id
    summary = next(s for s in grpc_client.iter_sessions() if s.id == info.id)
    assert (summary.states, summary.update_mode) == (50, "async")
    assert summary.idle_ms is None, "no observation yet"
    grpc_client.observe(info.id, 3)
    summary = next(s for s in grpc_client.iter_sessions() if s.id == info.id)
    assert summary.idle_ms is not None and 0 <= summary.idle_ms < 60_000

    grpc_client.delete_session(info.id)
    with pytest.raises(NotFound) as e:
        grpc_client.get_session(info.id)
    assert (e.value.code, e.value.status, e.value.grpc_code) == ("not_found", 404, "NOT_FOUND")


def test_same_answers_as_rest(client: Client, grpc_client: GrpcClient) -> None:
    """Twin sessions, one per transport, fed the same observations, agree on
    every step, the session details and every value table."""
    world = models.hallway()
    rest_id = client.create_session(world, seed=31, history=1000).id
    grpc_id = grpc_client.create_session(world, seed=31, history=1000).id
    rng = random.Random(7)
    state = 30
    a = client.observe(rest_id, state)
    b = grpc_client.observe(grpc_id, state)
    assert a == b
    for i in range(120):
        state = world.sample_next(state, a.action_index, rng)
        xi = world.stimulus(state, noise_sd=2.0, rng=rng)
        taken = a.action if i % 10 else None
        a = client.observe(rest_id, state, xi, action_taken=taken)
        b = grpc_client.observe(grpc_id, state, xi, action_taken=taken)
        assert a == b
    batch = [Observation(state, [0.0, 0.0], "stay"), Observation(state, [0.0, 0.0], 2)]
    assert client.observe_batch(rest_id, batch) == grpc_client.observe_batch(grpc_id, batch)
    rest_info, grpc_info = client.get_session(rest_id), grpc_client.get_session(grpc_id)
    assert (rest_info.tick, rest_info.drive, rest_info.state) == (
        grpc_info.tick,
        grpc_info.drive,
        grpc_info.state,
    )
    assert rest_info.stats == grpc_info.stats
    assert rest_info.model == grpc_info.model
    rest_values = client.values(rest_id, "all")
    grpc_values = grpc_client.values(grpc_id, ["all"])
    assert rest_values == grpc_values
    assert grpc_client.values(grpc_id, "q,r").q == rest_values.q
    # A fresh client (no cached shape) gets the same dense tables.
    with GrpcClient(grpc_client.target) as fresh:
        assert fresh.values(grpc_id, "xi").xi == rest_values.xi


def test_interact_step_loop(grpc_client: GrpcClient) -> None:
    world = models.hallway()
    sid = grpc_client.create_session(world, seed=3).id
    rng = random.Random(3)
    state = 25
    with grpc_client.interact(sid) as stream:
        step = stream.step(state)
        assert step.tick == 0
        for i in range(1, 200):
            state = world.sample_next(state, step.action_index, rng)
            step = stream.step(state, world.stimulus(state))
            assert step.tick == i
        assert stream.pending == 0
    info = grpc_client.get_session(sid)
    assert info.tick == 199 and info.state == state and info.drive == step.drive


def test_interact_pipelined_replay_equals_the_unary_batch(grpc_client: GrpcClient) -> None:
    world = models.hallway()
    rng = random.Random(5)
    log = [Observation(rng.randrange(50))]
    for _ in range(499):
        prev = log[-1].state
        action = rng.choice(world.available_actions(prev))
        nxt = world.sample_next(prev, action, rng)
        log.append(Observation(nxt, world.stimulus(nxt, noise_sd=2.0, rng=rng), world.actions[action]))
    streamed_id = grpc_client.create_session(world, seed=44).id
    batch_id = grpc_client.create_session(world, seed=44).id
    with grpc_client.interact(streamed_id) as stream:
        for obs in log:  # all sent before any reply is read: the server holds back
            stream.send(obs.state, obs.stimulus, obs.action_taken)
        assert stream.pending == 500
        streamed = list(stream)
        assert stream.pending == 0 and list(stream) == []
    assert streamed == grpc_client.observe_batch(batch_id, log)


def test_interact_error_ends_the_stream_after_applied_observations(grpc_client: GrpcClient) -> None:
    sid = grpc_client.create_session("hallway").id
    with grpc_client.interact(sid) as stream:
        stream.step(3)
        stream.step(4, [0.0, 0.0])
        with pytest.raises(InvalidObservation) as e:
            stream.step(5, [0.0])
        assert e.value.code == "stimulus_length" and e.value.grpc_code == "INVALID_ARGUMENT"
    assert grpc_client.get_session(sid).tick == 1, "the observations before the error stay applied"


def test_interact_unknown_session(grpc_client: GrpcClient) -> None:
    with grpc_client.interact("s0000.01AAAAAAAAAAAAAAAAAAAAAAAA") as stream:
        with pytest.raises(NotFound) as e:
            stream.step(0)
    assert e.value.status == 404


def test_interact_batch_steps_sessions_together_like_interact(grpc_client: GrpcClient) -> None:
    """Three sessions stepped as vectorised worlds over one InteractBatch
    stream get the very steps that three Interact streams get; a refused
    observation is a result, not the end of the stream."""
    world = models.hallway()
    seeds = [7, 8, 9]
    batched = [grpc_client.create_session(world, seed=s).id for s in seeds]
    single = [grpc_client.create_session(world, seed=s).id for s in seeds]
    rng = random.Random(11)
    starts = [25, 3, 47]
    states = list(starts)
    with grpc_client.interact_batch() as stream:
        first = stream.step([(sid, Observation(s)) for sid, s in zip(batched, states)])
        for t in range(1, 120):
            entries = []
            for i, sid in enumerate(batched):
                step = first[i]
                assert not isinstance(step, McapiError), step
                states[i] = world.sample_next(states[i], step.action_index, rng)
                entries.append((sid, (states[i], world.stimulus(states[i]))))
            if t == 60:  # a wrong stimulus length for the middle session, sent first
                entries.insert(0, (batched[1], (states[1], [0.0])))
            results = stream.step(entries)
            if t == 60:
                bad, skipped = results[0], results[2]
                assert isinstance(bad, InvalidObservation) and bad.code == "stimulus_length"
                assert bad.grpc_code == "INVALID_ARGUMENT"
                assert isinstance(skipped, BadRequest) and "not applied" in skipped.message
                results = [results[1], results[2], results[3]]
                # Resend the middle one alone; the others already moved on.
                (results[1],) = stream.step([(batched[1], (states[1], world.stimulus(states[1])))])
            first = results
        unknown = stream.step([("s0000.01AAAAAAAAAAAAAAAAAAAAAAAA", (1,))])
        assert isinstance(unknown[0], NotFound) and unknown[0].status == 404
        assert stream.step([]) == []
    # The same observations through Interact, one stream per session.
    for b, s, start in zip(batched, single, starts):
        log = grpc_client.history(b)  # ticks 1 to 119; tick 0 is the start
        assert len(log) == 119
        with grpc_client.interact(s) as stream:
            stream.send(start)
            for e in log:
                stream.send(e.state, e.stimulus)
            replayed = list(stream)
        assert replayed[-1].drive == grpc_client.get_session(b).drive
        assert grpc_client.get_session(s).tick == grpc_client.get_session(b).tick == 119


def test_interact_sends_the_session_metadata(server: object) -> None:
    """The client names the session only in `x-mcapi-session`: the raw stub
    without it is refused, so the metadata is what carried it."""
    with GrpcClient(server.grpc_target) as mc:  # type: ignore[attr-defined]
        sid = mc.create_session("hallway").id
        with mc.interact(sid) as stream:
            assert stream.step(1).tick == 0
    with grpc.insecure_channel(server.grpc_target) as channel:  # type: ignore[attr-defined]
        stub = pb_grpc.AgentsStub(channel)
        with pytest.raises(grpc.RpcError) as e:
            list(stub.Interact(iter([pb.Observation(state=2)])))
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "x-mcapi-session" in e.value.details()


def test_watch_streams_snapshots_until_the_session_is_deleted(grpc_client: GrpcClient) -> None:
    sid = grpc_client.create_session("hallway", seed=1).id
    snapshots = []
    with grpc_client.watch(sid, interval=0.02) as watch:
        first = next(watch)
        assert first.id == sid and first.tick == 0 and first.state is None
        grpc_client.observe(sid, 7)
        grpc_client.observe(sid, 8, [0.0, 0.0])
        deadline = time.monotonic() + 10
        for snap in watch:
            snapshots.append(snap)
            if snap.tick == 1 or time.monotonic() > deadline:
                break
    assert snapshots[-1].tick == 1 and snapshots[-1].state == 8

    # Deleting the session ends the iteration (not an error).
    done = threading.Event()
    seen: list[int] = []

    def read() -> None:
        with grpc_client.watch(sid, interval=0.02) as watch:
            for snap in watch:
                seen.append(snap.tick)
        done.set()

    reader = threading.Thread(target=read)
    reader.start()
    while not seen:
        time.sleep(0.01)
    grpc_client.delete_session(sid)
    assert done.wait(10), "the watch ends when its session is deleted"
    reader.join()


def test_watch_cancel_and_errors(grpc_client: GrpcClient) -> None:
    sid = grpc_client.create_session("hallway").id
    watch = grpc_client.watch(sid, interval=10)
    assert next(watch).id == sid
    watch.cancel()
    assert list(watch) == []
    with pytest.raises(NotFound):
        next(grpc_client.watch("s0000.01AAAAAAAAAAAAAAAAAAAAAAAA"))
    with pytest.raises(ValueError):
        grpc_client.watch(sid, interval=0.001)


def test_grid_models_carry_their_layout_on_both_transports(
    client: Client, grpc_client: GrpcClient
) -> None:
    """A grid model's map (rows, cols, cell per state, marks) is the same
    over REST and gRPC; other models have none."""
    rest = client.create_session("three_room").model
    grpc = grpc_client.create_session("three_room").model
    assert rest.layout is not None and rest.layout == grpc.layout
    assert len(rest.layout.cells) == rest.states
    assert all(0 <= r < rest.layout.rows and 0 <= c < rest.layout.cols for r, c in rest.layout.cells)
    assert len(set(rest.layout.cells)) == rest.states, "one cell per state"
    assert grpc_client.create_session("hallway").model.layout is None


def test_both_transports_report_the_same_session_cost(client: Client, grpc_client: GrpcClient) -> None:
    # The server's estimate of memory and per-observation CPU time is part of
    # a session's info; it depends only on the model and configuration.
    via_rest = client.create_session(models.hallway(), seed=5, history=1000)
    via_grpc = grpc_client.create_session(models.hallway(), seed=5, history=1000)
    assert via_rest.cost is not None and via_grpc.cost is not None
    assert via_rest.cost == via_grpc.cost
    assert via_rest.cost.bytes > 0 and via_rest.cost.tick_us >= 1
    longer = client.create_session(models.hallway(), seed=5, history=5000)
    assert longer.cost is not None and longer.cost.bytes > via_rest.cost.bytes
    for s in (via_rest, longer):
        client.delete_session(s.id)
    grpc_client.delete_session(via_grpc.id)


_TYPED_MODELS = [
    {"preset": "hallway"},
    {"preset": "three_room", "basis": {"kind": "proto_value", "k": 4}},
    {"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1}, "stimuli": ["food", "water"]},
    {"states": 3, "actions": ["l", "r"], "next": [[0, 1], [0, 2], [1, None]], "stimuli": ["x"]},
    {
        "states": 2,
        "actions": ["go", "stay"],
        "stimuli": ["x"],
        "transitions": [
            {"state": 0, "action": "go", "next": [[1, 0.25], [0, 0.75]]},
            {"state": 1, "action": 1, "next": [[1, 1.0]]},
        ],
        "basis": {"kind": "custom", "state_features": [[1.0, 0.0], [0.0, 1.0]]},
    },
]


@pytest.mark.parametrize("model", _TYPED_MODELS)
def test_models_travel_typed_and_match_rest(client: Client, grpc_client: GrpcClient, model: dict) -> None:
    """Every form goes as the typed ``Model`` (not the deprecated
    ``model_json``) and gives the session REST gives."""
    from mcapi_client import _pb

    assert _pb.create_request(model, _pb.AgentOptions()).HasField("model")
    rest = client.create_session(model, seed=3)
    over_grpc = grpc_client.create_session(model, seed=3)
    assert rest.model == over_grpc.model
    client.delete_session(rest.id)
    grpc_client.delete_session(over_grpc.id)


def test_models_the_typed_form_cannot_carry_go_as_json(client: Client, grpc_client: GrpcClient) -> None:
    """A model with an unknown key goes as ``model_json``, so the server
    refuses it with the error REST gives."""
    from mcapi_client import _pb

    bad = {"preset": "hallway", "colour": "red"}
    assert not _pb.create_request(bad, _pb.AgentOptions()).HasField("model")
    with pytest.raises(Exception) as over_rest:
        client.create_session(bad)
    with pytest.raises(Exception) as over_grpc:
        grpc_client.create_session(bad)
    assert type(over_rest.value) is type(over_grpc.value)
    assert getattr(over_rest.value, "code", None) == getattr(over_grpc.value, "code", None)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        # A negative state is an unknown one, refused before sending on both
        # transports (test_errors: InvalidObservation, `unknown_state`).
        ({"state": 1 << 64}, "state"),
        ({"state": 3, "stimulus": [0.0, 0.0], "action_taken": -2}, "action_taken"),
        ({"state": 3, "stimulus": [0.0, 0.0], "action_taken": 1 << 32}, "action_taken"),
    ],
)
def test_out_of_range_indices_are_bad_requests_as_over_rest(
    client: Client, grpc_client: GrpcClient, kwargs: dict, field: str
) -> None:
    """Protobuf cannot carry a negative or too large index; the gRPC client
    answers it with the ``bad_request`` REST gives, not protobuf's own
    ``ValueError``, and the session is untouched."""
    sid = grpc_client.create_session("hallway").id
    grpc_client.observe(sid, 5)
    before = grpc_client.get_session(sid).tick
    with pytest.raises(BadRequest) as over_grpc:
        grpc_client.observe(sid, **kwargs)
    assert over_grpc.value.code == "bad_request"
    assert f"`{field}`" in over_grpc.value.message
    # REST refuses it too (`bad_request`, or for an index the server can
    # read but the session does not have, `invalid_observation`).
    with pytest.raises(BadRequest):
        client.observe(sid, **kwargs)
    with grpc_client.interact(sid) as stream, pytest.raises(BadRequest):
        stream.step(**kwargs)
    assert grpc_client.get_session(sid).tick == before
