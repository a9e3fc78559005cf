"""The gRPC clients: :class:`GrpcClient` (blocking) and its asyncio twin
:class:`AsyncGrpcClient` (``grpc.aio``), with the REST client's operations,
the bidirectional ``interact`` stream for high-rate loops and the ``watch``
stream of snapshots. Needs the ``grpc`` extra (``pip install
'./clients/python[grpc]'`` from the mcapi repository: grpcio and protobuf).

    from mcapi_client import GrpcClient, models

    world = models.hallway()
    with GrpcClient("127.0.0.1:50051") as mc:
        session = mc.create_session(world, seed=7)
        with mc.interact(session.id) as stream:
            step = stream.step(25)                       # first: state only
            for _ in range(1000):
                state = ...                              # apply step.action
                step = stream.step(state, world.stimulus(state))

    async with AsyncGrpcClient("127.0.0.1:50051") as mc:
        session = await mc.create_session(world, seed=7)
        async with mc.interact(session.id) as stream:
            step = await stream.step(25)

Each call names its session in the ``x-mcapi-session`` metadata (routers
read it; the server checks it against the message), and sends the API key as
``authorization: Bearer <key>``. Errors are the same
:class:`~mcapi_client.McapiError` subclasses as over REST, read from the
status and the ``x-mcapi-error-code`` trailer. Both clients run the same
operations of :mod:`mcapi_client._pb` (messages built and read once);
numbers may be numpy scalars and vectors numpy arrays.
"""

from __future__ import annotations

import asyncio
import collections
import queue
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable, Iterator, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

try:
    import google.protobuf  # noqa: F401  (the stubs' messages)
    import grpc
    import grpc.aio
except ImportError as e:  # pragma: no cover - exercised in a subprocess by tests/test_package.py
    raise ImportError(
        "the gRPC clients (mcapi_client.GrpcClient, AsyncGrpcClient) need grpcio and protobuf: "
        "install the `grpc` extra, pip install './clients/python[grpc]' "
        "(from the mcapi repository)",
        name=e.name,
    ) from e

from . import _pb
from ._normalise import FloatLike, FloatsLike, IntLike, as_int
from ._pb import ERROR_CODE_TRAILER, SESSION_METADATA, Call, Metadata, rpc_error
from ._proto.mcapi.v1 import agents_pb2 as pb
from ._proto.mcapi.v1 import agents_pb2_grpc as pb_grpc
from ._sansio import adrive, drive
from ._seq import Sequences
from .errors import McapiError, TransportError, Unavailable
from .models import ModelLike, model_json
from .retry import DEFAULT_RETRY, Attempts, RetryCounter, RetryPolicy
from .types import (
    ActionRef,
    AgentKwargs,
    AgentOptions,
    HistoryEntry,
    Observation,
    ObservationLike,
    SessionInfo,
    SessionPage,
    SessionSummary,
    Step,
    Values,
)

if TYPE_CHECKING:
    from typing_extensions import Unpack

    from .groups import AsyncVectorAgents, GroupInfo, VectorAgents

__all__ = [
    "GrpcClient",
    "Interaction",
    "BatchInteraction",
    "Watch",
    "AsyncGrpcClient",
    "AsyncInteraction",
    "AsyncBatchInteraction",
    "AsyncWatch",
    "DEFAULT_TARGET",
    "SESSION_METADATA",
    "ERROR_CODE_TRAILER",
    "rpc_error",
]

DEFAULT_TARGET = "127.0.0.1:50051"
"""Where ``mcapi serve`` listens for gRPC by default."""


def _channel_options(target: str, options: Sequence[tuple[str, Any]]) -> list[tuple[str, Any]]:
    """The channel's options: replies up to 64 MiB, and for a Unix socket
    (``unix:PATH``, the server's ``--grpc-socket``) the ``:authority``
    ``localhost``. gRPC would otherwise send the socket's path there,
    escaped, which is not a valid authority, and the server's HTTP/2 layer
    resets every call with ``PROTOCOL_ERROR``. Options given win."""
    opts: list[tuple[str, Any]] = [("grpc.max_receive_message_length", 64 << 20)]
    given = {name for name, _ in options}
    if target.startswith("unix:") and "grpc.default_authority" not in given:
        opts.append(("grpc.default_authority", "localhost"))
    return [*opts, *options]


def _stream_ended() -> Unavailable:
    return Unavailable("the server ended the stream before replying", code="stream_closed")


def _stream_error(e: grpc.RpcError) -> McapiError:
    """The error of a broken ``Interact`` stream or numbered ``Observe``. One the server did not send
    (no ``x-mcapi-error-code`` trailer) is the connection's: grpc.aio reports
    a stream cut while it writes as ``INTERNAL`` ("Internal error from
    Core"); it is a ``transport_error``, after which a numbered stream is
    reopened."""
    err = rpc_error(e)
    if err.code not in ("transport_error", "timeout", "cancelled") and not _pb.from_server(e):
        return TransportError(err.message, code="transport_error", grpc_code=err.grpc_code)
    return err


def _batch(
    entries: Iterable[tuple[str, ObservationLike]], seqs: Sequences | None
) -> pb.ObservationBatch:
    """An ``InteractBatch`` message. Its observations are not numbered (at
    least once): the client forgets the count of each session in it, to read
    it again before that session's next numbered observation."""
    msg = _pb.observation_batch(entries)
    if seqs is not None:
        for obs in msg.observations:
            seqs.forget(obs.session_id)
    return msg


