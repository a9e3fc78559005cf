"""The curiosity channel's types and conversions, without a server: the REST
JSON and the gRPC messages of the same content give the same results."""

from __future__ import annotations

import json
import math

import pytest

from mcapi_client import (
    CuriosityConfig,
    CuriosityInfo,
    FrozenModule,
    InvalidObservation,
    InvalidParameter,
    Observation,
    Step,
    TickCuriosity,
    _json,
    _pb,
)
from mcapi_client._proto.mcapi.v1 import agents_pb2 as pb
from mcapi_client.types import AgentOptions, as_curiosity, as_observation


def _options(**kw: object) -> AgentOptions:
    return AgentOptions(**kw)  # type: ignore[arg-type]


def test_observation_json_carries_the_signal() -> None:
    obs = Observation(3, [0.0, 1.0], "stay", signal=[0.5, -1], signal_source=1)
    assert obs.to_json() == {
        "state": 3, "stimulus": [0.0, 1.0], "action_taken": "stay",
        "signal": [0.5, -1.0], "signal_source": 1,
    }
    assert "signal" not in Observation(3, [0.0]).to_json()
    assert as_observation({"state": 3, "stimulus": [0.0, 1.0], "action_taken": "stay",
                           "signal": [0.5, -1], "signal_source": 1}) == obs
    assert as_observation((3, [0.0, 1.0], "stay", [0.5, -1], 1)) == obs
    with pytest.raises(TypeError):
        as_observation({"state": 3, "sygnal": [1.0]})


def test_a_non_finite_signal_is_refused_as_the_server_would() -> None:
    with pytest.raises(InvalidObservation) as e:
        Observation(3, [0.0], signal=[1.0, math.inf]).to_json()
    assert e.value.code == "non_finite_number" and "`signal[1]`" in str(e.value)


def test_an_empty_signal_is_refused_on_both_transports() -> None:
    """gRPC cannot tell an empty signal from none, REST refuses it: refused here."""
    with pytest.raises(InvalidParameter) as e:
        Observation(3, [0.0], signal=[]).to_json()
    assert e.value.code == "invalid_parameter" and e.value.status == 400
    with pytest.raises(InvalidParameter):
        _pb.observation(3, [0.0], None, signal=[])


def test_the_observation_message_carries_the_signal() -> None:
    msg = _pb.observation(3, [0.0, 1.0], 2, signal=[0.5, -1.0], signal_source=1)
    assert list(msg.signal) == [0.5, -1.0] and msg.HasField("signal_source") and msg.signal_source == 1
    plain = _pb.observation(3, [0.0, 1.0], None)
    assert list(plain.signal) == [] and not plain.HasField("signal_source")
    batch = _pb.observations([Observation(3, [0.0], signal=[1.0, 2.0])])
    assert list(batch[0].signal) == [1.0, 2.0] and not batch[0].HasField("signal_source")


def test_curiosity_arguments_and_the_create_requests() -> None:
    assert as_curiosity(2) == CuriosityConfig(2)
    assert as_curiosity({"signal_dim": 2, "params": {"gain": 400}}) == CuriosityConfig(2, {"gain": 400})
    with pytest.raises(TypeError):
        as_curiosity({"signal_dim": 2, "gian": 1})
    with pytest.raises(TypeError):
        as_curiosity(True)

    opts = _options(curiosity={"signal_dim": 2, "params": {"gain": 400}}, seed=1)
    assert opts.to_json() == {"seed": 1, "curiosity": {"signal_dim": 2, "params": {"gain": 400}}}
    assert _options(curiosity=2).to_json() == {"curiosity": {"signal_dim": 2}}
    assert "curiosity" not in _options().to_json()

    req = _pb.create_request({"preset": "hallway"}, opts)
    assert req.agent.HasField("curiosity") and req.agent.curiosity.signal_dim == 2
    assert json.loads(req.agent.curiosity.params_json) == {"gain": 400}
    bare = _pb.create_request({"preset": "hallway"}, _options(curiosity=2)).agent.curiosity
    assert (bare.signal_dim, bare.params_json) == (2, "")
    assert not _pb.create_request({"preset": "hallway"}, _options()).agent.HasField("curiosity")


