"""The agent options: one list, ``_params.AGENT_OPTIONS`` (generated from the
server's parameter table), that ``AgentKwargs``, ``AgentOptions``, the
effective ``AgentConfig`` and the four ``create_session`` methods agree with;
an unknown or positional option is a ``TypeError`` before anything is sent."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from _effective import effective_json, effective_message, of_kind, value_of_kind
from conftest import Blocking

from mcapi_client import (
    AGENT_OPTIONS,
    AgentConfig,
    AgentKwargs,
    AgentOptions,
    AsyncClient,
    AsyncGrpcClient,
    Client,
    CuriosityConfig,
    GrpcClient,
    _json,
    _pb,
    models,
)
from mcapi_client._params import AGENT_KINDS, CURIOSITY_PARAMS

# Nothing listens there: a client that sent anything would fail otherwise
# than with a TypeError.
NOWHERE_HTTP, NOWHERE_GRPC = "http://127.0.0.1:9", "127.0.0.1:9"


def _names(cls: Any) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def test_agent_kwargs_agent_options_and_agent_config_list_the_same_options() -> None:
    assert len(set(AGENT_OPTIONS)) == len(AGENT_OPTIONS)
    assert {"eta", "seed", "update_mode", "curiosity"} <= set(AGENT_OPTIONS)
    assert tuple(AgentKwargs.__annotations__) == AGENT_OPTIONS
    assert AgentKwargs.__required_keys__ == frozenset()
    assert _names(AgentOptions) == AGENT_OPTIONS
    assert _names(AgentConfig) == AGENT_OPTIONS


def test_curiosity_params_follow_the_core_defaults_order() -> None:
    assert len(set(CURIOSITY_PARAMS)) == len(CURIOSITY_PARAMS) == 16
    assert CURIOSITY_PARAMS[0] == "max_centres" and CURIOSITY_PARAMS[-1] == "max_sources"


def _every_option(**named: Any) -> dict[str, Any]:
    """A value for every agent option (an "object" ``None``): each real a whole
    number of its own, each integer one of its own, the rest the value of their
    kind; ``named`` as given."""
    values = {name: value_of_kind(name) for name in AGENT_OPTIONS}
    values |= {name: i for i, name in enumerate(of_kind("real"))}
    values |= {name: 100 + i for i, name in enumerate(of_kind("integer"))}
    return values | named


def test_agent_options_normalise_every_option() -> None:
    given = _every_option(
        eta=1, priorities=(1, 0.5), stimulus_rate=1, seed=3, update_mode="async", history=8, curiosity=2,
    )
    opts = AgentOptions(**given)
    assert (opts.eta, opts.priorities, opts.stimulus_rate, opts.seed, opts.update_mode, opts.history) == (
        1.0, [1.0, 0.5], 1.0, 3, "async", 8,
    )
    assert opts.curiosity == CuriosityConfig(2)
    assert {name: getattr(opts, name) for name in of_kind("real") + of_kind("integer")} == {
        name: given[name] for name in of_kind("real") + of_kind("integer")
    }
    assert all(type(getattr(opts, n)) is float for n in of_kind("real") + ["stimulus_rate"])
    assert all(type(getattr(opts, n)) is int for n in of_kind("integer"))
    assert all(type(x) is float for n in of_kind("per_stimulus") for x in getattr(opts, n))
    assert AgentOptions(stimulus_rate="sample_mean").stimulus_rate == "sample_mean"
    assert AgentOptions(**{name: None for name in AGENT_OPTIONS}) == AgentOptions()
    assert AgentOptions().to_json() == {}
    with pytest.raises(TypeError, match="`history` must be an integer, not a bool"):
        AgentOptions(history=False)
    with pytest.raises(TypeError, match="`gamma` must be a number, not str"):
        AgentOptions(gamma="0.5")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"`priorities\[1\]` must be a number, not a bool"):
        AgentOptions(priorities=[1.0, True])


def test_an_unknown_agent_option_is_a_type_error() -> None:
    with pytest.raises(TypeError, match=r"unexpected keyword argument 'etaa' \(did you mean 'eta'\?\)"):
        AgentOptions(etaa=0.1)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="unexpected keyword arguments 'sed'.*, 'zzz'"):
        AgentOptions(sed=1, zzz=2)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="positional"):
        AgentOptions(0.1)  # type: ignore[call-arg, arg-type]


@pytest.fixture(params=["rest", "grpc", "async-rest", "async-grpc"])
def unreachable(request: pytest.FixtureRequest) -> Iterator[Any]:
    """Each of the four clients, of an address nothing listens on."""
    make: Callable[[], Any]
    if request.param == "rest":
        with Client(NOWHERE_HTTP) as c:
            yield c
        return
    if request.param == "grpc":
        with GrpcClient(NOWHERE_GRPC) as g:
            yield g
        return
    if request.param == "async-rest":
        make = lambda: AsyncClient(NOWHERE_HTTP)  # noqa: E731
    else:
        make = lambda: AsyncGrpcClient(NOWHERE_GRPC)  # noqa: E731
    wrapped = Blocking(make)
    try:
        yield wrapped
    finally:
        wrapped.close()


def test_create_session_refuses_unknown_and_positional_options(unreachable: Any) -> None:
    with pytest.raises(TypeError, match="'etaa' \\(did you mean 'eta'\\?\\)"):
        unreachable.create_session("hallway", etaa=0.1)
    with pytest.raises(TypeError, match="'priority' \\(did you mean 'priorities'\\?\\)"):
        unreachable.create_session("hallway", seed=1, priority=[1.0, 1.0])
    with pytest.raises(TypeError, match="positional"):
        unreachable.create_session("hallway", 0.1)
    with pytest.raises(TypeError, match="`seed` must be an integer, not a bool"):
        unreachable.create_session("hallway", seed=True)


def test_every_option_reaches_the_grpc_request() -> None:
    given = _every_option(
        eta=0.02, priorities=[1.0, 0.5, 1.0], stimulus_rate=0.25, seed=3, update_mode="async",
        history=8, curiosity=2,
    )
    given |= {name: 1 / (i + 2) for i, name in enumerate(of_kind("real")) if name != "eta"}  # not whole
    cfg = _pb.create_request(models.model_json("hallway"), AgentOptions(**given)).agent

    def field(name: str) -> str:
        if AGENT_KINDS[name] != "real_or_name":
            return name
        return f"{name}_rule" if isinstance(given[name], str) else f"{name}_constant"

    sent = {f.name for f, _ in cfg.ListFields()}
    assert sent == {field(name) for name in AGENT_OPTIONS if given[name] is not None}
    assert "stimulus_rate_constant" in sent and "curiosity" in sent
    assert {name: getattr(cfg, name) for name in of_kind("real") + of_kind("integer")} == {
        name: given[name] for name in of_kind("real") + of_kind("integer")
    }
    assert (cfg.eta, cfg.seed, cfg.history, cfg.stimulus_rate_constant) == (0.02, 3, 8, 0.25)
    assert (list(cfg.priorities), cfg.update_mode) == ([1.0, 0.5, 1.0], _pb.pb.UPDATE_MODE_ASYNC)
    assert not _pb.create_request(models.model_json("hallway"), AgentOptions()).agent.ListFields()


def test_the_effective_configuration_lists_every_option_and_curiosity_constant(any_client: Any) -> None:
    info = any_client.create_session(models.hallway(), seed=5, curiosity=2)
    got = any_client.get_session(info.id)
    assert got == info
    assert _names(type(got.agent)) == AGENT_OPTIONS
    assert all(getattr(got.agent, name) is not None for name in AGENT_OPTIONS)
    assert got.agent.curiosity is not None and got.agent.curiosity.params is not None
    assert tuple(got.agent.curiosity.params) == CURIOSITY_PARAMS
    any_client.delete_session(info.id)


_FIELD_TYPES = {"real": "float", "integer": "int", "per_stimulus": "list[float]"}


def test_agent_config_fields_have_the_type_of_their_kind() -> None:
    # The readers convert plain numbers by kind alone, so a field's type must agree.
    for f in dataclasses.fields(AgentConfig):
        kind = AGENT_KINDS[f.name]
        if kind in _FIELD_TYPES:
            assert f.type == _FIELD_TYPES[kind], f.name


# What each kind reads as from _EFFECTIVE_JSON (its "real_or_name" options are names).
_TYPE_NAMES = {
    "real": "float", "integer": "int", "per_stimulus": "list", "real_or_name": "str", "choice": "str",
    "object": "NoneType",
}

# Every real a whole number of its own and every integer a whole float of its
# own, so that each must be converted; the options named are those checked by name.
_EFFECTIVE_JSON: dict[str, Any] = effective_json(**(
    {name: i for i, name in enumerate(of_kind("real"))}
    | {name: float(200 + i) for i, name in enumerate(of_kind("integer"))}
    | {"eta": 1, "priorities": [1, 0.5], "stimulus_rate": "sample_mean", "seed": 7.0, "update_mode": "async"}
))


def test_the_json_reader_converts_each_option_by_its_kind() -> None:
    cfg = _json.agent_config(_EFFECTIVE_JSON)
    assert cfg == AgentConfig(**_EFFECTIVE_JSON)  # equal values, 1 == 1.0: the types are checked below
    assert (cfg.eta, cfg.priorities, cfg.stimulus_rate, cfg.seed, cfg.update_mode, cfg.curiosity) == (
        1.0, [1.0, 0.5], "sample_mean", 7, "async", None,
    )
    assert [type(getattr(cfg, n)).__name__ for n in AGENT_OPTIONS] == [
        _TYPE_NAMES[AGENT_KINDS[n]] for n in AGENT_OPTIONS
    ]
    assert all(type(x) is float for n in of_kind("per_stimulus") for x in getattr(cfg, n))
    rate = _json.agent_config({**_EFFECTIVE_JSON, "stimulus_rate": 1}).stimulus_rate
    assert rate == 1.0 and type(rate) is float
    with_channel = {**_EFFECTIVE_JSON, "curiosity": {"signal_dim": 2, "params": {"gain": 800}}}
    assert _json.agent_config(with_channel).curiosity == CuriosityConfig(2, {"gain": 800})
    for name in AGENT_OPTIONS:
        if AGENT_KINDS[name] != "object":  # only an "object" may be left out
            with pytest.raises(KeyError, match=f"^'{name}'$"):
                _json.agent_config({k: v for k, v in _EFFECTIVE_JSON.items() if k != name})


def test_the_grpc_reader_converts_each_option_by_its_kind() -> None:
    pb = _pb.pb
    m = effective_message(
        _EFFECTIVE_JSON, eta=1, priorities=[1, 0.5], stimulus_rate_rule=pb.STIMULUS_RATE_RULE_SAMPLE_MEAN,
        seed=7, update_mode=pb.UPDATE_MODE_ASYNC,
    )
    cfg = _pb.agent_config(m)
    assert cfg == _json.agent_config(_EFFECTIVE_JSON)
    assert [type(getattr(cfg, n)) for n in AGENT_OPTIONS] == [
        type(getattr(_json.agent_config(_EFFECTIVE_JSON), n)) for n in AGENT_OPTIONS
    ]
    m.stimulus_rate_constant = 0.25
    m.curiosity.signal_dim = 2
    m.curiosity.params_json = '{"gain": 800}'
    cfg = _pb.agent_config(m)
    assert (cfg.stimulus_rate, cfg.curiosity) == (0.25, CuriosityConfig(2, {"gain": 800}))
    # What the client cannot name reads as the default, as it always did.
    unnamed = pb.EffectiveConfig(update_mode=pb.UPDATE_MODE_UNSPECIFIED)
    assert (_pb.agent_config(unnamed).update_mode, _pb.agent_config(unnamed).stimulus_rate) == (
        "lockstep", "sample_mean",
    )
    assert _pb.agent_config(pb.EffectiveConfig(update_mode=7)).update_mode == "lockstep"  # type: ignore[arg-type]
    page = _pb.session_page(pb.ListSessionsResponse(sessions=[{"update_mode": pb.UPDATE_MODE_ASYNC}]))
    assert page.sessions[0].update_mode == "async"


def test_the_grpc_request_encodes_named_values_or_refuses_them() -> None:
    hallway = models.model_json("hallway")
    cfg = _pb.create_request(
        hallway, AgentOptions(stimulus_rate="sample_mean", update_mode="lockstep")
    ).agent
    assert cfg.WhichOneof("stimulus_rate") == "stimulus_rate_rule"
    assert cfg.stimulus_rate_rule == _pb.pb.STIMULUS_RATE_RULE_SAMPLE_MEAN
    assert cfg.update_mode == _pb.pb.UPDATE_MODE_LOCKSTEP
    assert _pb.create_request(hallway, AgentOptions(curiosity=2)).agent.HasField("curiosity")
    with pytest.raises(ValueError, match=r"^unknown stimulus_rate 'mean' \(use 'sample_mean' or a number\)$"):
        _pb.create_request(hallway, AgentOptions(stimulus_rate="mean"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^unknown update_mode 'sync' \(use 'lockstep' or 'async'\)$"):
        _pb.create_request(hallway, AgentOptions(update_mode="sync"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^unknown update_mode 'unspecified'"):
        _pb.create_request(hallway, AgentOptions(update_mode="unspecified"))  # type: ignore[arg-type]
