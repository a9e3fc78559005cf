"""The gRPC API without I/O: conversions between the messages and the typed
results (one place), each call as the RPCs it makes (:class:`GrpcProtocol`),
and the error of a failed RPC (:func:`rpc_error`).

:class:`~mcapi_client.GrpcClient` and :class:`~mcapi_client.AsyncGrpcClient`
run the same operations (:mod:`mcapi_client._sansio`), sending each
:class:`Call` over a blocking or a ``grpc.aio`` channel. This module needs
protobuf (the stubs' messages) but not grpcio.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

from google.protobuf.descriptor import EnumDescriptor
from google.protobuf.message import Message

from ._normalise import as_float, as_opt_int
from ._params import AGENT_KINDS, AGENT_OPTIONS
from ._proto.mcapi.v1 import agents_pb2 as pb
from ._sansio import Op, SessionCache
from ._seq import Sequences, numbered
from .continuous import ContinuousModel
from .errors import (
    McapiError,
    SequenceRefused,
    Timeout,
    TransportError,
    WrongReplica,
    error_for,
)
from .models import ModelLike, model_json
from .types import (
    ActionRef,
    AgentConfig,
    AgentOptions,
    BasisSummary,
    ContinuousStats,
    CuriosityConfig,
    CuriosityInfo,
    FrozenModule,
    GridLayout,
    HistoryEntry,
    LearnedSummary,
    ModelSummary,
    Observation,
    ObservationLike,
    SessionCost,
    SessionInfo,
    SessionPage,
    SessionStats,
    SessionSummary,
    Step,
    TickCuriosity,
    UpdateMode,
    Values,
    as_observation,
    check_signal,
)

if TYPE_CHECKING:
    from ._columns import GroupInfo, GroupSeqs, GroupSeqTable

SESSION_METADATA = "x-mcapi-session"
"""Metadata key naming the session a call concerns."""

ERROR_CODE_TRAILER = "x-mcapi-error-code"
"""Trailer carrying the server's stable error code."""

OWNER_TRAILER = "x-mcapi-owner"
"""Trailer naming the replica that owns a misdirected session's shard."""

EXPECTED_SEQ_TRAILER = "x-mcapi-expected-seq"
"""Trailer of a ``seq_gap``: the seq the session expects next."""

OLDEST_SEQ_TRAILER = "x-mcapi-oldest-seq"
"""Trailer of a ``seq_expired``: the oldest seq the session still replays."""

Metadata = tuple[tuple[str, str], ...]

class _NotTyped(Exception):
    """A model JSON that the typed ``Model`` cannot carry as it is."""


def _uint(value: Any) -> int:
    if type(value) is not int or value < 0:
        raise _NotTyped
    return value


def _number(value: Any) -> float:
    if type(value) not in (int, float):
        raise _NotTyped
    return float(value)


def _strings(value: Any) -> list[str]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise _NotTyped
    return value


def _only(obj: dict[str, Any], *keys: str) -> None:
    if not set(obj) <= set(keys):
        raise _NotTyped


def _basis(spec: Any, out: pb.Basis) -> None:
    if not isinstance(spec, dict):
        raise _NotTyped
    kind = spec.get("kind")
    if kind == "indicator":
        _only(spec, "kind")
        out.indicator.SetInParent()
    elif kind == "proto_value":
        _only(spec, "kind", "k")
        out.proto_value.k = _uint(spec.get("k"))
    elif kind == "custom":
        _only(spec, "kind", "state_features")
        rows = spec.get("state_features")
        if not isinstance(rows, list):
            raise _NotTyped
        for row in rows:
            if not isinstance(row, list):
                raise _NotTyped
            out.custom.state_features.add().features.extend(_number(v) for v in row)
        out.custom.SetInParent()
    else:
        raise _NotTyped


_OPTIMISM = {"absorbing": pb.OPTIMISM_ABSORBING, "stimulus": pb.OPTIMISM_STIMULUS}
_OPTIMISM_NAMES = {v: k for k, v in _OPTIMISM.items()}


def _learning(learning: Any, out: pb.LearnedTransitions) -> None:
    """REST ``learning`` (m and the optimism rule) as the typed message."""
    if learning is None:
        return
    if not isinstance(learning, dict):
        raise _NotTyped
    _only(learning, "known_after", "optimism")
    if learning.get("known_after") is not None:
        known_after = _uint(learning["known_after"])
        if known_after >= 1 << 32:
            raise _NotTyped  # the server names the mistake, as REST does
        out.known_after = known_after
    optimism = learning.get("optimism")
    if optimism is not None:
        if optimism not in _OPTIMISM:
            raise _NotTyped
        out.optimism = _OPTIMISM[optimism]