TICK = {"xi_cur": 12.0, "epsilon": 0.9, "modules": 1, "source": 0}
INFO = {
    "samples": 140, "epsilon": 0.25, "active_source": None, "active_samples": 7,
    "all_explained": True,
    "modules": [{"source": 0, "frozen_tick": 130, "learned_samples": 120}],
}


def test_steps_agree_across_transports() -> None:
    d = {"tick": 5, "action": "stay", "action_index": 2, "drive": [0.6, 0.8, 0.0],
         "reward": 1.5, "policy_version": 5}
    m = pb.Step(tick=5, action="stay", action_index=2, drive=[0.6, 0.8, 0.0], reward=1.5, policy_version=5)
    assert _json.step(d) == _pb.step(m) and _json.step(d).curiosity is None
    m.curiosity.CopyFrom(pb.TickCuriosity(xi_cur=12.0, epsilon=0.9, modules=1, source=0))
    step = _json.step({**d, "curiosity": TICK})
    assert step == _pb.step(m)
    assert step.curiosity == TickCuriosity(xi_cur=12.0, epsilon=0.9, modules=1, source=0)
    no_source = _json.step({**d, "curiosity": {**TICK, "source": None}})
    m.curiosity.ClearField("source")
    assert no_source == _pb.step(m) and isinstance(no_source, Step)
    assert no_source.curiosity is not None and no_source.curiosity.source is None


def test_curiosity_info_agrees_across_transports() -> None:
    m = pb.CuriosityInfo(
        samples=140, epsilon=0.25, active_samples=7, all_explained=True,
        modules=[pb.FrozenModule(source=0, frozen_tick=130, learned_samples=120)],
    )
    expected = CuriosityInfo(
        samples=140, epsilon=0.25, active_source=None, active_samples=7, all_explained=True,
        modules=[FrozenModule(source=0, frozen_tick=130, learned_samples=120)],
    )
    assert _json.curiosity_info(INFO) == _pb.curiosity_info(m) == expected
    m.active_source = 1
    assert _pb.curiosity_info(m).active_source == 1
    values = pb.Values(tick=3, policy_version=3)
    assert _pb.values(values, 1, 1).curiosity is None
    values.curiosity.CopyFrom(m)
    assert _pb.values(values, 1, 1).curiosity == _json.values(
        {"tick": 3, "policy_version": 3, "curiosity": {**INFO, "active_source": 1}}
    ).curiosity


def test_effective_config_agrees_across_transports() -> None:
    params = {"gain": 800.0, "tau": 20, "dt": 0.08}
    assert _json.curiosity_config({"signal_dim": 2, "params": params}) == _pb.curiosity_config(
        pb.CuriosityConfig(signal_dim=2, params_json=json.dumps(params))
    ) == CuriosityConfig(2, params)
    assert _json.curiosity_config(None) is None


def test_history_entries_agree_across_transports() -> None:
    actions = ["left", "right", "stay"]
    d = {"tick": 4, "state": 7, "action": 2, "drive": [0.6, 0.8, 0.0], "reward": 1.0,
         "lstdq_error": 0.1, "stimulus": [0.0, 0.0, 12.0], "curiosity": TICK}
    m = pb.History(entries=[pb.HistoryEntry(
        tick=4, state=7, action_index=2, drive=[0.6, 0.8, 0.0], reward=1.0, lstdq_error=0.1,
        stimulus=pb.Stimulus(values=[0.0, 0.0, 12.0]),
        curiosity=pb.TickCuriosity(xi_cur=12.0, epsilon=0.9, modules=1, source=0),
    )])
    (a,), (b,) = _json.history([d], actions), _pb.history(m, actions)
    assert a == b and a.action == "stay" and a.stimulus == [0.0, 0.0, 12.0]
    assert a.curiosity is not None and a.curiosity.xi_cur == 12.0
    # An entry restored from an old store, of a plain session; a first tick.
    old = {k: v for k, v in d.items() if k not in ("stimulus", "curiosity")}
    m.entries[0].ClearField("stimulus")
    m.entries[0].ClearField("curiosity")
    (a,), (b,) = _json.history([old], actions), _pb.history(m, actions)
    assert a == b and a.stimulus is None and a.curiosity is None
    m.entries[0].stimulus.SetInParent()
    first = _json.history([{**old, "stimulus": []}], actions)[0]
    assert _pb.history(m, actions)[0].stimulus == [] == first.stimulus
