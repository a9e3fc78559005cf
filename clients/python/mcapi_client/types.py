"""Typed results and inputs shared by the REST and gRPC clients.

Both transports return these same dataclasses, so a program can switch from
:class:`~mcapi_client.Client` to :class:`~mcapi_client.GrpcClient` without
touching the code that reads the results. Drives are plain ``list[float]``
in the order of the model's ``stimuli``; actions come with their names.

The inputs (:class:`Observation`, :class:`AgentOptions`,
:class:`CuriosityConfig`) take numpy scalars and arrays as well as Python
numbers (:data:`IntLike`, :data:`FloatLike`, :data:`FloatsLike`) and hold
plain ``int``, ``float`` and ``list`` once built; a bool where a number
belongs is a ``TypeError``.
"""

from __future__ import annotations

import copy
import difflib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, SupportsIndex, Union, cast

from ._inputs import (
    CuriosityConfig,
    CuriosityLike,
    StimulusRate,
    UpdateMode,
    as_curiosity,
)
from ._normalise import (
    FloatLike,
    FloatsLike,
    IntLike,
    as_float,
    as_floats,
    as_int,
    as_opt_floats,
    as_opt_int,
)
from ._params import AGENT_KINDS, AGENT_OPTIONS, AgentKwargs
from .continuous import ContinuousModel
from .errors import error_for

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = [
    "IntLike",
    "FloatLike",
    "FloatsLike",
    "UpdateMode",
    "StimulusRate",
    "ActionRef",
    "CuriosityConfig",
    "TickCuriosity",
    "FrozenModule",
    "CuriosityInfo",
    "Step",
    "BasisSummary",
    "ModelSummary",
    "LearnedSummary",
    "ContinuousStats",
    "AgentConfig",
    "AgentKwargs",
    "AGENT_OPTIONS",
    "AgentOptions",
    "SessionStats",
    "SessionInfo",
    "SessionSummary",
    "SessionPage",
    "Values",
    "HistoryEntry",
    "Observation",
    "ObservationLike",
]

ActionRef = Union[str, SupportsIndex]
"""An action by name (``"left"``) or by index into the model's actions (an
``int`` or a numpy integer)."""


def as_action(a: object, name: str = "action_taken") -> str | int:
    """An action reference as a plain ``str`` or ``int``."""
    if isinstance(a, str):
        return str(a)
    return as_int(a, name)


def _finite(name: str, xs: list[float]) -> list[float]:
    """``xs``, checked finite: JSON has no NaN or infinity, so they are
    refused here with the error the server would give."""
    for i, x in enumerate(xs):
        if not math.isfinite(x):
            raise error_for("non_finite_number", f"`{name}[{i}]` is {x}, not a finite number")
    return list(xs)


def check_signal(signal: list[float]) -> list[float]:
    """``signal``, refused when empty: REST would refuse it, while gRPC cannot
    tell an empty signal from none, so both transports refuse it here."""
    if len(signal) == 0:
        raise error_for(
            "invalid_parameter",
            "invalid parameter `signal`: is empty (leave it out when there is no signal sample)",
        )
    return signal


@dataclass(frozen=True, slots=True)
class TickCuriosity:
    """The curiosity channel at one tick (in :class:`Step` and :class:`HistoryEntry`).

    Attributes:
        xi_cur: The intrinsic reward of the tick, the paper's Eq. 7: the
            clipped learning progress of the active module (0 without a
            signal sample, and once every source is explained).
        epsilon: The active module's estimation error after the tick.
        modules: Frozen modules in the library after the tick.
        source: The source of the tick's signal sample, ``None`` without one.
    """

    xi_cur: float
    epsilon: float
    modules: int
    source: int | None


@dataclass(frozen=True, slots=True)
class FrozenModule:
    """One frozen module of a session's curiosity library.

    Attributes:
        source: The signal source it learned.
        frozen_tick: The session's tick when it froze.
        learned_samples: Samples it learned from before freezing.
    """

    source: int
    frozen_tick: int
    learned_samples: int