def _full(model: dict[str, Any], out: pb.FullModel) -> None:
    learn = model.get("transitions") == "learn"
    if learn:
        # No table: the agent learns P (docs/algorithm.md section 8).
        _only(model, "states", "state_names", "actions", "transitions", "stimuli", "basis",
              "learning")
    else:
        _only(model, "states", "state_names", "actions", "next", "transitions", "stimuli",
              "basis")
    out.states = _uint(model.get("states"))
    if model.get("state_names") is not None:
        out.state_names.extend(_strings(model["state_names"]))
        if not out.state_names:
            raise _NotTyped  # an explicit empty list: proto3 would send none
    out.actions.extend(_strings(model.get("actions")))
    out.stimuli.extend(_strings(model.get("stimuli")))
    nxt, transitions = model.get("next"), model.get("transitions")
    if learn:
        out.learn.SetInParent()
        _learning(model.get("learning"), out.learn)
    elif (nxt is None) == (transitions is None):
        raise _NotTyped  # both or neither: the server says which, as REST does
    elif nxt is not None:
        if not isinstance(nxt, list):
            raise _NotTyped
        out.next.SetInParent()
        for row in nxt:
            if not isinstance(row, list):
                raise _NotTyped
            out.next.rows.add().next.extend(-1 if s is None else _uint(s) for s in row)
    else:
        if not isinstance(transitions, list):
            raise _NotTyped
        out.stochastic.SetInParent()
        for t in transitions:
            if not isinstance(t, dict) or set(t) != {"state", "action", "next"}:
                raise _NotTyped
            msg = out.stochastic.transitions.add(state=_uint(t["state"]))
            if isinstance(t["action"], str):
                msg.action_name = t["action"]
            else:
                msg.action_index = _uint(t["action"])
            if not isinstance(t["next"], list):
                raise _NotTyped
            for succ in t["next"]:
                if not isinstance(succ, list) or len(succ) != 2:
                    raise _NotTyped
                msg.next.add(state=_uint(succ[0]), probability=_number(succ[1]))
    if model.get("basis") is not None:
        _basis(model["basis"], out.basis)


def _uint32(value: Any) -> int:
    n = _uint(value)
    if n >= 1 << 32:
        raise _NotTyped  # the server names the mistake, as REST does
    return n


_OUT_OF_BOUNDS = {"clip": pb.OUT_OF_BOUNDS_CLIP, "refuse": pb.OUT_OF_BOUNDS_REFUSE}
_OUT_OF_BOUNDS_NAMES = {v: k for k, v in _OUT_OF_BOUNDS.items()}

# The fields of each continuous basis: (required, optional), as REST names them.
_CONTINUOUS_BASES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "fourier": (("order",), ("max_coupling",)),
    "rbf": (("centres_per_dim",), ("width",)),
    "tiles": (("tilings", "tiles_per_dim"), ("table",)),
    "pvf": (("k",), ("nodes", "neighbours")),
    "grid": (("cells_per_dim",), ("neighbours", "reach")),
}


def _continuous_basis(spec: Any, out: pb.ContinuousBasis) -> None:
    """A continuous world's REST ``basis`` (tagged by ``kind``) as the typed oneof."""
    if not isinstance(spec, dict) or spec.get("kind") not in _CONTINUOUS_BASES:
        raise _NotTyped
    kind = spec["kind"]
    required, optional = _CONTINUOUS_BASES[kind]
    _only(spec, "kind", *required, *optional)
    if not all(spec.get(f) is not None for f in required):
        raise _NotTyped  # proto3 would send 0: REST's message names the missing field
    msg = getattr(out, kind)
    msg.SetInParent()
    for field in required + optional:
        value = spec.get(field)
        if value is None:
            continue
        setattr(msg, field, _number(value) if field in ("width", "reach") else _uint32(value))


