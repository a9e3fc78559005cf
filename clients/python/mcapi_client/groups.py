"""Session groups: N agents of one model stepped by columns (numpy arrays in,
numpy arrays out), for vectorised simulators. Needs the ``vector`` extra
(numpy), and the transport's: ``grpc`` for :class:`VectorAgents` and
:class:`AsyncVectorAgents`, nothing more for the REST ones.

    from mcapi_client import GrpcClient, models

    with GrpcClient("127.0.0.1:50051") as mc:
        with mc.create_group(models.hallway(), n=1000, seed=7) as agents:
            step = agents.step(states)                   # first: states only
            for _ in range(100):
                states = ...                             # apply step.actions
                step = agents.step(states, stimuli)      # stimuli: (N, n)

Four objects step a group, all with the same :meth:`~VectorAgents.step` and
the same :class:`GroupStep` of numpy arrays:

- :class:`VectorAgents` (``GrpcClient.create_group``) and
  :class:`AsyncVectorAgents` (``AsyncGrpcClient.create_group``): the
  ``StepGroup`` stream, with :meth:`~VectorAgents.send` and
  :meth:`~VectorAgents.recv` to keep several steps in flight (the server
  reads up to 8 ahead and answers in order);
- :class:`RestVectorAgents` (``Client.create_group``) and
  :class:`AsyncRestVectorAgents` (``AsyncClient.create_group``): one
  ``POST /v1/groups/{id}/steps`` per step.

Every column is checked against the group before it is sent (its length,
its width, integers in range, the mask strictly increasing and below N): a
mistake is a ``ValueError`` naming the column, and nothing is sent. What
depends on the model or on a member (a state beyond the model's, an unknown
action) is the server's to refuse. The layout on the wire is the server's
``docs/groups.md``.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

try:
    import numpy as np
except ImportError as e:  # pragma: no cover - depends on the installed extras
    raise ImportError(
        "session groups (mcapi_client.groups) need numpy: install the `vector` extra, "
        "pip install './clients/python[vector]' (from the mcapi repository)",
        name=e.name,
    ) from e

from .errors import error_for

if TYPE_CHECKING:
    import numpy.typing as npt

    from ._group_grpc import AsyncVectorAgents, VectorAgents

__all__ = [
    "ADVISED",
    "GroupInfo",
    "GroupStep",
    "MemberStatus",
    "Columns",
    "GroupAgents",
    "VectorAgents",
    "AsyncVectorAgents",
    "RestVectorAgents",
    "AsyncRestVectorAgents",
    "member_seed",
    "check_columns",
]

ADVISED = 0xFFFF_FFFF
"""``action_taken`` entry for a member that took its advised action; also the
``actions`` entry of a member whose observation was refused."""

F64 = np.dtype("<f8")
"""The dtype of every real-number column (little-endian binary64)."""

# The gRPC stream objects need grpcio and protobuf: imported on first use, so
# that the REST side of groups needs numpy only.
_GRPC = {"VectorAgents", "AsyncVectorAgents"}


def __getattr__(name: str) -> Any:
    if name not in _GRPC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    try:
        from . import _group_grpc
    except ImportError as e:
        raise ImportError(
            f"mcapi_client.groups.{name} needs grpcio and protobuf: install the `grpc` extra, "
            "pip install './clients/python[grpc,vector]' (from the mcapi repository)",
            name=e.name,
        ) from e
    value = getattr(_group_grpc, name)
    globals()[name] = value
    return value


@dataclass(frozen=True)
class GroupInfo:
    """A group as the server describes it (``GroupInfo``)."""

    id: str
    """``s<shard>.g<ULID>``."""
    size: int
    """Members (N)."""
    seed: int
    """The group's seed; member i's is :func:`member_seed` (seed, i)."""
    update_mode: str
    """``lockstep`` or ``async``, every member's."""
    stimuli: int
    """Stimulus dimensions (n): the width of ``stimuli`` and ``drives``."""
    observation_dim: int
    """A continuous model's observation dimensions (d), else 0."""
    members: list[str]
    """The member session ids by index (``""`` for a member the server could
    not rebuild at a restart)."""


@dataclass(frozen=True)
class MemberStatus:
    """Why one member's observation of a step was refused."""

    index: int
    """The member's index in the group."""
    code: str
    """The stable error code (``unknown_action``, ``not_found``...)."""
    message: str