class _Closing:
    """How every request stream here ends, blocking or asyncio: the request
    iterator is ended once (``None`` in the outbox), then the call is
    cancelled once, dropping replies not yet received."""

    _outbox: queue.SimpleQueue[Any] | asyncio.Queue[Any]
    _call: Any

    def __init__(self) -> None:
        self._half_closed = False
        self._closed = False

    def close(self) -> None:
        """Ends the stream: no more observations, unreceived steps are dropped."""
        if self._closed:
            return
        self._closed = True
        if not self._half_closed:
            self._half_closed = True
            self._outbox.put_nowait(None)
        self._call.cancel()


class _Stream(_Closing):
    """What both ``Interact`` streams count, number and check, with no I/O.

    With the client's ``exactly_once`` (the default), each observation sent
    takes the session's next seq, and the observations whose steps have not
    arrived yet are kept: when the stream breaks (``UNAVAILABLE``, a reset
    connection, a server restarting, a stream ended without its replies),
    it is opened again and they are sent again, from the first unanswered
    one, within the retry policy's deadline; the server replays those it had
    already applied (``Step.replayed``) and applies the others, once.
    """

    def __init__(
        self,
        stub: pb_grpc.AgentsStub,
        session_id: str,
        metadata: Metadata,
        seqs: Sequences | None,
        retry: RetryPolicy | None,
        counter: RetryCounter | None,
    ) -> None:
        super().__init__()
        self.session_id = session_id
        self._stub = stub
        self._metadata = metadata
        self._seqs = seqs
        self._retry = retry
        self._counter = counter
        self._unacked: collections.deque[pb.Observation] = collections.deque()
        self._sent = 0
        self._received = 0

    def _number(self, msg: pb.Observation) -> None:
        """Gives ``msg`` the session's next seq, if the client numbers observations."""
        if self._seqs is not None:
            _, first = self._seqs.take(self.session_id, 1)
            if first is not None:
                msg.seq = first

    def _resumable(self) -> bool:
        return self._seqs is not None and all(m.HasField("seq") for m in self._unacked)

    def _attempts(self) -> Attempts:
        return Attempts(self._retry, time.monotonic(), self._counter, f"Interact {self.session_id}")

    def _answered(self) -> None:
        self._received += 1
        msg = self._unacked.popleft()
        if self._seqs is not None and msg.HasField("seq"):
            self._seqs.answered(self.session_id, msg.seq, 1)

    def _failed(self, err: McapiError) -> None:
        """The stream failed for good: what the client now knows of the
        session's count (see :mod:`mcapi_client._seq`)."""
        if self._seqs is None or not self._unacked:
            return
        first = self._unacked[0]
        if first.HasField("seq"):
            self._seqs.failed(self.session_id, first.seq, len(self._unacked), err)
        else:
            self._seqs.forget(self.session_id)

    def close(self) -> None:
        """Ends the stream: no more observations, unreceived steps are dropped
        (the session's count is then read again before its next numbered
        observation: those may or may not have been applied)."""
        if not self._closed and self._unacked and self._seqs is not None:
            self._seqs.forget(self.session_id)
        super().close()

    @property
    def pending(self) -> int:
        """Observations sent whose steps have not been received yet."""
        return self._sent - self._received

    def _message(
        self,
        state: IntLike | None,
        stimulus: FloatsLike | None,
        action_taken: ActionRef | None,
        signal: FloatsLike | None,
        signal_source: IntLike | None,
        observation: FloatsLike | None = None,
    ) -> pb.Observation:
        if self._half_closed:
            raise RuntimeError("this interaction no longer accepts observations")
        return _pb.observation_message(
            Observation(state, stimulus, action_taken, signal, signal_source, observation=observation)
        )

    def _expect_reply(self) -> None:
        if self.pending == 0:
            raise RuntimeError("no observation is waiting for its step; send one first")