@dataclass(frozen=True, slots=True)
class CuriosityInfo:
    """The state of a session's curiosity channel (in :class:`SessionInfo` and :class:`Values`).

    Attributes:
        samples: Signal samples received.
        epsilon: The active module's estimation error.
        active_source: The source the active module learns, ``None`` until bound.
        active_samples: Samples the active module learned from.
        all_explained: Every known source is explained by a frozen module;
            the drive's ``curiosity`` component is then held at 0.
        modules: The frozen modules, in freezing order.
    """

    samples: int
    epsilon: float
    active_source: int | None
    active_samples: int
    all_explained: bool
    modules: list[FrozenModule]


@dataclass(frozen=True, slots=True)
class Step:
    """The reply to one observation: the next action and the agent's drive.

    Attributes:
        tick: Ticks of the session so far.
        action: Name of the action the agent advises next.
        action_index: Index of that action in the model's actions.
        drive: The drive D after this tick, one float per stimulus dimension.
        reward: |r| of this tick (the paper's Eq. 3).
        policy_version: Policy updates applied so far.
        curiosity: The curiosity channel at this tick; ``None`` for a
            session without one.
        replayed: ``True`` when the server answered a resent observation
            (same ``seq``) with the reply it recorded when it applied it:
            nothing was applied this time. Not compared: a replayed step
            equals the original one.
    """

    tick: int
    action: str
    action_index: int
    drive: list[float]
    reward: float
    policy_version: int
    curiosity: TickCuriosity | None = None
    replayed: bool = field(default=False, compare=False)


@dataclass(frozen=True, slots=True)
class BasisSummary:
    """The feature basis of a session's value function.

    Attributes:
        kind: ``"indicator"``, ``"proto_value"`` or ``"custom"``.
        k: Features per action block (0 for the indicator basis).
    """

    kind: str
    k: int


@dataclass(frozen=True, slots=True)
class GridLayout:
    """The map of a grid model.

    Attributes:
        rows: Map height in cells.
        cols: Map width in cells.
        cells: ``(row, col)`` of each state, indexed by state.
        marks: The marked cells (stimulus sources) in row-major order, as
            ``(mark, state)``.
    """

    rows: int
    cols: int
    cells: list[tuple[int, int]]
    marks: list[tuple[str, int]]


@dataclass(frozen=True, slots=True)
class ModelSummary:
    """What a session's environment model looks like.

    Attributes:
        states: Number of states (states are ``0..states-1``).
        actions: Action names, in index order.
        stimuli: Stimulus dimension names, in the order of the drive.
        pairs: Available state-action pairs.
        transitions: Stored transitions (non-zero entries of P).
        deterministic: Whether every pair has exactly one successor.
        basis: The basis in use.
        features: Number of features.
        layout: The map of a grid model (grid maps and ``three_room``), for
            drawing values over it; ``None`` for other models.
        learned: How the agent learns the transitions, for a model posted
            with ``"learn": true`` or ``"transitions": "learn"``
            (docs/algorithm.md section 8); ``None`` when they were posted.
        continuous: For a continuous world, the model as the server built
            it (its basis and sample store filled in); ``states``, ``pairs``
            and ``transitions`` are then 0 and ``features`` is k x |A|.
            ``None`` for a model with numbered states.
    """

    states: int
    actions: list[str]
    stimuli: list[str]
    pairs: int
    transitions: int
    deterministic: bool
    basis: BasisSummary
    features: int
    layout: GridLayout | None = None
    learned: LearnedSummary | None = None
    continuous: ContinuousModel | None = None


@dataclass(frozen=True, slots=True)
class LearnedSummary:
    """How a session learns its transition model (docs/algorithm.md section 8).

    Attributes:
        known_after: m: a pair's estimated row is used once it was seen this often.
        optimism: ``"absorbing"`` (R-max) or ``"stimulus"``.
        max_transitions: The most (pair, successor) entries the session stores;
            an observation that would store one more fails with ``limit_exceeded``.
    """

    known_after: int
    optimism: str
    max_transitions: int


@dataclass(frozen=True, slots=True)
class AgentConfig:
    """The effective configuration of a session, every field set (the seed
    included, drawn by the server when not given).

    Attributes:
        eta: MCA rate (Eq. 1).
        gamma: Discount.
        priorities: Priority rho per stimulus dimension.
        stimulus_rate: ``"sample_mean"`` or a constant rate.
        optimistic_sd: Sd of the optimistic initialisation of the stimulus function.
        ridge: Ridge added to A only when singular.
        epsilon: Epsilon-greedy exploration.
        seed: Seed of the session's RNG.
        update_mode: ``"lockstep"`` or ``"async"``.
        history: Recent ticks kept for :meth:`~mcapi_client.Client.history`.
        curiosity: The curiosity channel with every constant filled in;
            ``None`` for a session without one.
    """

    eta: float
    gamma: float
    priorities: list[float]
    stimulus_rate: StimulusRate
    optimistic_sd: float
    ridge: float
    epsilon: float
    seed: int
    update_mode: UpdateMode
    history: int
    curiosity: CuriosityConfig | None = None


