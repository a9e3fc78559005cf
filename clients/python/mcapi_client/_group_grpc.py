"""Session groups over gRPC: the ``StepGroup`` stream, blocking
(:class:`VectorAgents`) and asyncio (:class:`AsyncVectorAgents`), and the
group messages. Imported through :mod:`mcapi_client.groups`; needs the
``grpc`` and ``vector`` extras (grpcio, protobuf, numpy).

Integers travel as packed ``repeated`` fields, real numbers as little-endian
binary64 ``bytes``, row-major, one row per member stepped (docs/groups.md).
"""

from __future__ import annotations

import asyncio
import collections
import queue
from collections.abc import AsyncIterator, Iterator, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ._columns import F64, Columns, GroupInfo, GroupSeqs, GroupStep, MemberStatus, check_columns, stepped
from ._pb import rpc_error
from ._proto.mcapi.v1 import agents_pb2 as pb
from .errors import Unavailable

if TYPE_CHECKING:
    import numpy.typing as npt

    from ._proto.mcapi.v1 import agents_pb2_grpc as pb_grpc

__all__ = ["VectorAgents", "AsyncVectorAgents", "group_info", "step_request", "group_step"]


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


def step_request(
    group_id: str, seq: int, columns: Columns, seqs: npt.NDArray[np.uint64] | None = None
) -> pb.GroupStepRequest:
    """One ``GroupStepRequest`` of checked columns (and its members' ``seqs``)."""
    msg = pb.GroupStepRequest(group_id=group_id, seq=seq)
    if seqs is not None:
        msg.seqs.extend(seqs.tolist())
    if columns.states is not None:
        msg.states.extend(columns.states.tolist())
    if columns.observations is not None:
        msg.observations = columns.observations.tobytes()
    if columns.stimuli is not None:
        msg.stimuli = columns.stimuli.tobytes()
    if columns.action_taken is not None:
        msg.action_taken.extend(columns.action_taken.tolist())
    if columns.mask is not None:
        msg.mask.extend(columns.mask.tolist())
    return msg


def group_step(msg: pb.GroupStepReply, stimuli: int) -> GroupStep:
    """The columns of a ``GroupStepReply`` as numpy arrays."""
    actions = np.asarray(msg.actions, dtype=np.uint32)
    drives = np.frombuffer(msg.drives, dtype=F64).reshape(len(actions), stimuli)
    return GroupStep(
        seq=msg.seq,
        actions=actions,
        drives=drives,
        rewards=np.frombuffer(msg.rewards, dtype=F64),
        policy_versions=np.asarray(msg.policy_versions, dtype=np.uint64),
        ticks=np.asarray(msg.ticks, dtype=np.uint64),
        errors=[
            MemberStatus(
                s.index,
                s.code,
                s.message,
                s.expected_seq if s.HasField("expected_seq") else None,
                s.oldest_seq if s.HasField("oldest_seq") else None,
            )
            for s in msg.statuses
        ],
        replayed=(
            np.asarray(msg.replayed, dtype=np.bool_)
            if len(msg.replayed)
            else np.zeros(len(actions), dtype=np.bool_)
        ),
    )


def _is_rpc_error(e: BaseException) -> bool:
    """A ``grpc.RpcError`` (a call's status), told without importing grpc here."""
    return hasattr(e, "code") and hasattr(e, "trailing_metadata")


class _GroupStream:
    """What both ``StepGroup`` streams count, check and build, with no I/O."""

    _outbox: queue.SimpleQueue[pb.GroupStepRequest | None] | asyncio.Queue[pb.GroupStepRequest | None]
    _call: Any

    def __init__(
        self, info: GroupInfo, metadata: Sequence[tuple[str, str]], seqs: GroupSeqs | None = None
    ) -> None:
        self.info = info
        self._metadata = (*metadata, ("x-mcapi-session", info.id))
        self._seq = 0
        self._sent = 0
        self._received = 0
        self._closed = False
        self._seqs = seqs
        # Per step sent and not answered, oldest first: its members and seqs.
        self._unanswered: collections.deque[
            tuple[npt.NDArray[np.intp], npt.NDArray[np.uint64] | None]
        ] = collections.deque()

    @property
    def pending(self) -> int:
        """Steps sent whose replies have not been received yet."""
        return self._sent - self._received

    def _message(
        self, states: Any, stimuli: Any, observations: Any, action_taken: Any, mask: Any
    ) -> pb.GroupStepRequest:
        if self._closed:
            raise RuntimeError("this group stream is closed")
        columns = check_columns(
            self.info, states, stimuli, observations=observations, action_taken=action_taken, mask=mask
        )
        members = stepped(self.info, columns)
        sent = self._seqs.take(members) if self._seqs is not None else None
        self._unanswered.append((members, sent))
        return step_request(self.info.id if self._sent == 0 else "", self._seq, columns, sent)

    def _queued(self, msg: pb.GroupStepRequest) -> int:
        self._seq += 1
        self._sent += 1
        return msg.seq

    def _lost(self) -> None:
        """The stream ended with steps unanswered: their seqs are taken
        again (newest first), so that this client's next stream sends them
        again and the members that applied them replay."""
        while self._unanswered:
            members, sent = self._unanswered.pop()
            if self._seqs is not None:
                self._seqs.failed(members, sent)

    def _expect_reply(self) -> None:
        if self.pending == 0:
            raise RuntimeError("no step is waiting for its reply; send one first")

    def _reply(self, msg: pb.GroupStepReply) -> GroupStep:
        self._received += 1
        step = group_step(msg, self.info.stimuli)
        if self._unanswered:
            members, sent = self._unanswered.popleft()
            if self._seqs is not None:
                self._seqs.answered(members, sent, step)
        return step

    def close(self) -> None:
        """Ends the stream; replies not received are dropped (the group stays;
        with ``exactly_once`` their steps' seqs are taken again)."""
        if self._closed:
            return
        self._closed = True
        self._lost()
        self._outbox.put_nowait(None)
        self._call.cancel()