class Interaction(_Stream):
    """One ``Interact`` stream: observations in, one step out per observation, in order.

    A broken stream is reopened and its unanswered observations resent,
    transparently, when the client numbers observations (see the README's
    "Delivery"); each reopening counts in ``client.retries``.

    Get one from :meth:`GrpcClient.interact` and use it as a context manager.
    :meth:`step` sends an observation and waits for its reply (a simulation
    loop); :meth:`send` only queues one, and iterating yields the replies to
    the observations sent so far (replaying a log at full speed):

        with client.interact(session_id) as stream:
            for obs in logged:
                stream.send(obs.state, obs.stimulus)
            steps = list(stream)

    The server reads the next observation only when its bounded reply buffer
    has room, so a fast sender is held back rather than flooding it. An error
    (say an unknown state) raises its :class:`~mcapi_client.McapiError` from
    :meth:`step` or the iteration and ends the stream; the observations
    before it stay applied.
    """

    def __init__(
        self,
        stub: pb_grpc.AgentsStub,
        session_id: str,
        metadata: Metadata,
        seqs: Sequences | None = None,
        retry: RetryPolicy | None = None,
        counter: RetryCounter | None = None,
        learn: Callable[[], object] | None = None,
    ) -> None:
        super().__init__(stub, session_id, metadata, seqs, retry, counter)
        self._learn = learn
        # Before the first observation of a session whose count is not known.
        self._learning = seqs is not None and not seqs.take(session_id, 0)[0]
        self._open()

    def _open(self) -> None:
        outbox: queue.SimpleQueue[pb.Observation | None] = queue.SimpleQueue()
        for msg in self._unacked:
            outbox.put(msg)
        self._outbox = outbox
        self._call = self._stub.Interact(self._requests(outbox), metadata=self._metadata)

    def _reopen(self) -> None:
        self._outbox.put(None)
        self._call.cancel()
        self._open()

    @staticmethod
    def _requests(outbox: queue.SimpleQueue[pb.Observation | None]) -> Iterator[pb.Observation]:
        while True:
            msg = outbox.get()
            if msg is None:
                return
            yield msg

    def send(
        self,
        state: IntLike | None = None,
        stimulus: FloatsLike | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: FloatsLike | None = None,
        signal_source: IntLike | None = None,
        observation: FloatsLike | None = None,
    ) -> None:
        """Queues one observation without waiting for its step.

        Args:
            state: The state the agent is in now (numbered states).
            stimulus: What it received on arriving there; leave out on the
                session's first observation.
            action_taken: The action actually taken, by name or index, if not
                the advised one.
            signal: A raw signal sample, for a session with a curiosity
                channel (``stimulus`` is then the extrinsic part only).
            signal_source: The signal's source (server default 0).
            observation: A continuous world's observation vector, instead
                of ``state``.
        """
        msg = self._message(state, stimulus, action_taken, signal, signal_source, observation)
        if self._learning:
            if self._learn is not None:
                self._learn()  # the session's next_seq (or its error)
            self._learning = False
        self._number(msg)
        self._unacked.append(msg)
        self._outbox.put(msg)
        self._sent += 1

    def recv(self) -> Step:
        """Waits for the step of the oldest observation not yet answered
        (reopening a broken stream, see :class:`Interaction`)."""
        self._expect_reply()
        attempts: Attempts | None = None
        while True:
            cause: BaseException | None = None
            err: McapiError
            try:
                msg = next(self._call)
            except StopIteration:
                err = _stream_ended()
            except grpc.RpcError as e:
                err, cause = _stream_error(e), e
            else:
                self._answered()
                return _pb.step(msg)
            if attempts is None:
                attempts = self._attempts()
            wait = (
                attempts.next_wait(err, time.monotonic(), resend=True)
                if self._resumable() and not self._closed
                else None
            )
            if wait is None:
                self._failed(err)
                raise err from cause
            time.sleep(wait)
            self._reopen()

    def step(
        self,
        state: IntLike | None = None,
        stimulus: FloatsLike | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: FloatsLike | None = None,
        signal_source: IntLike | None = None,
        observation: FloatsLike | None = None,
    ) -> Step:
        """Sends one observation and returns its step (the next action);
        arguments as :meth:`send`."""
        self.send(
            state,
            stimulus,
            action_taken,
            signal=signal,
            signal_source=signal_source,
            observation=observation,
        )
        return self.recv()

    def __iter__(self) -> Interaction:
        return self

    def __next__(self) -> Step:
        """The next reply to an observation sent; stops when none is pending."""
        if self.pending == 0:
            raise StopIteration
        return self.recv()

    def __enter__(self) -> Interaction:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class BatchInteraction(_Closing):
    """One ``InteractBatch`` stream: several sessions stepped together, as a
    vectorised simulator steps its worlds.

    Get one from :meth:`GrpcClient.interact_batch` and use it as a context
    manager. Each :meth:`step` sends one message of ``(session_id,
    observation)`` pairs and returns one result per pair, in order: the
    :class:`~mcapi_client.Step`, or the :class:`~mcapi_client.McapiError` of
    an observation the server refused (returned, not raised: the other
    sessions' steps stand and the stream goes on):

        with client.interact_batch() as stream:
            results = stream.step([(a, (25,)), (b, (3,))])
            for r in results:
                if isinstance(r, McapiError): ...

    A session's observations in one message are applied in order; after one
    is refused, its later ones are not applied. A failure of the stream
    itself (a message with more than ``--max-batch`` observations, the
    server shutting down) raises.
    """

    def __init__(
        self, stub: pb_grpc.AgentsStub, metadata: Metadata, seqs: Sequences | None = None
    ) -> None:
        super().__init__()
        self._seqs = seqs
        self._outbox: queue.SimpleQueue[pb.ObservationBatch | None] = queue.SimpleQueue()
        self._call = stub.InteractBatch(self._requests(), metadata=metadata)

    def _requests(self) -> Iterator[pb.ObservationBatch]:
        while True:
            msg = self._outbox.get()
            if msg is None:
                return
            yield msg

    def step(
        self, entries: Iterable[tuple[str, ObservationLike]]
    ) -> list[Step | McapiError]:
        """Sends one message and returns its results, one per entry.

        Args:
            entries: ``(session_id, observation)`` pairs; an observation is
                an :class:`~mcapi_client.Observation`, a mapping or a tuple
                ``(state, stimulus[, action_taken[, signal[, signal_source]]])``.
        """
        if self._closed:
            raise RuntimeError("this interaction is closed")
        self._outbox.put(_batch(entries, self._seqs))
        try:
            msg = next(self._call)
        except StopIteration:
            raise _stream_ended() from None
        except grpc.RpcError as e:
            raise rpc_error(e) from e
        return _pb.step_results(msg)

    def __enter__(self) -> BatchInteraction:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Watch:
    """Snapshots of a session at a fixed interval, the first at once.

    An iterator of :class:`~mcapi_client.types.SessionInfo`; iteration ends
    when the session is deleted or :meth:`cancel` is called. Use it as a
    context manager so the stream is cancelled when you stop reading.
    """

    def __init__(self, call: Any) -> None:
        self._call = call
        self._seen = 0
        self._cancelled = False

    def __iter__(self) -> Watch:
        return self

    def __next__(self) -> SessionInfo:
        """The next snapshot (waits for the interval)."""
        if self._cancelled:
            raise StopIteration
        try:
            msg = next(self._call)
        except grpc.RpcError as e:
            err = rpc_error(e)
            if _pb.watch_ends(err, self._seen, self._cancelled):
                raise StopIteration from None
            raise err from e
        self._seen += 1
        return _pb.session_info(msg)

    def cancel(self) -> None:
        """Stops the stream."""
        self._cancelled = True
        self._call.cancel()

    def __enter__(self) -> Watch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.cancel()