def _continuous(model: dict[str, Any], out: pb.ContinuousModel) -> None:
    """A continuous world's REST JSON (``observation_space``, ...) as the typed message."""
    _only(model, "observation_space", "actions", "stimuli", "basis", "out_of_bounds", "samples")
    space = model.get("observation_space")
    if not isinstance(space, dict):
        raise _NotTyped
    _only(space, "low", "high")
    low, high = space.get("low"), space.get("high")
    if not isinstance(low, list) or not isinstance(high, list):
        raise _NotTyped
    out.low.extend(_number(x) for x in low)
    out.high.extend(_number(x) for x in high)
    out.actions.extend(_strings(model.get("actions")))
    out.stimuli.extend(_strings(model.get("stimuli")))
    if model.get("basis") is not None:
        _continuous_basis(model["basis"], out.basis)
    oob = model.get("out_of_bounds")
    if oob is not None:
        if oob not in _OUT_OF_BOUNDS:
            raise _NotTyped
        out.out_of_bounds = _OUT_OF_BOUNDS[oob]
    samples = model.get("samples")
    if samples is not None:
        if not isinstance(samples, dict):
            raise _NotTyped
        _only(samples, "cells_per_dim", "per_cell", "max", "known_after")
        out.samples.SetInParent()
        for field, value in samples.items():
            if value is not None:
                setattr(out.samples, field, _uint32(value))


def continuous_model(m: pb.ContinuousModel) -> ContinuousModel:
    """A typed continuous model (a session's ``model.continuous``), as REST has it."""
    d: dict[str, Any] = {
        "observation_space": {"low": list(m.low), "high": list(m.high)},
        "actions": list(m.actions),
        "stimuli": list(m.stimuli),
        "out_of_bounds": _OUT_OF_BOUNDS_NAMES.get(m.out_of_bounds, "clip"),
    }
    if m.HasField("basis"):
        kind = m.basis.WhichOneof("kind")
        if kind is not None:
            msg = getattr(m.basis, kind)
            basis: dict[str, Any] = {"kind": kind}
            required, optional = _CONTINUOUS_BASES.get(kind, ((), ()))
            for field in required:
                basis[field] = getattr(msg, field)
            for field in optional:
                if msg.HasField(field):
                    basis[field] = getattr(msg, field)
            d["basis"] = basis
    if m.HasField("samples"):
        d["samples"] = {
            f: getattr(m.samples, f)
            for f in ("cells_per_dim", "per_cell", "max", "known_after")
            if m.samples.HasField(f)
        }
    return ContinuousModel.from_json(d, check=False)


def model_message(model: dict[str, Any]) -> pb.Model | None:
    """The typed ``Model`` of a model's REST JSON, or ``None`` when the JSON
    does not map onto it as it is (unknown keys, wrong types, an explicit
    empty list): such a model is sent as the deprecated ``model_json``, so the
    server names the mistake exactly as REST does."""
    out = pb.Model()
    try:
        if not isinstance(model, dict):
            raise _NotTyped
        if "preset" in model:
            _only(model, "preset", "basis")
            if not isinstance(model["preset"], str):
                raise _NotTyped
            out.preset.name = model["preset"]
            out.preset.SetInParent()
            if model.get("basis") is not None:
                _basis(model["basis"], out.preset.basis)
        elif "observation_space" in model:
            _continuous(model, out.continuous)
            out.continuous.SetInParent()
        elif "grid" in model:
            _only(model, "grid", "sources", "stimuli", "basis", "learn", "learning")
            learn = model.get("learn", False)
            if not isinstance(learn, bool) or (not learn and "learning" in model):
                raise _NotTyped
            out.grid.learn = learn
            if learn and model.get("learning") is not None:
                _learning(model["learning"], out.grid.learning)
            out.grid.rows.extend(_strings(model["grid"]))
            sources = model.get("sources", {})
            if not isinstance(sources, dict) or not all(isinstance(k, str) for k in sources):
                raise _NotTyped
            for mark, dim in sources.items():
                out.grid.sources[mark] = _uint(dim)
            if model.get("stimuli") is not None:
                out.grid.stimuli.extend(_strings(model["stimuli"]))
                if not out.grid.stimuli:
                    raise _NotTyped
            out.grid.SetInParent()
            if model.get("basis") is not None:
                _basis(model["basis"], out.grid.basis)
        else:
            _full(model, out.full)
            out.full.SetInParent()
    except (_NotTyped, OverflowError, ValueError, TypeError):
        return None
    return out


def curiosity_message(c: CuriosityConfig, out: pb.CuriosityConfig) -> None:
    """A curiosity channel into its message (set even with every default)."""
    out.signal_dim = c.signal_dim
    # The constants travel as the JSON object REST takes; empty: every default.
    if c.params:
        out.params_json = json.dumps(c.params)
    out.SetInParent()


