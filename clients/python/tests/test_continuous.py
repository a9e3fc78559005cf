"""Continuous worlds from Python: the model form, observation vectors over
REST and gRPC (unary and the stream), Gymnasium ``Box`` spaces, MO-Gymnasium's
minecart, and a session that survives ``kill -9``."""

from __future__ import annotations

import math
import random
from pathlib import Path

import httpx
import pytest
from conftest import Server, start_server

from mcapi_client import Client, GrpcClient, Observation, models
from mcapi_client.continuous import ContinuousEnvironment, ContinuousModel
from mcapi_client.errors import InvalidObservation, McapiError


def square(**kw: object) -> ContinuousModel:
    return ContinuousModel(
        low=(0.0, 0.0),
        high=(1.0, 1.0),
        actions=("north", "south", "east", "west"),
        stimuli=("food", "rest"),
        **kw,  # type: ignore[arg-type]
    )


class Point:
    """A point in the unit square; food near (0.2, 0.2), rest near (0.8, 0.8)."""

    MOVES = ((0.0, 0.04), (0.0, -0.04), (0.04, 0.0), (-0.04, 0.0))

    def __init__(self, seed: int) -> None:
        self.x = [0.5, 0.5]
        self.rng = random.Random(seed)

    def step(self, action: int) -> list[float]:
        dx, dy = self.MOVES[action]
        self.x = [
            min(1.0, max(0.0, self.x[0] + dx + self.rng.uniform(-0.005, 0.005))),
            min(1.0, max(0.0, self.x[1] + dy + self.rng.uniform(-0.005, 0.005))),
        ]
        near = lambda c: math.dist(self.x, c) < 0.15  # noqa: E731
        return [6.0 if near((0.2, 0.2)) else 0.0, 6.0 if near((0.8, 0.8)) else 0.0]


def test_the_model_is_checked_and_posted_as_the_server_takes_it() -> None:
    m = square(basis={"kind": "fourier", "order": 3}, samples={"max": 256})
    assert m.to_json() == {
        "observation_space": {"low": [0.0, 0.0], "high": [1.0, 1.0]},
        "actions": ["north", "south", "east", "west"],
        "stimuli": ["food", "rest"],
        "out_of_bounds": "clip",
        "basis": {"kind": "fourier", "order": 3},
        "samples": {"max": 256},
    }
    assert models.model_json(m) == m.to_json()
    for bad in (
        {"low": (0.0,) * 65, "high": (1.0,) * 65},
        {"low": (0.0, 1.0), "high": (1.0, 1.0)},
        {"low": (0.0, math.nan), "high": (1.0, 1.0)},
        {"low": (0.0, -1e300), "high": (1.0, 1.0)},
        {"low": (0.0,), "high": (1.0, 1.0)},
    ):
        with pytest.raises(ValueError):
            ContinuousModel(actions=("a",), stimuli=("x",), **bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="duplicate"):
        ContinuousModel(low=(0.0,), high=(1.0,), actions=("a", "a"), stimuli=("x",))
    with pytest.raises(ValueError, match="stimulus"):
        ContinuousModel(low=(0.0,), high=(1.0,), actions=("a",), stimuli=())


def test_an_observation_has_a_state_or_a_vector() -> None:
    assert Observation(observation=[0.5, 0.25], stimulus=[0, 1]).to_json() == {
        "observation": [0.5, 0.25],
        "stimulus": [0.0, 1.0],
    }
    with pytest.raises(TypeError, match="exactly one"):
        Observation(3, observation=[0.5])
    with pytest.raises(TypeError, match="exactly one"):
        Observation()
    with pytest.raises(McapiError):
        Observation(observation=[math.inf]).to_json()


def test_gymnasium_box_spaces_become_continuous_worlds() -> None:
    gym = pytest.importorskip("gymnasium")
    world = models.from_gymnasium(
        gym.make("MountainCar-v0"),
        stimuli=["goal"],
        stimulus_of=lambda x, _r, _i: [1.0 if x[0] >= 0.5 else 0.0],
    )
    assert isinstance(world, ContinuousEnvironment)
    assert world.model.dim == 2 and len(world.model.actions) == 3
    x = world.reset(seed=1)
    assert len(x) == 2 and world.model.low[0] <= x[0] <= world.model.high[0]
    s = world.step(2)
    assert len(s.observation) == 2 and s.stimulus in ([0.0], [1.0])
    # CartPole's velocities are unbounded: bounds must be given.
    with pytest.raises(ValueError, match="unbounded"):
        models.from_gymnasium(gym.make("CartPole-v1"))
    cart = models.from_gymnasium(
        gym.make("CartPole-v1"), bounds=[(-4.8, 4.8), (-5, 5), (-0.42, 0.42), (-5, 5)]
    )
    assert cart.model.stimuli == ("reward",)