@dataclass(frozen=True)
class GroupStep:
    """One step's columns, one entry (row) per member stepped, in mask order.

    A refused member's entries are the same placeholders over both
    transports: action :data:`ADVISED`, a drive row of 0, reward 0, policy
    version and ticks 0.
    """

    seq: int
    """The step's sequence number on its stream (gRPC); over REST, the
    number of the step among those its :class:`RestVectorAgents` sent (0 for
    a bare ``step_group``)."""
    actions: npt.NDArray[np.uint32]
    """Each member's next action (:data:`ADVISED` for a refused member)."""
    drives: npt.NDArray[np.float64]
    """Each member's drive after the step, shape (M, n)."""
    rewards: npt.NDArray[np.float64]
    """|r| of each member's step, shape (M,)."""
    policy_versions: npt.NDArray[np.uint64]
    ticks: npt.NDArray[np.uint64]
    errors: list[MemberStatus]
    """The members refused (their rows are placeholders); empty when none was."""


def member_seed(seed: int, index: int) -> int:
    """Member ``index``'s seed in a group of seed ``seed``: output ``index`` of
    SplitMix64 started at ``seed`` (the server's formula, docs/groups.md)."""
    mask = (1 << 64) - 1
    z = (seed + (index + 1) * 0x9E3779B97F4A7C15) & mask
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
    return z ^ (z >> 31)


# -- the columns, checked ---------------------------------------------------


@dataclass(frozen=True)
class Columns:
    """One step's columns, checked against a group by :func:`check_columns`:
    plain numpy arrays of the wire's types, M rows each."""

    members: int
    """M, the members stepped."""
    states: npt.NDArray[np.uint32] | None
    observations: npt.NDArray[np.float64] | None
    """Shape (M, d)."""
    stimuli: npt.NDArray[np.float64] | None
    """Shape (M, n)."""
    action_taken: npt.NDArray[np.uint32] | None
    mask: npt.NDArray[np.uint32] | None


def _integers(values: Any, name: str, *, none_is: int | None = None) -> npt.NDArray[np.uint32]:
    """A 1-d column of integers in 0..2^32-1 (``None`` entries as ``none_is``)."""
    array = np.asarray(values)
    if array.dtype == object and none_is is not None:
        array = np.asarray([none_is if v is None else v for v in array.ravel()]).reshape(array.shape)
    if array.ndim != 1:
        raise ValueError(
            f"`{name}` must be one-dimensional (one entry per member stepped), not of shape {array.shape}"
        )
    if array.size == 0:
        return np.zeros(0, dtype=np.uint32)
    if array.dtype.kind not in "iu":
        raise ValueError(f"`{name}` must hold integers, not {array.dtype} values")
    low, high = int(array.min()), int(array.max())
    if low < 0 or high > 0xFFFF_FFFF:
        bad = low if low < 0 else high
        raise ValueError(f"`{name}` holds {bad}, outside 0..4294967295")
    return array.astype(np.uint32, copy=False)


def _rows(values: Any, m: int, width: int, name: str, what: str) -> npt.NDArray[np.float64]:
    """An (M, width) column of real numbers."""
    array = np.asarray(values)
    if array.dtype.kind not in "iuf":
        raise ValueError(f"`{name}` must hold numbers, not {array.dtype} values")
    if array.shape != (m, width):
        raise ValueError(
            f"`{name}` must have shape ({m}, {width}): one row per member stepped ({m}), "
            f"{what} ({width}); not {array.shape}"
        )
    return np.ascontiguousarray(array, dtype=F64)


