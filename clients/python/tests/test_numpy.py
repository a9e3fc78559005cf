"""numpy at the boundary: every method takes numpy integer and float scalars
and arrays (and anything `operator.index` or `__float__` takes), sends the
same requests as for plain Python numbers, and refuses bools where a number
belongs."""

from __future__ import annotations

import json
import math
import random
from decimal import Decimal
from fractions import Fraction
from typing import Any

import pytest
from conftest import Server, open_client, run_async

from mcapi_client import (
    AgentOptions,
    AsyncGrpcClient,
    CuriosityConfig,
    GrpcClient,
    InvalidObservation,
    Observation,
    _pb,
    models,
)
from mcapi_client._normalise import as_float, as_floats, as_int, plain
from mcapi_client.types import as_curiosity

np = pytest.importorskip("numpy")


def _exactly(value: Any, expected: Any) -> None:
    """``value == expected`` with the same plain types all the way down."""
    assert value == expected
    assert type(value) is type(expected), (value, type(value))
    if isinstance(value, dict):
        for k in value:
            _exactly(value[k], expected[k])
    elif isinstance(value, (list, tuple)):
        for a, b in zip(value, expected):
            _exactly(a, b)


@pytest.mark.parametrize(
    "x", [np.int64(7), np.int8(7), np.uint64(7), np.array(7), 7, np.array([7])[0]]
)
def test_integers(x: Any) -> None:
    _exactly(as_int(x, "state"), 7)


@pytest.mark.parametrize(
    ("x", "message"),
    [
        (True, "not a bool"),
        (np.True_, "not a bool"),
        (np.array(False), "not a bool"),
        (2.0, "must be an integer, not float"),
        (np.float64(2.0), "must be an integer, not float64"),
        ("3", "must be an integer, not str"),
        (np.array([3]), "must be an integer, not ndarray"),
        (None, "must be an integer, not NoneType"),
    ],
)
def test_not_integers(x: Any, message: str) -> None:
    with pytest.raises(TypeError, match=message) as e:
        as_int(x, "state")
    assert "`state`" in str(e.value)


@pytest.mark.parametrize(
    "x", [np.float32(0.25), np.float64(0.25), np.array(0.25), Decimal("0.25"), Fraction(1, 4), 0.25]
)
def test_floats(x: Any) -> None:
    _exactly(as_float(x, "eta"), 0.25)


def test_floats_from_integers_and_non_finite_values() -> None:
    _exactly(as_float(np.int64(3), "x"), 3.0)
    _exactly(as_float(3, "x"), 3.0)
    assert math.isnan(as_float(np.float64("nan"), "x")), "NaN passes: the server answers it"
    assert as_float(np.inf, "x") == math.inf


@pytest.mark.parametrize("x", [True, np.True_, "1.5", b"1", None, [1.0], object()])
def test_not_floats(x: Any) -> None:
    with pytest.raises(TypeError, match="`eta` must be a number"):
        as_float(x, "eta")


def test_vectors() -> None:
    _exactly(as_floats(np.array([0.5, 6.0], dtype=np.float32), "stimulus"), [0.5, 6.0])
    _exactly(as_floats(np.array([0, 6]), "stimulus"), [0.0, 6.0])
    _exactly(as_floats((np.float64(1.5), 2), "stimulus"), [1.5, 2.0])
    _exactly(as_floats((x for x in [np.int32(1)]), "stimulus"), [1.0])
    _exactly(as_floats(np.zeros(0), "stimulus"), [])
    with pytest.raises(TypeError, match=r"`stimulus\[1\]` must be a number, not a bool"):
        as_floats([0.0, True], "stimulus")
    with pytest.raises(TypeError, match=r"`stimulus\[0\]` must be a number, not a bool"):
        as_floats(np.array([True, False]), "stimulus")
    with pytest.raises(TypeError, match=r"`stimulus\[0\]` must be a number, not list"):
        as_floats(np.zeros((2, 2)), "stimulus")
    for bad in ("01", {"a": 1.0}, np.float64(1.0), 3):
        with pytest.raises(TypeError, match="`stimulus` must be a sequence of numbers"):
            as_floats(bad, "stimulus")


def test_plain_json_values() -> None:
    value = {
        "n": np.int64(2), "x": np.float32(0.5), "flag": np.True_, "v": np.arange(3),
        "nested": [{"p": np.float64(0.25)}, (np.int16(1), None)], np.int64(4): "key",
    }
    _exactly(
        plain(value),
        {"n": 2, "x": 0.5, "flag": True, "v": [0, 1, 2], "nested": [{"p": 0.25}, [1, None]], 4: "key"},
    )
    json.dumps(plain(value))


