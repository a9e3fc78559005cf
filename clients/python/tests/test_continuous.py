"""Continuous worlds from Python: the model form (checked here, posted as
REST JSON and as the typed gRPC message), observation vectors over REST and
gRPC (unary, batches, the streams; numpy arrays), the continuous parts of the
session, history and values replies, Gymnasium ``Box`` spaces, MO-Gymnasium's
minecart, and a session that survives ``kill -9``."""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import Any

import httpx
import pytest
from conftest import Server, async_test, start_server

from mcapi_client import AsyncGrpcClient, BadRequest, Client, ContinuousStats, GrpcClient, Observation, models
from mcapi_client import _json as rest_json
from mcapi_client.continuous import SAMPLE_KEYS, ContinuousEnvironment, ContinuousModel
from mcapi_client.errors import InvalidObservation, McapiError

# MO-Gymnasium's reward spaces are float64 Boxes cast to float32.
pytestmark = pytest.mark.filterwarnings("ignore:.*precision lowered:UserWarning")


def square(**kw: object) -> ContinuousModel:
    return ContinuousModel(
        low=(0.0, 0.0),
        high=(1.0, 1.0),
        actions=("north", "south", "east", "west"),
        stimuli=("food", "rest"),
        **kw,  # type: ignore[arg-type]
    )


class _Fixed:
    """An environment of the given spaces that never moves."""

    def __init__(self, observation_space: object, action_space: object) -> None:
        self.observation_space, self.action_space = observation_space, action_space


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
    assert world.model.dim == 2 and world.model.actions == ("push_left", "none", "push_right")
    assert world.model.stimuli == ("goal",) and world.to_json() == world.model.to_json()
    assert world.model.low + world.model.high == pytest.approx((-1.2, -0.07, 0.6, 0.07))
    x = world.reset(seed=1)
    assert len(x) == 2 and world.model.contains(x) and all(type(v) is float for v in x)
    s = world.step(2)
    assert len(s.observation) == 2 and s.stimulus in ([0.0], [1.0])
    assert world.ticks == 1 and world.returns == -1.0
    with pytest.raises(ValueError, match="action 3 is not in 0..3"):
        world.step(3)
    # CartPole's velocities are unbounded: bounds must be given, the message names the component.
    with pytest.raises(ValueError, match="component 1 is unbounded"):
        models.from_gymnasium(gym.make("CartPole-v1"))
    with pytest.raises(ValueError, match="component 3 is unbounded"):
        models.from_gymnasium(gym.make("CartPole-v1"), bounds=[None, (-5, 5), None, None])
    cart = models.from_gymnasium(gym.make("CartPole-v1"), bounds=[None, (-5, 5), None, (-5, 5)])
    assert cart.model.stimuli == ("reward",) and cart.model.actions == ("push_left", "push_right")
    assert cart.model.low[1:] == (-5.0, pytest.approx(-0.41887903), -5.0)
    assert cart.model.high[0] == pytest.approx(4.8)
    cart.reset(seed=3)
    assert cart.step(0).stimulus == [1.0]  # the positive part of CartPole's reward
    # Names and stimuli: given names are taken; several stimuli need stimulus_of.
    rbf = {"kind": "rbf", "centres_per_dim": 5}
    named = models.from_gymnasium(gym.make("MountainCar-v0"), actions=["l", "n", "r"], basis=rbf)
    assert named.model.actions == ("l", "n", "r") and named.model.basis == rbf
    with pytest.raises(ValueError, match="2 action names for 3 actions"):
        models.from_gymnasium(gym.make("MountainCar-v0"), actions=["l", "r"])
    with pytest.raises(ValueError, match="without `stimulus_of`"):
        models.from_gymnasium(gym.make("MountainCar-v0"), stimuli=["left", "right"])
    two = models.from_gymnasium(
        gym.make("MountainCar-v0"),
        stimuli=["left", "right"],
        stimulus_of=lambda x, _r, _i: [float(x[0] < -1.0), float(x[0] > 0.4)],
    )
    two.reset(seed=0)
    assert two.step(1).stimulus == [0.0, 0.0]
    broken = models.from_gymnasium(
        gym.make("MountainCar-v0"), stimuli=["a"], stimulus_of=lambda *_: [0.0, 1.0]
    )
    broken.reset(seed=0)
    with pytest.raises(ValueError, match="2 components for 1 stimuli"):
        broken.step(0)
    # What is not a 1-d Box with Discrete actions is refused, saying why.
    with pytest.raises(TypeError, match="Discrete observations: give `sources`"):
        models.from_gymnasium(gym.make("FrozenLake-v1"))
    with pytest.raises(TypeError, match="only Discrete actions"):
        models.from_gymnasium(gym.make("MountainCarContinuous-v0"))
    flat = gym.spaces.Box(low=0.0, high=1.0, shape=(2, 2))
    with pytest.raises(TypeError, match="only a 1-d Box"):
        models.from_gymnasium(_Fixed(flat, gym.spaces.Discrete(2)))


