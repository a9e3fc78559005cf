"""Conversions between the gRPC messages and the typed results (one place)."""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from typing import Any

from ._proto.mcapi.v1 import agents_pb2 as pb
from .types import (
    ActionRef,
    AgentConfig,
    AgentOptions,
    BasisSummary,
    CuriosityConfig,
    CuriosityInfo,
    FrozenModule,
    GridLayout,
    HistoryEntry,
    ModelSummary,
    Observation,
    SessionInfo,
    SessionPage,
    SessionCost,
    SessionStats,
    SessionSummary,
    Step,
    TickCuriosity,
    UpdateMode,
    Values,
    check_signal,
)

_UPDATE_MODES: dict[str, int] = {"lockstep": pb.UPDATE_MODE_LOCKSTEP, "async": pb.UPDATE_MODE_ASYNC}
_UPDATE_MODE_NAMES: dict[int, UpdateMode] = {
    pb.UPDATE_MODE_LOCKSTEP: "lockstep",
    pb.UPDATE_MODE_ASYNC: "async",
}


def create_request(model: dict[str, Any], agent: AgentOptions) -> pb.CreateSessionRequest:
    """``CreateSession``: the model travels as the JSON the REST API takes."""
    cfg = pb.SessionConfig()
    for name in ("eta", "gamma", "optimistic_sd", "ridge", "epsilon", "seed", "history"):
        value = getattr(agent, name)
        if value is not None:
            setattr(cfg, name, value)
    if agent.priorities is not None:
        cfg.priorities.extend(float(p) for p in agent.priorities)
    if agent.stimulus_rate == "sample_mean":
        cfg.stimulus_rate_rule = pb.STIMULUS_RATE_RULE_SAMPLE_MEAN
    elif isinstance(agent.stimulus_rate, str):
        raise ValueError(f"unknown stimulus_rate {agent.stimulus_rate!r} (use 'sample_mean' or a number)")
    elif agent.stimulus_rate is not None:
        cfg.stimulus_rate_constant = float(agent.stimulus_rate)
    if agent.update_mode is not None:
        if agent.update_mode not in _UPDATE_MODES:
            raise ValueError(f"unknown update_mode {agent.update_mode!r} (use 'lockstep' or 'async')")
        cfg.update_mode = _UPDATE_MODES[agent.update_mode]  # type: ignore[assignment]
    if agent.curiosity is not None:
        cfg.curiosity.signal_dim = agent.curiosity.signal_dim
        # The constants travel as the JSON object REST takes; empty: every default.
        if agent.curiosity.params:
            cfg.curiosity.params_json = json.dumps(agent.curiosity.params)
        cfg.curiosity.SetInParent()
    return pb.CreateSessionRequest(model_json=json.dumps(model), agent=cfg)


def observation(
    state: int,
    stimulus: Sequence[float] | None,
    action_taken: ActionRef | None,
    session_id: str = "",
    signal: Sequence[float] | None = None,
    signal_source: int | None = None,
) -> pb.Observation:
    """One observation message (``session_id`` empty: the metadata names it)."""
    msg = pb.Observation(session_id=session_id, state=state)
    if stimulus is not None:
        msg.stimulus.values.extend(float(x) for x in stimulus)
        msg.stimulus.SetInParent()  # an empty stimulus is still sent as given
    if isinstance(action_taken, str):
        msg.action_name = action_taken
    elif action_taken is not None:
        msg.action_index = int(action_taken)
    if signal is not None:
        msg.signal.extend(float(x) for x in check_signal(signal))
    if signal_source is not None:
        msg.signal_source = signal_source
    return msg


def observations(obs: Iterable[Observation]) -> list[pb.Observation]:
    """Batch entries as messages."""
    return [
        observation(
            o.state, o.stimulus, o.action_taken, signal=o.signal, signal_source=o.signal_source
        )
        for o in obs
    ]


def tick_curiosity(m: pb.TickCuriosity) -> TickCuriosity:
    """The curiosity channel at one tick."""
    return TickCuriosity(
        xi_cur=m.xi_cur,
        epsilon=m.epsilon,
        modules=m.modules,
        source=m.source if m.HasField("source") else None,
    )


def curiosity_info(m: pb.CuriosityInfo) -> CuriosityInfo:
    """The state of a session's curiosity channel."""
    return CuriosityInfo(
        samples=m.samples,
        epsilon=m.epsilon,
        active_source=m.active_source if m.HasField("active_source") else None,
        active_samples=m.active_samples,
        all_explained=m.all_explained,
        modules=[
            FrozenModule(source=f.source, frozen_tick=f.frozen_tick, learned_samples=f.learned_samples)
            for f in m.modules
        ],
    )


def curiosity_config(m: pb.CuriosityConfig) -> CuriosityConfig:
    """A session's effective curiosity channel (constants as JSON, as REST has them)."""
    return CuriosityConfig(
        signal_dim=m.signal_dim, params=json.loads(m.params_json) if m.params_json else {}
    )