def _group_create_call(model: ModelLike, n: IntLike, agent: AgentKwargs) -> Call:
    """The ``CreateGroup`` call: ``agent`` without ``seed``, which is the group's."""
    rest = agent.copy()
    seed = rest.pop("seed", None)
    request = _pb.create_request(model_json(model), AgentOptions(**rest))
    if not request.HasField("model"):
        raise ValueError("a group's model must be one the typed gRPC `Model` carries")
    msg = pb.CreateGroupRequest(model=request.model, agent=request.agent, n=as_int(n, "n"))
    if seed is not None:
        msg.seed = as_int(seed, "seed")
    return Call("CreateGroup", msg)


class GrpcClient:
    """A client of the mcapi gRPC API (service ``mcapi.v1.Agents``).

    Args:
        target: ``host:port`` of the server's gRPC listener, or
            ``unix:PATH`` for its Unix socket (``mcapi serve --grpc-socket``).
        api_key: Sent as ``authorization: Bearer <key>`` metadata.
        timeout: Seconds per unary call (streams have none).
        credentials: TLS channel credentials; plaintext when ``None``.
        options: Extra channel options, e.g. ``[("grpc.max_receive_message_length", n)]``.
        retry: Which failures of unary calls to retry and for how long (a
            cluster's ``wrong_replica``, ``shard_moving``, ``unavailable``;
            for numbered observations also a lost answer and a broken
            ``interact`` stream; see :mod:`mcapi_client.retry`); ``None``: never.
        exactly_once: Number each session's observations (``seq``) so that
            a resend after a lost answer is applied once (see the README's
            "Delivery"); ``False``: unnumbered, at least once.

    Attributes:
        retries: The retries made so far, by reason
            (:class:`~mcapi_client.RetryCounter`).

    Offers the REST client's operations, with the same results. Use as a
    context manager, or call :meth:`close`.
    """

    def __init__(
        self,
        target: str = DEFAULT_TARGET,
        api_key: str | None = None,
        timeout: float | None = 30.0,
        *,
        credentials: grpc.ChannelCredentials | None = None,
        options: Sequence[tuple[str, Any]] = (),
        retry: RetryPolicy | None = DEFAULT_RETRY,
        exactly_once: bool = True,
    ) -> None:
        self.target = target
        self.retry = retry
        self.retries = RetryCounter()
        opts = _channel_options(target, options)
        self._channel = (
            grpc.secure_channel(target, credentials, options=opts)
            if credentials is not None
            else grpc.insecure_channel(target, options=opts)
        )
        self._stub = pb_grpc.AgentsStub(self._channel)  # type: ignore[no-untyped-call]
        self._timeout = timeout
        self._protocol = _pb.GrpcProtocol(api_key, exactly_once)

    def close(self) -> None:
        """Closes the channel (and with it any open stream)."""
        self._channel.close()

    def __enter__(self) -> GrpcClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send(self, call: Call) -> Any:
        method = getattr(self._stub, call.rpc)
        metadata = self._protocol.metadata(call.session_id)
        attempts = Attempts(self.retry, time.monotonic(), self.retries, call.rpc)
        while True:
            try:
                return method(call.request, metadata=metadata, timeout=self._timeout)
            except grpc.RpcError as e:
                err: McapiError = _stream_error(e) if call.resend else rpc_error(e)
                wait = attempts.next_wait(err, time.monotonic(), resend=call.resend)
                if wait is None:
                    raise err from e
            time.sleep(wait)

    def ready(self, timeout: float = 1.0) -> bool:
        """Whether the channel connects within ``timeout`` seconds."""
        try:
            grpc.channel_ready_future(self._channel).result(timeout=timeout)
        except grpc.FutureTimeoutError:
            return False
        return True

    def create_session(self, model: ModelLike, **agent: Unpack[AgentKwargs]) -> SessionInfo:
        """Creates a session; arguments as :meth:`mcapi_client.Client.create_session`."""
        options = AgentOptions(**agent)
        return drive(self._protocol.create_session(model, options), self._send)

    def create_group(
        self,
        model: ModelLike,
        n: IntLike,
        **agent: Unpack[AgentKwargs],
    ) -> VectorAgents:
        """Creates a group of ``n`` sessions of one model and configuration
        (``CreateGroup``) and opens its ``StepGroup`` stream.

        Args:
            model: Every member's model.
            n: Members, 1 to the server's ``--max-group-members``.
            agent: Every member's configuration, as
                :meth:`mcapi_client.Client.create_session` takes it, except
                ``seed``: it is the group's (member i's is
                :func:`mcapi_client.groups.member_seed` of it; drawn when
                absent).

        Needs the ``vector`` extra (numpy).
        """
        from . import _group_grpc

        info = _group_grpc.group_info(self._send(_group_create_call(model, n, agent)))
        seqs = self._protocol.group_seqs(info, created=True)
        return _group_grpc.VectorAgents(self._stub, info, self._protocol.metadata(), seqs)

    def get_group(self, group_id: str) -> GroupInfo:
        """A group: its seed, shape and member session ids (``GetGroup``)."""
        from . import _group_grpc

        reply = self._send(Call("GetGroup", pb.GetGroupRequest(group_id=group_id), group_id))
        return _group_grpc.group_info(reply)

    def vector_agents(self, group_id: str) -> VectorAgents:
        """Opens a ``StepGroup`` stream on an existing group."""
        from . import _group_grpc

        info = self.get_group(group_id)
        seqs = self._protocol.group_seqs(info)
        return _group_grpc.VectorAgents(self._stub, info, self._protocol.metadata(), seqs)

    def delete_group(self, group_id: str) -> None:
        """Deletes every member of a group, then the group (``DeleteGroup``)."""
        self._send(Call("DeleteGroup", pb.DeleteGroupRequest(group_id=group_id), group_id))
        self._protocol.forget_group(group_id)

    def get_session(self, session_id: str) -> SessionInfo:
        """A session's drive, tick, policy version, model, configuration and statistics."""
        return drive(self._protocol.get_session(session_id), self._send)

    def list_sessions(self, after: str | None = None, limit: IntLike | None = None) -> SessionPage:
        """One page of sessions in id order.

        Args:
            after: Start after this id (the ``next`` of the previous page).
            limit: Page size, 1 to 1000 (server default 100).
        """
        return drive(self._protocol.list_sessions(after, limit), self._send)

    def iter_sessions(self, page_size: IntLike = 100) -> Iterator[SessionSummary]:
        """Every session in id order, fetching pages of ``page_size`` as needed."""
        after: str | None = None
        while True:
            page = self.list_sessions(after=after, limit=page_size)
            yield from page.sessions
            if page.next is None:
                return
            after = page.next

    def delete_session(self, session_id: str) -> None:
        """Deletes a session."""
        drive(self._protocol.delete_session(session_id), self._send)

    def observe(
        self,
        session_id: str,
        state: IntLike | None = None,
        stimulus: FloatsLike | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: FloatsLike | None = None,
        signal_source: IntLike | None = None,
        observation: FloatsLike | None = None,
        seq: IntLike | None = None,
    ) -> Step:
        """Reports one observation (unary ``Observe``) and returns the next
        action; arguments as :meth:`mcapi_client.Client.observe`.

        For a loop of many observations, :meth:`interact` saves a round of
        call set-up per tick.
        """
        obs = Observation(
            state, stimulus, action_taken, signal, signal_source, observation=observation, seq=seq
        )
        return drive(self._protocol.observe(session_id, obs), self._send)

    def observe_batch(
        self, session_id: str, observations: Iterable[ObservationLike]
    ) -> list[Step]:
        """Applies observations in order; one step each (see the REST client)."""
        return drive(self._protocol.observe_batch(session_id, observations), self._send)

    def values(self, session_id: str, include: str | Iterable[str] | None = None) -> Values:
        """Value tables of a session, shaped as the REST client returns them.

        Args:
            session_id: The session.
            include: Tables among ``v``, ``q``, ``policy``, ``r``, ``xi``, or
                ``all``; default ``v`` and ``policy``.
        """
        return drive(self._protocol.values(session_id, include), self._send)

    def history(self, session_id: str, limit: IntLike | None = None) -> list[HistoryEntry]:
        """The most recent ticks of a session (at most ``limit``), oldest first
        (``GetHistory``); the same entries as :meth:`mcapi_client.Client.history`."""
        return drive(self._protocol.history(session_id, limit), self._send)

    def interact(self, session_id: str) -> Interaction:
        """Opens an ``Interact`` stream on a session; see :class:`Interaction`.
        For a session this client has neither created nor read, its
        ``next_seq`` is read before the first observation (numbered by default)."""
        return Interaction(
            self._stub,
            session_id,
            self._protocol.metadata(session_id),
            self._protocol.seqs,
            self.retry,
            self.retries,
            lambda: self.get_session(session_id),
        )

    def interact_batch(self) -> BatchInteraction:
        """Opens an ``InteractBatch`` stream (several sessions per message);
        see :class:`BatchInteraction`. Its observations are not numbered."""
        return BatchInteraction(self._stub, self._protocol.metadata(), self._protocol.seqs)

    def watch(self, session_id: str, interval: FloatLike = 1.0) -> Watch:
        """Snapshots of a session every ``interval`` seconds (0.01 to 3600),
        the first at once; see :class:`Watch`.

        Raises:
            ValueError: The interval is out of range.
        """
        request = _pb.watch_request(session_id, interval)
        return Watch(self._stub.Watch(request, metadata=self._protocol.metadata(session_id)))