def test_minecart_becomes_a_continuous_world_with_its_ores_as_stimuli() -> None:
    mo = pytest.importorskip("mo_gymnasium")
    np = pytest.importorskip("numpy")
    env = mo.make("minecart-v0")
    world = models.from_mo_gymnasium(env, observations="continuous", scale=6)
    assert world.model.stimuli == ("ore1", "ore2")  # fuel, a cost, is no stimulus
    assert world.model.actions == ("mine", "left", "right", "accelerate", "brake", "none")
    # The box the cart reaches, not the [-1, 1]^7 the space declares.
    assert env.observation_space.low.tolist() == [-1.0] * 7
    assert world.model.low == (0.0, 0.0, 0.0, -1.0, -1.0, 0.0, 0.0)
    assert world.model.high == (1.0,) * 7
    np.random.seed(1)  # minecart's mines draw from numpy's global generator
    assert world.model.contains(world.reset(seed=1))
    returns = np.zeros(3)
    for t in range(300):
        s = world.step((3, 3, 3, 0, 1, 5)[t % 6])
        assert world.model.contains(s.observation), s.observation
        assert len(s.stimulus) == 2 and min(s.stimulus) >= 0.0
        returns += np.asarray(s.reward)
    assert world.returns == pytest.approx(returns.tolist(), abs=1e-4)  # fuel included
    assert world.returns[2] < 0 and world.stimulus_totals == pytest.approx(
        [6 * max(r, 0.0) for r in world.returns[:2]], abs=1e-4
    )
    # Given bounds replace the preset's, None keeping the space's own.
    loose = models.from_mo_gymnasium(env, observations="continuous", observation_bounds=[None] * 7)
    assert loose.model.low == (-1.0,) * 7
    with pytest.raises(models.UnsupportedEnvironment, match="observations='continuous'"):
        models.from_mo_gymnasium(mo.make("minecart-v0"))
    # mo-mountaincar's objectives are all penalties: no stimulus to receive.
    with pytest.raises(models.UnsupportedEnvironment, match="all penalties"):
        models.from_mo_gymnasium(mo.make("mo-mountaincar-v0"), observations="continuous")