def test_observations_hold_plain_values() -> None:
    obs = Observation(
        np.int64(25), np.array([0.0, 6.0]), np.int64(2), signal=np.array([0.5, -1.0], np.float32),
        signal_source=np.uint8(1),
    )
    plain_obs = Observation(25, [0.0, 6.0], 2, signal=[0.5, -1.0], signal_source=1)
    assert obs == plain_obs
    _exactly(obs.to_json(), plain_obs.to_json())
    json.dumps(obs.to_json())
    assert _pb.observation_message(obs) == _pb.observation_message(plain_obs)
    assert Observation(np.int64(1), action_taken=np.str_("left")).action_taken == "left"
    for bad in (True, np.True_):
        with pytest.raises(TypeError, match="not a bool"):
            Observation(bad)
        with pytest.raises(TypeError, match="`action_taken` must be an integer, not a bool"):
            Observation(1, [0.0], bad)


def test_non_finite_stimuli_over_rest_are_refused_before_sending_and_sent_over_grpc() -> None:
    """REST's habit (JSON cannot carry NaN) is kept; gRPC lets the server answer."""
    obs = Observation(np.int64(1), np.array([np.nan, 0.0]))
    with pytest.raises(InvalidObservation) as e:
        obs.to_json()
    assert e.value.code == "non_finite_number" and "`stimulus[0]`" in e.value.message
    assert math.isnan(_pb.observation_message(obs).stimulus.values[0])


def test_agent_options_and_curiosity_hold_plain_values() -> None:
    opts = AgentOptions(
        eta=np.float64(0.02), gamma=np.float32(0.5), priorities=np.array([1.0, 0.5]),
        stimulus_rate=np.float64(0.25), seed=np.uint64(11), history=np.int32(64),
        curiosity={"signal_dim": np.int64(2), "params": {"gain": np.float64(800), "tau": np.int64(20)}},
    )
    expected = AgentOptions(
        eta=0.02, gamma=0.5, priorities=[1.0, 0.5], stimulus_rate=0.25, seed=11, history=64,
        curiosity=CuriosityConfig(2, {"gain": 800.0, "tau": 20}),
    )
    assert opts == expected
    _exactly(opts.to_json(), expected.to_json())
    json.dumps(opts.to_json())
    model = models.model_json("hallway")
    assert _pb.create_request(model, opts) == _pb.create_request(model, expected)
    assert as_curiosity(np.int64(3)) == CuriosityConfig(3)
    with pytest.raises(TypeError):
        as_curiosity(np.True_)
    with pytest.raises(TypeError, match="`seed` must be an integer, not a bool"):
        AgentOptions(seed=True)


def test_models_from_numpy_tables() -> None:
    # A deterministic table as a 2-d integer array.
    det = models.from_transition_table(np.array([[1], [0]]), ["flip"], {"x": np.int64(0)})
    assert det == models.from_transition_table([[1], [0]], ["flip"], {"x": 0})
    _exactly(det.to_json(), {"states": 2, "actions": ["flip"], "next": [[1], [0]], "stimuli": ["x"]})
    # Stochastic cells as {numpy int: numpy float}, and rows keyed by numpy ints.
    table = {
        np.int64(0): {np.int64(0): {np.int64(1): np.float64(0.25), np.int64(0): np.float32(0.75)}},
        np.int64(1): [np.int64(0)],
    }
    m = models.from_transition_table(table, ["go"], {"food": np.array([1])})
    assert m == models.from_transition_table([[{1: 0.25, 0: 0.75}], [0]], ["go"], {"food": [1]})
    json.dumps(m.to_json())
    _exactly(m.table, ((((1, 0.25), (0, 0.75)),), (((0, 1.0),),)))
    # A next state must be an integer: (k, 2) float arrays are refused by name.
    refused = r"state 0, action `go`: next state np.float64\(1.0\) is not an integer"
    with pytest.raises(ValueError, match=refused):
        models.from_transition_table([[np.array([[1, 0.5], [0, 0.5]])]], ["go"], {"x": 0})
    with pytest.raises(ValueError, match="is not a next state"):
        models.from_transition_table([[np.True_]], ["go"], {"x": 0})
    # Built directly, a Model converts its numpy parts too.
    direct = models.Model(
        states=np.int64(2), actions=("a",), stimuli=("x",),
        table=(((( np.int64(1), np.float64(1.0)),),), (((np.int64(0), np.float64(1.0)),),)),
        sources=(models.Source(np.int64(1), np.int64(0)),),
    )
    assert direct == models.from_transition_table([[1], [0]], ["a"], {"x": 1})
    json.dumps(direct.to_json())
    assert models.hallway(np.int64(5), {"x": np.array([0, 4])}) == models.hallway(5, {"x": [0, 4]})
    grid = models.grid(["#a.b#"], {"a": np.int64(0), "b": np.int64(1)})
    assert grid == models.grid(["#a.b#"], {"a": 0, "b": 1})
    assert grid.stimulus(np.int64(0)) == [6.0, 0.0]
    assert grid.available_actions(np.int64(0)) == grid.available_actions(0)


