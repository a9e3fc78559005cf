"""The REST clients: :class:`Client` (blocking) and :class:`AsyncClient` (asyncio),
over httpx, with the same methods and results.

    from mcapi_client import Client, models

    with Client("http://127.0.0.1:8080") as mc:
        session = mc.create_session(models.hallway(), seed=7)
        step = mc.observe(session.id, state=25)            # first: state only
        step = mc.observe(session.id, state=26, stimulus=[0.0, 0.0])
        print(step.action, step.drive)
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterable, Iterator, Mapping, Sequence
from typing import Any, Union
from urllib.parse import quote

import httpx

from . import _json
from .errors import McapiError, Timeout, TransportError, error_for
from .models import Model
from .types import (
    ActionRef,
    AgentOptions,
    CuriosityLike,
    HistoryEntry,
    Observation,
    ObservationLike,
    SessionInfo,
    SessionPage,
    SessionSummary,
    Step,
    StimulusRate,
    UpdateMode,
    Values,
    as_curiosity,
    as_observation,
)

__all__ = ["Client", "AsyncClient", "DEFAULT_URL", "ModelLike"]

DEFAULT_URL = "http://127.0.0.1:8080"
"""Where ``mcapi serve`` listens for REST by default."""

ModelLike = Union[Model, Mapping[str, Any], str]
"""A model to create a session from: a :class:`~mcapi_client.models.Model`,
the model's JSON as a mapping (a full model, ``{"preset": "hallway"}`` or
``{"grid": [...], "sources": {...}}``), or a preset name (``"hallway"``,
``"three_room"``)."""


def model_json(model: ModelLike) -> dict[str, Any]:
    """The ``model`` JSON of a create request."""
    if isinstance(model, Model):
        return model.to_json()
    if isinstance(model, str):
        return {"preset": model}
    if isinstance(model, Mapping):
        return dict(model)
    raise TypeError(f"not a model: {type(model).__name__}")


def _headers(api_key: str | None, extra: Mapping[str, str] | None) -> dict[str, str]:
    headers = {"accept": "application/json", **(extra or {})}
    if api_key is not None:
        headers["authorization"] = f"Bearer {api_key}"
    return headers


def _raise_for(response: httpx.Response) -> None:
    if response.is_success:
        return
    try:
        body = response.json()
    except ValueError:
        body = None
    code, message = _json.error_fields(body)
    raise error_for(
        code,
        message or response.text or response.reason_phrase,
        status=response.status_code,
    )


def _wrap_transport(e: httpx.HTTPError, url: str) -> McapiError:
    if isinstance(e, httpx.TimeoutException):
        return Timeout(f"{url}: {e or type(e).__name__}", code="timeout")
    return TransportError(f"{url}: {e or type(e).__name__}", code="transport_error")


# Sessions whose action names a client keeps (to name history entries).
_ACTION_CACHE = 1024


def _remember_actions(cache: dict[str, list[str]], info: SessionInfo) -> None:
    cache.pop(info.id, None)
    cache[info.id] = info.model.actions
    while len(cache) > _ACTION_CACHE:
        del cache[next(iter(cache))]


def _path(session_id: str, tail: str = "") -> str:
    return f"/v1/sessions/{quote(session_id, safe='')}{tail}"


def _observation(
    state: int,
    stimulus: Sequence[float] | None,
    action_taken: ActionRef | None,
    signal: Sequence[float] | None,
    signal_source: int | None,
) -> dict[str, object]:
    return Observation(state, stimulus, action_taken, signal, signal_source).to_json()


def agent_options(
    *,
    eta: float | None,
    gamma: float | None,
    priorities: Sequence[float] | None,
    stimulus_rate: StimulusRate | None,
    optimistic_sd: float | None,
    ridge: float | None,
    epsilon: float | None,
    seed: int | None,
    update_mode: UpdateMode | None,
    history: int | None,
    curiosity: CuriosityLike | None,
) -> AgentOptions:
    """The :class:`AgentOptions` of ``create_session``'s keyword arguments."""
    return AgentOptions(
        eta=eta, gamma=gamma, priorities=priorities, stimulus_rate=stimulus_rate,
        optimistic_sd=optimistic_sd, ridge=ridge, epsilon=epsilon, seed=seed,
        update_mode=update_mode, history=history,
        curiosity=None if curiosity is None else as_curiosity(curiosity),
    )


def _batch(observations: Iterable[ObservationLike]) -> dict[str, object]:
    return {"observations": [as_observation(o).to_json() for o in observations]}


def _list_params(after: str | None, limit: int | None) -> dict[str, str | int]:
    params: dict[str, str | int] = {}
    if after is not None:
        params["after"] = after
    if limit is not None:
        params["limit"] = limit
    return params