def test_the_model_checks_names_bases_and_samples_and_reads_back() -> None:
    np = pytest.importorskip("numpy")
    m = ContinuousModel(
        low=np.zeros(3),
        high=np.array([1.0, 2.0, 3.0], dtype=np.float32),
        actions=["a", "b"],
        stimuli=["x"],
        basis={"kind": "rbf", "centres_per_dim": np.int64(4), "width": np.float32(0.5)},
        samples={"max": np.uint16(512), "known_after": 2},
        out_of_bounds="refuse",
    )
    assert (m.low, m.high, m.dim) == ((0.0, 0.0, 0.0), (1.0, 2.0, 3.0), 3)
    assert m.basis == {"kind": "rbf", "centres_per_dim": 4, "width": 0.5}
    assert type(m.basis["centres_per_dim"]) is int and m.samples == {"max": 512, "known_after": 2}
    assert ContinuousModel.from_json(m.to_json()) == m
    assert m.contains([0.0, 2.0, 1.5]) and not m.contains([0.0, 2.5, 1.5]) and not m.contains([0.0])
    one = {"low": (0.0,), "high": (1.0,), "actions": ("a",), "stimuli": ("x",)}
    for bad, message in (
        ({"basis": {"kind": "wavelet"}}, "basis.kind"),
        ({"basis": {"kind": "fourier", "order": 3, "width": 1.0}}, "no field 'width'"),
        ({"basis": "fourier"}, "mapping"),
        ({"samples": {"cells": 4}}, "no field 'cells'"),
        ({"samples": {"max": -1}}, "not a count"),
        ({"actions": ("a", "")}, "action 1"),
        ({"stimuli": ("x", 3)}, "stimulus 1"),
        ({"actions": tuple(f"a{i}" for i in range(65))}, "65 actions"),
        ({"out_of_bounds": "wrap"}, "out_of_bounds"),
        ({"low": (math.inf,)}, r"`low\[0\]` is inf"),
        ({"high": (2e12,)}, r"`high\[0\]`"),
    ):
        with pytest.raises((ValueError, TypeError), match=message):
            ContinuousModel(**{**one, **bad})  # type: ignore[arg-type]
    # A server's summary is taken as sent, a basis field this client does not know included.
    built = {**m.to_json(), "basis": {"kind": "rbf", "centres_per_dim": 4, "spread": 2}}
    assert ContinuousModel.from_json(built, check=False).basis == built["basis"]
    with pytest.raises(ValueError, match="spread"):
        ContinuousModel.from_json(built)


BASES = [
    {"kind": "fourier", "order": 5, "max_coupling": 2},
    {"kind": "fourier", "order": 3},
    {"kind": "rbf", "centres_per_dim": 6, "width": 0.75},
    {"kind": "tiles", "tilings": 4, "tiles_per_dim": 8, "table": 4096},
    {"kind": "pvf", "k": 20, "nodes": 300, "neighbours": 8},
    None,
]


@pytest.mark.parametrize("basis", BASES, ids=lambda b: b["kind"] + str(len(b)) if b else "default")
def test_the_model_travels_typed_over_grpc(basis: dict[str, object] | None) -> None:
    pytest.importorskip("grpc")
    from mcapi_client import _pb
    from mcapi_client.types import AgentOptions

    m = square(basis=basis, out_of_bounds="refuse", samples={"cells_per_dim": 10, "max": 300})
    request = _pb.create_request(models.model_json(m), AgentOptions())
    assert not request.model_json and request.model.WhichOneof("form") == "continuous"
    typed = request.model.continuous
    assert (list(typed.low), list(typed.high)) == ([0.0, 0.0], [1.0, 1.0])
    assert list(typed.actions) == list(m.actions) and list(typed.stimuli) == list(m.stimuli)
    assert typed.out_of_bounds == _pb.pb.OUT_OF_BOUNDS_REFUSE
    assert typed.samples.cells_per_dim == 10 and not typed.samples.HasField("per_cell")
    assert typed.HasField("basis") == (basis is not None)
    # Read back (a session's model.continuous), it is the model posted.
    assert _pb.continuous_model(typed) == m
    assert _pb.continuous_model(_pb.pb.ContinuousModel(low=[0], high=[1], actions=["a"], stimuli=["x"])) == (
        ContinuousModel(low=(0.0,), high=(1.0,), actions=("a",), stimuli=("x",))
    )


