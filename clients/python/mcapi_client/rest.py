"""The REST clients: :class:`Client` (blocking) and :class:`AsyncClient` (asyncio),
over httpx, with the same methods and results. A plain install has httpx
(``pip install './clients/python'`` from the mcapi repository).

    from mcapi_client import Client, models

    with Client("http://127.0.0.1:8080") as mc:
        session = mc.create_session(models.hallway(), seed=7)
        step = mc.observe(session.id, state=25)            # first: state only
        step = mc.observe(session.id, state=26, stimulus=[0.0, 0.0])
        print(step.action, step.drive)

Both clients run the same operations of :mod:`mcapi_client._protocol`,
which build each request and read each reply; a client only sends the
request over httpx. Numbers may be numpy scalars and vectors numpy arrays.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Iterable, Iterator, Mapping
from typing import TYPE_CHECKING, Any

try:
    import httpx
except ImportError as e:  # pragma: no cover - exercised in a subprocess by tests/test_package.py
    raise ImportError(
        "the REST clients (mcapi_client.Client, AsyncClient) need httpx: "
        "install the client with its dependencies, pip install './clients/python' "
        "(from the mcapi repository)",
        name=e.name,
    ) from e

from ._normalise import FloatsLike, IntLike
from ._protocol import READY, Request, RestProtocol, group_path, read_reply
from ._protocol import headers as request_headers
from ._sansio import adrive, drive
from .errors import McapiError, Timeout, TransportError, WrongReplica
from .models import ModelLike
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

    from .groups import AsyncRestVectorAgents, GroupInfo, GroupStep, RestVectorAgents

__all__ = ["Client", "AsyncClient", "DEFAULT_URL", "ModelLike"]

DEFAULT_URL = "http://127.0.0.1:8080"
"""Where ``mcapi serve`` listens for REST by default."""

POOL_LIMITS = httpx.Limits(max_connections=20, max_keepalive_connections=20)
"""The connection pool of both clients: 20 connections, every one kept
alive (httpx's default is 100, of which 20 kept alive). With more open
than kept alive, httpcore closes each connection that goes idle while the
pool holds more than 20, and under threads sharing one client it can close
one it has just handed to a waiting request: that request then waits for
its whole ``timeout`` on a closed socket and fails ("Bad file descriptor"),
too late to be retried, after the server may have applied it. Kept alive,
an idle connection is closed only when the server closed it or its
keep-alive (5 s) expired. 20 rather than 100: httpcore's pool scans its
connections on every request, and 150 threads sharing a pool of 100 made
11% and 25% fewer observations per second than with 20, in two
interleaved runs (BENCHMARKS.md §13); more requests wait for a connection
instead."""


def _reply(response: httpx.Response) -> Any:
    """The reply's JSON, or its error with the owner a misdirected one names."""
    try:
        return read_reply(response.status_code, response.content, response.reason_phrase)
    except WrongReplica as e:
        e.owner = response.headers.get("x-mcapi-owner")
        raise


def _retry_after(response: httpx.Response | None) -> float | None:
    """A ``Retry-After`` in seconds, if the refusal carried one."""
    value = response.headers.get("retry-after") if response is not None else None
    try:
        return float(value) if value is not None else None
    except ValueError:
        return None


def _what(request: Request) -> str:
    return f"{request.method} {request.path}"


def _transport_error(e: httpx.HTTPError, url: str) -> McapiError:
    if isinstance(e, httpx.TimeoutException):
        return Timeout(f"{url}: {e or type(e).__name__}", code="timeout")
    return TransportError(f"{url}: {e or type(e).__name__}", code="transport_error")


class Client:
    """A blocking client of the mcapi REST API.

    Args:
        base_url: The server, e.g. ``"http://127.0.0.1:8080"``.
        api_key: Sent as ``Authorization: Bearer <key>`` when the server has keys.
        timeout: Seconds per request (or an ``httpx.Timeout``).
        headers: Extra headers for every request.
        transport: An httpx transport (tests, proxies, retries).
        retry: Which failures to retry and for how long (a cluster's 421
            and 503s; for numbered observations also a lost answer, see
            :mod:`mcapi_client.retry`); ``None``: never.
        exactly_once: Number each session's observations (``seq``) so that
            a resend after a lost answer is applied once (see the README's
            "Delivery"); ``False``: send them unnumbered, at least once.

    Attributes:
        retries: The retries made so far, by reason
            (:class:`~mcapi_client.RetryCounter`).

    Every method raises a :class:`~mcapi_client.McapiError` subclass on
    failure. Use as a context manager, or call :meth:`close`.
    """

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        api_key: str | None = None,
        timeout: float | httpx.Timeout = 30.0,
        *,
        headers: Mapping[str, str] | None = None,
        transport: httpx.BaseTransport | None = None,
        retry: RetryPolicy | None = DEFAULT_RETRY,
        exactly_once: bool = True,
    ) -> None:
        self.retry = retry
        self.retries = RetryCounter()
        self.base_url = base_url.rstrip("/")
        self._http = httpx.Client(
            base_url=self.base_url,
            headers=request_headers(api_key, headers),
            timeout=timeout,
            transport=transport,
            limits=POOL_LIMITS,
        )
        self._protocol = RestProtocol(exactly_once)

    def close(self) -> None:
        """Closes the connection pool."""
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send(self, request: Request) -> Any:
        attempts = Attempts(self.retry, time.monotonic(), self.retries, _what(request))
        while True:
            response: httpx.Response | None = None
            try:
                response = self._http.request(
                    request.method, request.path, params=request.params, json=request.json
                )
                return _reply(response)
            except httpx.HTTPError as e:
                err = _transport_error(e, self.base_url + request.path)
                wait = attempts.next_wait(err, time.monotonic(), None, request.resend)
                if wait is None:
                    raise err from e
            except McapiError as e:
                wait = attempts.next_wait(e, time.monotonic(), _retry_after(response), request.resend)
                if wait is None:
                    raise
            time.sleep(wait)

    def ready(self) -> bool:
        """Whether the server answers ``/readyz`` with 200 (up and recovered)."""
        try:
            return self._http.request(READY.method, READY.path).status_code == 200
        except httpx.HTTPError:
            return False

    def create_session(self, model: ModelLike, **agent: Unpack[AgentKwargs]) -> SessionInfo:
        """Creates a session on a model; unset agent options take the server's defaults.

        Args:
            model: A :class:`~mcapi_client.models.Model`, the model's JSON, or a preset name.
            **agent: The agent options, by keyword: those of
                :class:`~mcapi_client.AgentKwargs`, documented there (``seed``,
                ``eta``, ``curiosity``, ...). Numbers may be numpy scalars and
                ``priorities`` a numpy array; an unknown keyword is a ``TypeError``.

        Returns:
            The new session, with its effective configuration (seed included).
        """
        options = AgentOptions(**agent)
        return drive(self._protocol.create_session(model, options), self._send)

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
        """Reports one observation and returns the next action.

        Numbers may be numpy scalars (``state=np.int64(3)``) and vectors
        numpy arrays.

        Args:
            session_id: The session.
            state: The state the agent is in now.
            stimulus: What it received on arriving there; leave out on the
                session's first observation.
            action_taken: The action actually taken, by name or index, if not
                the one the session advised.
            signal: A raw signal sample received on arriving there, for a
                session with a curiosity channel; ``stimulus`` is then the
                extrinsic part only and the server appends xi_cur (see
                ``step.curiosity``). Not on the first observation.
            signal_source: The signal's source, e.g. 0 = book, 1 = music
                (server default 0); only with ``signal``.
            observation: A continuous world's observation vector, instead
                of ``state``.
            seq: The observation's seq, sent as given; leave out to let the
                client number observations (the default, see the README's
                "Delivery").

        A step whose observation was resent after a lost answer, and had been
        applied, is the recorded one, with ``replayed`` set.
        """
        obs = Observation(
            state, stimulus, action_taken, signal, signal_source, observation=observation, seq=seq
        )
        return drive(self._protocol.observe(session_id, obs), self._send)

    def observe_batch(
        self, session_id: str, observations: Iterable[ObservationLike]
    ) -> list[Step]:
        """Applies observations in order (e.g. replaying a log); one step each.

        Each entry is an :class:`~mcapi_client.Observation` (which may carry
        a ``signal``), a mapping or a tuple. On an error at observation i,
        the i before it stay applied and the error's message says so.
        """
        return drive(self._protocol.observe_batch(session_id, observations), self._send)

    def values(
        self, session_id: str, include: str | Iterable[str] | None = None
    ) -> Values:
        """Value tables of a session.

        Args:
            session_id: The session.
            include: Tables among ``v``, ``q``, ``policy``, ``r``, ``xi``, or
                ``all`` (as a list or a comma-separated string); default
                ``v`` and ``policy``.
        """
        return drive(self._protocol.values(session_id, include), self._send)

    def history(self, session_id: str, limit: IntLike | None = None) -> list[HistoryEntry]:
        """The most recent ticks of a session (at most ``limit``), oldest first.

        Each entry has the full stimulus received (with a curiosity channel,
        xi_cur last) and, for a curious session, the channel at that tick.
        """
        return drive(self._protocol.history(session_id, limit), self._send)

    # -- session groups (the `vector` extra: numpy) --

    def create_group(
        self, model: ModelLike, n: IntLike, **agent: Unpack[AgentKwargs]
    ) -> RestVectorAgents:
        """Creates a group of ``n`` sessions of one model and configuration
        (``POST /v1/groups``); returns the object that steps it.

        Args:
            model: Every member's model.
            n: Members, 1 to the server's ``--max-group-members``.
            agent: Every member's configuration, as :meth:`create_session`
                takes it, except ``seed``: it is the group's (member i's is
                :func:`mcapi_client.groups.member_seed` of it; drawn when
                absent).

        Needs the ``vector`` extra (numpy).
        """
        info = drive(self._protocol.create_group(model, n, agent), self._send)
        return self._vector_agents(info)

    def get_group(self, group_id: str) -> GroupInfo:
        """A group: its seed, shape and member session ids (``GET /v1/groups/{id}``)."""
        return drive(self._protocol.get_group(group_id), self._send)

    def vector_agents(self, group_id: str) -> RestVectorAgents:
        """The object that steps an existing group (it reads the group first)."""
        return self._vector_agents(self.get_group(group_id))

    def _vector_agents(self, info: GroupInfo) -> RestVectorAgents:
        from .groups import RestVectorAgents

        path = group_path(info.id, "/steps")
        return RestVectorAgents(
            info,
            lambda body, resend: self._send(Request("POST", path, json=body, resend=resend)),
            self._protocol.group_seqs(info),
        )

    def delete_group(self, group_id: str) -> None:
        """Deletes every member of a group, then the group (``DELETE /v1/groups/{id}``)."""
        drive(self._protocol.delete_group(group_id), self._send)

    def step_group(
        self,
        group_id: str,
        states: Any = None,
        stimuli: Any = None,
        *,
        observations: Any = None,
        action_taken: Any = None,
        mask: Any = None,
    ) -> GroupStep:
        """One step of a group's members (``POST /v1/groups/{id}/steps``): the
        columns of :meth:`mcapi_client.groups.VectorAgents.send`, checked
        against the group's shape (read once if this client has not seen the
        group), and the same :class:`~mcapi_client.groups.GroupStep` of numpy
        arrays as over gRPC: a refused member is in ``errors``, its ``null``
        entries as the gRPC placeholders (action
        :data:`~mcapi_client.groups.ADVISED`, a drive row of 0, reward 0).

        Raises:
            ValueError: A column does not fit the group; nothing was sent.
            McapiError: The server refused the step whole (``unknown_state``,
                ``stimulus_too_large``, ``not_found``...), or a stimulus is
                not finite (``non_finite_number``: JSON cannot carry it).
        """
        op = self._protocol.step_group(group_id, states, stimuli, observations, action_taken, mask)
        return drive(op, self._send)