class AsyncInteraction(_Stream):
    """One ``Interact`` stream under asyncio; :class:`Interaction`'s twin.

    Get one from :meth:`AsyncGrpcClient.interact` and use it with ``async
    with``. :meth:`send` queues an observation and returns at once (like
    ``asyncio.StreamWriter.write``, it is not awaited); :meth:`recv` and
    :meth:`step` are awaited, and ``async for`` yields the replies to the
    observations sent so far:

        async with client.interact(session_id) as stream:
            step = await stream.step(3)
            for obs in logged:
                stream.send(obs.state, obs.stimulus)
            steps = [s async for s in stream]

    Errors end the stream, and a broken stream is reopened, as in
    :class:`Interaction`. For a session this client has neither created nor
    read, the stream reads the session's ``next_seq`` before its first
    observation goes out.
    """

    def __init__(
        self,
        stub: pb_grpc.AgentsStub,
        session_id: str,
        metadata: Metadata,
        seqs: Sequences | None = None,
        retry: RetryPolicy | None = None,
        counter: RetryCounter | None = None,
        learn: Callable[[], Awaitable[object]] | None = None,
    ) -> None:
        super().__init__(stub, session_id, metadata, seqs, retry, counter)
        self._learn = learn
        # Observations are numbered once the session's count is known.
        self._learning = seqs is not None and not seqs.take(session_id, 0)[0]
        self._learn_error: McapiError | None = None
        self._open()

    def _open(self) -> None:
        outbox: asyncio.Queue[pb.Observation | None] = asyncio.Queue()
        for msg in self._unacked:
            outbox.put_nowait(msg)
        self._outbox = outbox
        self._call = self._stub.Interact(self._requests(outbox), metadata=self._metadata)

    def _reopen(self) -> None:
        self._outbox.put_nowait(None)
        self._call.cancel()
        self._open()

    async def _requests(
        self, outbox: asyncio.Queue[pb.Observation | None]
    ) -> AsyncIterator[pb.Observation]:
        while True:
            msg = await outbox.get()
            if msg is None:
                return
            if self._learning:
                try:
                    await self._number_all()
                except McapiError as e:
                    self._learn_error = e
                    return  # ends the stream: recv raises the error
            yield msg

    async def _number_all(self) -> None:
        """Reads the session's count, then numbers every observation sent so far."""
        if self._learn is not None:
            await self._learn()
        self._learning = False
        for m in self._unacked:
            if not m.HasField("seq"):
                self._number(m)

    def send(
        self,
        state: IntLike | None = None,
        stimulus: FloatsLike | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: FloatsLike | None = None,
        signal_source: IntLike | None = None,
        observation: FloatsLike | None = None,
    ) -> None:
        """Queues one observation without waiting for its step (not awaited);
        arguments as :meth:`Interaction.send`."""
        msg = self._message(state, stimulus, action_taken, signal, signal_source, observation)
        if not self._learning:
            self._number(msg)
        self._unacked.append(msg)
        self._outbox.put_nowait(msg)
        self._sent += 1

    async def recv(self) -> Step:
        """Waits for the step of the oldest observation not yet answered
        (reopening a broken stream, see :class:`Interaction`)."""
        self._expect_reply()
        attempts: Attempts | None = None
        while True:
            cause: BaseException | None = None
            err: McapiError
            try:
                msg = await self._call.read()
            except grpc.RpcError as e:
                err, cause = _stream_error(e), e
            else:
                if msg is not grpc.aio.EOF:
                    self._answered()
                    return _pb.step(msg)
                err = self._learn_error or _stream_ended()
            if attempts is None:
                attempts = self._attempts()
            wait = (
                attempts.next_wait(err, time.monotonic(), resend=True)
                if self._learn_error is None and self._resumable() and not self._closed
                else None
            )
            if wait is None:
                self._failed(err)
                raise err from cause
            await asyncio.sleep(wait)
            self._reopen()

    async def step(
        self,
        state: IntLike | None = None,
        stimulus: FloatsLike | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: FloatsLike | None = None,
        signal_source: IntLike | None = None,
        observation: FloatsLike | None = None,
    ) -> Step:
        """Sends one observation and returns its step (the next action);
        arguments as :meth:`Interaction.send`."""
        self.send(
            state,
            stimulus,
            action_taken,
            signal=signal,
            signal_source=signal_source,
            observation=observation,
        )
        return await self.recv()

    def __aiter__(self) -> AsyncInteraction:
        return self

    async def __anext__(self) -> Step:
        """The next reply to an observation sent; stops when none is pending."""
        if self.pending == 0:
            raise StopAsyncIteration
        return await self.recv()

    async def __aenter__(self) -> AsyncInteraction:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


