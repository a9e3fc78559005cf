"""The sans-I/O layers: the REST and gRPC operations stepped by hand (no
server), the error of a failed RPC read by duck typing, and, over the real
server, the blocking and the asyncio REST clients making exactly the same
requests for the same calls."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Generator
from typing import Any

import httpx
import pytest
from _effective import effective_json
from conftest import Server

from mcapi_client import (
    AgentOptions,
    AsyncClient,
    Client,
    InvalidObservation,
    McapiError,
    NotFound,
    Observation,
    Timeout,
    TransportError,
    UnknownRoute,
    models,
)
from mcapi_client._pb import Call, GrpcProtocol, rpc_error
from mcapi_client._proto.mcapi.v1 import agents_pb2 as pb
from mcapi_client._protocol import Request, RestProtocol, read_reply
from mcapi_client._sansio import adrive, drive

SESSION = "s0001.01AAAAAAAAAAAAAAAAAAAAAAAA"


def session_json(sid: str = SESSION) -> dict[str, Any]:
    """A session's JSON as the server sends it (two states, actions a and b)."""
    return {
        "id": sid, "tick": 0, "drive": [1.0], "policy_version": 0, "state": None,
        "model": {"states": 2, "actions": ["a", "b"], "stimuli": ["x"], "pairs": 3, "transitions": 3,
                  "deterministic": True, "basis": {"kind": "indicator", "k": 0}, "features": 3},
        "agent": effective_json(priorities=[1.0], seed=1),
        "stats": {"lstdq_error": 0.0, "lambda1_estimate": 0.0, "condition_1_holds": True,
                  "constant_stimuli": [], "factorisation_reuses": 0, "factorisations": 0},
    }


HISTORY = [{"tick": 1, "state": 1, "action": 1, "drive": [1.0], "reward": 0.5, "lstdq_error": 0.0,
            "stimulus": [6.0]}]


def run_with(op: Generator[Any, Any, Any], replies: dict[str, Any]) -> tuple[Any, list[Any]]:
    """Runs an operation, answering each request from ``replies`` by path (or
    RPC name); returns the result and the requests made."""
    made: list[Any] = []

    def send(request: Any) -> Any:
        made.append(request)
        return replies[request.path if isinstance(request, Request) else request.rpc]

    return drive(op, send), made


def test_rest_requests_and_replies() -> None:
    proto = RestProtocol()
    op = proto.create_session(
        models.from_transition_table([[1, None], [0, 0]], ["a", "b"], {"x": 1}), AgentOptions(seed=1)
    )
    request = next(op)
    assert (request.method, request.path, request.params) == ("POST", "/v1/sessions", None)
    assert request.json["agent"] == {"seed": 1} and request.json["model"]["next"] == [[1, None], [0, 0]]
    with pytest.raises(StopIteration) as done:
        op.send(session_json())
    assert done.value.value.model.actions == ["a", "b"]

    obs = Observation(1, [6.0], "b")
    (step_request,) = run_with(proto.observe(SESSION, obs), {
        f"/v1/sessions/{SESSION}/observations":
            {"tick": 1, "action": "a", "action_index": 0, "drive": [1.0], "reward": 0.5, "policy_version": 1},
    })[1]
    assert step_request == Request("POST", f"/v1/sessions/{SESSION}/observations",
                                   json={"state": 1, "stimulus": [6.0], "action_taken": "b"})
    assert next(proto.list_sessions("s1", 5)) == Request("GET", "/v1/sessions", {"after": "s1", "limit": 5})
    assert next(proto.values(SESSION, ["v", "q"])).params == {"include": "v,q"}
    assert next(proto.delete_session("a/b")).path == "/v1/sessions/a%2Fb"


def test_rest_history_asks_for_the_action_names_only_when_unknown() -> None:
    replies = {f"/v1/sessions/{SESSION}/history": HISTORY, f"/v1/sessions/{SESSION}": session_json()}
    fresh = RestProtocol()
    entries, made = run_with(fresh.history(SESSION, None), replies)
    assert [r.path for r in made] == [f"/v1/sessions/{SESSION}/history", f"/v1/sessions/{SESSION}"]
    assert entries[0].action == "b"
    entries, made = run_with(fresh.history(SESSION, 1), replies)
    assert len(made) == 1 and made[0].params == {"limit": 1}, "the names are remembered"
    run_with(fresh.delete_session(SESSION), {f"/v1/sessions/{SESSION}": None})
    assert len(run_with(fresh.history(SESSION, None), replies)[1]) == 2, "and forgotten on delete"