class NumpyToyText:
    """A toy-text P whose entries are numpy scalars (as CliffWalking's next states are)."""

    def __init__(self) -> None:
        f, i, b = np.float64, np.int64, np.bool_
        self.P = {
            0: {0: [(f(0.5), i(1), f(0.0), b(False)), (f(0.5), i(0), f(0.0), b(False))],
                1: [(f(1.0), i(0), f(0.0), b(False))]},
            1: {0: [(f(1.0), i(2), f(1.0), b(True))], 1: [(f(1.0), i(0), f(0.0), b(False))]},
            2: {0: [(f(1.0), i(2), f(0.0), b(True))], 1: [(f(1.0), i(2), f(0.0), b(True))]},
        }
        self.initial_state_distrib = np.array([1.0, 0.0, 0.0])

    @property
    def unwrapped(self) -> NumpyToyText:
        return self


def test_from_gymnasium_with_numpy_entries() -> None:
    m = models.from_gymnasium(NumpyToyText(), sources={"food": np.int64(2)})
    json.dumps(m.to_json())
    assert m.successors(0, 0) == ((1, 0.5), (0, 0.5))
    assert m.successors(2, 1) == ((0, 1.0),), "terminal states restart"
    _exactly(m.to_json()["transitions"][0], {"state": 0, "action": 0, "next": [[1, 0.5], [0, 0.5]]})


def test_mapping_models_are_made_plain() -> None:
    spec = {"states": np.int64(2), "actions": ["a"], "stimuli": ["x"], "next": np.array([[1], [0]])}
    _exactly(models.model_json(spec), {"states": 2, "actions": ["a"], "stimuli": ["x"], "next": [[1], [0]]})


@pytest.mark.parametrize("kind", ["rest", "grpc", "async-rest", "async-grpc"])
def test_every_method_takes_numpy_over_the_wire(kind: str, server: Server) -> None:
    """Twin sessions, one fed numpy values and one plain Python values, give
    the same steps, tables and history on each client."""
    world = models.hallway()
    rng = random.Random(3)
    with open_client(kind, server) as mc:
        options = dict(gamma=0.9, priorities=[1.0, 0.5], epsilon=0.0, history=50)
        np_id = mc.create_session(
            world, seed=np.int64(8), gamma=np.float64(0.9), priorities=np.array([1.0, 0.5]),
            epsilon=np.float32(0.0), history=np.int32(50),
        ).id
        py_id = mc.create_session(world, seed=8, **options).id
        state = np.int64(25)  # once failed: "Object of type int64 is not JSON serializable"
        a, b = mc.observe(np_id, state), mc.observe(py_id, int(state))
        assert a == b
        for i in range(40):
            state = np.int64(world.sample_next(state, a.action_index, rng))
            xi = np.asarray(world.stimulus(state), dtype=np.float32)
            taken = np.int64(a.action_index) if i % 5 == 0 else None
            a = mc.observe(np_id, state, xi, action_taken=taken)
            b = mc.observe(py_id, int(state), [float(x) for x in xi],
                           action_taken=None if taken is None else int(taken))
            assert a == b
        batch = [Observation(state, np.zeros(2)), (state, np.zeros(2), np.int64(2))]
        plain_batch = [(int(state), [0.0, 0.0]), (int(state), [0.0, 0.0], 2)]
        assert mc.observe_batch(np_id, batch) == mc.observe_batch(py_id, plain_batch)
        assert mc.values(np_id, "all") == mc.values(py_id, "all")
        assert mc.history(np_id, limit=np.int64(5)) == mc.history(py_id, limit=5)
        assert len(mc.list_sessions(limit=np.int64(1)).sessions) == 1
        tick = mc.get_session(np_id).tick
        for bad in (True, np.True_):
            with pytest.raises(TypeError, match="not a bool"):
                mc.observe(np_id, bad, [0.0, 0.0])
        assert mc.get_session(np_id).tick == tick, "a refused argument sends nothing"


def test_the_interact_streams_take_numpy(server: Server) -> None:
    world = models.hallway()
    states = [np.int64(s) for s in (25, 26, 27, 27, 26)]
    with GrpcClient(server.grpc_target) as mc:
        sid = mc.create_session(world, seed=3).id
        with mc.interact(sid) as stream:
            steps = [stream.step(states[0])]
            steps += [stream.step(s, np.zeros(2, np.float32), np.int64(2)) for s in states[1:]]
        twin = mc.create_session(world, seed=3).id
        plain_steps = mc.observe_batch(twin, [(25,)] + [(int(s), [0.0, 0.0], 2) for s in states[1:]])
        assert steps == plain_steps

    async def run() -> list[Any]:
        async with AsyncGrpcClient(server.grpc_target) as amc:
            sid = (await amc.create_session(world, seed=3)).id
            async with amc.interact(sid) as stream:
                out = [await stream.step(states[0])]
                for s in states[1:]:
                    out.append(await stream.step(s, np.zeros(2), np.int64(2)))
            return out

    assert run_async(run()) == plain_steps