def test_a_continuous_json_the_typed_form_cannot_carry_is_sent_as_json() -> None:
    pytest.importorskip("grpc")
    from mcapi_client import _pb

    base = square().to_json()
    for odd in (
        {**base, "transitions": "learn"},  # the server refuses it, naming the field
        {**base, "basis": {"kind": "fourier"}},  # no order: REST's message says so
        {**base, "basis": {"kind": "fourier", "order": 1 << 32}},
        {**base, "observation_space": {"low": [0, 0], "high": [1, "1"]}},
        {**base, "out_of_bounds": "wrap"},
        {**base, "samples": {"max": -1}},
    ):
        assert _pb.model_message(odd) is None, odd


def test_the_replies_of_a_continuous_session_are_read_on_both_transports() -> None:
    built = square(
        basis={"kind": "rbf", "centres_per_dim": 8},
        samples={"cells_per_dim": 25, "per_cell": 2, "max": 2048, "known_after": 1},
    )
    info = {
        "id": "s0.X", "tick": 2, "drive": [0.5, 0.5], "policy_version": 2, "state": None,
        "model": {
            "states": 0, "actions": list(built.actions), "stimuli": list(built.stimuli), "pairs": 0,
            "transitions": 0, "deterministic": False, "basis": {"kind": "rbf", "k": 64},
            "features": 256, "continuous": built.to_json(),
        },
        "agent": {
            "eta": 0.01, "gamma": 0.95, "priorities": [1.0, 1.0], "stimulus_rate": "sample_mean",
            "optimistic_sd": 0.3, "ridge": 1e-6, "epsilon": 0.0, "seed": 3, "update_mode": "lockstep",
            "history": 256,
        },
        "stats": {
            "lstdq_error": 0.0, "lambda1_estimate": 1.0, "condition_1_holds": True, "constant_stimuli": [],
            "factorisation_reuses": 0, "factorisations": 0,
            "continuous": {
                "clipped": 1, "samples": 2, "slots": 2, "updates": 3, "rebuilds": 0, "basis_builds": 0,
            },
        },
    }
    got = rest_json.session_info(info)
    assert got.model.continuous == built and got.model.states == 0
    assert got.stats.continuous == ContinuousStats(clipped=1, samples=2, slots=2, updates=3, rebuilds=0)
    entry = {"tick": 1, "state": 0, "action": 2, "drive": [0.4, 0.9], "reward": 0.9, "lstdq_error": 0.0,
             "stimulus": [0.0, 1.0], "observation": [0.52, 0.5]}
    (h,) = rest_json.history([entry], list(built.actions))
    assert (h.observation, h.action, h.state) == ([0.52, 0.5], "east", 0)
    values = rest_json.values({"tick": 2, "policy_version": 2, "v": [1.0, 2.0],
                               "points": [[0.0, 0.0], [0.5, 0.0]]})
    assert values.points == [[0.0, 0.0], [0.5, 0.0]] and values.v == [1.0, 2.0]
    # Numbered states have none of these.
    assert rest_json.history([{**entry, "observation": None}], ["a"] * 4)[0].observation is None

    pytest.importorskip("grpc")
    from mcapi_client import _pb

    pb = _pb.pb
    msg = pb.SessionInfo(id="s0.X", tick=2, drive=[0.5, 0.5])
    msg.model.continuous.CopyFrom(_pb.model_message(built.to_json()).continuous)  # type: ignore[union-attr]
    counters = pb.ContinuousStats(clipped=1, samples=2, slots=2, updates=3, basis_builds=4)
    msg.stats.continuous.CopyFrom(counters)
    typed = _pb.session_info(msg)
    assert typed.model.continuous == built
    assert typed.stats.continuous == ContinuousStats(1, 2, 2, 3, 0, 4)
    assert _pb.session_info(pb.SessionInfo(id="s0.Y")).model.continuous is None
    history = pb.History(entries=[pb.HistoryEntry(tick=1, action_index=2, observation=[0.52, 0.5])])
    assert _pb.history(history, list(built.actions))[0].observation == [0.52, 0.5]
    assert _pb.history(pb.History(entries=[pb.HistoryEntry(tick=1)]), ["a"])[0].observation is None
    # gRPC lists pairs: a continuous session's tables have a row per point.
    v = pb.Values(tick=2, points=[pb.Point(x=[0.0, 0.0]), pb.Point(x=[0.5, 0.0]), pb.Point(x=[1.0, 0.0])])
    v.q.pairs.add(state=2, action=3, value=7.0)
    read = _pb.values(v, states=0, actions=4)
    assert read.points == [[0.0, 0.0], [0.5, 0.0], [1.0, 0.0]]
    assert read.q is not None and len(read.q) == 3 and read.q[2][3] == 7.0


