"""With the durable store, a session outlives its server: a client carries on
after a restart on the same data directory as if nothing happened."""

from __future__ import annotations

import math
import random
import re
from pathlib import Path

import pytest
from conftest import serve_help, start_server

from mcapi_client import Client, GrpcClient, Observation, models


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


def test_a_curious_session_survives_a_restart(tmp_path: Path) -> None:
    """The curiosity channel (its frozen module, the active one, the history
    with xi_cur) comes back after a restart, and the next steps are those of
    a twin that never stopped."""
    if not re.search(r"^\s*-\s*redb\b", serve_help(), re.MULTILINE):
        pytest.skip("this mcapi binary has no durable store (--store redb) yet")
    site = 25

    def book(n: int) -> list[float]:
        t = 0.08 * n
        return [math.sin(t) + math.cos(11 * t) ** 2, math.cos(11 * t)]

    log = [Observation(site)] + [Observation(site, [0.0, 0.0], "stay", signal=book(n)) for n in range(300)]
    later = [Observation(site, [0.0, 0.0], "stay", signal=book(n)) for n in range(300, 340)]
    first = start_server(tmp_path)
    try:
        with Client(first.http_url) as mc:
            sid = mc.create_session(models.hallway(), seed=4, curiosity=2, history=50).id
            twin = mc.create_session(models.hallway(), seed=4, curiosity=2, history=50).id
            mc.observe_batch(sid, log)
            before, history = mc.get_session(sid), mc.history(sid)
            assert before.curiosity is not None and len(before.curiosity.modules) == 1
    finally:
        first.stop()
    second = start_server(tmp_path)
    try:
        with Client(second.http_url) as mc, GrpcClient(second.grpc_target) as grpc:
            after = mc.get_session(sid)
            assert after.curiosity == before.curiosity
            assert (after.drive, after.agent) == (before.drive, before.agent)
            assert mc.history(sid) == history == grpc.history(sid)
            steps = grpc.observe_batch(sid, later)
            assert mc.observe_batch(twin, log + later)[-len(later):] == steps
    finally:
        second.stop()
