"""The agent options: one list, ``_params.AGENT_OPTIONS`` (generated from the
server's parameter table), that ``AgentKwargs``, ``AgentOptions``, the
effective ``AgentConfig`` and the four ``create_session`` methods agree with;
an unknown or positional option is a ``TypeError`` before anything is sent."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from typing import Any

import pytest
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
    _pb,
    models,
)
from mcapi_client._params import CURIOSITY_PARAMS

# Nothing listens there: a client that sent anything would fail otherwise
# than with a TypeError.
NOWHERE_HTTP, NOWHERE_GRPC = "http://127.0.0.1:9", "127.0.0.1:9"


def _names(cls: Any) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def test_agent_kwargs_agent_options_and_agent_config_list_the_same_options() -> None:
    assert len(set(AGENT_OPTIONS)) == len(AGENT_OPTIONS) == 11
    assert tuple(AgentKwargs.__annotations__) == AGENT_OPTIONS
    assert AgentKwargs.__required_keys__ == frozenset()
    assert _names(AgentOptions) == AGENT_OPTIONS
    assert _names(AgentConfig) == AGENT_OPTIONS


def test_curiosity_params_follow_the_core_defaults_order() -> None:
    assert len(set(CURIOSITY_PARAMS)) == len(CURIOSITY_PARAMS) == 16
    assert CURIOSITY_PARAMS[0] == "max_centres" and CURIOSITY_PARAMS[-1] == "max_sources"


def test_agent_options_normalise_every_option() -> None:
    opts = AgentOptions(
        eta=1, gamma=0.5, priorities=(1, 0.5), stimulus_rate=1, optimistic_sd=0, ridge=1,
        epsilon=0, seed=3, update_mode="async", history=8, curiosity=2,
    )
    assert dataclasses.astuple(opts)[:10] == (
        1.0, 0.5, [1.0, 0.5], 1.0, 0.0, 1.0, 0.0, 3, "async", 8,
    )
    assert opts.curiosity == CuriosityConfig(2)
    assert all(type(getattr(opts, n)) is float for n in ("eta", "stimulus_rate", "optimistic_sd"))
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
    opts = AgentOptions(
        eta=0.02, gamma=0.5, priorities=[1.0, 0.5, 1.0], stimulus_rate=0.25, optimistic_sd=0.1,
        ridge=1e-5, epsilon=0.1, seed=3, update_mode="async", history=8, curiosity=2,
    )
    cfg = _pb.create_request(models.model_json("hallway"), opts).agent
    sent = {f.name for f, _ in cfg.ListFields()}
    assert sent == set(AGENT_OPTIONS) - {"stimulus_rate"} | {"stimulus_rate_constant"}
    assert (cfg.eta, cfg.gamma, cfg.optimistic_sd, cfg.ridge, cfg.epsilon) == (0.02, 0.5, 0.1, 1e-5, 0.1)
    assert (cfg.seed, cfg.history, cfg.stimulus_rate_constant) == (3, 8, 0.25)
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
