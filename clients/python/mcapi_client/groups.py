"""Session groups over gRPC: N agents of one model stepped by columns
(numpy arrays in, numpy arrays out), for vectorised simulators. Needs the
``grpc`` and ``vector`` extras (grpcio, protobuf, numpy).

    from mcapi_client import GrpcClient, models

    with GrpcClient("127.0.0.1:50051") as mc:
        with mc.create_group(models.hallway(), n=1000, seed=7) as agents:
            step = agents.step(states)                   # first: states only
            for _ in range(100):
                states = ...                             # apply step.actions
                step = agents.step(states, stimuli)      # stimuli: (N, n)

:meth:`VectorAgents.send` and :meth:`VectorAgents.recv` split a step in two,
so that a client can keep several in flight (the server reads up to 8 ahead
and answers in order). The layout of every column is the server's
``docs/groups.md``: integers as packed fields, real numbers as little-endian
binary64 ``bytes``, row-major, one row per member stepped.
"""

from __future__ import annotations

import queue
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

try:
    import numpy as np
except ImportError as e:  # pragma: no cover - depends on the installed extras
    raise ImportError(
        "session groups (mcapi_client.groups) need numpy: install the `vector` extra, "
        "pip install './clients/python[grpc,vector]' (from the mcapi repository)",
        name=e.name,
    ) from e

from ._pb import rpc_error
from ._proto.mcapi.v1 import agents_pb2 as pb
from .errors import Unavailable

if TYPE_CHECKING:
    import numpy.typing as npt

    from ._proto.mcapi.v1 import agents_pb2_grpc as pb_grpc

__all__ = ["ADVISED", "GroupInfo", "GroupStep", "MemberStatus", "VectorAgents"]

ADVISED = 0xFFFF_FFFF
"""``action_taken`` entry for a member that took its advised action; also the
``actions`` entry of a member whose observation was refused."""

_F64 = np.dtype("<f8")


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
    """The member session ids by index."""


@dataclass(frozen=True)
class MemberStatus:
    """Why one member's observation of a step was refused."""

    index: int
    """The member's index in the group."""
    code: str
    """The stable error code (``unknown_state``, ``non_finite_number``...)."""
    message: str


@dataclass(frozen=True)
class GroupStep:
    """One step's columns, one entry (row) per member stepped, in mask order."""

    seq: int
    actions: npt.NDArray[np.uint32]
    """Each member's next action (:data:`ADVISED` for a refused member)."""
    drives: npt.NDArray[np.float64]
    """Each member's drive after the step, shape (M, n)."""
    rewards: npt.NDArray[np.float64]
    """|r| of each member's step, shape (M,)."""
    policy_versions: npt.NDArray[np.uint64]
    ticks: npt.NDArray[np.uint64]
    errors: list[MemberStatus]
    """The members refused (their rows are not meaningful); empty when none was."""


def member_seed(seed: int, index: int) -> int:
    """Member ``index``'s seed in a group of seed ``seed``: output ``index`` of
    SplitMix64 started at ``seed`` (the server's formula, docs/groups.md)."""
    mask = (1 << 64) - 1
    z = (seed + (index + 1) * 0x9E3779B97F4A7C15) & mask
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
    return z ^ (z >> 31)


def group_info(msg: pb.GroupInfo) -> GroupInfo:
    """The dataclass of a ``GroupInfo`` message."""
    return GroupInfo(
        id=msg.group_id,
        size=msg.size,
        seed=msg.seed,
        update_mode=pb.UpdateMode.Name(msg.update_mode).removeprefix("UPDATE_MODE_").lower(),
        stimuli=msg.stimuli,
        observation_dim=msg.observation_dim,
        members=list(msg.member_ids),
    )


def _rows(values: Any, width: int, name: str) -> bytes:
    """``values`` (M × width numbers, any array-like) as little-endian binary64."""
    array = np.ascontiguousarray(values, dtype=_F64)
    if width and array.ndim == 2 and array.shape[1] != width:
        raise ValueError(f"`{name}` must have {width} columns, not {array.shape[1]}")
    return array.tobytes()


def step_request(
    group_id: str,
    seq: int,
    states: Any = None,
    stimuli: Any = None,
    *,
    observations: Any = None,
    action_taken: Any = None,
    mask: Any = None,
    stimuli_width: int = 0,
    observation_dim: int = 0,
) -> pb.GroupStepRequest:
    """One ``GroupStepRequest``; the server checks every length against the group."""
    msg = pb.GroupStepRequest(group_id=group_id, seq=seq)
    if states is not None:
        msg.states.extend(np.asarray(states, dtype=np.uint32).ravel().tolist())
    if observations is not None:
        msg.observations = _rows(observations, observation_dim, "observations")
    if stimuli is not None:
        msg.stimuli = _rows(stimuli, stimuli_width, "stimuli")
    if action_taken is not None:
        msg.action_taken.extend(np.asarray(action_taken, dtype=np.uint32).ravel().tolist())
    if mask is not None:
        msg.mask.extend(np.asarray(mask, dtype=np.uint32).ravel().tolist())
    return msg