# The agent options, encoded and read as AGENT_KINDS says. The messages follow
# the server's parameter table: an option is the field of its name, except a
# "real_or_name" one, the oneof of its name of the fields `<name>_rule` (an
# enum of the named rules) and `<name>_constant`.


@functools.cache
def _enum_names(enum: EnumDescriptor) -> dict[int, str]:
    """The client's name of each value of a proto enum but the zero one:
    ``UPDATE_MODE_ASYNC`` is ``"async"``, lower-cased without the prefix that
    names the zero value (``UPDATE_MODE_UNSPECIFIED``)."""
    prefix = enum.values_by_number[0].name.removesuffix("UNSPECIFIED")
    return {
        int(v.number): str(v.name).removeprefix(prefix).lower() for v in enum.values if v.number != 0
    }


@functools.cache
def _enum_numbers(enum: EnumDescriptor) -> dict[str, int]:
    """The number of each client's name of a proto enum (see :func:`_enum_names`)."""
    return {name: number for number, name in _enum_names(enum).items()}


def _enum_of(m: Message, field: str) -> EnumDescriptor:
    return m.DESCRIPTOR.fields_by_name[field].enum_type


def _enum_name(m: Message, field: str) -> str:
    """The name of the value of an enum field. One the client cannot name (the
    zero value, never sent by the server, or one newer than these stubs) reads
    as the enum's first named value, which is the server's default
    (``"lockstep"``, ``"sample_mean"``)."""
    names = _enum_names(_enum_of(m, field))
    return names.get(getattr(m, field), next(iter(names.values())))


def _enum_number(m: Message, field: str, option: str, value: object, otherwise: str = "") -> int:
    """The number of the enum value named ``value``.

    Raises:
        ValueError: The enum has no value of that name.
    """
    numbers = _enum_numbers(_enum_of(m, field))
    if value not in numbers:
        choices = " or ".join([repr(name) for name in numbers] + ([otherwise] if otherwise else []))
        raise ValueError(f"unknown {option} {value!r} (use {choices})")
    return numbers[value]


def _read_real_or_name(m: pb.EffectiveConfig, name: str) -> float | str:
    constant = f"{name}_constant"
    if m.WhichOneof(name) == constant:
        return float(getattr(m, constant))
    return _enum_name(m, f"{name}_rule")


def _write_real_or_name(cfg: pb.SessionConfig, name: str, value: float | str) -> None:
    if isinstance(value, str):
        setattr(cfg, f"{name}_rule", _enum_number(cfg, f"{name}_rule", name, value, "a number"))
    else:
        setattr(cfg, f"{name}_constant", value)


def _write_choice(cfg: pb.SessionConfig, name: str, value: object) -> None:
    setattr(cfg, name, _enum_number(cfg, name, name, value))


@dataclass(frozen=True, slots=True)
class _Field:
    """How an agent option is read from ``EffectiveConfig`` and written into
    ``SessionConfig``; each takes the message and the option's name."""

    read: Callable[[pb.EffectiveConfig, str], object]
    write: Callable[[pb.SessionConfig, str, Any], None]


def _set(cfg: pb.SessionConfig, name: str, value: float) -> None:
    setattr(cfg, name, value)


def _extend(cfg: pb.SessionConfig, name: str, value: list[float]) -> None:
    getattr(cfg, name).extend(value)


_PLAIN_NUMBERS = ("real", "integer")

_KIND_FIELDS: dict[str, _Field] = {
    "real": _Field(lambda m, name: float(getattr(m, name)), _set),
    "integer": _Field(lambda m, name: int(getattr(m, name)), _set),
    "per_stimulus": _Field(lambda m, name: [float(x) for x in getattr(m, name)], _extend),
    "real_or_name": _Field(_read_real_or_name, _write_real_or_name),
    "choice": _Field(_enum_name, _write_choice),
}
"""The encoding of each kind of agent option (AGENT_KINDS) but "object"."""

_OBJECT_FIELDS: dict[str, _Field] = {
    "curiosity": _Field(
        lambda m, name: curiosity_config(m.curiosity) if m.HasField(name) else None,
        lambda cfg, name, value: curiosity_message(value, cfg.curiosity),
    ),
}
"""The encoding of each agent option of the kind "object", by name (unset: ``None``)."""