def step(m: pb.Step) -> Step:
    """A step."""
    return Step(
        tick=m.tick,
        action=m.action,
        action_index=m.action_index,
        drive=list(m.drive),
        reward=m.reward,
        policy_version=m.policy_version,
        curiosity=tick_curiosity(m.curiosity) if m.HasField("curiosity") else None,
    )


def session_info(m: pb.SessionInfo) -> SessionInfo:
    """A session's details."""
    model, agent, stats = m.model, m.agent, m.stats
    which = agent.WhichOneof("stimulus_rate")
    rate: Any = (
        agent.stimulus_rate_constant if which == "stimulus_rate_constant" else "sample_mean"
    )
    return SessionInfo(
        id=m.id,
        tick=m.tick,
        drive=list(m.drive),
        policy_version=m.policy_version,
        state=m.state if m.HasField("state") else None,
        model=ModelSummary(
            states=model.states,
            actions=list(model.actions),
            stimuli=list(model.stimuli),
            pairs=model.pairs,
            transitions=model.transitions,
            deterministic=model.deterministic,
            basis=BasisSummary(kind=model.basis.kind, k=model.basis.k),
            features=model.features,
            layout=(
                GridLayout(
                    rows=model.layout.rows,
                    cols=model.layout.cols,
                    cells=[(c.row, c.col) for c in model.layout.cells],
                    marks=[(m.mark, m.state) for m in model.layout.marks],
                )
                if model.HasField("layout")
                else None
            ),
        ),
        agent=AgentConfig(
            eta=agent.eta,
            gamma=agent.gamma,
            priorities=list(agent.priorities),
            stimulus_rate=rate,
            optimistic_sd=agent.optimistic_sd,
            ridge=agent.ridge,
            epsilon=agent.epsilon,
            seed=agent.seed,
            update_mode=_UPDATE_MODE_NAMES.get(agent.update_mode, "lockstep"),
            history=agent.history,
            curiosity=curiosity_config(agent.curiosity) if agent.HasField("curiosity") else None,
        ),
        stats=SessionStats(
            lstdq_error=stats.lstdq_error,
            lambda1_estimate=stats.lambda1_estimate,
            condition_1_holds=stats.condition_1_holds,
            constant_stimuli=list(stats.constant_stimuli),
            factorisation_reuses=stats.factorisation_reuses,
            factorisations=stats.factorisations,
        ),
        curiosity=curiosity_info(m.curiosity) if m.HasField("curiosity") else None,
        cost=(
            SessionCost(bytes=m.cost.bytes, tick_us=m.cost.tick_us)
            if m.HasField("cost")
            else None
        ),
    )


def session_page(m: pb.ListSessionsResponse) -> SessionPage:
    """A page of the session listing."""
    return SessionPage(
        sessions=[
            SessionSummary(
                id=s.id,
                tick=s.tick,
                states=s.states,
                update_mode=_UPDATE_MODE_NAMES.get(s.update_mode, "lockstep"),
                idle_ms=s.idle_ms if s.HasField("idle_ms") else None,
            )
            for s in m.sessions
        ],
        next=m.next if m.HasField("next") else None,
    )


def _dense_values(pairs: Iterable[pb.PairValue], states: int, actions: int) -> list[list[float | None]]:
    table: list[list[float | None]] = [[None] * actions for _ in range(states)]
    for p in pairs:
        table[p.state][p.action] = p.value
    return table


def _dense_vectors(
    pairs: Iterable[pb.PairVector], states: int, actions: int
) -> list[list[list[float] | None]]:
    table: list[list[list[float] | None]] = [[None] * actions for _ in range(states)]
    for p in pairs:
        table[p.state][p.action] = list(p.values)
    return table


def values(m: pb.Values, states: int, actions: int) -> Values:
    """Value tables; gRPC lists available pairs only, made dense here as REST sends them."""
    return Values(
        tick=m.tick,
        policy_version=m.policy_version,
        v=list(m.v.values) if m.HasField("v") else None,
        q=_dense_values(m.q.pairs, states, actions) if m.HasField("q") else None,
        policy=list(m.policy.actions) if m.HasField("policy") else None,
        r=_dense_values(m.r.pairs, states, actions) if m.HasField("r") else None,
        xi=_dense_vectors(m.xi.pairs, states, actions) if m.HasField("xi") else None,
        curiosity=curiosity_info(m.curiosity) if m.HasField("curiosity") else None,
    )


def history(m: pb.History, actions: Sequence[str]) -> list[HistoryEntry]:
    """History entries, the actions named with ``actions`` as the REST client does."""
    n = len(actions)
    return [
        HistoryEntry(
            tick=e.tick,
            state=e.state,
            action=actions[e.action_index] if e.action_index < n else str(e.action_index),
            action_index=e.action_index,
            drive=list(e.drive),
            reward=e.reward,
            lstdq_error=e.lstdq_error,
            stimulus=list(e.stimulus.values) if e.HasField("stimulus") else None,
            curiosity=tick_curiosity(e.curiosity) if e.HasField("curiosity") else None,
        )
        for e in m.entries
    ]
