"""With the durable store, a session outlives its server: a client carries on
after a restart on the same data directory as if nothing happened."""

from __future__ import annotations

import random
import re
from pathlib import Path

import pytest
from conftest import serve_help, start_server

from mcapi_client import Client, GrpcClient, models


def test_sessions_survive_a_restart(tmp_path: Path) -> None:
    if not re.search(r"^\s*-\s*redb\b", serve_help(), re.MULTILINE):
        pytest.skip("this mcapi binary has no durable store (--store redb) yet")
    world = models.hallway()
    rng = random.Random(6)
    first = start_server(tmp_path)
    try:
        with Client(first.http_url) as mc:
            sid = mc.create_session(world, seed=6).id
            twin = mc.create_session(world, seed=6).id  # replays everything at the end
            state = 20
            step = mc.observe(sid, state)
            log: list[tuple[int, list[float] | None]] = [(state, None)]
            for _ in range(150):
                state = world.sample_next(state, step.action_index, rng)
                xi = world.stimulus(state, noise_sd=2.0, rng=rng)
                step = mc.observe(sid, state, xi)
                log.append((state, xi))
            before = mc.get_session(sid)
    finally:
        first.stop()
    second = start_server(tmp_path)
    try:
        with Client(second.http_url) as mc, GrpcClient(second.grpc_target) as grpc:
            after = mc.get_session(sid)
            assert (after.tick, after.state, after.drive) == (before.tick, before.state, before.drive)
            assert after.agent == before.agent
            # The next steps are those of a session that never stopped.
            with grpc.interact(sid) as stream:
                for _ in range(30):
                    state = world.sample_next(state, step.action_index, rng)
                    xi = world.stimulus(state, noise_sd=2.0, rng=rng)
                    step = stream.step(state, xi)
                    log.append((state, xi))
            replay = mc.observe_batch(twin, log)
            assert replay[-1] == step
    finally:
        second.stop()
