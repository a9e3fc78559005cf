"""The REST API without I/O: each call as the requests it makes and the typed
result (or :class:`~mcapi_client.McapiError`) it reads from the replies.

:class:`RestProtocol` holds what a client remembers between calls (the
action names of the sessions it saw, to name history entries); its methods
return operations (:data:`~mcapi_client._sansio.Op`) that
:class:`~mcapi_client.Client` and :class:`~mcapi_client.AsyncClient` run
with :func:`~mcapi_client._sansio.drive` and
:func:`~mcapi_client._sansio.adrive`, doing only the HTTP themselves. It
needs no HTTP library: the core of the package imports it without httpx.

    op = RestProtocol().get_session("s1.X")
    request = next(op)              # Request(method="GET", path="/v1/sessions/s1.X", ...)
    op.send(read_reply(200, body, "OK"))  # -> StopIteration(SessionInfo(...))
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

from . import _json
from ._normalise import as_int, as_opt_int
from ._sansio import Op, SessionCache
from ._seq import Sequences, numbered
from .errors import SequenceRefused, error_for
from .models import ModelLike, model_json
from .types import (
    AgentOptions,
    HistoryEntry,
    Observation,
    ObservationLike,
    SessionInfo,
    SessionPage,
    Step,
    Values,
    as_observation,
)

if TYPE_CHECKING:
    from ._columns import GroupInfo, GroupSeqs, GroupSeqTable, GroupStep
    from .types import AgentKwargs

__all__ = [
    "Request",
    "RestProtocol",
    "READY",
    "headers",
    "read_reply",
    "session_path",
    "group_path",
]


@dataclass(frozen=True, slots=True)
class Request:
    """One HTTP request to make.

    Attributes:
        method: ``"GET"``, ``"POST"`` or ``"DELETE"``.
        path: The path under the base URL, its session id percent-encoded.
        params: The query parameters, if any.
        json: The JSON body, plain Python values only; ``None``: no body.
        resend: Safe to send again after a lost answer (numbered
            observations): retried on :data:`~mcapi_client.retry.RESEND_CODES` too.
    """

    method: str
    path: str
    params: dict[str, str | int] | None = None
    json: Any = None
    resend: bool = False


READY = Request("GET", "/readyz")
"""Readiness: up and recovered when it answers 200 (no error body to read)."""


def headers(api_key: str | None, extra: Mapping[str, str] | None) -> dict[str, str]:
    """The headers of every request: JSON, the API key as a bearer token, ``extra``."""
    out = {"accept": "application/json", **(extra or {})}
    if api_key is not None:
        out["authorization"] = f"Bearer {api_key}"
    return out


def session_path(session_id: str, tail: str = "") -> str:
    """``/v1/sessions/<id><tail>``, the id one path segment whatever it contains."""
    return f"/v1/sessions/{quote(session_id, safe='')}{tail}"


def group_path(group_id: str, tail: str = "") -> str:
    """``/v1/groups/<id><tail>``, the id one path segment whatever it contains."""
    return f"/v1/groups/{quote(group_id, safe='')}{tail}"


def read_reply(status: int, content: bytes, reason: str) -> Any:
    """The JSON body of a reply (``None`` when empty).

    Raises:
        McapiError: The status is not 2xx: the subclass of the body's
            ``code``, else of the status.
    """
    if 200 <= status < 300:
        return json.loads(content) if content else None
    try:
        body = json.loads(content)
    except ValueError:
        body = None
    code, message = _json.error_fields(body)
    text = content.decode("utf-8", errors="replace")
    err = error_for(code, message or text or reason, status=status)
    if isinstance(err, SequenceRefused) and isinstance(body, dict):
        err.expected_seq = _opt_seq(body.get("expected_seq"))
        err.oldest_seq = _opt_seq(body.get("oldest_seq"))
    raise err


def _opt_seq(value: object) -> int | None:
    return value if type(value) is int else None


def _set_seq(obs: dict[str, object], seq: int) -> None:
    obs["seq"] = seq


def _list_params(after: str | None, limit: object) -> dict[str, str | int]:
    params: dict[str, str | int] = {}
    if after is not None:
        params["after"] = after
    n = as_opt_int(limit, "limit")
    if n is not None:
        params["limit"] = n
    return params


class RestProtocol:
    """The REST calls as operations, the action names per session they need
    and, with ``exactly_once``, the seq of each session's next observation
    (:mod:`mcapi_client._seq`)."""

    def __init__(self, exactly_once: bool = False) -> None:
        self._actions: SessionCache[list[str]] = SessionCache()
        self._groups: SessionCache[GroupInfo] = SessionCache()
        self.seqs: Sequences | None = Sequences() if exactly_once else None
        # Made on first use (it needs numpy, the `vector` extra).
        self._group_seqs: GroupSeqTable | None = None

    def group_seqs(self, info: GroupInfo, created: bool = False) -> GroupSeqs | None:
        """With ``exactly_once``, the counts of a group's members (every
        count 0 for a group just ``created``, else kept or learned)."""
        if self.seqs is None:
            return None
        if self._group_seqs is None:
            from ._columns import GroupSeqTable

            self._group_seqs = GroupSeqTable()
        return self._group_seqs.created(info) if created else self._group_seqs.of(info)

    def _remember(self, info: SessionInfo, created: bool = False) -> SessionInfo:
        self._actions.put(info.id, info.model.actions)
        if self.seqs is not None:
            self.seqs.learn(info.id, info.next_seq, force=created)
        return info

    def create_session(self, model: ModelLike, agent: AgentOptions) -> Op[Request, SessionInfo]:
        """``POST /v1/sessions``."""
        body = {"model": model_json(model), "agent": agent.to_json()}
        reply = yield Request("POST", "/v1/sessions", json=body)
        return self._remember(_json.session_info(reply), created=True)

    def get_session(self, session_id: str) -> Op[Request, SessionInfo]:
        """``GET /v1/sessions/{id}``."""
        reply = yield Request("GET", session_path(session_id))
        return self._remember(_json.session_info(reply))

    def list_sessions(self, after: str | None, limit: object) -> Op[Request, SessionPage]:
        """``GET /v1/sessions?after=&limit=``."""
        reply = yield Request("GET", "/v1/sessions", params=_list_params(after, limit))
        return _json.session_page(reply)

    def delete_session(self, session_id: str) -> Op[Request, None]:
        """``DELETE /v1/sessions/{id}``."""
        yield Request("DELETE", session_path(session_id))
        self._actions.drop(session_id)
        if self.seqs is not None:
            self.seqs.forget(session_id)

    def observe(self, session_id: str, observation: Observation) -> Op[Request, Step]:
        """``POST /v1/sessions/{id}/observations`` with one observation,
        numbered (see :func:`mcapi_client._seq.numbered`)."""
        body = observation.to_json()
        path = session_path(session_id, "/observations")
        reply = yield from numbered(
            self.seqs,
            session_id,
            (body,),
            observation.seq,
            _set_seq,
            lambda resend: Request("POST", path, json=body, resend=resend),
            lambda: self.get_session(session_id),
        )
        return _json.step(reply)

    def observe_batch(
        self, session_id: str, observations: Iterable[ObservationLike]
    ) -> Op[Request, list[Step]]:
        """``POST /v1/sessions/{id}/observations`` with a batch, numbered
        consecutively (unless its observations carry their own seqs)."""
        obs = [as_observation(o) for o in observations]
        body = {"observations": [o.to_json() for o in obs]}
        path = session_path(session_id, "/observations")
        given = next((o.seq for o in obs if o.seq is not None), None)
        reply = yield from numbered(
            self.seqs,
            session_id,
            body["observations"],
            given,
            _set_seq,
            lambda resend: Request("POST", path, json=body, resend=resend),
            lambda: self.get_session(session_id),
        )
        return [_json.step(s) for s in reply["steps"]]

    def values(self, session_id: str, include: str | Iterable[str] | None) -> Op[Request, Values]:
        """``GET /v1/sessions/{id}/values?include=``."""
        inc = _json.include_param(include)
        params: dict[str, str | int] | None = {"include": inc} if inc is not None else None
        reply = yield Request("GET", session_path(session_id, "/values"), params=params)
        return _json.values(reply)

    def history(self, session_id: str, limit: object) -> Op[Request, list[HistoryEntry]]:
        """``GET /v1/sessions/{id}/history?limit=``, then the session when its
        action names are not known yet."""
        n = as_opt_int(limit, "limit")
        params: dict[str, str | int] | None = {"limit": n} if n is not None else None
        entries = yield Request("GET", session_path(session_id, "/history"), params=params)
        actions = self._actions.get(session_id)
        if actions is None:
            actions = (yield from self.get_session(session_id)).model.actions
        return _json.history(entries, actions)

    # Session groups (numpy: the `vector` extra, imported when first used).

    def create_group(self, model: ModelLike, n: object, agent: AgentKwargs) -> Op[Request, GroupInfo]:
        """``POST /v1/groups``; ``agent``'s ``seed`` is the group's."""
        from . import _columns

        rest = agent.copy()
        seed = as_opt_int(rest.pop("seed", None), "seed")
        body: dict[str, Any] = {
            "model": model_json(model),
            "agent": AgentOptions(**rest).to_json(),
            "n": as_int(n, "n"),
        }
        if seed is not None:
            body["seed"] = seed
        reply = yield Request("POST", "/v1/groups", json=body)
        info = _columns.group_info_json(reply)
        self._groups.put(info.id, info)
        self.group_seqs(info, created=True)
        return info

    def get_group(self, group_id: str) -> Op[Request, GroupInfo]:
        """``GET /v1/groups/{id}``."""
        from . import _columns

        reply = yield Request("GET", group_path(group_id))
        info = _columns.group_info_json(reply)
        self._groups.put(info.id, info)
        return info

    def delete_group(self, group_id: str) -> Op[Request, None]:
        """``DELETE /v1/groups/{id}``."""
        yield Request("DELETE", group_path(group_id))
        self._groups.drop(group_id)
        if self._group_seqs is not None:
            self._group_seqs.drop(group_id)

    def group(self, group_id: str) -> Op[Request, GroupInfo]:
        """The group's shape: remembered, else read (``GET /v1/groups/{id}``)."""
        info = self._groups.get(group_id)
        if info is None:
            info = yield from self.get_group(group_id)
        return info

    def step_group(
        self,
        group_id: str,
        states: Any,
        stimuli: Any,
        observations: Any,
        action_taken: Any,
        mask: Any,
    ) -> Op[Request, GroupStep]:
        """``POST /v1/groups/{id}/steps``, the columns checked against the
        group's shape first (read once when not known yet), numbered with
        ``exactly_once`` (:class:`mcapi_client.groups.GroupSeqs`)."""
        from . import _columns

        info = yield from self.group(group_id)
        columns = _columns.check_columns(
            info, states, stimuli, observations=observations, action_taken=action_taken, mask=mask
        )
        seqs = self.group_seqs(info)
        body, members, sent = _columns.numbered_body(info, columns, seqs)
        path = group_path(group_id, "/steps")
        try:
            reply = yield Request("POST", path, json=body, resend=sent is not None)
        except BaseException:
            if seqs is not None:
                seqs.failed(members, sent)
            raise
        step = _columns.group_step_json(reply, info.stimuli)
        if seqs is not None:
            seqs.answered(members, sent, step)
        return step