class Client:
    """A blocking client of the mcapi REST API.

    Args:
        base_url: The server, e.g. ``"http://127.0.0.1:8080"``.
        api_key: Sent as ``Authorization: Bearer <key>`` when the server has keys.
        timeout: Seconds per request (or an ``httpx.Timeout``).
        headers: Extra headers for every request.
        transport: An httpx transport (tests, proxies, retries).

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
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self._http = httpx.Client(
            base_url=self.base_url,
            headers=_headers(api_key, headers),
            timeout=timeout,
            transport=transport,
        )
        # Action names per session, to name the actions of history entries.
        self._actions: dict[str, list[str]] = {}

    def close(self) -> None:
        """Closes the connection pool."""
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _request(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, str | int] | None = None,
        json: object = None,
    ) -> Any:
        try:
            response = self._http.request(method, path, params=params, json=json)
        except httpx.HTTPError as e:
            raise _wrap_transport(e, self.base_url + path) from e
        _raise_for(response)
        return response.json() if response.content else None

    def _remember(self, info: SessionInfo) -> SessionInfo:
        _remember_actions(self._actions, info)
        return info

    def ready(self) -> bool:
        """Whether the server answers ``/readyz`` with 200 (up and recovered)."""
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.HTTPError:
            return False

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
        """Creates a session on a model; unset agent options take the server's defaults.

        Args:
            model: A :class:`~mcapi_client.models.Model`, the model's JSON, or a preset name.
            eta: MCA rate, 0 < eta <= 0.5.
            gamma: Discount in [0, 1).
            priorities: Priority in (0, 1] per stimulus dimension.
            stimulus_rate: ``"sample_mean"`` or a constant rate in (0, 1].
            optimistic_sd: Sd of the optimistic initialisation of Xi.
            ridge: Ridge added to A only when singular.
            epsilon: Epsilon-greedy exploration in [0, 1].
            seed: Seed of the session's RNG (drawn by the server when unset).
            update_mode: ``"lockstep"`` (default) or ``"async"``.
            history: Recent ticks kept for :meth:`history`.
            curiosity: A curiosity channel: a
                :class:`~mcapi_client.types.CuriosityConfig`, its JSON, or the
                signal dimension alone. The server appends a stimulus
                dimension ``"curiosity"`` (last) and computes it from the
                ``signal`` samples of observations; send only the model's own
                (extrinsic) stimulus components. ``priorities``, if given,
                need one entry for it too.

        Returns:
            The new session, with its effective configuration (seed included).
        """
        agent = agent_options(
            eta=eta, gamma=gamma, priorities=priorities, stimulus_rate=stimulus_rate,
            optimistic_sd=optimistic_sd, ridge=ridge, epsilon=epsilon, seed=seed,
            update_mode=update_mode, history=history, curiosity=curiosity,
        )
        body = {"model": model_json(model), "agent": agent.to_json()}
        return self._remember(_json.session_info(self._request("POST", "/v1/sessions", json=body)))

    def get_session(self, session_id: str) -> SessionInfo:
        """A session's drive, tick, policy version, model, configuration and statistics."""
        return self._remember(_json.session_info(self._request("GET", _path(session_id))))

    def list_sessions(self, after: str | None = None, limit: int | None = None) -> SessionPage:
        """One page of sessions in id order.

        Args:
            after: Start after this id (the ``next`` of the previous page).
            limit: Page size, 1 to 1000 (server default 100).
        """
        return _json.session_page(
            self._request("GET", "/v1/sessions", params=_list_params(after, limit))
        )

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
        self._request("DELETE", _path(session_id))
        self._actions.pop(session_id, None)

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
        """Reports one observation and returns the next action.

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
        """
        return _json.step(
            self._request(
                "POST",
                _path(session_id, "/observations"),
                json=_observation(state, stimulus, action_taken, signal, signal_source),
            )
        )

    def observe_batch(
        self, session_id: str, observations: Iterable[ObservationLike]
    ) -> list[Step]:
        """Applies observations in order (e.g. replaying a log); one step each.

        Each entry is an :class:`~mcapi_client.Observation` (which may carry
        a ``signal``), a mapping or a tuple. On an error at observation i,
        the i before it stay applied and the error's message says so.
        """
        reply = self._request(
            "POST", _path(session_id, "/observations"), json=_batch(observations)
        )
        return [_json.step(s) for s in reply["steps"]]

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
        inc = _json.include_param(include)
        params = {"include": inc} if inc is not None else None
        return _json.values(self._request("GET", _path(session_id, "/values"), params=params))

    def history(self, session_id: str, limit: int | None = None) -> list[HistoryEntry]:
        """The most recent ticks of a session (at most ``limit``), oldest first.

        Each entry has the full stimulus received (with a curiosity channel,
        xi_cur last) and, for a curious session, the channel at that tick.
        """
        params = {"limit": limit} if limit is not None else None
        entries = self._request("GET", _path(session_id, "/history"), params=params)
        actions = self._actions.get(session_id)
        if actions is None:
            actions = self.get_session(session_id).model.actions
        return _json.history(entries, actions)


