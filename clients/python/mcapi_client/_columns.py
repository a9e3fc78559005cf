"""What a group step carries and answers, and what the client keeps of it:
the group's description (:class:`GroupInfo`), one step's columns checked
against it (:class:`Columns`, :func:`check_columns`), its answer
(:class:`GroupStep`), their JSON forms, and the per-member counts of
exactly-once delivery (:class:`GroupSeqs`). Shared by both transports'
group objects; the public names are :mod:`mcapi_client.groups`'."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

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

ADVISED = 0xFFFF_FFFF
"""``action_taken`` entry for a member that took its advised action; also the
``actions`` entry of a member whose observation was refused."""

F64 = np.dtype("<f8")
"""The dtype of every real-number column (little-endian binary64)."""


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
    """The stable error code (``unknown_action``, ``not_found``, ``seq_gap``...)."""
    message: str
    expected_seq: int | None = None
    """``seq_gap``: the seq the member's session takes next."""
    oldest_seq: int | None = None
    """``seq_expired``: the oldest seq the member's session can still replay."""


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
    replayed: npt.NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=np.bool_))
    """Whether each member's step is the one recorded for its seq, replayed
    (nothing applied), shape (M,); all false for an unnumbered step or a
    refused member."""


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


def numbered_body(
    info: GroupInfo, columns: Columns, seqs: GroupSeqs | None
) -> tuple[dict[str, Any], npt.NDArray[np.intp], npt.NDArray[np.uint64] | None]:
    """The JSON body of a step numbered by ``seqs`` (unnumbered without, or
    while a member's count is unknown): the body, the members stepped and
    the seqs sent."""
    body = step_body(columns)
    members = stepped(info, columns)
    sent = seqs.take(members) if seqs is not None else None
    if sent is not None:
        body["seqs"] = sent.tolist()
    return body, members, sent


def _finite(rows: npt.NDArray[np.float64], name: str, code: str) -> None:
    ok = np.isfinite(rows)
    if not bool(ok.all()):
        j, k = (int(x) for x in np.argwhere(~ok)[0])
        raise error_for(code, f"`{name}[{j}][{k}]` is {rows[j, k]}, not a finite number")


def group_step_json(d: dict[str, Any], stimuli: int, seq: int = 0) -> GroupStep:
    """The columns of a REST step reply as numpy arrays, a refused member's
    ``null`` entries as the gRPC placeholders (:class:`GroupStep`)."""
    errors = [
        MemberStatus(
            int(e["index"]),
            str(e["code"]),
            str(e["message"]),
            _opt_int(e.get("expected_seq")),
            _opt_int(e.get("oldest_seq")),
        )
        for e in d["errors"]
    ]
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
        replayed=np.asarray(d.get("replayed") or [False] * m, dtype=np.bool_).reshape(m),
    )


def _opt_int(value: object) -> int | None:
    return value if type(value) is int else None


# -- exactly once: one count per member ---------------------------------------

_UNKNOWN = -1
"""A member count the client does not know."""

_FORGET = frozenset({"seq_conflict", "seq_expired", "numerical_failure"})
"""Member refusals after which the member's count is read again (from the
next unnumbered step's ``ticks``): someone else numbered it, a resend came
too late, or the observation was applied and failed."""


