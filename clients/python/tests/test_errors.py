"""Error mapping: the same McapiError subclass, code and status over REST and gRPC."""

from __future__ import annotations

import re
import socket
from collections.abc import Callable, Iterator
from http import HTTPStatus
from typing import Any

import pytest
from conftest import CLIENT_KINDS, REPO_ROOT, Server, open_client, start_server

from mcapi_client import (
    BadRequest,
    Client,
    GrpcClient,
    InvalidModel,
    InvalidObservation,
    InvalidParameter,
    LimitExceeded,
    McapiError,
    NotFound,
    Timeout,
    TooManySessions,
    TransportError,
    UnknownRoute,
    models,
)
from mcapi_client._protocol import Request
from mcapi_client.errors import ERROR_CODES, error_for

UNKNOWN_ID = "s0000.01AAAAAAAAAAAAAAAAAAAAAAAA"


def test_every_server_code_is_mapped_with_its_status() -> None:
    """Reads the server's one error table and checks this client knows each
    code with the same HTTP status."""
    source = (REPO_ROOT / "crates" / "mcapi-server" / "src" / "api" / "error.rs").read_text()
    rows = re.findall(r"\(\s*H::([A-Z_]+)\s*,\s*G::(\w+)\s*,\s*\"([a-z_]+)\"\s*,?\s*\)", source)
    assert len(rows) >= 15, "the table in crates/mcapi-server/src/api/error.rs was not found"
    for status_name, _grpc, code in rows:
        assert code in ERROR_CODES, f"server code `{code}` is not in mcapi_client.errors.ERROR_CODES"
        assert ERROR_CODES[code][1] == _http_status(status_name), code


def _http_status(rust_name: str) -> int:
    """The number of a Rust `http::StatusCode` constant (names differ a little from Python's)."""
    renamed = {"PAYLOAD_TOO_LARGE": 413, "MISDIRECTED_REQUEST": 421, "UNPROCESSABLE_ENTITY": 422}
    return renamed.get(rust_name) or HTTPStatus[rust_name].value


def test_unknown_codes_fall_back_on_the_status() -> None:
    assert type(error_for("brand_new", "x", status=404)) is NotFound
    assert type(error_for(None, "x", status=502)).__name__ == "InternalError"
    e = error_for(None, "x", grpc_code="RESOURCE_EXHAUSTED")
    assert isinstance(e, LimitExceeded) and e.code == "resource_exhausted"
    assert type(error_for("brand_new", "x", status=418)) is McapiError


Transport = Callable[[str], Any]


@pytest.fixture(params=CLIENT_KINDS)
def mc(request: pytest.FixtureRequest, server: Server) -> Iterator[Client | GrpcClient]:
    """Each client, REST and gRPC, blocking and asyncio: each test runs over all four."""
    with open_client(request.param, server) as c:
        yield c


def _raises(cls: type[McapiError], code: str, status: int, fn: Callable[[], object]) -> McapiError:
    with pytest.raises(cls) as info:
        fn()
    e = info.value
    assert (e.code, e.status) == (code, status), repr(e)
    assert e.message and code in str(e)
    return e


def test_unknown_session(mc: Client | GrpcClient) -> None:
    e = _raises(NotFound, "not_found", 404, lambda: mc.get_session(UNKNOWN_ID))
    assert UNKNOWN_ID in e.message
    _raises(NotFound, "not_found", 404, lambda: mc.observe(UNKNOWN_ID, 0))
    _raises(NotFound, "not_found", 404, lambda: mc.values(UNKNOWN_ID))
    _raises(NotFound, "not_found", 404, lambda: mc.delete_session(UNKNOWN_ID))


def test_bad_models_and_parameters(mc: Client | GrpcClient) -> None:
    bad = {"states": 2, "actions": ["a"], "stimuli": ["x"], "next": [[1], [None]]}
    e = _raises(InvalidModel, "invalid_model", 400, lambda: mc.create_session(bad))
    assert "state 1 has no available action" in e.message
    _raises(BadRequest, "bad_request", 400, lambda: mc.create_session("no_such_preset"))
    e = _raises(InvalidParameter, "invalid_parameter", 400, lambda: mc.create_session("hallway", eta=2.0))
    assert "eta" in e.message
    _raises(InvalidParameter, "invalid_parameter", 400,
            lambda: mc.create_session("hallway", priorities=[1.0]))
    _raises(InvalidModel, "invalid_basis", 400,
            lambda: mc.create_session(models.hallway(basis={"kind": "proto_value", "k": 0})))
    _raises(LimitExceeded, "limit_exceeded", 413, lambda: mc.create_session("hallway", history=10**9))


