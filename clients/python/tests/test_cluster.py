"""The clients in front of a cluster (docs/cluster.md): every gRPC call of a
session names it in ``x-mcapi-session``; a refusal that did nothing (421
``wrong_replica``, 503 ``shard_moving``/``unavailable``, gRPC UNAVAILABLE
with those codes) is retried with jittered backoff until the policy's
deadline; anything else is raised at once. Against stubs (httpx's mock
transport, an in-process gRPC server) and two real replicas."""

from __future__ import annotations

import asyncio
import http.server
import random
import socketserver
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from concurrent import futures
from pathlib import Path
from typing import Any

import grpc
import httpx
import pytest
from conftest import BINARY, serve_help, start_server

from mcapi_client import (
    AsyncClient,
    Client,
    GrpcClient,
    McapiError,
    NotFound,
    RetryPolicy,
    Unavailable,
    WrongReplica,
)
from mcapi_client._proto.mcapi.v1 import agents_pb2 as pb
from mcapi_client._proto.mcapi.v1 import agents_pb2_grpc as pb_grpc

SID = "s0042.01JDX4AAAAAAAAAAAAAAAAAAAA"
FAST = RetryPolicy(deadline=2.0, initial_backoff=0.01, max_backoff=0.05, rng=random.Random(1))


def _json(status: int, code: str, headers: dict[str, str] | None = None) -> httpx.Response:
    return httpx.Response(status, json={"code": code, "message": code}, headers=headers)


WRONG = _json(421, "wrong_replica", {"x-mcapi-owner": "mcapi-1"})


def _scripted(replies: list[httpx.Response]) -> tuple[httpx.MockTransport, list[httpx.Request]]:
    """A transport answering each request with the next reply (the last one repeats)."""
    seen: list[httpx.Request] = []

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return replies[min(len(seen) - 1, len(replies) - 1)]

    return httpx.MockTransport(handle), seen


def test_rest_retries_refusals_until_one_succeeds() -> None:
    transport, seen = _scripted(
        [
            WRONG,
            _json(503, "shard_moving", {"retry-after": "0"}),
            httpx.Response(503, text="<html>503 Service Unavailable</html>"),  # the router's own
            httpx.Response(204),
        ]
    )
    with Client("http://router", transport=transport, retry=FAST) as mc:
        mc.delete_session(SID)
    assert len(seen) == 4
    assert all(r.url.path == f"/v1/sessions/{SID}" for r in seen)


def test_rest_gives_up_at_the_deadline_with_the_owner() -> None:
    transport, seen = _scripted([WRONG])
    policy = RetryPolicy(deadline=0.5, initial_backoff=0.02, max_backoff=0.1)
    started = time.monotonic()
    with Client("http://router", transport=transport, retry=policy) as mc, pytest.raises(WrongReplica) as e:
        mc.delete_session(SID)
    took = time.monotonic() - started
    assert e.value.owner == "mcapi-1" and e.value.status == 421 and e.value.code == "wrong_replica"
    assert isinstance(e.value, Unavailable)
    assert 3 <= len(seen) and took < 0.5 + 0.3, (len(seen), took)


@pytest.mark.parametrize(
    "reply",
    [
        _json(503, "request_timeout"),  # may have taken effect
        _json(404, "not_found"),
        httpx.Response(502, text="bad gateway"),
    ],
)
def test_rest_does_not_retry_what_may_have_taken_effect(reply: httpx.Response) -> None:
    transport, seen = _scripted([reply])
    with Client("http://router", transport=transport, retry=FAST) as mc, pytest.raises(McapiError):
        mc.delete_session(SID)
    assert len(seen) == 1


def test_rest_without_a_policy_never_retries() -> None:
    transport, seen = _scripted([WRONG, httpx.Response(204)])
    with Client("http://router", transport=transport, retry=None) as mc, pytest.raises(WrongReplica):
        mc.delete_session(SID)
    assert len(seen) == 1


def test_async_rest_retries_too() -> None:
    seen: list[httpx.Request] = []
    replies = [
        lambda: _json(421, "wrong_replica", {"x-mcapi-owner": "mcapi-1"}),
        lambda: _json(503, "unavailable"),
        lambda: httpx.Response(204),
    ]

    async def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return replies[len(seen) - 1]()

    async def run() -> None:
        async with AsyncClient(
            "http://router", transport=httpx.MockTransport(handle), retry=FAST
        ) as mc:
            await mc.delete_session(SID)

    asyncio.run(run())
    assert len(seen) == 3