def _agent_field(name: str) -> _Field:
    """The encoding of the agent option ``name``, by its kind."""
    kind = AGENT_KINDS[name]
    if kind == "object" and name in _OBJECT_FIELDS:
        return _OBJECT_FIELDS[name]
    if kind != "object" and kind in _KIND_FIELDS:
        return _KIND_FIELDS[kind]
    raise RuntimeError(
        f"agent option `{name}` of kind `{kind}` (mcapi_client/_params.py): no gRPC encoding; "
        "add one to mcapi_client._pb._KIND_FIELDS or _OBJECT_FIELDS"
    )


_AGENT_FIELDS: dict[str, _Field] = {name: _agent_field(name) for name in AGENT_OPTIONS}
"""The encoding of each agent option, in the server's order."""


def agent_config(m: pb.EffectiveConfig) -> AgentConfig:
    """A session's effective agent configuration, every option read as its kind says."""
    fields: dict[str, Any] = {name: f.read(m, name) for name, f in _AGENT_FIELDS.items()}
    return AgentConfig(**fields)


def create_request(model: dict[str, Any], agent: AgentOptions) -> pb.CreateSessionRequest:
    """``CreateSession``: the model as the typed ``Model`` (see
    :func:`model_message`), else as the JSON the REST API takes."""
    cfg = pb.SessionConfig()
    # Plain numbers first (protobuf refuses one out of its field's range), then
    # the rest, each encoded as its kind says (see _AGENT_FIELDS).
    for name in sorted(AGENT_OPTIONS, key=lambda n: AGENT_KINDS[n] not in _PLAIN_NUMBERS):
        value = getattr(agent, name)
        if value is not None:
            _AGENT_FIELDS[name].write(cfg, name, value)
    typed = model_message(model)
    if typed is not None:
        return pb.CreateSessionRequest(model=typed, agent=cfg)
    # Deprecated on the server; kept for models the typed form cannot carry.
    return pb.CreateSessionRequest(model_json=json.dumps(model), agent=cfg)


def _unsigned(value: int, field: str, bits: int) -> int:
    """``value`` if the message's unsigned field can hold it; otherwise the
    ``bad_request`` the REST server answers for a negative or too large
    index, instead of protobuf's own ``ValueError``."""
    if not 0 <= value < 1 << bits:
        raise error_for(
            "bad_request",
            f"malformed observation: `{field}` must be an integer from 0 to 2^{bits} - 1, not {value}",
        )
    return value


def observation_message(obs: Observation, session_id: str = "") -> pb.Observation:
    """One observation message (``session_id`` empty: the metadata names it).

    Non-finite stimulus values are sent as they are: the server answers them
    (``non_finite_number``). A negative or too large state, action index or
    signal source is refused here as ``bad_request``, as over REST.
    """
    if obs.observation is not None:
        # A continuous world: the vector, and `state` left 0.
        msg = pb.Observation(session_id=session_id, observation=obs.observation)
    else:
        msg = pb.Observation(session_id=session_id, state=_unsigned(obs.state or 0, "state", 64))
    if obs.stimulus is not None:
        msg.stimulus.values.extend(obs.stimulus)
        msg.stimulus.SetInParent()  # an empty stimulus is still sent as given
    if isinstance(obs.action_taken, str):
        msg.action_name = obs.action_taken
    elif obs.action_taken is not None:
        msg.action_index = _unsigned(obs.action_taken, "action_taken", 32)
    if obs.signal is not None:
        msg.signal.extend(check_signal(obs.signal))
    if obs.signal_source is not None:
        msg.signal_source = _unsigned(obs.signal_source, "signal_source", 32)
    if obs.seq is not None:
        msg.seq = obs.seq
    return msg


def observation(
    state: Any,
    stimulus: Any,
    action_taken: ActionRef | None,
    session_id: str = "",
    signal: Any = None,
    signal_source: Any = None,
) -> pb.Observation:
    """One observation message from its parts (see :class:`~mcapi_client.Observation`)."""
    return observation_message(
        Observation(state, stimulus, action_taken, signal, signal_source), session_id
    )


def observations(obs: Iterable[ObservationLike]) -> list[pb.Observation]:
    """Batch entries as messages."""
    return [observation_message(as_observation(o)) for o in obs]


def observation_batch(entries: Iterable[tuple[str, ObservationLike]]) -> pb.ObservationBatch:
    """One ``InteractBatch`` message: ``(session_id, observation)`` pairs."""
    return pb.ObservationBatch(
        observations=[observation_message(as_observation(o), str(sid)) for sid, o in entries]
    )