def test_an_observation_is_a_state_or_a_vector_of_plain_floats() -> None:
    np = pytest.importorskip("numpy")
    obs = Observation(observation=np.array([0.25, 0.5], dtype=np.float32), stimulus=np.zeros(2))
    assert obs.observation == [0.25, 0.5] and type(obs.observation[0]) is float and obs.state is None
    assert Observation(observation=(np.float64(0.1), 1)).observation == [0.1, 1.0]
    with pytest.raises(TypeError, match="exactly one"):
        Observation(np.int64(2), observation=np.zeros(2))
    with pytest.raises(TypeError):
        Observation(observation=["0.5"])
    with pytest.raises(TypeError):
        Observation(observation=[True, 0.5])
    # JSON cannot carry NaN: refused before sending over REST, as a stimulus is.
    with pytest.raises(InvalidObservation, match=r"`observation\[1\]` is nan") as e:
        Observation(observation=[0.5, math.nan]).to_json()
    assert e.value.code == "non_finite_number"
    pytest.importorskip("grpc")
    from mcapi_client import _pb

    msg = _pb.observation_message(Observation(observation=np.array([0.5, math.nan]), stimulus=[1, 0]))
    assert list(msg.observation)[0] == 0.5 and math.isnan(msg.observation[1]) and msg.state == 0
    assert list(msg.stimulus.values) == [1.0, 0.0]


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