class AsyncClient:
    """An asyncio client of the mcapi REST API, with the methods of :class:`Client`.

    Args:
        base_url: The server, e.g. ``"http://127.0.0.1:8080"``.
        api_key: Sent as ``Authorization: Bearer <key>`` when the server has keys.
        timeout: Seconds per request (or an ``httpx.Timeout``).
        headers: Extra headers for every request.
        transport: An httpx async transport.
        retry: As :class:`Client`'s.
        exactly_once: As :class:`Client`'s.

    Attributes:
        retries: The retries made so far, by reason.

    Use as ``async with AsyncClient(...) as mc:``, or call :meth:`aclose`.
    """

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        api_key: str | None = None,
        timeout: float | httpx.Timeout = 30.0,
        *,
        headers: Mapping[str, str] | None = None,
        transport: httpx.AsyncBaseTransport | None = None,
        retry: RetryPolicy | None = DEFAULT_RETRY,
        exactly_once: bool = True,
    ) -> None:
        self.retry = retry
        self.retries = RetryCounter()
        self.base_url = base_url.rstrip("/")
        self._http = httpx.AsyncClient(
            base_url=self.base_url,
            headers=request_headers(api_key, headers),
            timeout=timeout,
            transport=transport,
            limits=POOL_LIMITS,
        )
        self._protocol = RestProtocol(exactly_once)

    async def aclose(self) -> None:
        """Closes the connection pool."""
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _send(self, request: Request) -> Any:
        attempts = Attempts(self.retry, time.monotonic(), self.retries, _what(request))
        while True:
            response: httpx.Response | None = None
            try:
                response = await self._http.request(
                    request.method, request.path, params=request.params, json=request.json
                )
                return _reply(response)
            except httpx.HTTPError as e:
                err = _transport_error(e, self.base_url + request.path)
                wait = attempts.next_wait(err, time.monotonic(), None, request.resend)
                if wait is None:
                    raise err from e
            except McapiError as e:
                wait = attempts.next_wait(e, time.monotonic(), _retry_after(response), request.resend)
                if wait is None:
                    raise
            await asyncio.sleep(wait)

    async def ready(self) -> bool:
        """Whether the server answers ``/readyz`` with 200 (up and recovered)."""
        try:
            return (await self._http.request(READY.method, READY.path)).status_code == 200
        except httpx.HTTPError:
            return False

    async def create_session(self, model: ModelLike, **agent: Unpack[AgentKwargs]) -> SessionInfo:
        """Creates a session; see :meth:`Client.create_session`."""
        options = AgentOptions(**agent)
        return await adrive(self._protocol.create_session(model, options), self._send)

    async def get_session(self, session_id: str) -> SessionInfo:
        """A session's details; see :meth:`Client.get_session`."""
        return await adrive(self._protocol.get_session(session_id), self._send)

    async def list_sessions(
        self, after: str | None = None, limit: IntLike | None = None
    ) -> SessionPage:
        """One page of sessions in id order; see :meth:`Client.list_sessions`."""
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
        """Reports one observation; see :meth:`Client.observe`."""
        obs = Observation(
            state, stimulus, action_taken, signal, signal_source, observation=observation, seq=seq
        )
        return await adrive(self._protocol.observe(session_id, obs), self._send)

    async def observe_batch(
        self, session_id: str, observations: Iterable[ObservationLike]
    ) -> list[Step]:
        """Applies observations in order; see :meth:`Client.observe_batch`."""
        return await adrive(self._protocol.observe_batch(session_id, observations), self._send)

    async def values(
        self, session_id: str, include: str | Iterable[str] | None = None
    ) -> Values:
        """Value tables; see :meth:`Client.values`."""
        return await adrive(self._protocol.values(session_id, include), self._send)

    async def history(self, session_id: str, limit: IntLike | None = None) -> list[HistoryEntry]:
        """Recent ticks, oldest first; see :meth:`Client.history`."""
        return await adrive(self._protocol.history(session_id, limit), self._send)

    # -- session groups (the `vector` extra: numpy) --

    async def create_group(
        self, model: ModelLike, n: IntLike, **agent: Unpack[AgentKwargs]
    ) -> AsyncRestVectorAgents:
        """Creates a group; see :meth:`Client.create_group`."""
        info = await adrive(self._protocol.create_group(model, n, agent), self._send)
        return self._vector_agents(info)

    async def get_group(self, group_id: str) -> GroupInfo:
        """A group: its seed, shape and member session ids."""
        return await adrive(self._protocol.get_group(group_id), self._send)

    async def vector_agents(self, group_id: str) -> AsyncRestVectorAgents:
        """The object that steps an existing group (it reads the group first)."""
        return self._vector_agents(await self.get_group(group_id))

    def _vector_agents(self, info: GroupInfo) -> AsyncRestVectorAgents:
        from .groups import AsyncRestVectorAgents

        path = group_path(info.id, "/steps")

        async def send(body: dict[str, Any], resend: bool) -> Any:
            return await self._send(Request("POST", path, json=body, resend=resend))

        return AsyncRestVectorAgents(info, send, self._protocol.group_seqs(info))

    async def delete_group(self, group_id: str) -> None:
        """Deletes every member of a group, then the group."""
        await adrive(self._protocol.delete_group(group_id), self._send)

    async def step_group(
        self,
        group_id: str,
        states: Any = None,
        stimuli: Any = None,
        *,
        observations: Any = None,
        action_taken: Any = None,
        mask: Any = None,
    ) -> GroupStep:
        """One step of a group's members; see :meth:`Client.step_group`."""
        op = self._protocol.step_group(group_id, states, stimuli, observations, action_taken, mask)
        return await adrive(op, self._send)