def test_minecart_becomes_a_continuous_world_with_its_ores_as_stimuli() -> None:
    mo = pytest.importorskip("mo_gymnasium")
    world = models.from_mo_gymnasium(mo.make("minecart-v0"), observations="continuous")
    assert world.model.stimuli == ("ore1", "ore2")  # fuel, a cost, is no stimulus
    assert world.model.dim == 7 and len(world.model.actions) == 6
    with pytest.raises(models.UnsupportedEnvironment):
        models.from_mo_gymnasium(mo.make("minecart-v0"))


def drive_rest(mc: Client, sid: str, world: Point, ticks: int) -> list[object]:
    step = mc.observe(sid, observation=world.x)
    out: list[object] = [step]
    for _ in range(ticks):
        xi = world.step(step.action_index)
        step = mc.observe(sid, observation=world.x, stimulus=xi)
        out.append(step)
    return out


def test_a_continuous_session_over_rest_and_grpc(server: Server) -> None:
    with Client(server.http_url) as mc, GrpcClient(server.grpc_target) as grpc:
        rest_id = mc.create_session(square(), seed=5).id
        grpc_id = grpc.create_session(square(), seed=5).id
        rest_steps = drive_rest(mc, rest_id, Point(1), 60)
        # The same seed and observations over the gRPC stream: the same steps.
        world = Point(1)
        with grpc.interact(grpc_id) as stream:
            step = stream.step(observation=world.x)
            grpc_steps: list[object] = [step]
            for _ in range(60):
                xi = world.step(step.action_index)
                step = stream.step(observation=world.x, stimulus=xi)
                grpc_steps.append(step)
        assert grpc_steps == rest_steps
        info = httpx.get(f"{server.http_url}/v1/sessions/{rest_id}").json()
        assert info["tick"] == 60
        assert info["model"]["continuous"]["observation_space"]["low"] == [0.0, 0.0]
        assert info["stats"]["continuous"]["samples"] > 10
        history = mc.history(rest_id, limit=1)
        assert len(history) == 1
        with pytest.raises(InvalidObservation):
            mc.observe(rest_id, observation=[0.5], stimulus=[0.0, 0.0])
        with pytest.raises(InvalidObservation):
            grpc.observe(grpc_id, observation=[0.5, 0.5, 0.5], stimulus=[0.0, 0.0])
        with pytest.raises(McapiError, match="continuous"):
            mc.observe(rest_id, 3, [0.0, 0.0])
        mc.delete_session(rest_id)
        grpc.delete_session(grpc_id)


def test_minecart_is_driven_through_the_client(server: Server) -> None:
    mo = pytest.importorskip("mo_gymnasium")
    world = models.from_mo_gymnasium(mo.make("minecart-v0"), observations="continuous")
    with Client(server.http_url) as mc:
        sid = mc.create_session(world, seed=2).id
        step = mc.observe(sid, observation=world.reset(seed=2))
        for _ in range(200):
            s = world.step(step.action_index)
            step = mc.observe(sid, observation=s.observation, stimulus=s.stimulus)
        assert step.tick == 200 and world.ticks == 200
        assert all(math.isfinite(d) for d in step.drive)
        mc.delete_session(sid)


def test_a_continuous_session_survives_kill_9(tmp_path: Path) -> None:
    first = start_server(tmp_path)
    world = Point(7)
    log: list[Observation] = []
    try:
        with Client(first.http_url) as mc:
            model = square(basis={"kind": "fourier", "order": 3})
            sid = mc.create_session(model, seed=9).id
            twin = mc.create_session(model, seed=9).id  # replays everything at the end
            step = mc.observe(sid, observation=world.x)
            log.append(Observation(observation=world.x))
            for _ in range(150):
                xi = world.step(step.action_index)
                step = mc.observe(sid, observation=world.x, stimulus=xi)
                log.append(Observation(observation=world.x, stimulus=xi))
            before = mc.get_session(sid)
    finally:
        first.process.kill()  # SIGKILL: no snapshot, no clean shutdown
        first.process.wait()
    second = start_server(tmp_path)
    try:
        with Client(second.http_url) as mc, GrpcClient(second.grpc_target) as grpc:
            after = mc.get_session(sid)
            assert (after.tick, after.drive) == (before.tick, before.drive)
            with grpc.interact(sid) as stream:
                for _ in range(40):
                    xi = world.step(step.action_index)
                    step = stream.step(observation=world.x, stimulus=xi)
                    log.append(Observation(observation=world.x, stimulus=xi))
            # The session that was killed answers as one that never stopped.
            replay = mc.observe_batch(twin, log)
            assert replay[-1] == step
    finally:
        second.stop()