class _CountingServer(socketserver.ThreadingMixIn, http.server.HTTPServer):
    """A kept-alive HTTP/1.1 server answering every GET with 200 after
    ``delay`` seconds, counting the connections it accepts."""

    daemon_threads = True
    request_queue_size = 256

    def __init__(self, delay: float) -> None:
        self.accepted = 0
        self.delay = delay
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def setup(self) -> None:
                server.accepted += 1
                super().setup()

            def do_GET(self) -> None:  # noqa: N802 (the stdlib's name)
                time.sleep(server.delay)
                self.send_response(200)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        super().__init__(("127.0.0.1", 0), Handler)


def test_rest_keeps_every_pooled_connection_alive() -> None:
    # With httpx's default pool (20 connections kept alive), httpcore closes
    # each connection that goes idle while the pool holds more than 20, and
    # can so close one just handed to a waiting thread's request: that
    # request hangs for its whole timeout, then fails ("Bad file
    # descriptor"), after the server may have applied it. Seen once in 20
    # runs of benches/exactly_once.py. The client's pool keeps every
    # connection it opens: a second burst of 40 concurrent requests finds
    # the first burst's connections, and opens none (with httpx's default
    # pool the first burst opens up to 40, and the second opens some again).
    server = _CountingServer(delay=0.1)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with Client(f"http://127.0.0.1:{server.server_address[1]}") as mc:

            def burst() -> None:
                start = threading.Barrier(40)

                def one() -> None:
                    start.wait()
                    assert mc.ready()

                threads = [threading.Thread(target=one) for _ in range(40)]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()

            burst()
            first = server.accepted
            assert first > 1, f"the first burst opened only {first} connection"
            burst()
            assert server.accepted == first, f"{server.accepted - first} connections opened again"
    finally:
        server.shutdown()
        server.server_close()


def test_backoff_is_jittered_bounded_and_growing() -> None:
    policy = RetryPolicy(initial_backoff=0.1, max_backoff=0.8, rng=random.Random(7))
    waits = policy.waits()
    first = [next(waits) for _ in range(40)]
    assert all(0 <= w <= 0.8 for w in first)
    assert max(first[:1]) <= 0.1 and max(first[10:]) > 0.4
    assert len(set(first)) == len(first), "jittered, not fixed"
    with pytest.raises(ValueError):
        RetryPolicy(initial_backoff=0)


# ------------------------------------------------------------------ gRPC stub


class _Agents(pb_grpc.AgentsServicer):
    """Refuses the first ``refusals`` calls as a misdirected replica, then
    answers NOT_FOUND (or an empty reply to DeleteSession); records each
    call's ``x-mcapi-session``."""

    def __init__(self, refusals: int) -> None:
        self.refusals = refusals
        self.calls: list[tuple[str, str | None]] = []

    def _seen(self, rpc: str, context: grpc.ServicerContext) -> None:
        meta = dict(context.invocation_metadata())
        self.calls.append((rpc, meta.get("x-mcapi-session")))
        if self.refusals > 0:
            self.refusals -= 1
            context.set_trailing_metadata(
                (("x-mcapi-error-code", "wrong_replica"), ("x-mcapi-owner", "mcapi-2"))
            )
            context.abort(grpc.StatusCode.UNAVAILABLE, "owned by mcapi-2")

    def _missing(self, rpc: str, context: grpc.ServicerContext) -> Any:
        self._seen(rpc, context)
        context.set_trailing_metadata((("x-mcapi-error-code", "not_found"),))
        context.abort(grpc.StatusCode.NOT_FOUND, "no such session")

    def DeleteSession(self, request: Any, context: grpc.ServicerContext) -> Any:  # noqa: N802
        self._seen("DeleteSession", context)
        return pb.DeleteSessionResponse()

    def GetSession(self, request: Any, context: grpc.ServicerContext) -> Any:  # noqa: N802
        return self._missing("GetSession", context)

    def Observe(self, request: Any, context: grpc.ServicerContext) -> Any:  # noqa: N802
        return self._missing("Observe", context)

    def GetValues(self, request: Any, context: grpc.ServicerContext) -> Any:  # noqa: N802
        return self._missing("GetValues", context)

    def GetHistory(self, request: Any, context: grpc.ServicerContext) -> Any:  # noqa: N802
        return self._missing("GetHistory", context)