def test_bad_observations(mc: Client | GrpcClient) -> None:
    sid = mc.create_session("hallway").id
    _raises(InvalidObservation, "first_observation", 400, lambda: mc.observe(sid, 3, [0.0, 0.0]))
    _raises(InvalidObservation, "unknown_state", 400, lambda: mc.observe(sid, 50))
    mc.observe(sid, 0)
    _raises(InvalidObservation, "missing_stimulus", 400, lambda: mc.observe(sid, 1))
    _raises(InvalidObservation, "stimulus_length", 400, lambda: mc.observe(sid, 1, [1.0]))
    _raises(InvalidObservation, "non_finite_number", 400, lambda: mc.observe(sid, 1, [float("nan"), 0.0]))
    _raises(InvalidObservation, "action_not_available", 400,
            lambda: mc.observe(sid, 1, [0.0, 0.0], action_taken="left"))
    _raises(InvalidObservation, "unknown_action", 400, lambda: mc.observe(sid, 1, [0.0, 0.0], action_taken=7))
    _raises(BadRequest, "bad_request", 400, lambda: mc.observe(sid, 1, [0.0, 0.0], action_taken="jump"))
    # In a batch, the error names the entry and the earlier ones stay applied.
    e = _raises(BadRequest, "bad_request", 400,
                lambda: mc.observe_batch(sid, [(1, [0.0, 0.0]), (2, [0.0])]))
    assert "observations[1]" in e.message
    assert mc.get_session(sid).tick == 1
    _raises(BadRequest, "bad_request", 400, lambda: mc.observe_batch(sid, []))


def test_bad_queries(mc: Client | GrpcClient) -> None:
    sid = mc.create_session("hallway").id
    e = _raises(BadRequest, "bad_request", 400, lambda: mc.values(sid, "v,nope"))
    assert "nope" in e.message
    _raises(BadRequest, "bad_request", 400, lambda: mc.list_sessions(limit=0))
    _raises(BadRequest, "bad_request", 400, lambda: mc.list_sessions(limit=1001))


def test_rest_only_errors(client: Client) -> None:
    e = _raises(UnknownRoute, "unknown_route", 404, lambda: client._send(Request("GET", "/v2/nothing")))
    assert isinstance(e, NotFound)
    _raises(BadRequest, "bad_request", 400, lambda: client._send(Request("POST", "/v1/sessions", json=[1])))


def test_limits(tmp_path_factory: pytest.TempPathFactory) -> None:
    """A server with small caps: too many sessions (429), an oversized batch
    and an oversized body (413), over both transports."""
    small = start_server(
        tmp_path_factory.mktemp("small"),
        ["--max-sessions", "2", "--max-batch", "3", "--max-body-bytes", "4096"],
    )
    try:
        with Client(small.http_url) as rest, GrpcClient(small.grpc_target) as grpc:
            sid = rest.create_session("hallway").id
            grpc.create_session("hallway")
            four = [(0,), (1, [0, 0]), (2, [0, 0]), (3, [0, 0])]
            for c in (rest, grpc):
                _raises(TooManySessions, "too_many_sessions", 429, lambda c=c: c.create_session("hallway"))
                _raises(LimitExceeded, "limit_exceeded", 413, lambda c=c: c.observe_batch(sid, four))
            big = [(i % 50, [0.0, 0.0]) for i in range(300)]
            _raises(LimitExceeded, "payload_too_large", 413, lambda: rest.observe_batch(sid, big))
            with pytest.raises(LimitExceeded) as e:
                grpc.observe_batch(sid, big)
            # tonic refuses an oversized message with OUT_OF_RANGE before mcapi sees it.
            assert e.value.grpc_code in ("RESOURCE_EXHAUSTED", "OUT_OF_RANGE")
            assert e.value.status == 413
    finally:
        small.stop()


def test_unreachable_server_and_timeouts() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # Nothing listens on `port`: connection refused.
    with Client(f"http://127.0.0.1:{port}", timeout=2) as rest:
        e = _raises_transport(lambda: rest.get_session("x"))
        assert e.code == "transport_error" and e.status is None
    with GrpcClient(f"127.0.0.1:{port}", timeout=2) as grpc:
        e = _raises_transport(lambda: grpc.get_session("x"))
        assert e.code == "transport_error" and e.grpc_code == "UNAVAILABLE"
    # A socket that accepts connections but never answers: a timeout.
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        addr = f"127.0.0.1:{silent.getsockname()[1]}"
        with Client(f"http://{addr}", timeout=0.3) as rest, pytest.raises(Timeout) as t:
            rest.get_session("x")
        assert t.value.code == "timeout"
        with GrpcClient(addr, timeout=0.3) as grpc, pytest.raises(Timeout) as t:
            grpc.get_session("x")
        assert t.value.grpc_code == "DEADLINE_EXCEEDED"


def _raises_transport(fn: Callable[[], object]) -> McapiError:
    with pytest.raises(TransportError) as info:
        fn()
    return info.value


def test_a_negative_state_is_an_invalid_observation_on_both_transports(server: Server) -> None:
    with Client(server.http_url) as mc, GrpcClient(server.grpc_target) as grpc:
        for client in (mc, grpc):
            sid = client.create_session("hallway", seed=1).id
            with pytest.raises(InvalidObservation, match="negative"):
                client.observe(sid, -1)
            client.delete_session(sid)