def check_columns(
    info: GroupInfo,
    states: Any = None,
    stimuli: Any = None,
    *,
    observations: Any = None,
    action_taken: Any = None,
    mask: Any = None,
) -> Columns:
    """One step's columns checked against the group ``info`` describes.

    Raises:
        ValueError: A column of the wrong shape (M entries or rows, n or d
            columns), an integer column with a float, a negative entry or
            one beyond 2^32-1, ``states`` for a continuous model or
            ``observations`` for one with numbered states, or a mask that
            is not strictly increasing or names a member beyond N.
    """
    n_members = info.size
    picked: npt.NDArray[np.uint32] | None = None
    m = n_members
    if mask is not None:
        picked = _integers(mask, "mask")
        if picked.size:
            if picked.size > 1 and not bool((picked[1:] > picked[:-1]).all()):
                raise ValueError("`mask` must be strictly increasing (each member stepped once, in order)")
            if int(picked[-1]) >= n_members:
                raise ValueError(f"`mask` names member {int(picked[-1])}; the group has {n_members}")
            m = int(picked.size)
    continuous = info.observation_dim > 0
    cols_states: npt.NDArray[np.uint32] | None = None
    cols_obs: npt.NDArray[np.float64] | None = None
    if continuous:
        if states is not None:
            raise ValueError("this group's model is continuous: pass `observations`, not `states`")
        if observations is None:
            raise ValueError("a step needs `observations` (one row per member stepped)")
        cols_obs = _rows(observations, m, info.observation_dim, "observations", "one per coordinate")
    else:
        if observations is not None:
            raise ValueError("this group's model has numbered states: pass `states`, not `observations`")
        if states is None:
            raise ValueError("a step needs `states` (one per member stepped)")
        cols_states = _integers(states, "states")
        if cols_states.size != m:
            raise ValueError(
                f"`states` has {cols_states.size} entries; {m} expected (one per member stepped)"
            )
    cols_stimuli = None
    if stimuli is not None:
        cols_stimuli = _rows(stimuli, m, info.stimuli, "stimuli", "one per stimulus dimension")
    cols_actions = None
    if action_taken is not None:
        cols_actions = _integers(action_taken, "action_taken", none_is=ADVISED)
        if cols_actions.size != m:
            raise ValueError(
                f"`action_taken` has {cols_actions.size} entries; {m} expected (one per member stepped)"
            )
    return Columns(m, cols_states, cols_obs, cols_stimuli, cols_actions, picked)


# -- REST: JSON bodies and replies -----------------------------------------


def group_info_json(d: dict[str, Any]) -> GroupInfo:
    """A ``GroupInfo`` of its REST JSON."""
    return GroupInfo(
        id=str(d["id"]),
        size=int(d["size"]),
        seed=int(d["seed"]),
        update_mode=str(d["update_mode"]),
        stimuli=int(d["stimuli"]),
        observation_dim=int(d.get("observation_dim") or 0),
        members=["" if m is None else str(m) for m in d["members"]],
    )


def step_body(columns: Columns) -> dict[str, Any]:
    """The JSON body of ``POST /v1/groups/{id}/steps``.

    Raises:
        InvalidObservation: A stimulus or observation that is NaN or
            infinite (JSON cannot carry it): the server's code for it.
    """
    body: dict[str, Any] = {}
    if columns.mask is not None and columns.mask.size:
        body["mask"] = columns.mask.tolist()
    if columns.states is not None:
        body["states"] = columns.states.tolist()
    if columns.observations is not None:
        _finite(columns.observations, "observations", "invalid_observation")
        body["observations"] = columns.observations.tolist()
    if columns.stimuli is not None:
        _finite(columns.stimuli, "stimuli", "non_finite_number")
        body["stimuli"] = columns.stimuli.tolist()
    if columns.action_taken is not None:
        taken = columns.action_taken.tolist()
        if (columns.action_taken == ADVISED).any():
            taken = [None if a == ADVISED else a for a in taken]
        body["action_taken"] = taken
    return body


def _finite(rows: npt.NDArray[np.float64], name: str, code: str) -> None:
    ok = np.isfinite(rows)
    if not bool(ok.all()):
        j, k = (int(x) for x in np.argwhere(~ok)[0])
        raise error_for(code, f"`{name}[{j}][{k}]` is {rows[j, k]}, not a finite number")


