"""gRPC over the server's Unix socket (``mcapi serve --grpc-socket``): the
blocking and asyncio clients take ``unix:PATH`` as their target and give the
same steps as over TCP, groups included."""

from __future__ import annotations

import random
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import Server, run_async, serve_help, start_server

from mcapi_client import AsyncGrpcClient, GrpcClient, models
from mcapi_client.grpc_client import _channel_options


@pytest.fixture(scope="module")
def socket_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Server, Path]]:
    """A server with a gRPC socket as well as its port."""
    if "--grpc-socket" not in serve_help():
        pytest.skip("this mcapi binary has no --grpc-socket flag: rebuild it")
    # A short directory: a socket's path holds at most 107 bytes.
    short = Path(tempfile.mkdtemp(prefix="mcapi-"))
    path = short / "grpc.sock"
    srv = start_server(tmp_path_factory.mktemp("socket"), ["--grpc-socket", str(path)])
    yield srv, path
    srv.stop()
    assert not path.exists(), "the server removes its socket when it stops"
    short.rmdir()


def _trajectory(client: GrpcClient, steps: int) -> list[tuple[int, list[float]]]:
    world = models.hallway()
    rng = random.Random(5)
    sid = client.create_session(world, seed=21, update_mode="lockstep").id
    out = []
    with client.interact(sid) as stream:
        state = 25
        step = stream.step(state)
        for _ in range(steps):
            state = world.sample_next(state, step.action_index, rng)
            step = stream.step(state, world.stimulus(state))
            out.append((step.action_index, list(step.drive)))
    return out


def test_the_socket_gives_the_steps_of_the_port(socket_server: tuple[Server, Path]) -> None:
    server, path = socket_server
    with GrpcClient(f"unix:{path}") as over_socket, GrpcClient(server.grpc_target) as over_port:
        steps = _trajectory(over_socket, 150)
        assert steps == _trajectory(over_port, 150)
        assert {a for a, _ in steps} >= {0, 1}, "the agent moved both ways"


def test_a_group_steps_over_the_socket(socket_server: tuple[Server, Path]) -> None:
    _, path = socket_server
    world = models.hallway()
    with GrpcClient(f"unix:{path}") as client, client.create_group(world, 8, seed=3) as agents:
        rng = random.Random(1)
        states = np.full(8, 25)
        step = agents.step(states)
        for _ in range(20):
            moves = zip(states, step.actions, strict=True)
            states = np.array([world.sample_next(int(s), int(a), rng) for s, a in moves])
            step = agents.step(states, np.array([world.stimulus(int(s)) for s in states]))
        assert step.actions.shape == (8,) and step.drives.shape == (8, 2)
        assert np.allclose(np.linalg.norm(step.drives, axis=1), 1.0)


def test_the_async_client_takes_the_socket(socket_server: tuple[Server, Path]) -> None:
    _, path = socket_server

    async def run() -> int:
        async with AsyncGrpcClient(f"unix:{path}") as client:
            sid = (await client.create_session("hallway")).id
            async with client.interact(sid) as stream:
                await stream.step(3)
                step = await stream.step(4, [0.0, 0.0])
            return step.tick

    assert run_async(run()) == 1


def test_a_socket_target_gets_a_valid_authority() -> None:
    authority = ("grpc.default_authority", "localhost")
    assert authority in _channel_options("unix:/run/mcapi.sock", ())
    assert authority not in _channel_options("127.0.0.1:50051", ())
    mine = ("grpc.default_authority", "mcapi.internal")
    opts = _channel_options("unix:/run/mcapi.sock", [mine])
    assert mine in opts and authority not in opts, "the caller's authority wins"