def test_read_reply() -> None:
    assert read_reply(200, b'{"a": 1}', "OK") == {"a": 1}
    assert read_reply(204, b"", "No Content") is None
    with pytest.raises(InvalidObservation) as e:
        read_reply(400, b'{"code": "unknown_state", "message": "state 9"}', "Bad Request")
    assert (e.value.code, e.value.status, e.value.message) == ("unknown_state", 400, "state 9")
    with pytest.raises(McapiError) as e:
        read_reply(502, b"upstream gone", "Bad Gateway")
    assert (e.value.code, e.value.status, e.value.message) == ("http_502", 502, "upstream gone")
    with pytest.raises(UnknownRoute):
        read_reply(404, b'{"code": "unknown_route", "message": "no route"}', "Not Found")
    with pytest.raises(NotFound) as e:
        read_reply(404, b"", "Not Found")
    assert e.value.message == "Not Found"


def test_drivers_propagate_errors_and_close_the_operation() -> None:
    closed = []

    def op() -> Generator[str, Any, int]:
        try:
            a = yield "first"
            b = yield "second"
            return int(a) + int(b)
        finally:
            closed.append(True)

    assert drive(op(), lambda r: {"first": 1, "second": 2}[r]) == 3
    assert asyncio.run(adrive(op(), _async(lambda r: {"first": 1, "second": 2}[r]))) == 3

    def fail(request: str) -> Any:
        raise NotFound("gone", code="not_found", status=404)

    with pytest.raises(NotFound):
        drive(op(), fail)
    with pytest.raises(NotFound):
        asyncio.run(adrive(op(), _async(fail)))
    assert closed == [True] * 4


def _async(fn: Any) -> Any:
    async def send(request: Any) -> Any:
        return fn(request)

    return send


def test_grpc_calls_metadata_and_shapes() -> None:
    proto = GrpcProtocol("key-0123456789abcdef")
    assert proto.metadata() == (("authorization", "Bearer key-0123456789abcdef"),)
    assert proto.metadata(SESSION) == (
        ("x-mcapi-session", SESSION), ("authorization", "Bearer key-0123456789abcdef"),
    )
    assert GrpcProtocol(None).metadata(SESSION) == (("x-mcapi-session", SESSION),)
    info = pb.SessionInfo(id=SESSION)
    info.model.states, info.model.actions[:] = 2, ["a", "b"]
    values = pb.Values(tick=3)
    values.q.pairs.add(state=1, action=1, value=2.5)
    replies = {"GetValues": values, "GetSession": info}

    got, made = run_with(proto.values(SESSION, "q, v"), replies)
    assert [(c.rpc, c.session_id) for c in made] == [("GetValues", SESSION), ("GetSession", SESSION)]
    assert list(made[0].request.include) == ["q", "v"]
    assert got.q == [[None, None], [None, 2.5]], "made dense with the session's shape"
    assert [c.rpc for c in run_with(proto.values(SESSION, None), replies)[1]] == ["GetValues"]
    run_with(proto.delete_session(SESSION), {"DeleteSession": pb.DeleteSessionResponse()})
    assert len(run_with(proto.values(SESSION, None), replies)[1]) == 2

    call = next(proto.observe(SESSION, Observation(1, [6.0], 1)))
    assert isinstance(call, Call) and call.rpc == "Observe"
    assert call.request.observations[0].action_index == 1
    assert list(call.request.observations[0].stimulus.values) == [6.0]
    assert next(proto.list_sessions(None, 3)).request.limit == 3


class FakeRpcError(Exception):
    """The shape of a grpc.aio.AioRpcError (or a failed blocking call)."""

    def __init__(self, code: str, details: str, trailers: Any = ()) -> None:
        super().__init__(details)
        self._code, self._details, self._trailers = code, details, trailers

    def code(self) -> Any:
        return type("StatusCode", (), {"name": self._code})()

    def details(self) -> str:
        return self._details

    def trailing_metadata(self) -> Any:
        return self._trailers


