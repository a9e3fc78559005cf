"""The gRPC client: :class:`GrpcClient`, with the REST client's operations,
the bidirectional :meth:`~GrpcClient.interact` stream for high-rate loops and
the :meth:`~GrpcClient.watch` stream of snapshots.

    from mcapi_client import GrpcClient, models

    world = models.hallway()
    with GrpcClient("127.0.0.1:50051") as mc:
        session = mc.create_session(world, seed=7)
        with mc.interact(session.id) as stream:
            step = stream.step(25)                       # first: state only
            for _ in range(1000):
                state = ...                              # apply step.action
                step = stream.step(state, world.stimulus(state))

Each call names its session in the ``x-mcapi-session`` metadata (routers
read it; the server checks it against the message), and sends the API key as
``authorization: Bearer <key>``. Errors are the same
:class:`~mcapi_client.McapiError` subclasses as over REST, read from the
status and the ``x-mcapi-error-code`` trailer.
"""

from __future__ import annotations

import queue
from collections.abc import Iterable, Iterator, Sequence
from types import TracebackType
from typing import Any

import grpc

from . import _pb
from ._proto.mcapi.v1 import agents_pb2 as pb
from ._proto.mcapi.v1 import agents_pb2_grpc as pb_grpc
from .errors import McapiError, Timeout, TransportError, Unavailable, error_for
from .rest import ModelLike, agent_options, model_json
from .types import (
    ActionRef,
    CuriosityLike,
    HistoryEntry,
    ObservationLike,
    SessionInfo,
    SessionPage,
    SessionSummary,
    Step,
    StimulusRate,
    UpdateMode,
    Values,
    as_observation,
)

__all__ = ["GrpcClient", "Interaction", "Watch", "DEFAULT_TARGET", "SESSION_METADATA"]

DEFAULT_TARGET = "127.0.0.1:50051"
"""Where ``mcapi serve`` listens for gRPC by default."""

SESSION_METADATA = "x-mcapi-session"
"""Metadata key naming the session a call concerns."""

ERROR_CODE_TRAILER = "x-mcapi-error-code"
"""Trailer carrying the server's stable error code."""

_Metadata = tuple[tuple[str, str], ...]


def rpc_error(e: grpc.RpcError) -> McapiError:
    """The :class:`McapiError` for a failed gRPC call or stream."""
    code = e.code() if isinstance(e, grpc.Call) else None
    name = code.name if code is not None else "UNKNOWN"
    message = (e.details() if isinstance(e, grpc.Call) else None) or str(e)
    stable = None
    if isinstance(e, grpc.Call):
        for key, value in e.trailing_metadata() or ():
            if key == ERROR_CODE_TRAILER:
                stable = value if isinstance(value, str) else value.decode()
    if stable is None:
        # No answer from mcapi itself: the network or the client gave up.
        if code == grpc.StatusCode.UNAVAILABLE:
            return TransportError(message, code="transport_error", grpc_code=name)
        if code == grpc.StatusCode.DEADLINE_EXCEEDED:
            return Timeout(message, code="timeout", grpc_code=name)
        if code == grpc.StatusCode.CANCELLED:
            return McapiError(message, code="cancelled", grpc_code=name)
    return error_for(stable, message, grpc_code=name)