def _as_stimulus_rate(x: object, name: str) -> StimulusRate:
    """A ``stimulus_rate``: a rule's name as given (the server, or the gRPC
    encoding, refuses one it does not know), else a number."""
    return cast(StimulusRate, x) if isinstance(x, str) else as_float(x, name)


def _as_given(x: object, name: str) -> object:
    """A value passed on as given (an ``update_mode``: the server, or the gRPC
    encoding, refuses one it does not know)."""
    return x


def _as_curiosity(x: object, name: str) -> CuriosityConfig:
    return as_curiosity(cast(CuriosityLike, x))


_NORMALISERS: dict[str, Callable[[Any, str], object]] = {
    "FloatLike | None": as_float,
    "FloatsLike | None": as_floats,
    "IntLike | None": as_int,
    "StimulusRate | FloatLike | None": _as_stimulus_rate,
    "UpdateMode | None": _as_given,
    "CuriosityLike | None": _as_curiosity,
}
"""The normaliser of each kind of agent option, by the option's annotation in
:class:`~mcapi_client._params.AgentKwargs` (as written there; never given
``None``)."""


def _normaliser(name: str) -> Callable[[Any, str], object]:
    """The normaliser of the agent option ``name``, by its annotation's kind."""
    annotation = AgentKwargs.__annotations__[name]
    # With postponed annotations a TypedDict keeps each as a ForwardRef of its text.
    kind = str(getattr(annotation, "__forward_arg__", annotation))
    try:
        return _NORMALISERS[kind]
    except KeyError:
        raise RuntimeError(
            f"agent option `{name}`: no normaliser for its kind `{kind}` (mcapi_client/_params.py); "
            "add one to mcapi_client.types._NORMALISERS"
        ) from None


_AGENT_NORMALISERS: dict[str, Callable[[Any, str], object]] = {
    name: _normaliser(name) for name in AGENT_OPTIONS
}
"""The normaliser of each agent option, in the server's order."""