class AsyncClient:
    """An asyncio client of the mcapi REST API, with the methods of :class:`Client`.

    Args:
        base_url: The server, e.g. ``"http://127.0.0.1:8080"``.
        api_key: Sent as ``Authorization: Bearer <key>`` when the server has keys.
        timeout: Seconds per request (or an ``httpx.Timeout``).
        headers: Extra headers for every request.
        transport: An httpx async transport.

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
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self._http = httpx.AsyncClient(
            base_url=self.base_url,
            headers=_headers(api_key, headers),
            timeout=timeout,
            transport=transport,
        )
        self._actions: dict[str, list[str]] = {}

    async def aclose(self) -> None:
        """Closes the connection pool."""
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _request(
        self,
        method: str,
        path: str,
        *,
        params: Mapping[str, str | int] | None = None,
        json: object = None,
    ) -> Any:
        try:
            response = await self._http.request(method, path, params=params, json=json)
        except httpx.HTTPError as e:
            raise _wrap_transport(e, self.base_url + path) from e
        _raise_for(response)
        return response.json() if response.content else None

    def _remember(self, info: SessionInfo) -> SessionInfo:
        _remember_actions(self._actions, info)
        return info

    async def ready(self) -> bool:
        """Whether the server answers ``/readyz`` with 200 (up and recovered)."""
        try:
            return (await self._http.get("/readyz")).status_code == 200
        except httpx.HTTPError:
            return False

    async def create_session(
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
        """Creates a session; see :meth:`Client.create_session`."""
        agent = agent_options(
            eta=eta, gamma=gamma, priorities=priorities, stimulus_rate=stimulus_rate,
            optimistic_sd=optimistic_sd, ridge=ridge, epsilon=epsilon, seed=seed,
            update_mode=update_mode, history=history, curiosity=curiosity,
        )
        body = {"model": model_json(model), "agent": agent.to_json()}
        return self._remember(
            _json.session_info(await self._request("POST", "/v1/sessions", json=body))
        )

    async def get_session(self, session_id: str) -> SessionInfo:
        """A session's details; see :meth:`Client.get_session`."""
        return self._remember(_json.session_info(await self._request("GET", _path(session_id))))

    async def list_sessions(
        self, after: str | None = None, limit: int | None = None
    ) -> SessionPage:
        """One page of sessions in id order; see :meth:`Client.list_sessions`."""
        return _json.session_page(
            await self._request("GET", "/v1/sessions", params=_list_params(after, limit))
        )

    async def iter_sessions(self, page_size: int = 100) -> AsyncIterator[SessionSummary]:
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
        await self._request("DELETE", _path(session_id))
        self._actions.pop(session_id, None)

    async def observe(
        self,
        session_id: str,
        state: int,
        stimulus: Sequence[float] | None = None,
        action_taken: ActionRef | None = None,
        *,
        signal: Sequence[float] | None = None,
        signal_source: int | None = None,
    ) -> Step:
        """Reports one observation; see :meth:`Client.observe`."""
        return _json.step(
            await self._request(
                "POST",
                _path(session_id, "/observations"),
                json=_observation(state, stimulus, action_taken, signal, signal_source),
            )
        )

    async def observe_batch(
        self, session_id: str, observations: Iterable[ObservationLike]
    ) -> list[Step]:
        """Applies observations in order; see :meth:`Client.observe_batch`."""
        reply = await self._request(
            "POST", _path(session_id, "/observations"), json=_batch(observations)
        )
        return [_json.step(s) for s in reply["steps"]]

    async def values(
        self, session_id: str, include: str | Iterable[str] | None = None
    ) -> Values:
        """Value tables; see :meth:`Client.values`."""
        inc = _json.include_param(include)
        params = {"include": inc} if inc is not None else None
        return _json.values(
            await self._request("GET", _path(session_id, "/values"), params=params)
        )

    async def history(self, session_id: str, limit: int | None = None) -> list[HistoryEntry]:
        """Recent ticks, oldest first; see :meth:`Client.history`."""
        params = {"limit": limit} if limit is not None else None
        entries = await self._request("GET", _path(session_id, "/history"), params=params)
        actions = self._actions.get(session_id)
        if actions is None:
            actions = (await self.get_session(session_id)).model.actions
        return _json.history(entries, actions)