def group_step_json(d: dict[str, Any], stimuli: int, seq: int = 0) -> GroupStep:
    """The columns of a REST step reply as numpy arrays, a refused member's
    ``null`` entries as the gRPC placeholders (:class:`GroupStep`)."""
    errors = [MemberStatus(int(e["index"]), str(e["code"]), str(e["message"])) for e in d["errors"]]
    actions, drives, rewards = d["actions"], d["drives"], d["rewards"]
    versions, ticks = d["policy_versions"], d["ticks"]
    if errors:
        zero = [0.0] * stimuli
        actions = [ADVISED if a is None else a for a in actions]
        drives = [zero if row is None else row for row in drives]
        rewards = [0.0 if r is None else r for r in rewards]
        versions = [0 if v is None else v for v in versions]
        ticks = [0 if t is None else t for t in ticks]
    m = len(actions)
    return GroupStep(
        seq=seq,
        actions=np.asarray(actions, dtype=np.uint32).reshape(m),
        drives=np.asarray(drives, dtype=F64).reshape(m, stimuli),
        rewards=np.asarray(rewards, dtype=F64).reshape(m),
        policy_versions=np.asarray(versions, dtype=np.uint64).reshape(m),
        ticks=np.asarray(ticks, dtype=np.uint64).reshape(m),
        errors=errors,
    )


# -- what the adapters take ---------------------------------------------------


class GroupAgents(Protocol):
    """What steps a group, blocking: :class:`VectorAgents` (gRPC) and
    :class:`RestVectorAgents` (REST) both are one, and
    :class:`~mcapi_client.vector_env.VectorEnvAdapter` takes either."""

    @property
    def info(self) -> GroupInfo:
        """The group stepped."""
        ...

    def step(
        self,
        states: Any = None,
        stimuli: Any = None,
        *,
        observations: Any = None,
        action_taken: Any = None,
        mask: Any = None,
    ) -> GroupStep:
        """One step of the members (all, or those of ``mask``)."""
        ...


class RestVectorAgents:
    """A group stepped over REST: one ``POST /v1/groups/{id}/steps`` per
    :meth:`step`, with :class:`VectorAgents`' arguments and results.

    Get one from :meth:`mcapi_client.Client.create_group` or
    :meth:`mcapi_client.Client.vector_agents`. There is no stream to keep:
    closing it (or leaving its ``with`` block) only stops it stepping;
    ``delete_group`` deletes the members. A step refused whole raises its
    :class:`~mcapi_client.McapiError` (``column_length``, ``unknown_state``,
    ...); a member refused alone is listed in :attr:`GroupStep.errors`.
    """

    def __init__(self, info: GroupInfo, send: Callable[[dict[str, Any]], dict[str, Any]]) -> None:
        self._info = info
        self._send = send
        self._seq = 0
        self._closed = False

    @property
    def info(self) -> GroupInfo:
        """The group stepped."""
        return self._info

    def step(
        self,
        states: Any = None,
        stimuli: Any = None,
        *,
        observations: Any = None,
        action_taken: Any = None,
        mask: Any = None,
    ) -> GroupStep:
        """One step; arguments and result as :meth:`VectorAgents.step`."""
        if self._closed:
            raise RuntimeError("these vector agents are closed")
        cols = check_columns(
            self._info, states, stimuli, observations=observations, action_taken=action_taken, mask=mask
        )
        reply = self._send(step_body(cols))
        seq, self._seq = self._seq, self._seq + 1
        return group_step_json(reply, self._info.stimuli, seq)

    def close(self) -> None:
        """Stops stepping (the group and its members stay)."""
        self._closed = True

    def __enter__(self) -> RestVectorAgents:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncRestVectorAgents:
    """:class:`RestVectorAgents` under asyncio (:meth:`step` awaited); get one
    from :meth:`mcapi_client.AsyncClient.create_group`."""

    def __init__(
        self, info: GroupInfo, send: Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]
    ) -> None:
        self._info = info
        self._send = send
        self._seq = 0
        self._closed = False

    @property
    def info(self) -> GroupInfo:
        """The group stepped."""
        return self._info

    async def step(
        self,
        states: Any = None,
        stimuli: Any = None,
        *,
        observations: Any = None,
        action_taken: Any = None,
        mask: Any = None,
    ) -> GroupStep:
        """One step; arguments and result as :meth:`VectorAgents.step`."""
        if self._closed:
            raise RuntimeError("these vector agents are closed")
        cols = check_columns(
            self._info, states, stimuli, observations=observations, action_taken=action_taken, mask=mask
        )
        reply = await self._send(step_body(cols))
        seq, self._seq = self._seq, self._seq + 1
        return group_step_json(reply, self._info.stimuli, seq)

    def close(self) -> None:
        """Stops stepping (the group and its members stay)."""
        self._closed = True

    async def __aenter__(self) -> AsyncRestVectorAgents:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()