def test_rpc_errors_are_read_by_duck_typing() -> None:
    e = rpc_error(FakeRpcError("INVALID_ARGUMENT", "state 9", [("x-mcapi-error-code", b"unknown_state")]))
    assert isinstance(e, InvalidObservation)
    assert (e.code, e.status, e.grpc_code, e.message) == ("unknown_state", 400, "INVALID_ARGUMENT", "state 9")
    e = rpc_error(FakeRpcError("UNAVAILABLE", "connect failed"))
    assert isinstance(e, TransportError) and e.code == "transport_error"
    e = rpc_error(FakeRpcError("UNAVAILABLE", "stopping", [("x-mcapi-error-code", "unavailable")]))
    assert not isinstance(e, TransportError) and (e.code, e.status) == ("unavailable", 503)
    assert isinstance(rpc_error(FakeRpcError("DEADLINE_EXCEEDED", "late")), Timeout)
    assert rpc_error(FakeRpcError("CANCELLED", "bye")).code == "cancelled"
    bare = rpc_error(RuntimeError("no status at all"))
    assert (bare.grpc_code, bare.message) == ("UNKNOWN", "no status at all")


class Recording(httpx.HTTPTransport):
    """A real transport that records each request it sends."""

    def __init__(self, seen: list[tuple[str, str, bytes]]) -> None:
        super().__init__()
        self.seen = seen

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.seen.append((request.method, str(request.url), request.read()))
        return super().handle_request(request)


class AsyncRecording(httpx.AsyncHTTPTransport):
    """:class:`Recording` for the async client."""

    def __init__(self, seen: list[tuple[str, str, bytes]]) -> None:
        super().__init__()
        self.seen = seen

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        self.seen.append((request.method, str(request.url), await request.aread()))
        return await super().handle_async_request(request)


def test_sync_and_async_rest_clients_send_the_same_requests(server: Server) -> None:
    world = models.hallway()
    blocking: list[tuple[str, str, bytes]] = []
    concurrent: list[tuple[str, str, bytes]] = []

    with Client(server.http_url, transport=Recording(blocking)) as mc:
        sid = mc.create_session(world, seed=3, priorities=[1.0, 0.5], history=9).id
        mc.observe(sid, 4)
        mc.observe(sid, 5, [0.0, 0.0], "right")
        mc.observe_batch(sid, [(5, [0.0, 0.0]), Observation(6, [0.0, 0.0], 1)])
        mc.values(sid, ["v", "q"])
        mc.list_sessions(after=sid, limit=2)
        mc.history(sid, limit=2)
        with pytest.raises(NotFound):
            mc.delete_session(SESSION)

    async def run() -> None:
        async with AsyncClient(server.http_url, transport=AsyncRecording(concurrent)) as mc:
            sid2 = (await mc.create_session(world, seed=3, priorities=[1.0, 0.5], history=9)).id
            await mc.observe(sid2, 4)
            await mc.observe(sid2, 5, [0.0, 0.0], "right")
            await mc.observe_batch(sid2, [(5, [0.0, 0.0]), Observation(6, [0.0, 0.0], 1)])
            await mc.values(sid2, ["v", "q"])
            await mc.list_sessions(after=sid2, limit=2)
            await mc.history(sid2, limit=2)
            with pytest.raises(NotFound):
                await mc.delete_session(SESSION)

    asyncio.run(run())
    assert len(blocking) == len(concurrent) == 8
    sid2 = concurrent[1][1].split("/")[-2]  # .../v1/sessions/<id>/observations
    # Numbered by default: 0, 1, then the batch 2 and 3.
    assert sid2 != sid and json.loads(blocking[1][2]) == {"state": 4, "seq": 0}
    assert [o["seq"] for o in json.loads(blocking[3][2])["observations"]] == [2, 3]
    for (m1, u1, b1), (m2, u2, b2) in zip(blocking, concurrent):
        assert (m1, u1.replace(sid, "<id>"), b1) == (m2, u2.replace(sid2, "<id>"), b2)
