"""Conversions between the REST API's JSON and the typed results (one place)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from ._params import AGENT_KINDS, AGENT_OPTIONS
from .continuous import ContinuousModel
from .types import (
    AgentConfig,
    BasisSummary,
    ContinuousStats,
    CuriosityConfig,
    CuriosityInfo,
    FrozenModule,
    GridLayout,
    HistoryEntry,
    LearnedSummary,
    ModelSummary,
    SessionCost,
    SessionInfo,
    SessionPage,
    SessionStats,
    SessionSummary,
    Step,
    TickCuriosity,
    Values,
)

Json = dict[str, Any]


def _floats(xs: Iterable[Any]) -> list[float]:
    return [float(x) for x in xs]


def _opt_int(x: Any) -> int | None:
    return None if x is None else int(x)


def tick_curiosity(d: Json | None) -> TickCuriosity | None:
    """The curiosity channel at one tick (absent without a channel)."""
    if d is None:
        return None
    return TickCuriosity(
        xi_cur=float(d["xi_cur"]),
        epsilon=float(d["epsilon"]),
        modules=int(d["modules"]),
        source=_opt_int(d.get("source")),
    )


def curiosity_info(d: Json | None) -> CuriosityInfo | None:
    """The state of a session's curiosity channel (absent without a channel)."""
    if d is None:
        return None
    return CuriosityInfo(
        samples=int(d["samples"]),
        epsilon=float(d["epsilon"]),
        active_source=_opt_int(d.get("active_source")),
        active_samples=int(d["active_samples"]),
        all_explained=bool(d["all_explained"]),
        modules=[
            FrozenModule(
                source=int(m["source"]),
                frozen_tick=int(m["frozen_tick"]),
                learned_samples=int(m["learned_samples"]),
            )
            for m in d["modules"]
        ],
    )


def curiosity_config(d: Json | None) -> CuriosityConfig | None:
    """A session's effective curiosity channel (absent without a channel)."""
    if d is None:
        return None
    return CuriosityConfig(signal_dim=int(d["signal_dim"]), params=dict(d.get("params") or {}))


def step(d: Json) -> Step:
    """A step from an observation reply."""
    return Step(
        tick=int(d["tick"]),
        action=str(d["action"]),
        action_index=int(d["action_index"]),
        drive=_floats(d["drive"]),
        reward=float(d["reward"]),
        policy_version=int(d["policy_version"]),
        curiosity=tick_curiosity(d.get("curiosity")),
        replayed=d.get("replayed") is True,
    )


def model_summary(d: Json) -> ModelSummary:
    """The model summary of a session."""
    b = d["basis"]
    return ModelSummary(
        states=int(d["states"]),
        actions=[str(a) for a in d["actions"]],
        stimuli=[str(s) for s in d["stimuli"]],
        pairs=int(d["pairs"]),
        transitions=int(d["transitions"]),
        deterministic=bool(d["deterministic"]),
        basis=BasisSummary(kind=str(b["kind"]), k=int(b["k"])),
        features=int(d["features"]),
        layout=None if d.get("layout") is None else grid_layout(d["layout"]),
        learned=None if d.get("learned") is None else learned_summary(d["learned"]),
        continuous=(
            None
            if d.get("continuous") is None
            else ContinuousModel.from_json(d["continuous"], check=False)
        ),
    )


def continuous_stats(d: Json | None) -> ContinuousStats | None:
    """A continuous session's counters (absent for numbered states)."""
    if d is None:
        return None
    return ContinuousStats(
        clipped=int(d["clipped"]),
        samples=int(d["samples"]),
        slots=int(d["slots"]),
        updates=int(d["updates"]),
        rebuilds=int(d["rebuilds"]),
        basis_builds=int(d.get("basis_builds", 0)),
    )


def learned_summary(d: Json) -> LearnedSummary:
    """How a session learns its transitions."""
    return LearnedSummary(
        known_after=int(d["known_after"]),
        optimism=str(d["optimism"]),
        max_transitions=int(d["max_transitions"]),
    )


def grid_layout(d: Json) -> GridLayout:
    """The map of a grid model."""
    return GridLayout(
        rows=int(d["rows"]),
        cols=int(d["cols"]),
        cells=[(int(r), int(c)) for r, c in d["cells"]],
        marks=[(str(m["mark"]), int(m["state"])) for m in d["marks"]],
    )


def _real_or_name(x: Any) -> float | str:
    return x if isinstance(x, str) else float(x)


def _as_sent(x: Any) -> object:
    return x


_KIND_READERS: dict[str, Callable[[Any], object]] = {
    "real": float,
    "integer": int,
    "per_stimulus": _floats,
    "real_or_name": _real_or_name,  # a rule's name, or a number
    "choice": _as_sent,  # the name, as sent
}
"""The reader of each kind of agent option (AGENT_KINDS) but "object"."""

_OBJECT_READERS: dict[str, Callable[[Any], object]] = {"curiosity": curiosity_config}
"""The reader of each agent option of the kind "object", by name (given ``None`` when absent)."""