def group_step(msg: pb.GroupStepReply, stimuli: int) -> GroupStep:
    """The columns of a ``GroupStepReply`` as numpy arrays."""
    actions = np.asarray(msg.actions, dtype=np.uint32)
    drives = np.frombuffer(msg.drives, dtype=_F64).reshape(len(actions), stimuli)
    return GroupStep(
        seq=msg.seq,
        actions=actions,
        drives=drives,
        rewards=np.frombuffer(msg.rewards, dtype=_F64),
        policy_versions=np.asarray(msg.policy_versions, dtype=np.uint64),
        ticks=np.asarray(msg.ticks, dtype=np.uint64),
        errors=[MemberStatus(s.index, s.code, s.message) for s in msg.statuses],
    )


class VectorAgents:
    """A group's ``StepGroup`` stream: one message per step of its members.

    Get one from :meth:`mcapi_client.GrpcClient.create_group` or
    :meth:`mcapi_client.GrpcClient.vector_agents` and use it as a context
    manager. :meth:`step` sends one step and waits for its columns;
    :meth:`send` only queues one (returning its ``seq``), and :meth:`recv`
    takes the oldest reply, so that 2-4 steps can be kept in flight. A step
    that does not fit the group (a length, the mask, the sequence) raises
    its :class:`~mcapi_client.McapiError` and ends the stream; a member whose
    own observation is refused is listed in :attr:`GroupStep.errors` and
    the others are stepped.
    """

    def __init__(
        self, stub: pb_grpc.AgentsStub, info: GroupInfo, metadata: Sequence[tuple[str, str]]
    ) -> None:
        self.info = info
        self._outbox: queue.SimpleQueue[pb.GroupStepRequest | None] = queue.SimpleQueue()
        self._call = stub.StepGroup(self._requests(), metadata=(*metadata, ("x-mcapi-session", info.id)))
        self._seq = 0
        self._sent = 0
        self._received = 0
        self._closed = False

    def _requests(self) -> Iterator[pb.GroupStepRequest]:
        while True:
            msg = self._outbox.get()
            if msg is None:
                return
            yield msg

    @property
    def pending(self) -> int:
        """Steps sent whose replies have not been received yet."""
        return self._sent - self._received

    def send(
        self,
        states: Any = None,
        stimuli: Any = None,
        *,
        observations: Any = None,
        action_taken: Any = None,
        mask: Any = None,
    ) -> int:
        """Queues one step without waiting for its reply; returns its ``seq``.

        Args:
            states: The state of each member stepped (M integers), for models
                with numbered states.
            stimuli: What each member received on arriving there, shape
                (M, n); leave out on the members' first step.
            observations: A continuous model's observations, shape (M, d),
                instead of ``states``.
            action_taken: The action each member took (M integers,
                :data:`ADVISED` for the advised one); leave out when all
                took the advised action.
            mask: The member indices stepped, strictly increasing; leave
                out to step every member in order.
        """
        if self._closed:
            raise RuntimeError("this group stream is closed")
        msg = step_request(
            self.info.id if self._sent == 0 else "",
            self._seq,
            states,
            stimuli,
            observations=observations,
            action_taken=action_taken,
            mask=mask,
            stimuli_width=self.info.stimuli,
            observation_dim=self.info.observation_dim,
        )
        self._outbox.put(msg)
        self._seq += 1
        self._sent += 1
        return msg.seq

    def recv(self) -> GroupStep:
        """Waits for the reply of the oldest step not yet answered."""
        if self.pending == 0:
            raise RuntimeError("no step is waiting for its reply; send one first")
        try:
            msg = next(self._call)
        except StopIteration:
            raise Unavailable(
                "the server ended the stream before replying", code="stream_closed"
            ) from None
        except Exception as e:  # grpc.RpcError, without importing grpc here
            if hasattr(e, "code") and hasattr(e, "trailing_metadata"):
                raise rpc_error(e) from e
            raise
        self._received += 1
        return group_step(msg, self.info.stimuli)

    def step(
        self,
        states: Any = None,
        stimuli: Any = None,
        *,
        observations: Any = None,
        action_taken: Any = None,
        mask: Any = None,
    ) -> GroupStep:
        """Sends one step and returns its columns; arguments as :meth:`send`."""
        self.send(states, stimuli, observations=observations, action_taken=action_taken, mask=mask)
        return self.recv()

    def close(self) -> None:
        """Ends the stream; replies not received are dropped."""
        if self._closed:
            return
        self._closed = True
        self._outbox.put_nowait(None)
        self._call.cancel()

    def __enter__(self) -> VectorAgents:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
