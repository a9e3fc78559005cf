"""API keys: a server started with keys refuses calls without a valid one
(401 / UNAUTHENTICATED), and a key sees only the sessions it created."""

from __future__ import annotations

from collections.abc import Iterator

import httpx
import pytest
from conftest import Server, run_async, start_server, supports_api_keys

from mcapi_client import AsyncClient, AsyncGrpcClient, Client, GrpcClient, NotFound, Unauthenticated

# The server refuses keys shorter than 16 characters.
KEY_A, KEY_B = "test-key-a-0123456789", "test-key-b-0123456789"


@pytest.fixture(scope="module")
def keyed_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server with two API keys."""
    if not supports_api_keys():
        pytest.skip("this mcapi binary has no --api-key flag: it predates API keys; rebuild it")
    srv = start_server(tmp_path_factory.mktemp("keyed"), ["--api-key", KEY_A, "--api-key", KEY_B])
    yield srv
    srv.stop()


def _unauthenticated(fn: object) -> Unauthenticated:
    with pytest.raises(Unauthenticated) as info:
        fn()  # type: ignore[operator]
    e = info.value
    assert (e.code, e.status) == ("unauthenticated", 401), repr(e)
    return e


def test_rest_needs_a_valid_key(keyed_server: Server) -> None:
    with Client(keyed_server.http_url) as anonymous:
        _unauthenticated(lambda: anonymous.create_session("hallway"))
        _unauthenticated(lambda: anonymous.list_sessions())
    with Client(keyed_server.http_url, api_key="wrong") as wrong:
        _unauthenticated(lambda: wrong.create_session("hallway"))
    with Client(keyed_server.http_url, api_key=KEY_A) as a:
        sid = a.create_session("hallway").id
        assert a.observe(sid, 3).tick == 0
    with Client(keyed_server.http_url) as anonymous:
        _unauthenticated(lambda: anonymous.get_session(sid))
        _unauthenticated(lambda: anonymous.observe(sid, 4, [0.0, 0.0]))
    # Health, readiness and metrics stay open.
    for path in ("/healthz", "/readyz", "/metrics"):
        assert httpx.get(keyed_server.http_url + path).status_code == 200, path


def test_grpc_needs_a_valid_key(keyed_server: Server) -> None:
    with GrpcClient(keyed_server.grpc_target) as anonymous:
        e = _unauthenticated(lambda: anonymous.create_session("hallway"))
        assert e.grpc_code == "UNAUTHENTICATED"
    with GrpcClient(keyed_server.grpc_target, api_key="wrong") as wrong:
        _unauthenticated(lambda: wrong.list_sessions())
    with GrpcClient(keyed_server.grpc_target, api_key=KEY_A) as a:
        sid = a.create_session("hallway").id
        with a.interact(sid) as stream:
            assert stream.step(3).tick == 0
    with GrpcClient(keyed_server.grpc_target, api_key="wrong") as wrong:
        with wrong.interact(sid) as stream:
            _unauthenticated(lambda: stream.step(4, [0.0, 0.0]))
        with pytest.raises(Unauthenticated):
            next(wrong.watch(sid))


def test_a_key_sees_only_its_own_sessions(keyed_server: Server) -> None:
    with Client(keyed_server.http_url, api_key=KEY_A) as a, Client(
        keyed_server.http_url, api_key=KEY_B
    ) as b, GrpcClient(keyed_server.grpc_target, api_key=KEY_B) as b_grpc:
        mine = a.create_session("hallway").id
        theirs = b.create_session("hallway").id
        assert mine in {s.id for s in a.iter_sessions()}
        assert mine not in {s.id for s in b.iter_sessions()}
        assert theirs not in {s.id for s in a.iter_sessions()}
        for fn in (
            lambda: b.get_session(mine),
            lambda: b.observe(mine, 1),
            lambda: b.values(mine),
            lambda: b.history(mine),
            lambda: b.delete_session(mine),
            lambda: b_grpc.get_session(mine),
            lambda: b_grpc.observe(mine, 1),
            lambda: b_grpc.delete_session(mine),
        ):
            with pytest.raises(NotFound) as e:
                fn()
            assert (e.value.code, e.value.status) == ("not_found", 404)
        assert a.get_session(mine).tick == 0, "the other key's attempts changed nothing"


def test_the_async_clients_send_the_key(keyed_server: Server) -> None:
    async def run() -> None:
        async with AsyncClient(keyed_server.http_url) as anonymous:
            with pytest.raises(Unauthenticated) as e:
                await anonymous.create_session("hallway")
            assert (e.value.code, e.value.status) == ("unauthenticated", 401)
        async with AsyncGrpcClient(keyed_server.grpc_target, api_key="wrong") as wrong:
            with pytest.raises(Unauthenticated) as e:
                await wrong.list_sessions()
            assert e.value.grpc_code == "UNAUTHENTICATED"
        async with AsyncClient(keyed_server.http_url, api_key=KEY_A) as a, AsyncGrpcClient(
            keyed_server.grpc_target, api_key=KEY_A
        ) as g:
            sid = (await a.create_session("hallway")).id
            async with g.interact(sid) as stream:
                assert (await stream.step(3)).tick == 0
            assert (await g.get_session(sid)).tick == 0
        async with AsyncGrpcClient(keyed_server.grpc_target, api_key=KEY_B) as other:
            with pytest.raises(NotFound):
                await other.get_session(sid)
            async with other.interact(sid) as stream:
                with pytest.raises(NotFound):
                    await stream.step(4, [0.0, 0.0])

    run_async(run())