def _option_reader(name: str) -> Callable[[Json], object]:
    """The reader of the agent option ``name`` from the ``agent`` object, by its kind."""
    kind = AGENT_KINDS[name]
    if kind == "object" and name in _OBJECT_READERS:
        read_object = _OBJECT_READERS[name]
        return lambda d: read_object(d.get(name))  # absent: the session has none
    if kind != "object" and kind in _KIND_READERS:
        read = _KIND_READERS[kind]
        return lambda d: read(d[name])
    raise RuntimeError(
        f"agent option `{name}` of kind `{kind}` (mcapi_client/_params.py): no JSON reader; "
        "add one to mcapi_client._json._KIND_READERS or _OBJECT_READERS"
    )


_AGENT_READERS: dict[str, Callable[[Json], object]] = {
    name: _option_reader(name) for name in AGENT_OPTIONS
}
"""The reader of each agent option, in the server's order."""


def agent_config(d: Json) -> AgentConfig:
    """The effective agent configuration of a session, every option read as its kind says."""
    fields: dict[str, Any] = {name: read(d) for name, read in _AGENT_READERS.items()}
    return AgentConfig(**fields)


def session_info(d: Json) -> SessionInfo:
    """A session's details."""
    s = d["stats"]
    return SessionInfo(
        id=str(d["id"]),
        tick=int(d["tick"]),
        drive=_floats(d["drive"]),
        policy_version=int(d["policy_version"]),
        state=None if d.get("state") is None else int(d["state"]),
        model=model_summary(d["model"]),
        agent=agent_config(d["agent"]),
        stats=SessionStats(
            lstdq_error=float(s["lstdq_error"]),
            lambda1_estimate=float(s["lambda1_estimate"]),
            condition_1_holds=bool(s["condition_1_holds"]),
            constant_stimuli=[int(i) for i in s["constant_stimuli"]],
            factorisation_reuses=int(s["factorisation_reuses"]),
            factorisations=int(s["factorisations"]),
            continuous=continuous_stats(s.get("continuous")),
        ),
        curiosity=curiosity_info(d.get("curiosity")),
        cost=(
            None
            if d.get("cost") is None
            else SessionCost(bytes=int(d["cost"]["bytes"]), tick_us=int(d["cost"]["tick_us"]))
        ),
        next_seq=None if d.get("next_seq") is None else int(d["next_seq"]),
    )


def session_page(d: Json) -> SessionPage:
    """A page of the session listing."""
    return SessionPage(
        sessions=[
            SessionSummary(
                id=str(s["id"]),
                tick=int(s["tick"]),
                states=int(s["states"]),
                update_mode=s["update_mode"],
                idle_ms=None if s.get("idle_ms") is None else int(s["idle_ms"]),
            )
            for s in d["sessions"]
        ],
        next=d.get("next"),
    )


def _pair_table(rows: Sequence[Sequence[Any]] | None) -> list[list[float | None]] | None:
    if rows is None:
        return None
    return [[None if x is None else float(x) for x in row] for row in rows]


def values(d: Json) -> Values:
    """Value tables (REST sends per-pair tables dense, ``null`` where unavailable)."""
    xi = d.get("xi")
    v = d.get("v")
    policy = d.get("policy")
    points = d.get("points")
    return Values(
        tick=int(d["tick"]),
        policy_version=int(d["policy_version"]),
        v=None if v is None else _floats(v),
        q=_pair_table(d.get("q")),
        policy=None if policy is None else [str(a) for a in policy],
        r=_pair_table(d.get("r")),
        xi=None
        if xi is None
        else [[None if x is None else _floats(x) for x in row] for row in xi],
        curiosity=curiosity_info(d.get("curiosity")),
        known_fraction=None if d.get("known_fraction") is None else float(d["known_fraction"]),
        points=None if points is None else [_floats(p) for p in points],
    )


def history(entries: Sequence[Json], actions: Sequence[str]) -> list[HistoryEntry]:
    """History entries; the server sends action indices, named here with ``actions``."""
    out = []
    for e in entries:
        a = int(e["action"])
        stimulus = e.get("stimulus")
        observation = e.get("observation")
        out.append(
            HistoryEntry(
                tick=int(e["tick"]),
                state=int(e["state"]),
                action=actions[a] if 0 <= a < len(actions) else str(a),
                action_index=a,
                drive=_floats(e["drive"]),
                reward=float(e["reward"]),
                lstdq_error=float(e["lstdq_error"]),
                stimulus=None if stimulus is None else _floats(stimulus),
                curiosity=tick_curiosity(e.get("curiosity")),
                known_fraction=None
                if e.get("known_fraction") is None
                else float(e["known_fraction"]),
                observation=None if observation is None else _floats(observation),
            )
        )
    return out


def include_param(include: str | Iterable[str] | None) -> str | None:
    """The ``include`` query value: ``"v,q"`` from ``["v", "q"]`` or ``"v,q"``."""
    if include is None:
        return None
    if isinstance(include, str):
        return include
    return ",".join(include)


def error_fields(body: Any) -> tuple[str | None, str | None]:
    """``(code, message)`` of an error body, when it is the server's JSON shape."""
    if isinstance(body, Mapping):
        code, message = body.get("code"), body.get("message")
        return (
            code if isinstance(code, str) else None,
            message if isinstance(message, str) else None,
        )
    return None, None