def test_a_continuous_session_on_every_client(any_client: Any, request: pytest.FixtureRequest) -> None:
    """Create, 50 ticks, a batch, the summary, stats, history, values and the
    refusals, over REST and gRPC, blocking and asyncio."""
    np = pytest.importorskip("numpy")
    kind = request.node.callspec.params["any_client"]
    mc = any_client
    model = square(basis={"kind": "fourier", "order": 3}, out_of_bounds="refuse", samples={"max": 512})
    info = mc.create_session(model, seed=11, history=16)
    sid = info.id
    built = info.model.continuous
    assert built is not None, info.model
    assert (built.low, built.high, built.actions, built.stimuli) == (
        model.low, model.high, model.actions, model.stimuli
    )
    assert built.out_of_bounds == "refuse" and dict(built.basis or {})["order"] == 3
    assert built.samples is not None and built.samples["max"] == 512
    assert set(built.samples) == set(SAMPLE_KEYS)  # the defaults filled in
    assert (info.model.states, info.model.pairs, info.model.transitions) == (0, 0, 0)
    assert info.model.features == info.model.basis.k * len(model.actions)
    assert info.stats.continuous == ContinuousStats(0, 0, 0, 0, 0, 0)

    world = Point(3)
    step = mc.observe(sid, observation=np.array(world.x))  # the first: no stimulus
    sent = [list(world.x)]
    assert step.tick == 0
    for t in range(1, 51):
        xi = world.step(step.action_index)
        x = np.asarray(world.x, dtype=np.float32)  # as a float32 Box would give it
        step = mc.observe(sid, observation=x, stimulus=xi)
        sent.append(x.tolist())
        assert step.tick == t and step.action == model.actions[step.action_index], step
        assert len(step.drive) == 2 and math.isfinite(step.reward) and step.reward >= 0.0
    assert step.policy_version >= 50  # lockstep: one update per observation
    batch = mc.observe_batch(
        sid,
        [Observation(observation=world.x, stimulus=[0.0, 0.0]), {"observation": world.x, "stimulus": [0, 0]}],
    )
    assert [s.tick for s in batch] == [51, 52]
    sent += [list(world.x)] * 2

    got = mc.get_session(sid)
    assert got.tick == 52 and got.model.continuous == built
    stats = got.stats.continuous
    assert stats is not None and stats.clipped == 0 and stats.samples > 10 and stats.slots > 0, stats
    assert stats.updates > 0 and stats.basis_builds == 0
    history = mc.history(sid, limit=5)
    assert [h.tick for h in history] == [48, 49, 50, 51, 52]
    assert [h.observation for h in history] == sent[-5:] and {h.state for h in history} == {0}
    assert history[-1].stimulus == [0.0, 0.0]
    values = mc.values(sid, include="all")
    assert values.points is not None and len(values.points) == 31 * 31  # the grid over the square (d = 2)
    assert values.points[0] == [0.0, 0.0] and values.points[-1] == [1.0, 1.0]
    assert values.v is not None and values.q is not None and values.policy is not None
    assert len(values.v) == len(values.q) == len(values.policy) == len(values.points)
    assert set(values.policy) <= set(model.actions) and values.r is None and values.xi is None

    # Refused, and nothing changes: a wrong dimension, outside the box
    # ("refuse"), not a finite number, a state number.
    for bad in ([0.5], [0.5, 0.5, 0.5], [1.5, 0.5], [-0.01, 0.5]):
        with pytest.raises(InvalidObservation) as e:
            mc.observe(sid, observation=bad, stimulus=[0.0, 0.0])
        assert (e.value.code, e.value.status) == ("invalid_observation", 400), e.value
    with pytest.raises(InvalidObservation) as e:
        mc.observe(sid, observation=[math.nan, 0.5], stimulus=[0.0, 0.0])
    # JSON cannot carry NaN: the REST clients refuse it before sending; gRPC sends it.
    assert e.value.code == ("non_finite_number" if "rest" in kind else "invalid_observation"), e.value
    with pytest.raises(BadRequest, match="continuous"):
        mc.observe(sid, 3, [0.0, 0.0])
    assert mc.get_session(sid).tick == 52
    # In a batch of several, the entries before a refused one are applied (docs/errors.md).
    with pytest.raises(BadRequest, match=r"observations\[1\].*outside"):
        mc.observe_batch(sid, [{"observation": [0.5, 0.5], "stimulus": [0, 0]}, {"observation": [2.0, 0.5]}])
    assert mc.get_session(sid).tick == 53
    mc.delete_session(sid)


def test_nan_sent_by_hand_over_rest_is_refused(client: Client, server: Server) -> None:
    sid = client.create_session(square(), seed=1).id
    client.observe(sid, observation=[0.5, 0.5])
    url = f"{server.http_url}/v1/sessions/{sid}/observations"
    for text in ('{"observation": [NaN, 0.5], "stimulus": [0, 0]}', '{"observation": [1e999, 0.5]}'):
        reply = httpx.post(url, content=text, headers={"content-type": "application/json"})
        assert reply.status_code == 400, reply.text
        # Not JSON (NaN is no JSON number, 1e999 none a double holds): the
        # server refuses the body as it parses it.
        assert reply.json()["code"] in ("bad_request", "invalid_observation"), reply.text
    assert client.get_session(sid).tick == 0


def test_a_malformed_continuous_model_has_the_codes_of_the_error_table(server: Server) -> None:
    """Posted as raw JSON (ContinuousModel would refuse these before sending),
    over REST and as the typed gRPC message."""
    base = square(samples={"max": 256}).to_json()
    cases = {
        "invalid_model": {**base, "actions": ["a", "a"]},
        "invalid_basis": {**base, "basis": {"kind": "fourier", "order": 0}},
    }
    with Client(server.http_url) as mc, GrpcClient(server.grpc_target) as grpc:
        for code, model in cases.items():
            for client in (mc, grpc):
                with pytest.raises(McapiError) as e:
                    client.create_session(model)
                assert e.value.code == code, e.value