class AsyncBatchInteraction(_Closing):
    """One ``InteractBatch`` stream under asyncio; :class:`BatchInteraction`'s twin.

        async with client.interact_batch() as stream:
            results = await stream.step([(a, (25,)), (b, (3,))])
    """

    def __init__(
        self, stub: pb_grpc.AgentsStub, metadata: Metadata, seqs: Sequences | None = None
    ) -> None:
        super().__init__()
        self._seqs = seqs
        self._outbox: asyncio.Queue[pb.ObservationBatch | None] = asyncio.Queue()
        self._call = stub.InteractBatch(self._requests(), metadata=metadata)

    async def _requests(self) -> AsyncIterator[pb.ObservationBatch]:
        while True:
            msg = await self._outbox.get()
            if msg is None:
                return
            yield msg

    async def step(
        self, entries: Iterable[tuple[str, ObservationLike]]
    ) -> list[Step | McapiError]:
        """Sends one message and returns its results; see :meth:`BatchInteraction.step`."""
        if self._closed:
            raise RuntimeError("this interaction is closed")
        self._outbox.put_nowait(_batch(entries, self._seqs))
        try:
            msg = await self._call.read()
        except grpc.RpcError as e:
            raise rpc_error(e) from e
        if msg is grpc.aio.EOF:
            raise _stream_ended()
        return _pb.step_results(msg)

    async def __aenter__(self) -> AsyncBatchInteraction:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