class Interaction:
    """One ``Interact`` stream: observations in, one step out per observation, in order.

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

    def __init__(self, stub: pb_grpc.AgentsStub, session_id: str, metadata: _Metadata) -> None:
        self.session_id = session_id
        self._outbox: queue.SimpleQueue[pb.Observation | None] = queue.SimpleQueue()
        self._sent = 0
        self._received = 0
        self._half_closed = False
        self._closed = False
        self._call = stub.Interact(self._requests(), metadata=metadata)

    def _requests(self) -> Iterator[pb.Observation]:
        while True:
            msg = self._outbox.get()
            if msg is None:
                return
            yield msg

    @property
    def pending(self) -> int:
        """Observations sent whose steps have not been received yet."""
        return self._sent - self._received

    def send(
        self,
        state: int,
        stimulus: Sequence[float] | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: Sequence[float] | None = None,
        signal_source: int | None = None,
    ) -> None:
        """Queues one observation without waiting for its step.

        Args:
            state: The state the agent is in now.
            stimulus: What it received on arriving there; leave out on the
                session's first observation.
            action_taken: The action actually taken, by name or index, if not
                the advised one.
            signal: A raw signal sample, for a session with a curiosity
                channel (``stimulus`` is then the extrinsic part only).
            signal_source: The signal's source (server default 0).
        """
        if self._half_closed:
            raise RuntimeError("this interaction no longer accepts observations")
        self._outbox.put(
            _pb.observation(
                state, stimulus, action_taken, signal=signal, signal_source=signal_source
            )
        )
        self._sent += 1

    def recv(self) -> Step:
        """Waits for the step of the oldest observation not yet answered."""
        if self.pending == 0:
            raise RuntimeError("no observation is waiting for its step; send one first")
        try:
            msg = next(self._call)
        except StopIteration:
            raise Unavailable(
                "the server ended the stream before replying", code="stream_closed"
            ) from None
        except grpc.RpcError as e:
            raise rpc_error(e) from e
        self._received += 1
        return _pb.step(msg)

    def step(
        self,
        state: int,
        stimulus: Sequence[float] | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: Sequence[float] | None = None,
        signal_source: int | None = None,
    ) -> Step:
        """Sends one observation and returns its step (the next action);
        arguments as :meth:`send`."""
        self.send(state, stimulus, action_taken, signal=signal, signal_source=signal_source)
        return self.recv()

    def __iter__(self) -> Interaction:
        return self

    def __next__(self) -> Step:
        """The next reply to an observation sent; stops when none is pending."""
        if self.pending == 0:
            raise StopIteration
        return self.recv()

    def close(self) -> None:
        """Ends the stream: no more observations, unreceived steps are dropped."""
        if self._closed:
            return
        self._closed = True
        if not self._half_closed:
            self._half_closed = True
            self._outbox.put(None)
        self._call.cancel()

    def __enter__(self) -> Interaction:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
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
            if self._cancelled or err.code == "cancelled":
                raise StopIteration from None
            if self._seen and err.code == "not_found":
                raise StopIteration from None  # deleted while watched
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


class GrpcClient:
    """A client of the mcapi gRPC API (service ``mcapi.v1.Agents``).

    Args:
        target: ``host:port`` of the server's gRPC listener.
        api_key: Sent as ``authorization: Bearer <key>`` metadata.
        timeout: Seconds per unary call (streams have none).
        credentials: TLS channel credentials; plaintext when ``None``.
        options: Extra channel options, e.g. ``[("grpc.max_receive_message_length", n)]``.

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
    ) -> None:
        self.target = target
        opts = [("grpc.max_receive_message_length", 64 << 20), *options]
        self._channel = (
            grpc.secure_channel(target, credentials, options=opts)
            if credentials is not None
            else grpc.insecure_channel(target, options=opts)
        )
        self._stub = pb_grpc.AgentsStub(self._channel)  # type: ignore[no-untyped-call]
        self._timeout = timeout
        self._auth: _Metadata = (
            (("authorization", f"Bearer {api_key}"),) if api_key is not None else ()
        )
        # (states, action names) per session, to make per-pair value tables
        # dense and to name the actions of history entries.
        self._shapes: dict[str, tuple[int, list[str]]] = {}

    def close(self) -> None:
        """Closes the channel (and with it any open stream)."""
        self._channel.close()

    def __enter__(self) -> GrpcClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _metadata(self, session_id: str | None = None) -> _Metadata:
        if session_id is None:
            return self._auth
        return ((SESSION_METADATA, session_id), *self._auth)

    def _unary(self, method: Any, request: Any, session_id: str | None = None) -> Any:
        try:
            return method(request, metadata=self._metadata(session_id), timeout=self._timeout)
        except grpc.RpcError as e:
            raise rpc_error(e) from e

    def _remember(self, info: SessionInfo) -> SessionInfo:
        self._shapes.pop(info.id, None)
        self._shapes[info.id] = (info.model.states, info.model.actions)
        while len(self._shapes) > 1024:
            del self._shapes[next(iter(self._shapes))]
        return info

    def ready(self, timeout: float = 1.0) -> bool:
        """Whether the channel connects within ``timeout`` seconds."""
        try:
            grpc.channel_ready_future(self._channel).result(timeout=timeout)
        except grpc.FutureTimeoutError:
            return False
        return True

    def create_session(
        self,
        model: ModelLike,
        *,
        eta: float | None = None,
        gamma: float | None = None,
        priorities: Sequence[float] | None = None,
        stimulus_rate: StimulusRate | None = None,
        optimistic_sd: float | None = None,
        ridge: float | None = None,
        epsilon: float | None = None,
        seed: int | None = None,
        update_mode: UpdateMode | None = None,
        history: int | None = None,
        curiosity: CuriosityLike | None = None,
    ) -> SessionInfo:
        """Creates a session; arguments as :meth:`mcapi_client.Client.create_session`."""
        agent = agent_options(
            eta=eta, gamma=gamma, priorities=priorities, stimulus_rate=stimulus_rate,
            optimistic_sd=optimistic_sd, ridge=ridge, epsilon=epsilon, seed=seed,
            update_mode=update_mode, history=history, curiosity=curiosity,
        )
        request = _pb.create_request(model_json(model), agent)
        return self._remember(_pb.session_info(self._unary(self._stub.CreateSession, request)))

    def get_session(self, session_id: str) -> SessionInfo:
        """A session's drive, tick, policy version, model, configuration and statistics."""
        request = pb.GetSessionRequest(session_id=session_id)
        return self._remember(
            _pb.session_info(self._unary(self._stub.GetSession, request, session_id))
        )

    def list_sessions(self, after: str | None = None, limit: int | None = None) -> SessionPage:
        """One page of sessions in id order.

        Args:
            after: Start after this id (the ``next`` of the previous page).
            limit: Page size, 1 to 1000 (server default 100).
        """
        request = pb.ListSessionsRequest(after=after, limit=limit)
        return _pb.session_page(self._unary(self._stub.ListSessions, request))

    def iter_sessions(self, page_size: int = 100) -> Iterator[SessionSummary]:
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
        request = pb.DeleteSessionRequest(session_id=session_id)
        self._unary(self._stub.DeleteSession, request, session_id)
        self._shapes.pop(session_id, None)

    def observe(
        self,
        session_id: str,
        state: int,
        stimulus: Sequence[float] | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: Sequence[float] | None = None,
        signal_source: int | None = None,
    ) -> Step:
        """Reports one observation (unary ``Observe``) and returns the next
        action; arguments as :meth:`mcapi_client.Client.observe`.

        For a loop of many observations, :meth:`interact` saves a round of
        call set-up per tick.
        """
        request = pb.ObserveRequest(
            session_id=session_id,
            observations=[
                _pb.observation(
                    state, stimulus, action_taken, signal=signal, signal_source=signal_source
                )
            ],
        )
        reply = self._unary(self._stub.Observe, request, session_id)
        return _pb.step(reply.steps[0])

    def observe_batch(
        self, session_id: str, observations: Iterable[ObservationLike]
    ) -> list[Step]:
        """Applies observations in order; one step each (see the REST client)."""
        request = pb.ObserveRequest(
            session_id=session_id,
            observations=_pb.observations(as_observation(o) for o in observations),
        )
        reply = self._unary(self._stub.Observe, request, session_id)
        return [_pb.step(s) for s in reply.steps]

    def values(self, session_id: str, include: str | Iterable[str] | None = None) -> Values:
        """Value tables of a session, shaped as the REST client returns them.

        Args:
            session_id: The session.
            include: Tables among ``v``, ``q``, ``policy``, ``r``, ``xi``, or
                ``all``; default ``v`` and ``policy``.
        """
        tables = [include] if isinstance(include, str) else list(include or [])
        tables = [t.strip() for part in tables for t in part.split(",") if t.strip()]
        request = pb.GetValuesRequest(session_id=session_id, include=tables)
        reply = self._unary(self._stub.GetValues, request, session_id)
        states, actions = self._shape(session_id)
        return _pb.values(reply, states, len(actions))

    def history(self, session_id: str, limit: int | None = None) -> list[HistoryEntry]:
        """The most recent ticks of a session (at most ``limit``), oldest first
        (``GetHistory``); the same entries as :meth:`mcapi_client.Client.history`."""
        request = pb.GetHistoryRequest(session_id=session_id, limit=limit)
        reply = self._unary(self._stub.GetHistory, request, session_id)
        return _pb.history(reply, self._shape(session_id)[1])

    def _shape(self, session_id: str) -> tuple[int, list[str]]:
        shape = self._shapes.get(session_id)
        if shape is None:
            info = self.get_session(session_id)
            shape = (info.model.states, info.model.actions)
        return shape

    def interact(self, session_id: str) -> Interaction:
        """Opens an ``Interact`` stream on a session; see :class:`Interaction`."""
        return Interaction(self._stub, session_id, self._metadata(session_id))

    def watch(self, session_id: str, interval: float = 1.0) -> Watch:
        """Snapshots of a session every ``interval`` seconds (0.01 to 3600),
        the first at once; see :class:`Watch`.

        Raises:
            ValueError: The interval is out of range.
        """
        interval_ms = round(interval * 1000)
        if not 10 <= interval_ms <= 3_600_000:
            raise ValueError(f"interval {interval} s is not between 0.01 and 3600")
        request = pb.WatchRequest(session_id=session_id, interval_ms=interval_ms)
        return Watch(self._stub.Watch(request, metadata=self._metadata(session_id)))