def test_clipping_and_the_streams(server: Server) -> None:
    with Client(server.http_url) as mc, GrpcClient(server.grpc_target) as grpc:
        sid = mc.create_session(square(samples={"max": 256}), seed=4).id
        mc.observe(sid, observation=[0.5, 0.5])
        mc.observe(sid, observation=[1.5, -0.25], stimulus=[0.0, 0.0])  # "clip": taken, counted
        stats = mc.get_session(sid).stats.continuous
        assert stats is not None and stats.clipped == 1
        with grpc.interact(sid) as stream:
            stream.send(observation=[0.4, 0.4], stimulus=[0.0, 6.0])
            stream.send(observation=(0.45, 0.4), stimulus=[0.0, 0.0])
            assert [stream.recv().tick, stream.recv().tick] == [2, 3]
            with pytest.raises(TypeError, match="exactly one"):
                stream.send(stimulus=[0.0, 0.0])
        other = grpc.create_session(square(samples={"max": 256}), seed=4).id
        grpc.observe(other, observation=[0.5, 0.5])
        with grpc.interact_batch() as batch:
            results = batch.step(
                [
                    (sid, Observation(observation=[0.5, 0.4], stimulus=[0.0, 0.0])),
                    (other, {"observation": [0.5, 0.6], "stimulus": [6.0, 0.0]}),
                    (other, Observation(observation=[0.5], stimulus=[0.0, 0.0])),
                ]
            )
        assert [getattr(r, "tick", None) for r in results[:2]] == [4, 1]
        assert isinstance(results[2], InvalidObservation)
        assert [h.observation for h in grpc.history(other)] == [[0.5, 0.6]]
        for s in (sid, other):
            mc.delete_session(s)


@async_test
async def test_the_asyncio_stream_takes_observation_vectors(server: Server) -> None:
    np = pytest.importorskip("numpy")
    world = Point(5)
    async with AsyncGrpcClient(server.grpc_target) as mc:
        sid = (await mc.create_session(square(samples={"max": 256}), seed=5)).id
        async with mc.interact(sid) as stream:
            step = await stream.step(observation=np.array(world.x))
            for _ in range(20):
                xi = world.step(step.action_index)
                step = await stream.step(observation=np.array(world.x), stimulus=np.array(xi))
        assert step.tick == 20
        (last,) = await mc.history(sid, limit=1)
        assert last.observation == world.x
        await mc.delete_session(sid)


def test_minecart_is_driven_through_the_client(server: Server) -> None:
    mo = pytest.importorskip("mo_gymnasium")
    np = pytest.importorskip("numpy")
    world = models.from_mo_gymnasium(mo.make("minecart-v0"), observations="continuous", scale=6)
    np.random.seed(2)  # the mines' yields
    with Client(server.http_url) as mc:
        info = mc.create_session(world, seed=2)
        assert info.model.continuous is not None
        built = info.model.continuous
        assert built.low == world.model.low and built.stimuli == ("ore1", "ore2")
        assert info.model.basis.kind == "fourier"  # the default for d = 7
        sid = info.id
        step = mc.observe(sid, observation=world.reset(seed=2))
        for _ in range(200):
            s = world.step(step.action_index)
            step = mc.observe(sid, observation=s.observation, stimulus=s.stimulus)
        assert step.tick == 200 and world.ticks == 200
        assert all(math.isfinite(d) for d in step.drive)
        got = mc.get_session(sid)
        stats = got.stats.continuous
        # The preset box holds the cart: nothing clipped.
        assert stats is not None and stats.clipped == 0 and stats.samples > 50, stats
        last = mc.history(sid, limit=1)[0]
        assert last.observation == pytest.approx(s.observation) and len(last.observation or []) == 7
        assert len(world.returns) == 3 and world.returns[2] < 0  # fuel was spent
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