class AsyncWatch:
    """Snapshots of a session under asyncio (``async for``); :class:`Watch`'s twin.

    Iteration ends when the session is deleted or :meth:`cancel` is called;
    use it with ``async with`` so the stream is cancelled when you stop.
    """

    def __init__(self, call: Any) -> None:
        self._call = call
        self._seen = 0
        self._cancelled = False

    def __aiter__(self) -> AsyncWatch:
        return self

    async def __anext__(self) -> SessionInfo:
        """The next snapshot (waits for the interval)."""
        if self._cancelled:
            raise StopAsyncIteration
        try:
            msg = await self._call.read()
        except asyncio.CancelledError:
            if self._cancelled or self._call.cancelled():
                raise StopAsyncIteration from None
            raise
        except grpc.RpcError as e:
            err = rpc_error(e)
            if _pb.watch_ends(err, self._seen, self._cancelled):
                raise StopAsyncIteration from None
            raise err from e
        if msg is grpc.aio.EOF:
            raise StopAsyncIteration
        self._seen += 1
        return _pb.session_info(msg)

    def cancel(self) -> None:
        """Stops the stream."""
        self._cancelled = True
        self._call.cancel()

    async def __aenter__(self) -> AsyncWatch:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.cancel()


class AsyncGrpcClient:
    """An asyncio client of the mcapi gRPC API over ``grpc.aio``, with the
    methods of :class:`GrpcClient` (awaited) and the same results and errors.

    Args:
        target: ``host:port`` of the server's gRPC listener, or
            ``unix:PATH`` for its Unix socket (``mcapi serve --grpc-socket``).
        api_key: Sent as ``authorization: Bearer <key>`` metadata.
        timeout: Seconds per unary call (streams have none).
        credentials: TLS channel credentials; plaintext when ``None``.
        options: Extra channel options.
        retry: As :class:`GrpcClient`'s.
        exactly_once: As :class:`GrpcClient`'s.

    Attributes:
        retries: The retries made so far, by reason.

    Create it inside the event loop that uses it (``grpc.aio`` channels
    belong to one loop), as ``async with AsyncGrpcClient(...) as mc:``, or
    call :meth:`aclose`. ``grpc.aio`` completes a cancelled stream's call on
    its loop a moment later; a program that closes that loop at once and then
    runs another (two ``asyncio.run`` in one process) may see gRPC log
    "Event loop is closed" from the second loop.
    """

    def __init__(
        self,
        target: str = DEFAULT_TARGET,
        api_key: str | None = None,
        timeout: float | None = 30.0,
        *,
        credentials: grpc.ChannelCredentials | None = None,
        options: Sequence[tuple[str, Any]] = (),
        retry: RetryPolicy | None = DEFAULT_RETRY,
        exactly_once: bool = True,
    ) -> None:
        self.target = target
        self.retry = retry
        self.retries = RetryCounter()
        opts = _channel_options(target, options)
        self._channel = (
            grpc.aio.secure_channel(target, credentials, options=opts)
            if credentials is not None
            else grpc.aio.insecure_channel(target, options=opts)
        )
        self._stub = pb_grpc.AgentsStub(self._channel)  # type: ignore[no-untyped-call]
        self._timeout = timeout
        self._protocol = _pb.GrpcProtocol(api_key, exactly_once)

    async def aclose(self) -> None:
        """Closes the channel (and with it any open stream)."""
        await self._channel.close()

    async def __aenter__(self) -> AsyncGrpcClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _send(self, call: Call) -> Any:
        method = getattr(self._stub, call.rpc)
        metadata = self._protocol.metadata(call.session_id)
        attempts = Attempts(self.retry, time.monotonic(), self.retries, call.rpc)
        while True:
            try:
                return await method(call.request, metadata=metadata, timeout=self._timeout)
            except grpc.RpcError as e:
                err: McapiError = _stream_error(e) if call.resend else rpc_error(e)
                wait = attempts.next_wait(err, time.monotonic(), resend=call.resend)
                if wait is None:
                    raise err from e
            await asyncio.sleep(wait)

    async def ready(self, timeout: float = 1.0) -> bool:
        """Whether the channel connects within ``timeout`` seconds."""
        # Polled rather than awaited with grpc.aio's channel_ready(): that
        # leaves a connectivity watch pending in gRPC's core when it times
        # out, whose completion later lands on this event loop, perhaps
        # closed by then ("Event loop is closed" in another loop's callback).
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            state = self._channel.get_state(try_to_connect=True)
            if state == grpc.ChannelConnectivity.READY:
                return True
            if loop.time() >= deadline:
                return False
            await asyncio.sleep(min(0.01, max(0.0, deadline - loop.time())))

    async def create_session(self, model: ModelLike, **agent: Unpack[AgentKwargs]) -> SessionInfo:
        """Creates a session; arguments as :meth:`mcapi_client.Client.create_session`."""
        options = AgentOptions(**agent)
        return await adrive(self._protocol.create_session(model, options), self._send)

    async def create_group(
        self,
        model: ModelLike,
        n: IntLike,
        **agent: Unpack[AgentKwargs],
    ) -> AsyncVectorAgents:
        """Creates a group of ``n`` sessions and opens its ``StepGroup``
        stream; arguments as :meth:`GrpcClient.create_group`. Needs the
        ``vector`` extra (numpy)."""
        from . import _group_grpc

        info = _group_grpc.group_info(await self._send(_group_create_call(model, n, agent)))
        seqs = self._protocol.group_seqs(info, created=True)
        return _group_grpc.AsyncVectorAgents(self._stub, info, self._protocol.metadata(), seqs)

    async def get_group(self, group_id: str) -> GroupInfo:
        """A group: its seed, shape and member session ids (``GetGroup``)."""
        from . import _group_grpc

        reply = await self._send(Call("GetGroup", pb.GetGroupRequest(group_id=group_id), group_id))
        return _group_grpc.group_info(reply)

    async def vector_agents(self, group_id: str) -> AsyncVectorAgents:
        """Opens a ``StepGroup`` stream on an existing group (awaited: it reads
        the group first)."""
        from . import _group_grpc

        info = await self.get_group(group_id)
        seqs = self._protocol.group_seqs(info)
        return _group_grpc.AsyncVectorAgents(self._stub, info, self._protocol.metadata(), seqs)

    async def delete_group(self, group_id: str) -> None:
        """Deletes every member of a group, then the group (``DeleteGroup``)."""
        await self._send(Call("DeleteGroup", pb.DeleteGroupRequest(group_id=group_id), group_id))
        self._protocol.forget_group(group_id)

    async def get_session(self, session_id: str) -> SessionInfo:
        """A session's details; see :meth:`GrpcClient.get_session`."""
        return await adrive(self._protocol.get_session(session_id), self._send)

    async def list_sessions(
        self, after: str | None = None, limit: IntLike | None = None
    ) -> SessionPage:
        """One page of sessions in id order; see :meth:`GrpcClient.list_sessions`."""
        return await adrive(self._protocol.list_sessions(after, limit), self._send)

    async def iter_sessions(self, page_size: IntLike = 100) -> AsyncIterator[SessionSummary]:
        """Every session in id order (``async for``), a page at a time."""
        after: str | None = None
        while True:
            page = await self.list_sessions(after=after, limit=page_size)
            for s in page.sessions:
                yield s
            if page.next is None:
                return
            after = page.next

    async def delete_session(self, session_id: str) -> None:
        """Deletes a session."""
        await adrive(self._protocol.delete_session(session_id), self._send)

    async def observe(
        self,
        session_id: str,
        state: IntLike | None = None,
        stimulus: FloatsLike | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: FloatsLike | None = None,
        signal_source: IntLike | None = None,
        observation: FloatsLike | None = None,
        seq: IntLike | None = None,
    ) -> Step:
        """Reports one observation (unary ``Observe``); see :meth:`GrpcClient.observe`."""
        obs = Observation(
            state, stimulus, action_taken, signal, signal_source, observation=observation, seq=seq
        )
        return await adrive(self._protocol.observe(session_id, obs), self._send)

    async def observe_batch(
        self, session_id: str, observations: Iterable[ObservationLike]
    ) -> list[Step]:
        """Applies observations in order; see :meth:`GrpcClient.observe_batch`."""
        return await adrive(self._protocol.observe_batch(session_id, observations), self._send)

    async def values(
        self, session_id: str, include: str | Iterable[str] | None = None
    ) -> Values:
        """Value tables; see :meth:`GrpcClient.values`."""
        return await adrive(self._protocol.values(session_id, include), self._send)

    async def history(self, session_id: str, limit: IntLike | None = None) -> list[HistoryEntry]:
        """Recent ticks, oldest first; see :meth:`GrpcClient.history`."""
        return await adrive(self._protocol.history(session_id, limit), self._send)

    def interact(self, session_id: str) -> AsyncInteraction:
        """Opens an ``Interact`` stream on a session; see :class:`AsyncInteraction`."""
        return AsyncInteraction(
            self._stub,
            session_id,
            self._protocol.metadata(session_id),
            self._protocol.seqs,
            self.retry,
            self.retries,
            lambda: self.get_session(session_id),
        )

    def interact_batch(self) -> AsyncBatchInteraction:
        """Opens an ``InteractBatch`` stream; see :class:`AsyncBatchInteraction`.
        Its observations are not numbered."""
        return AsyncBatchInteraction(self._stub, self._protocol.metadata(), self._protocol.seqs)

    def watch(self, session_id: str, interval: FloatLike = 1.0) -> AsyncWatch:
        """Snapshots of a session every ``interval`` seconds (0.01 to 3600),
        the first at once; see :class:`AsyncWatch`.

        Raises:
            ValueError: The interval is out of range.
        """
        request = _pb.watch_request(session_id, interval)
        return AsyncWatch(self._stub.Watch(request, metadata=self._protocol.metadata(session_id)))
