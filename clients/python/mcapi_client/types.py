"""Typed results and inputs shared by the REST and gRPC clients.

Both transports return these same dataclasses, so a program can switch from
:class:`~mcapi_client.Client` to :class:`~mcapi_client.GrpcClient` without
touching the code that reads the results. Drives are plain ``list[float]``
in the order of the model's ``stimuli``; actions come with their names.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Union

from .errors import error_for

__all__ = [
    "UpdateMode",
    "StimulusRate",
    "ActionRef",
    "Step",
    "BasisSummary",
    "ModelSummary",
    "AgentConfig",
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

UpdateMode = Literal["lockstep", "async"]
"""``"lockstep"``: each reply comes after exactly one policy update (the
paper's Algorithm 1, reproducible for a seed); ``"async"``: the reply comes at
once and the server's tick loop improves the policy behind it."""

StimulusRate = Union[Literal["sample_mean"], float]
"""The learning rate of the stimulus function: the named rule
``"sample_mean"`` (rate 1/n(s, a)) or a constant in (0, 1]."""

ActionRef = Union[str, int]
"""An action by name (``"left"``) or by index into the model's actions."""


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
    """

    tick: int
    action: str
    action_index: int
    drive: list[float]
    reward: float
    policy_version: int


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
    """

    states: int
    actions: list[str]
    stimuli: list[str]
    pairs: int
    transitions: int
    deterministic: bool
    basis: BasisSummary
    features: int


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


@dataclass(frozen=True, slots=True)
class AgentOptions:
    """The agent configuration a client asks for; ``None`` takes the server's default.

    Clients build this from the keyword arguments of ``create_session``.

    Attributes:
        eta: MCA rate, 0 < eta <= 0.5 (default 0.01).
        gamma: Discount in [0, 1) (default 0.95).
        priorities: Priority in (0, 1] per stimulus dimension (default all 1).
        stimulus_rate: ``"sample_mean"`` (default) or a constant in (0, 1].
        optimistic_sd: Sd of the optimistic initialisation (default 0.3).
        ridge: Ridge added to A only when singular (default 1e-6).
        epsilon: Epsilon-greedy exploration in [0, 1] (default 0).
        seed: Seed of the session's RNG (default: drawn by the server).
        update_mode: ``"lockstep"`` (default) or ``"async"``.
        history: Recent ticks kept for the history (default 256).
    """

    eta: float | None = None
    gamma: float | None = None
    priorities: Sequence[float] | None = None
    stimulus_rate: StimulusRate | None = None
    optimistic_sd: float | None = None
    ridge: float | None = None
    epsilon: float | None = None
    seed: int | None = None
    update_mode: UpdateMode | None = None
    history: int | None = None

    def to_json(self) -> dict[str, object]:
        """The ``agent`` object of a REST create request (unset fields left out)."""
        out: dict[str, object] = {}
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if value is None:
                continue
            out[name] = list(value) if name == "priorities" else value
        return out


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
    """

    lstdq_error: float
    lambda1_estimate: float
    condition_1_holds: bool
    constant_stimuli: list[int]
    factorisation_reuses: int
    factorisations: int


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
    """

    id: str
    tick: int
    drive: list[float]
    policy_version: int
    state: int | None
    model: ModelSummary
    agent: AgentConfig
    stats: SessionStats

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
    """

    id: str
    tick: int
    states: int
    update_mode: UpdateMode


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
    """

    tick: int
    policy_version: int
    v: list[float] | None = None
    q: list[list[float | None]] | None = None
    policy: list[str] | None = None
    r: list[list[float | None]] | None = None
    xi: list[list[list[float] | None]] | None = None


@dataclass(frozen=True, slots=True)
class HistoryEntry:
    """One recent tick of a session.

    Attributes:
        tick: The tick.
        state: The state observed at that tick.
        action: Name of the action advised for that state.
        action_index: Index of that action.
        drive: The drive after the tick.
        reward: |r| of the tick.
        lstdq_error: LSTDQ error of the newest policy update at the time.
    """

    tick: int
    state: int
    action: str
    action_index: int
    drive: list[float]
    reward: float
    lstdq_error: float


@dataclass(frozen=True, slots=True)
class Observation:
    """One observation, for batches (``observe_batch``) and streams.

    Attributes:
        state: The state the agent is in now.
        stimulus: The stimulus received on arriving there, one float per
            stimulus dimension; ``None`` on a session's first observation.
        action_taken: The action actually taken to get here, by name or
            index, when it was not the advised one (exploration, an override).
    """

    state: int
    stimulus: Sequence[float] | None = None
    action_taken: ActionRef | None = None

    def to_json(self) -> dict[str, object]:
        """The observation as the REST API takes it."""
        out: dict[str, object] = {"state": self.state}
        if self.stimulus is not None:
            stimulus = [float(x) for x in self.stimulus]
            for i, x in enumerate(stimulus):
                if not math.isfinite(x):
                    # JSON has no NaN or infinity: refused here as the server would.
                    raise error_for(
                        "non_finite_number", f"`stimulus[{i}]` is {x}, not a finite number"
                    )
            out["stimulus"] = stimulus
        if self.action_taken is not None:
            out["action_taken"] = self.action_taken
        return out


ObservationLike = Union[Observation, Mapping[str, object], tuple[Any, ...]]
"""What batch methods accept per observation: an :class:`Observation`, a
mapping with ``state``/``stimulus``/``action_taken`` keys, or a tuple
``(state, stimulus[, action_taken])``."""


def as_observation(obs: ObservationLike) -> Observation:
    """Normalises one batch entry to an :class:`Observation`."""
    if isinstance(obs, Observation):
        return obs
    if isinstance(obs, Mapping):
        unknown = set(obs) - {"state", "stimulus", "action_taken"}
        if unknown:
            raise TypeError(f"unknown observation keys: {sorted(unknown)}")
        return Observation(
            state=int(obs["state"]),  # type: ignore[call-overload]
            stimulus=obs.get("stimulus"),  # type: ignore[arg-type]
            action_taken=obs.get("action_taken"),  # type: ignore[arg-type]
        )
    if isinstance(obs, tuple) and 1 <= len(obs) <= 3:
        return Observation(*obs)
    raise TypeError(f"not an observation: {obs!r}")