def _unknown_options(names: list[str]) -> str:
    """The message of the ``TypeError`` for keyword arguments that are not agent options."""
    parts = []
    for name in names:
        close = difflib.get_close_matches(name, AGENT_OPTIONS, n=1)
        parts.append(f"{name!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    plural = "s" if len(names) > 1 else ""
    return (
        f"unexpected keyword argument{plural} {', '.join(parts)}: "
        f"the agent options are {', '.join(AGENT_OPTIONS)}"
    )


@dataclass(frozen=True, slots=True, init=False)
class AgentOptions:
    """The agent configuration a client asks for; ``None`` takes the server's default.

    Clients build this from the keyword arguments of ``create_session``, the
    options of :class:`~mcapi_client.AgentKwargs` (documented there), given
    by keyword; an unknown keyword is a ``TypeError``. Numbers may be numpy
    scalars, ``priorities`` a numpy array, ``curiosity`` anything
    :data:`CuriosityLike`.

    The fields, one per option in the order of :data:`~mcapi_client.AGENT_OPTIONS`,
    hold plain Python values: ``float``, ``int``, ``list[float]``, a
    :class:`CuriosityConfig`. With a curiosity channel the server appends the
    stimulus dimension ``"curiosity"``, so ``priorities``, if given, have one
    entry more than the model's stimuli.
    """

    eta: float | None
    gamma: float | None
    priorities: list[float] | None
    stimulus_rate: StimulusRate | None
    optimistic_sd: float | None
    ridge: float | None
    epsilon: float | None
    seed: int | None
    update_mode: UpdateMode | None
    history: int | None
    curiosity: CuriosityConfig | None

    def __init__(self, **options: Unpack[AgentKwargs]) -> None:
        given: Mapping[str, object] = options
        unknown = [name for name in given if name not in _AGENT_NORMALISERS]
        if unknown:
            raise TypeError(_unknown_options(unknown))
        for name in AGENT_OPTIONS:
            value = given.get(name)
            normalise = _AGENT_NORMALISERS[name]
            object.__setattr__(self, name, None if value is None else normalise(value, name))

    def to_json(self) -> dict[str, object]:
        """The ``agent`` object of a REST create request (unset fields left out)."""
        out: dict[str, object] = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if value is None:
                continue
            kind = AGENT_KINDS[name]
            if kind == "per_stimulus":
                out[name] = list(value)
            elif kind == "object":
                out[name] = value.to_json()
            else:
                out[name] = value
        return out


@dataclass(frozen=True, slots=True)
class SessionCost:
    """What a session costs the server, as estimated when it was created and
    checked against the server's budgets (README, "Limits and quotas").

    Attributes:
        bytes: Memory the session may hold at most.
        tick_us: Worst-case CPU time of one lockstep observation, in µs.
    """

    bytes: int
    tick_us: int


@dataclass(frozen=True, slots=True)
class ContinuousStats:
    """The counters of a continuous session (:attr:`SessionStats.continuous`).

    Attributes:
        clipped: Observations outside the box, clipped into it.
        samples: Transitions in the sample store now (on a grid: the moves
            kept, each counted once for every (cell, action) it teaches).
        slots: (cell, action) slots visited (on a grid: the pairs whose
            successor is known).
        updates: Rank-one updates of the planner's inverse.
        rebuilds: Rebuilds of the planner's inverse.
        basis_builds: Builds of a ``pvf`` basis (0 for the other bases).
    """

    clipped: int
    samples: int
    slots: int
    updates: int
    rebuilds: int
    basis_builds: int = 0


@dataclass(frozen=True, slots=True)
class SessionStats:
    """Statistics of a session's learner.

    Attributes:
        lstdq_error: |Q_t - Q_{t+1}| of the last policy update.
        lambda1_estimate: Running estimate of the largest eigenvalue lambda_1
            of E[Lambda xi xi^T Lambda] (the paper's condition (1)).
        condition_1_holds: Whether eta * lambda_1 < 0.5 for the estimate.
        constant_stimuli: Stimulus dimensions whose column of Xi is constant.
        factorisation_reuses: Policy updates that reused the factorisation.
        factorisations: Full factorisations of A.
        continuous: A continuous session's sample store and clipping;
            ``None`` for a session with numbered states.
    """

    lstdq_error: float
    lambda1_estimate: float
    condition_1_holds: bool
    constant_stimuli: list[int]
    factorisation_reuses: int
    factorisations: int
    continuous: ContinuousStats | None = None


@dataclass(frozen=True, slots=True)
class SessionInfo:
    """A session: its drive, progress, model, configuration and statistics.

    Attributes:
        id: The session id, ``s<shard>.<ULID>``.
        tick: Ticks so far.
        drive: The drive D, one float per stimulus dimension.
        policy_version: Policy updates applied.
        state: The agent's current state, ``None`` before its first observation.
        model: Summary of the environment model.
        agent: The effective agent configuration.
        stats: Learner statistics.
        curiosity: The curiosity channel's state; ``None`` for a session
            without one.
        cost: The session's estimated memory and per-observation CPU time
            (``None`` from a server that does not report it).
        next_seq: The ``seq`` of the session's next observation: how many
            it has applied (``None`` from a server without sequence numbers).
    """

    id: str
    tick: int
    drive: list[float]
    policy_version: int
    state: int | None
    model: ModelSummary
    agent: AgentConfig
    stats: SessionStats
    curiosity: CuriosityInfo | None = None
    cost: SessionCost | None = None
    next_seq: int | None = None

    def drive_by_stimulus(self) -> dict[str, float]:
        """The drive keyed by stimulus name, e.g. ``{"food": 0.6, "rest": 0.8}``."""
        return dict(zip(self.model.stimuli, self.drive))

    def dominant_stimulus(self) -> str:
        """The name of the stimulus with the largest |D_i|: what the agent seeks now."""
        i = max(range(len(self.drive)), key=lambda j: abs(self.drive[j]))
        return self.model.stimuli[i]


@dataclass(frozen=True, slots=True)
class SessionSummary:
    """One line of a session listing.

    Attributes:
        id: Session id.
        tick: Ticks so far.
        states: Number of states of its model.
        update_mode: ``"lockstep"`` or ``"async"``.
        idle_ms: Milliseconds since its last observation; ``None`` if it had
            none since the server started.
    """

    id: str
    tick: int
    states: int
    update_mode: UpdateMode
    idle_ms: int | None = None


@dataclass(frozen=True, slots=True)
class SessionPage:
    """A page of sessions, ordered by id.

    Attributes:
        sessions: The sessions of this page.
        next: Pass as ``after`` to get the next page; ``None`` on the last page.
    """

    sessions: list[SessionSummary]
    next: str | None


@dataclass(frozen=True, slots=True)
class Values:
    """Value tables of a session; a table not asked for is ``None``.

    Per-pair tables are indexed ``[state][action_index]`` and hold ``None``
    where the action is not available in the state.

    Attributes:
        tick: Ticks so far.
        policy_version: Policy updates applied.
        v: V(s) = Q(s, pi(s)) per state.
        q: Q(s, a).
        policy: Name of the greedy action per state.
        r: R(s, a) = |Xi Lambda D| as of the last update.
        xi: Xi(s, a), the learned stimulus vector per pair.
        curiosity: The curiosity channel's state (always sent, whatever the
            tables asked for); ``None`` for a session without one.
        known_fraction: For a session that learns its transitions, the
            fraction of pairs seen at least m times (always sent); ``None``
            for a session with posted transitions.
        points: For a continuous session, the observations the tables are
            given at: "state" i of ``v``, ``q`` and ``policy`` is
            ``points[i]`` (a grid over the box for d <= 2, else the history's
            observations); ``None`` for a session with numbered states.
    """

    tick: int
    policy_version: int
    v: list[float] | None = None
    q: list[list[float | None]] | None = None
    policy: list[str] | None = None
    r: list[list[float | None]] | None = None
    xi: list[list[list[float] | None]] | None = None
    curiosity: CuriosityInfo | None = None
    known_fraction: float | None = None
    points: list[list[float]] | None = None


@dataclass(frozen=True, slots=True)
class HistoryEntry:
    """One recent tick of a session.

    Attributes:
        tick: The tick.
        state: The state observed at that tick (0 in a continuous world:
            see ``observation``).
        action: Name of the action advised for that state.
        action_index: Index of that action.
        drive: The drive after the tick.
        reward: |r| of the tick.
        lstdq_error: LSTDQ error of the newest policy update at the time.
        stimulus: The full stimulus received at the tick, one float per
            stimulus dimension (with a curiosity channel, xi_cur last);
            ``None`` only for ticks restored from a store written by an
            older server.
        curiosity: The curiosity channel at the tick; ``None`` for a session
            without one.
    """

    tick: int
    state: int
    action: str
    action_index: int
    drive: list[float]
    reward: float
    lstdq_error: float
    stimulus: list[float] | None = None
    curiosity: TickCuriosity | None = None
    known_fraction: float | None = None
    """For a session that learns its transitions: the fraction of pairs seen
    at least m times after this tick (``None`` otherwise)."""
    observation: list[float] | None = None
    """For a continuous session: the observation vector of this tick
    (``None`` for a session with numbered states)."""


@dataclass(frozen=True, slots=True, init=False)
class Observation:
    """One observation, for batches (``observe_batch``) and streams.

    Takes numpy scalars and arrays as well as Python numbers (``state`` a
    ``numpy.int64``, ``stimulus`` a 1-d array, ...) and holds plain
    ``int``, ``float`` and ``list`` values.

    Attributes:
        state: The state the agent is in now (a model with numbered states);
            ``None`` for a continuous world.
        stimulus: The stimulus received on arriving there, one float per
            stimulus dimension; ``None`` on a session's first observation.
        action_taken: The action actually taken to get here, by name or
            index, when it was not the advised one (exploration, an override).
        signal: A raw signal sample x(t) received on arriving there, for a
            session with a curiosity channel (``signal_dim`` floats); the
            ``stimulus`` is then the extrinsic part only and the server
            appends xi_cur. Not on a session's first observation.
        signal_source: The signal's source (e.g. 0 = book, 1 = music);
            the server's default is 0. Only with a ``signal``.
        observation: The observation vector of a continuous world (one float
            per dimension of its space), instead of ``state``.
        seq: The observation's index in the session's stream of applied
            observations (docs/sessions.md, "Delivery guarantees"). Leave it
            ``None``: the clients number observations themselves (see the
            README's "Delivery"); one given here is sent as it is.
    """

    state: int | None
    stimulus: list[float] | None
    action_taken: str | int | None
    signal: list[float] | None
    signal_source: int | None
    observation: list[float] | None
    seq: int | None

    def __init__(
        self,
        state: IntLike | None = None,
        stimulus: FloatsLike | None = None,
        action_taken: ActionRef | None = None,
        signal: FloatsLike | None = None,
        signal_source: IntLike | None = None,
        *,
        observation: FloatsLike | None = None,
        seq: IntLike | None = None,
    ) -> None:
        if (state is None) == (observation is None):
            raise TypeError(
                "give `state` (a model with numbered states) or `observation` "
                "(a continuous world), exactly one"
            )
        index = None if state is None else as_int(state, "state")
        if index is not None and index < 0:
            # The server's answer to a state it does not have, on both
            # transports (over gRPC a negative state cannot even be encoded).
            raise error_for("unknown_state", f"state {index} is negative: states are 0, 1, ...")
        object.__setattr__(self, "state", index)
        object.__setattr__(self, "observation", as_opt_floats(observation, "observation"))
        object.__setattr__(self, "stimulus", as_opt_floats(stimulus, "stimulus"))
        object.__setattr__(
            self, "action_taken", None if action_taken is None else as_action(action_taken)
        )
        object.__setattr__(self, "signal", as_opt_floats(signal, "signal"))
        object.__setattr__(self, "signal_source", as_opt_int(signal_source, "signal_source"))
        n = as_opt_int(seq, "seq")
        if n is not None and not 0 <= n < 1 << 64:
            raise error_for("bad_request", f"`seq` must be an integer from 0 to 2^64 - 1, not {n}")
        object.__setattr__(self, "seq", n)

    def with_seq(self, seq: int | None) -> Observation:
        """This observation with another ``seq``."""
        out = copy.copy(self)
        object.__setattr__(out, "seq", seq)
        return out

    def to_json(self) -> dict[str, object]:
        """The observation as the REST API takes it."""
        out: dict[str, object] = (
            {"state": self.state}
            if self.observation is None
            else {"observation": _finite("observation", self.observation)}
        )
        if self.stimulus is not None:
            out["stimulus"] = _finite("stimulus", self.stimulus)
        if self.action_taken is not None:
            out["action_taken"] = self.action_taken
        if self.signal is not None:
            out["signal"] = _finite("signal", check_signal(self.signal))
        if self.signal_source is not None:
            out["signal_source"] = self.signal_source
        if self.seq is not None:
            out["seq"] = self.seq
        return out


ObservationLike = Union[Observation, Mapping[str, object], tuple[Any, ...]]
"""What batch methods accept per observation: an :class:`Observation`, a
mapping with ``state``/``stimulus``/``action_taken``/``signal``/``signal_source``
(and ``seq``) keys, or a tuple ``(state, stimulus[, action_taken[, signal[, signal_source]]])``."""

_OBSERVATION_KEYS = {
    "state", "stimulus", "action_taken", "signal", "signal_source", "observation", "seq"
}


def as_observation(obs: ObservationLike) -> Observation:
    """Normalises one batch entry to an :class:`Observation`."""
    if isinstance(obs, Observation):
        return obs
    if isinstance(obs, Mapping):
        unknown = set(obs) - _OBSERVATION_KEYS
        if unknown:
            raise TypeError(f"unknown observation keys: {sorted(unknown)}")
        return Observation(
            state=obs.get("state"),  # type: ignore[arg-type]
            observation=obs.get("observation"),  # type: ignore[arg-type]
            stimulus=obs.get("stimulus"),  # type: ignore[arg-type]
            action_taken=obs.get("action_taken"),  # type: ignore[arg-type]
            signal=obs.get("signal"),  # type: ignore[arg-type]
            signal_source=obs.get("signal_source"),  # type: ignore[arg-type]
            seq=obs.get("seq"),  # type: ignore[arg-type]
        )
    if isinstance(obs, tuple) and 1 <= len(obs) <= 5:
        return Observation(*obs)
    raise TypeError(f"not an observation: {obs!r}")