@pytest.fixture
def stub() -> Iterator[Callable[[int], tuple[_Agents, str]]]:
    servers: list[grpc.Server] = []

    def start(refusals: int) -> tuple[_Agents, str]:
        agents = _Agents(refusals)
        server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
        pb_grpc.add_AgentsServicer_to_server(agents, server)
        port = server.add_insecure_port("127.0.0.1:0")
        server.start()
        servers.append(server)
        return agents, f"127.0.0.1:{port}"

    yield start
    for s in servers:
        s.stop(None)


def test_grpc_names_the_session_on_every_call(stub: Callable[[int], tuple[_Agents, str]]) -> None:
    agents, target = stub(0)
    # Unnumbered: a numbered observe of a session it does not know reads the
    # session first (GetSession), which this stub refuses before Observe.
    with GrpcClient(target, retry=FAST, exactly_once=False) as mc:
        for call in (
            lambda: mc.get_session(SID),
            lambda: mc.observe(SID, state=3),
            lambda: mc.values(SID),
            lambda: mc.history(SID),
        ):
            with pytest.raises(NotFound):
                call()
        mc.delete_session(SID)
    assert [rpc for rpc, _ in agents.calls] == [
        "GetSession", "Observe", "GetValues", "GetHistory", "DeleteSession",
    ]
    assert all(session == SID for _, session in agents.calls), agents.calls


def test_grpc_retries_unavailable_refusals(stub: Callable[[int], tuple[_Agents, str]]) -> None:
    agents, target = stub(3)
    with GrpcClient(target, retry=FAST) as mc:
        mc.delete_session(SID)
    assert len(agents.calls) == 4 and all(s == SID for _, s in agents.calls)


def test_grpc_gives_up_at_the_deadline_with_the_owner(
    stub: Callable[[int], tuple[_Agents, str]],
) -> None:
    agents, target = stub(10_000)
    policy = RetryPolicy(deadline=0.4, initial_backoff=0.02, max_backoff=0.1)
    with GrpcClient(target, retry=policy) as mc, pytest.raises(WrongReplica) as e:
        mc.delete_session(SID)
    assert e.value.owner == "mcapi-2" and e.value.grpc_code == "UNAVAILABLE"
    assert len(agents.calls) >= 3
    agents.calls.clear()
    with GrpcClient(target, retry=None) as mc, pytest.raises(WrongReplica):
        mc.delete_session(SID)
    assert len(agents.calls) == 1


# ------------------------------------------------------------------ real replicas


def test_two_real_replicas_refuse_each_others_sessions(tmp_path: Path) -> None:
    """A client sent to the wrong replica (a stale router) retries, then
    raises WrongReplica naming the owner; the owner serves the session."""
    if "--shard-map" not in serve_help():
        pytest.skip("this mcapi binary has no --shard-map")
    map_path = tmp_path / "shards.map"
    subprocess.run(
        [str(BINARY), "cluster", "plan", "--replicas", "2", "--out", str(map_path)],
        check=True,
        capture_output=True,
    )
    a = start_server(tmp_path / "a", ["--shard-map", str(map_path), "--replica", "mcapi-0"])
    b = start_server(tmp_path / "b", ["--shard-map", str(map_path), "--replica", "mcapi-1"])
    try:
        with Client(a.http_url) as owner:
            session = owner.create_session("hallway", seed=3)
            assert owner.observe(session.id, state=25).tick == 0
        policy = RetryPolicy(deadline=0.3, initial_backoff=0.02, max_backoff=0.05)
        with Client(b.http_url, retry=policy) as stale, pytest.raises(WrongReplica) as e:
            stale.get_session(session.id)
        assert e.value.owner == "mcapi-0" and e.value.status == 421
        with GrpcClient(b.grpc_target, retry=policy) as stale, pytest.raises(WrongReplica) as g:
            stale.observe(session.id, state=25, stimulus=[0.0, 0.0])
        assert g.value.owner == "mcapi-0" and g.value.grpc_code == "UNAVAILABLE"
        with GrpcClient(a.grpc_target) as owner_grpc:
            assert owner_grpc.get_session(session.id).tick == 0, "nothing was applied by the refusal"
    finally:
        a.stop()
        b.stop()