def step_results(m: pb.StepBatch) -> list[Step | McapiError]:
    """An ``InteractBatch`` reply: a step, or the error of a refused observation."""
    out: list[Step | McapiError] = []
    for r in m.results:
        if r.HasField("step"):
            out.append(step(r.step))
            continue
        e = r.error
        name = _GRPC_CODE_NAMES.get(e.status, "UNKNOWN")
        err = error_for(e.code or None, e.message, grpc_code=name)
        if isinstance(err, WrongReplica):
            err.owner = e.owner or None
        out.append(err)
    return out


# gRPC status names by number (the `status` of a StepError).
_GRPC_CODE_NAMES = {
    0: "OK",
    1: "CANCELLED",
    2: "UNKNOWN",
    3: "INVALID_ARGUMENT",
    4: "DEADLINE_EXCEEDED",
    5: "NOT_FOUND",
    6: "ALREADY_EXISTS",
    7: "PERMISSION_DENIED",
    8: "RESOURCE_EXHAUSTED",
    9: "FAILED_PRECONDITION",
    10: "ABORTED",
    11: "OUT_OF_RANGE",
    12: "UNIMPLEMENTED",
    13: "INTERNAL",
    14: "UNAVAILABLE",
    15: "DATA_LOSS",
    16: "UNAUTHENTICATED",
}


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
        replayed=m.replayed,
    )


def session_info(m: pb.SessionInfo) -> SessionInfo:
    """A session's details."""
    model, stats = m.model, m.stats
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
            learned=(
                LearnedSummary(
                    known_after=model.learned.known_after,
                    optimism=_OPTIMISM_NAMES.get(model.learned.optimism, "absorbing"),
                    max_transitions=model.learned.max_transitions,
                )
                if model.HasField("learned")
                else None
            ),
            continuous=continuous_model(model.continuous) if model.HasField("continuous") else None,
        ),
        agent=agent_config(m.agent),
        stats=SessionStats(
            lstdq_error=stats.lstdq_error,
            lambda1_estimate=stats.lambda1_estimate,
            condition_1_holds=stats.condition_1_holds,
            constant_stimuli=list(stats.constant_stimuli),
            factorisation_reuses=stats.factorisation_reuses,
            factorisations=stats.factorisations,
            continuous=(
                ContinuousStats(
                    clipped=stats.continuous.clipped,
                    samples=stats.continuous.samples,
                    slots=stats.continuous.slots,
                    updates=stats.continuous.updates,
                    rebuilds=stats.continuous.rebuilds,
                    basis_builds=stats.continuous.basis_builds,
                )
                if stats.HasField("continuous")
                else None
            ),
        ),
        curiosity=curiosity_info(m.curiosity) if m.HasField("curiosity") else None,
        cost=(
            SessionCost(bytes=m.cost.bytes, tick_us=m.cost.tick_us)
            if m.HasField("cost")
            else None
        ),
        next_seq=m.next_seq,
    )