class GroupSeqs:
    """Per member of one group, the seq of its next observation: what the
    ``seqs`` column of the group's next step carries (thread-safe; numpy, one
    entry per member).

    :meth:`take` numbers a step (or leaves it unnumbered while a member's
    count is unknown); :meth:`answered` and :meth:`failed` say what became
    of it, in the order the steps were sent.
    """

    def __init__(self, size: int, *, known: bool) -> None:
        """``known``: the group was just created (every count 0); otherwise
        every count is learned from the first step's ``ticks``."""
        self._lock = threading.Lock()
        self._next: npt.NDArray[np.int64] = np.full(size, 0 if known else _UNKNOWN, dtype=np.int64)
        # Unnumbered steps in flight per member: its count is learned from
        # their replies, so it is not known until the last one is answered.
        self._unnumbered: npt.NDArray[np.int64] = np.zeros(size, dtype=np.int64)

    def next_seqs(self) -> npt.NDArray[np.int64]:
        """A copy of every member's count (-1: not known)."""
        with self._lock:
            out: npt.NDArray[np.int64] = self._next.copy()
        return out

    def take(self, members: npt.NDArray[np.intp]) -> npt.NDArray[np.uint64] | None:
        """Reserves one seq for each member stepped (``members``, the mask's
        indices): their seqs, or ``None`` when a count is not known (the step
        goes unnumbered)."""
        with self._lock:
            nxt = self._next[members]
            if bool((nxt < 0).any()) or bool(self._unnumbered[members].any()):
                self._unnumbered[members] += 1
                return None
            self._next[members] = nxt + 1
            return nxt.astype(np.uint64)

    def answered(
        self, members: npt.NDArray[np.intp], sent: npt.NDArray[np.uint64] | None, step: GroupStep
    ) -> None:
        """The reply of a step that carried ``sent`` (``None``: unnumbered)."""
        with self._lock:
            if sent is None:
                self._unnumbered[members] -= 1
                applied = np.ones(members.size, dtype=np.bool_)
                position = {int(i): j for j, i in enumerate(members.tolist())} if step.errors else {}
                for e in step.errors:
                    j = position.get(e.index)
                    if j is not None:
                        applied[j] = False
                        if e.code in _FORGET:
                            self._next[e.index] = _UNKNOWN
                ticks = step.ticks.astype(np.int64)
                self._next[members[applied]] = ticks[applied] + 1
                return
            if not step.errors:
                return
            position = {int(i): j for j, i in enumerate(members.tolist())}
            for e in step.errors:
                j = position.get(e.index)
                if j is None:
                    continue
                seq = int(sent[j])
                # No later step of this member was numbered meanwhile.
                last = int(self._next[e.index]) == seq + 1
                if e.code == "seq_gap" and e.expected_seq is not None:
                    if last:
                        self._next[e.index] = e.expected_seq
                elif e.code in _FORGET:
                    self._next[e.index] = _UNKNOWN
                elif last:
                    # Not applied: the member's next observation takes it.
                    self._next[e.index] = seq

    def failed(self, members: npt.NDArray[np.intp], sent: npt.NDArray[np.uint64] | None) -> None:
        """A step got no reply (or was refused whole): its seqs are taken
        again, so that sending it again replays what the members applied of
        it. Several steps in flight are failed newest first."""
        with self._lock:
            if sent is None:
                self._unnumbered[members] -= 1
                self._next[members] = _UNKNOWN
                return
            after = sent.astype(np.int64) + 1
            back = self._next[members] == after
            self._next[members[back]] = after[back] - 1
            self._next[members[~back]] = _UNKNOWN

    def forget(self) -> None:
        """Every count is learned again."""
        with self._lock:
            self._next[:] = _UNKNOWN


def stepped(info: GroupInfo, columns: Columns) -> npt.NDArray[np.intp]:
    """The member indices a step's columns are for, in order."""
    if columns.mask is not None and columns.mask.size:
        return columns.mask.astype(np.intp)
    return np.arange(info.size, dtype=np.intp)


class GroupSeqTable:
    """A client's :class:`GroupSeqs`, by group id (created with its group, or
    on first use, unknown)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._groups: dict[str, GroupSeqs] = {}

    def created(self, info: GroupInfo) -> GroupSeqs:
        """A group just created: every count 0."""
        seqs = GroupSeqs(info.size, known=True)
        with self._lock:
            self._groups[info.id] = seqs
        return seqs

    def of(self, info: GroupInfo) -> GroupSeqs:
        """The counts of a group: kept, else unknown."""
        with self._lock:
            seqs = self._groups.get(info.id)
            if seqs is None:
                seqs = self._groups[info.id] = GroupSeqs(info.size, known=False)
            return seqs

    def drop(self, group_id: str) -> None:
        """A group deleted."""
        with self._lock:
            self._groups.pop(group_id, None)
