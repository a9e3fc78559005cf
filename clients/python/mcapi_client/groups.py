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

**Exactly once.** With the client's ``exactly_once`` (the default), every
step carries a ``seqs`` column, each member's observation numbered in that
member's stream as a lone observation is (docs/sessions.md, "Delivery
guarantees"). The client keeps one count per member of each group it
stepped (:class:`GroupSeqs`), from 0 for a group it created; a step that
got no answer may therefore be resent as it was, and the members that had
applied it are answered with their recorded steps (:attr:`GroupStep.replayed`).
A resent step is one the caller sends again with the same columns: the
REST clients resend a numbered step on a lost answer themselves, and a
``StepGroup`` stream that broke gives its unanswered steps' seqs back, so
the same client's next stream (``vector_agents``) sends them again. A
member whose count the client does not know (a group it did not create,
or after ``seq_conflict``, ``seq_expired`` or ``numerical_failure``) makes
a step unnumbered, at least once, and its count is then learned from the
reply's ``ticks``. A member refused ``seq_gap`` goes on from the
``expected_seq`` the server named; refusals are in :attr:`GroupStep.errors`,
never raised.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any, Protocol

# Raises the `vector` extra's ImportError without numpy.
from ._columns import (
    ADVISED,
    F64,
    Columns,
    GroupInfo,
    GroupSeqs,
    GroupStep,
    MemberStatus,
    check_columns,
    group_step_json,
    member_seed,
    numbered_body,
)

if TYPE_CHECKING:

    from ._group_grpc import AsyncVectorAgents, VectorAgents

__all__ = [
    "ADVISED",
    "F64",
    "GroupInfo",
    "GroupStep",
    "MemberStatus",
    "Columns",
    "GroupAgents",
    "GroupSeqs",
    "VectorAgents",
    "AsyncVectorAgents",
    "RestVectorAgents",
    "AsyncRestVectorAgents",
    "member_seed",
    "check_columns",
]

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

    def __init__(
        self,
        info: GroupInfo,
        send: Callable[[dict[str, Any], bool], dict[str, Any]],
        seqs: GroupSeqs | None = None,
    ) -> None:
        self._info = info
        self._send = send
        self._seqs = seqs
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
        body, members, sent = numbered_body(self._info, cols, self._seqs)
        try:
            reply = self._send(body, sent is not None)
        except BaseException:
            if self._seqs is not None:
                self._seqs.failed(members, sent)
            raise
        seq, self._seq = self._seq, self._seq + 1
        step = group_step_json(reply, self._info.stimuli, seq)
        if self._seqs is not None:
            self._seqs.answered(members, sent, step)
        return step

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
        self,
        info: GroupInfo,
        send: Callable[[dict[str, Any], bool], Awaitable[dict[str, Any]]],
        seqs: GroupSeqs | None = None,
    ) -> None:
        self._info = info
        self._send = send
        self._seqs = seqs
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
        body, members, sent = numbered_body(self._info, cols, self._seqs)
        try:
            reply = await self._send(body, sent is not None)
        except BaseException:
            if self._seqs is not None:
                self._seqs.failed(members, sent)
            raise
        seq, self._seq = self._seq, self._seq + 1
        step = group_step_json(reply, self._info.stimuli, seq)
        if self._seqs is not None:
            self._seqs.answered(members, sent, step)
        return step

    def close(self) -> None:
        """Stops stepping (the group and its members stay)."""
        self._closed = True

    async def __aenter__(self) -> AsyncRestVectorAgents:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()