def session_page(m: pb.ListSessionsResponse) -> SessionPage:
    """A page of the session listing."""
    return SessionPage(
        sessions=[
            SessionSummary(
                id=s.id,
                tick=s.tick,
                states=s.states,
                update_mode=cast(UpdateMode, _enum_name(s, "update_mode")),
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
    """Value tables; gRPC lists available pairs only, made dense here as REST
    sends them (a continuous session's tables have a row per point)."""
    points = [list(p.x) for p in m.points] or None
    if points is not None:
        states = len(points)
    return Values(
        tick=m.tick,
        policy_version=m.policy_version,
        v=list(m.v.values) if m.HasField("v") else None,
        q=_dense_values(m.q.pairs, states, actions) if m.HasField("q") else None,
        policy=list(m.policy.actions) if m.HasField("policy") else None,
        r=_dense_values(m.r.pairs, states, actions) if m.HasField("r") else None,
        xi=_dense_vectors(m.xi.pairs, states, actions) if m.HasField("xi") else None,
        curiosity=curiosity_info(m.curiosity) if m.HasField("curiosity") else None,
        known_fraction=m.known_fraction if m.HasField("known_fraction") else None,
        points=points,
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
            known_fraction=e.known_fraction if e.HasField("known_fraction") else None,
            observation=list(e.observation) or None,
        )
        for e in m.entries
    ]


def include_tables(include: str | Iterable[str] | None) -> list[str]:
    """The ``include`` tables as a list: ``["v", "q"]`` from ``"v,q"`` or ``["v", "q"]``."""
    parts = [include] if isinstance(include, str) else list(include or [])
    return [t.strip() for part in parts for t in part.split(",") if t.strip()]


def watch_request(session_id: str, interval: object) -> pb.WatchRequest:
    """``Watch`` every ``interval`` seconds.

    Raises:
        ValueError: The interval is not between 0.01 and 3600 s.
    """
    seconds = as_float(interval, "interval")
    interval_ms = round(seconds * 1000) if math.isfinite(seconds) else 0
    if not 10 <= interval_ms <= 3_600_000:
        raise ValueError(f"interval {seconds} s is not between 0.01 and 3600")
    return pb.WatchRequest(session_id=session_id, interval_ms=interval_ms)


def rpc_error(e: BaseException) -> McapiError:
    """The :class:`McapiError` for a failed RPC or stream: a ``grpc.RpcError``
    of a blocking call or a ``grpc.aio.AioRpcError``, read by duck typing
    (``code()``, ``details()``, ``trailing_metadata()``)."""
    code = _call(e, "code")
    name = getattr(code, "name", None) or "UNKNOWN"
    message = _call(e, "details") or str(e)
    stable = None
    owner = None
    seqs: dict[str, int] = {}
    for key, value in _call(e, "trailing_metadata") or ():
        if key == ERROR_CODE_TRAILER:
            stable = value if isinstance(value, str) else value.decode()
        elif key == OWNER_TRAILER:
            owner = value if isinstance(value, str) else value.decode()
        elif key in (EXPECTED_SEQ_TRAILER, OLDEST_SEQ_TRAILER):
            text = value if isinstance(value, str) else value.decode()
            if text.isdigit():
                seqs[key] = int(text)
    if stable is None:
        # No answer from mcapi itself: the network or the client gave up.
        if name == "UNAVAILABLE":
            return TransportError(message, code="transport_error", grpc_code=name)
        if name == "DEADLINE_EXCEEDED":
            return Timeout(message, code="timeout", grpc_code=name)
        if name == "CANCELLED":
            return McapiError(message, code="cancelled", grpc_code=name)
    err = error_for(stable, message, grpc_code=name)
    if isinstance(err, WrongReplica):
        err.owner = owner
    if isinstance(err, SequenceRefused):
        err.expected_seq = seqs.get(EXPECTED_SEQ_TRAILER)
        err.oldest_seq = seqs.get(OLDEST_SEQ_TRAILER)
    return err


def from_server(e: BaseException) -> bool:
    """Whether a failed RPC's error came from mcapi (its trailer names the code)."""
    return any(key == ERROR_CODE_TRAILER for key, _ in _call(e, "trailing_metadata") or ())


def _call(e: BaseException, method: str) -> Any:
    fn = getattr(e, method, None)
    return fn() if callable(fn) else None


def watch_ends(err: McapiError, seen: int, cancelled: bool) -> bool:
    """Whether an error ends a ``Watch`` iteration quietly: the watch was
    cancelled, or its session deleted after at least one snapshot."""
    return cancelled or err.code == "cancelled" or (seen > 0 and err.code == "not_found")


def _set_seq(msg: pb.Observation, seq: int) -> None:
    msg.seq = seq


@dataclass(frozen=True, slots=True)
class Call:
    """One unary RPC to make.

    Attributes:
        rpc: The method of ``mcapi.v1.Agents`` (``"GetSession"``).
        request: The request message.
        session_id: The session it concerns, sent as ``x-mcapi-session``
            metadata; ``None`` for calls of no one session.
        resend: Safe to send again after a lost answer (numbered
            observations): retried on :data:`~mcapi_client.retry.RESEND_CODES` too.
    """

    rpc: str
    request: Any
    session_id: str | None = None
    resend: bool = False


class GrpcProtocol:
    """The gRPC calls as operations, the metadata they carry, and the shape
    (states, action names) per session that the value tables and history
    entries need."""

    def __init__(self, api_key: str | None, exactly_once: bool = False) -> None:
        self._auth: Metadata = (
            (("authorization", f"Bearer {api_key}"),) if api_key is not None else ()
        )
        self._shapes: SessionCache[tuple[int, list[str]]] = SessionCache()
        self.seqs: Sequences | None = Sequences() if exactly_once else None
        # Made on first use (it needs numpy, the `vector` extra).
        self._group_seqs: GroupSeqTable | None = None

    def group_seqs(self, info: GroupInfo, created: bool = False) -> GroupSeqs | None:
        """With ``exactly_once``, the counts of a group's members (every
        count 0 for a group just ``created``, else kept or learned): they
        outlive a ``StepGroup`` stream, so the next one resends what a
        broken one left unanswered with the same seqs."""
        if self.seqs is None:
            return None
        if self._group_seqs is None:
            from ._columns import GroupSeqTable

            self._group_seqs = GroupSeqTable()
        return self._group_seqs.created(info) if created else self._group_seqs.of(info)

    def forget_group(self, group_id: str) -> None:
        """A group deleted: its counts go."""
        if self._group_seqs is not None:
            self._group_seqs.drop(group_id)

    def metadata(self, session_id: str | None = None) -> Metadata:
        """The metadata of a call: the session (routers read it), the API key."""
        if session_id is None:
            return self._auth
        return ((SESSION_METADATA, session_id), *self._auth)

    def _remember(self, info: SessionInfo, created: bool = False) -> SessionInfo:
        self._shapes.put(info.id, (info.model.states, info.model.actions))
        if self.seqs is not None:
            self.seqs.learn(info.id, info.next_seq, force=created)
        return info

    def create_session(self, model: ModelLike, agent: AgentOptions) -> Op[Call, SessionInfo]:
        """``CreateSession``: the model travels typed (:func:`create_request`)."""
        reply = yield Call("CreateSession", create_request(model_json(model), agent))
        return self._remember(session_info(reply), created=True)

    def get_session(self, session_id: str) -> Op[Call, SessionInfo]:
        """``GetSession``."""
        reply = yield Call("GetSession", pb.GetSessionRequest(session_id=session_id), session_id)
        return self._remember(session_info(reply))

    def list_sessions(self, after: str | None, limit: object) -> Op[Call, SessionPage]:
        """``ListSessions``."""
        request = pb.ListSessionsRequest(after=after, limit=as_opt_int(limit, "limit"))
        return session_page((yield Call("ListSessions", request)))

    def delete_session(self, session_id: str) -> Op[Call, None]:
        """``DeleteSession``."""
        yield Call("DeleteSession", pb.DeleteSessionRequest(session_id=session_id), session_id)
        self._shapes.drop(session_id)
        if self.seqs is not None:
            self.seqs.forget(session_id)

    def observe(self, session_id: str, obs: Observation) -> Op[Call, Step]:
        """``Observe`` with one observation, numbered (see
        :func:`mcapi_client._seq.numbered`)."""
        return step((yield from self._observe(session_id, [obs])).steps[0])

    def observe_batch(
        self, session_id: str, obs: Iterable[ObservationLike]
    ) -> Op[Call, list[Step]]:
        """``Observe`` with a batch, numbered consecutively (unless its
        observations carry their own seqs)."""
        reply = yield from self._observe(session_id, [as_observation(o) for o in obs])
        return [step(s) for s in reply.steps]

    def _observe(self, session_id: str, obs: list[Observation]) -> Op[Call, Any]:
        request = pb.ObserveRequest(
            session_id=session_id, observations=[observation_message(o) for o in obs]
        )
        return (
            yield from numbered(
                self.seqs,
                session_id,
                request.observations,
                next((o.seq for o in obs if o.seq is not None), None),
                _set_seq,
                lambda resend: Call("Observe", request, session_id, resend),
                lambda: self.get_session(session_id),
            )
        )

    def values(self, session_id: str, include: str | Iterable[str] | None) -> Op[Call, Values]:
        """``GetValues``, then the session when its shape is not known yet."""
        request = pb.GetValuesRequest(session_id=session_id, include=include_tables(include))
        reply = yield Call("GetValues", request, session_id)
        states, actions = yield from self._shape(session_id)
        return values(reply, states, len(actions))

    def history(self, session_id: str, limit: object) -> Op[Call, list[HistoryEntry]]:
        """``GetHistory``, then the session when its action names are not known yet."""
        request = pb.GetHistoryRequest(session_id=session_id, limit=as_opt_int(limit, "limit"))
        reply = yield Call("GetHistory", request, session_id)
        _, actions = yield from self._shape(session_id)
        return history(reply, actions)

    def _shape(self, session_id: str) -> Op[Call, tuple[int, list[str]]]:
        shape = self._shapes.get(session_id)
        if shape is None:
            info = yield from self.get_session(session_id)
            shape = (info.model.states, info.model.actions)
        return shape