class VectorAgents(_GroupStream):
    """A group's ``StepGroup`` stream: one message per step of its members.

    Get one from :meth:`mcapi_client.GrpcClient.create_group` or
    :meth:`mcapi_client.GrpcClient.vector_agents` and use it as a context
    manager. :meth:`step` sends one step and waits for its columns;
    :meth:`send` only queues one (returning its ``seq``), and :meth:`recv`
    takes the oldest reply, so that 2-4 steps can be kept in flight. A step
    whose columns do not fit the group raises a ``ValueError`` before
    anything is sent; one the server refuses whole (a state beyond the
    model's, a stimulus too large) raises its
    :class:`~mcapi_client.McapiError` from :meth:`recv` and ends the stream;
    a member whose own observation is refused is listed in
    :attr:`GroupStep.errors` and the others are stepped.
    """

    def __init__(
        self,
        stub: pb_grpc.AgentsStub,
        info: GroupInfo,
        metadata: Sequence[tuple[str, str]],
        seqs: GroupSeqs | None = None,
    ) -> None:
        super().__init__(info, metadata, seqs)
        self._outbox: queue.SimpleQueue[pb.GroupStepRequest | None] = queue.SimpleQueue()
        self._call = stub.StepGroup(self._requests(), metadata=self._metadata)

    def _requests(self) -> Iterator[pb.GroupStepRequest]:
        while True:
            msg = self._outbox.get()
            if msg is None:
                return
            yield msg

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
                :data:`~mcapi_client.groups.ADVISED` or ``None`` for the
                advised one); leave out when all took the advised action.
            mask: The member indices stepped, strictly increasing; leave
                out to step every member in order.

        Raises:
            ValueError: A column does not fit the group (see
                :func:`~mcapi_client.groups.check_columns`); nothing was sent.
        """
        msg = self._message(states, stimuli, observations, action_taken, mask)
        self._outbox.put(msg)
        return self._queued(msg)

    def recv(self) -> GroupStep:
        """Waits for the reply of the oldest step not yet answered."""
        self._expect_reply()
        try:
            msg = next(self._call)
        except StopIteration:
            self._lost()
            raise Unavailable(
                "the server ended the stream before replying", code="stream_closed"
            ) from None
        except Exception as e:  # grpc.RpcError, without importing grpc here
            self._lost()
            if _is_rpc_error(e):
                raise rpc_error(e) from e
            raise
        return self._reply(msg)

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

    def __enter__(self) -> VectorAgents:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncVectorAgents(_GroupStream):
    """A group's ``StepGroup`` stream under asyncio; :class:`VectorAgents`' twin.

    Get one from :meth:`mcapi_client.AsyncGrpcClient.create_group` or
    :meth:`mcapi_client.AsyncGrpcClient.vector_agents` and use it with
    ``async with``. :meth:`send` queues a step and returns its ``seq`` at
    once (not awaited, like ``AsyncInteraction.send``); :meth:`recv` and
    :meth:`step` are awaited:

        async with await mc.create_group(world, 1000, seed=7) as agents:
            step = await agents.step(states)
            agents.send(states_a, stimuli_a, mask=evens)   # two in flight
            agents.send(states_b, stimuli_b, mask=odds)
            a, b = await agents.recv(), await agents.recv()

    Errors as in :class:`VectorAgents`.
    """

    def __init__(
        self,
        stub: pb_grpc.AgentsStub,
        info: GroupInfo,
        metadata: Sequence[tuple[str, str]],
        seqs: GroupSeqs | None = None,
    ) -> None:
        super().__init__(info, metadata, seqs)
        self._outbox: asyncio.Queue[pb.GroupStepRequest | None] = asyncio.Queue()
        self._call = stub.StepGroup(self._requests(), metadata=self._metadata)

    async def _requests(self) -> AsyncIterator[pb.GroupStepRequest]:
        while True:
            msg = await self._outbox.get()
            if msg is None:
                return
            yield msg

    def send(
        self,
        states: Any = None,
        stimuli: Any = None,
        *,
        observations: Any = None,
        action_taken: Any = None,
        mask: Any = None,
    ) -> int:
        """Queues one step without waiting for its reply (not awaited); returns
        its ``seq``. Arguments and errors as :meth:`VectorAgents.send`."""
        msg = self._message(states, stimuli, observations, action_taken, mask)
        self._outbox.put_nowait(msg)
        return self._queued(msg)

    async def recv(self) -> GroupStep:
        """Waits for the reply of the oldest step not yet answered."""
        self._expect_reply()
        try:
            msg = await self._call.read()
        except Exception as e:  # grpc.RpcError, without importing grpc here
            self._lost()
            if _is_rpc_error(e):
                raise rpc_error(e) from e
            raise
        if not isinstance(msg, pb.GroupStepReply):  # grpc.aio.EOF
            self._lost()
            raise Unavailable("the server ended the stream before replying", code="stream_closed")
        return self._reply(msg)

    async def step(
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
        return await self.recv()

    async def __aenter__(self) -> AsyncVectorAgents:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()
