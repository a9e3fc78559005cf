"""Conversions between the REST API's JSON and the typed results (one place)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from .types import (
    AgentConfig,
    BasisSummary,
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


def agent_config(d: Json) -> AgentConfig:
    """The effective agent configuration of a session."""
    rate = d["stimulus_rate"]
    return AgentConfig(
        eta=float(d["eta"]),
        gamma=float(d["gamma"]),
        priorities=_floats(d["priorities"]),
        stimulus_rate=rate if isinstance(rate, str) else float(rate),  # type: ignore[arg-type]
        optimistic_sd=float(d["optimistic_sd"]),
        ridge=float(d["ridge"]),
        epsilon=float(d["epsilon"]),
        seed=int(d["seed"]),
        update_mode=d["update_mode"],
        history=int(d["history"]),
        curiosity=curiosity_config(d.get("curiosity")),
    )


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
        ),
        curiosity=curiosity_info(d.get("curiosity")),
        cost=(
            None
            if d.get("cost") is None
            else SessionCost(bytes=int(d["cost"]["bytes"]), tick_us=int(d["cost"]["tick_us"]))
        ),
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
    )


def history(entries: Sequence[Json], actions: Sequence[str]) -> list[HistoryEntry]:
    """History entries; the server sends action indices, named here with ``actions``."""
    out = []
    for e in entries:
        a = int(e["action"])
        stimulus = e.get("stimulus")
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
