"""Errors raised by the clients.

Every error the server reports carries a stable snake_case ``code`` (the table
in the server's ``crates/mcapi-server/src/api/error.rs``); REST sends it in the JSON body
``{"code", "message"}``, gRPC in the ``x-mcapi-error-code`` trailer. Both
clients raise the same :class:`McapiError` subclass for the same code, with the
same ``code``, the HTTP ``status`` the code maps to and the server's
``message``, so code written against one transport handles the other's errors
unchanged.

    try:
        client.observe(session_id, state=3, stimulus=[0.0])
    except InvalidObservation as e:
        print(e.code, e.status, e.message)   # stimulus_length 400 ...
"""

from __future__ import annotations

from typing import Final

__all__ = [
    "McapiError",
    "one_line",
    "BadRequest",
    "InvalidModel",
    "InvalidParameter",
    "InvalidObservation",
    "Unauthenticated",
    "Forbidden",
    "NotFound",
    "UnknownRoute",
    "LimitExceeded",
    "PayloadTooLarge",
    "TooManySessions",
    "TooManyStreams",
    "QuotaExceeded",
    "SessionFailed",
    "MoveConflict",
    "SequenceRefused",
    "Unavailable",
    "TransportError",
    "WrongReplica",
    "Timeout",
    "InternalError",
    "ERROR_CODES",
    "error_for",
]


class McapiError(Exception):
    """An error reported by an mcapi server, or a failure to reach it.

    Attributes:
        code: The stable snake_case error code (``not_found``,
            ``stimulus_length``, ...), or a client-side code for failures
            that never reached the server (``transport_error``, ``timeout``).
        status: The HTTP status of the code (404, 400, ...), the same over
            REST and gRPC; ``None`` when no status applies.
        message: The server's message, naming the offending field.
        grpc_code: The name of the gRPC status code (``"NOT_FOUND"``) when the
            error came over gRPC, else ``None``.
    """

    def __init__(
        self,
        message: str,
        *,
        code: str,
        status: int | None = None,
        grpc_code: str | None = None,
    ) -> None:
        super().__init__(message)
        self.code = code
        self.status = status
        self.message = message
        self.grpc_code = grpc_code

    def __str__(self) -> str:
        where = f"HTTP {self.status}" if self.status is not None else "no status"
        if self.grpc_code is not None:
            where += f", gRPC {self.grpc_code}"
        return f"{self.code} ({where}): {self.message}"

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(code={self.code!r}, status={self.status!r}, "
            f"message={self.message!r})"
        )


class BadRequest(McapiError):
    """The request was malformed (HTTP 400, gRPC INVALID_ARGUMENT)."""


class InvalidModel(BadRequest):
    """The environment model or its basis was refused (``invalid_model``, ``invalid_basis``)."""


class InvalidParameter(BadRequest):
    """An agent parameter was out of range (``invalid_parameter``)."""


class InvalidObservation(BadRequest):
    """An observation was refused: unknown state or action, an unavailable
    action, a stimulus of the wrong length, too large or not finite, or a
    stimulus missing on (or sent with) a session's first observation, or an
    observation vector of the wrong dimension, not finite, or outside a space
    that refuses such observations (``invalid_observation``)."""


class Unauthenticated(McapiError):
    """The API key is missing or wrong (HTTP 401, gRPC UNAUTHENTICATED)."""


class Forbidden(McapiError):
    """An admin call of a cluster's shard moves without the admin key, or to a
    server with no ``--admin-key`` (HTTP 403, gRPC PERMISSION_DENIED,
    ``forbidden``)."""


class MoveConflict(McapiError):
    """A shard-move step that does not fit the shard's state on the replica,
    or whose epoch is not above the replica's (HTTP 409, gRPC
    FAILED_PRECONDITION, ``move_conflict``); nothing was done."""


class SequenceRefused(McapiError):
    """An observation's ``seq`` does not fit the session (HTTP 409, gRPC
    FAILED_PRECONDITION): beyond the next one (``seq_gap``), older than the
    replay window (``seq_expired``) or applied with other content
    (``seq_conflict``); nothing was applied (docs/sessions.md, "Delivery
    guarantees"). Never retried.

    Attributes:
        expected_seq: For ``seq_gap``, the seq the session expects next (REST
            ``expected_seq``, gRPC trailer ``x-mcapi-expected-seq``).
        oldest_seq: For ``seq_expired``, the oldest seq still replayed.
        seq: The first seq the refused request carried, when a client numbered it.
    """

    expected_seq: int | None = None
    oldest_seq: int | None = None
    seq: int | None = None


class NotFound(McapiError):
    """No such session, or not one the caller's key may see (HTTP 404, gRPC NOT_FOUND)."""


class UnknownRoute(NotFound):
    """No such route (REST only; ``unknown_route``)."""


class LimitExceeded(McapiError):
    """A size limit of the server was exceeded (HTTP 413, gRPC RESOURCE_EXHAUSTED)."""


class PayloadTooLarge(LimitExceeded):
    """The request body is larger than the server accepts (``payload_too_large``)."""


class TooManySessions(LimitExceeded):
    """The server holds its maximum number of sessions (HTTP 429, ``too_many_sessions``)."""


class TooManyStreams(LimitExceeded):
    """The caller (its API key, or its address without keys) already holds the
    server's maximum of open event and ``Watch`` streams (HTTP 429,
    ``too_many_streams``); close one first."""


class QuotaExceeded(LimitExceeded):
    """The caller's API key (or, without keys, all clients together) would
    exceed its quota of sessions or of their estimated memory (HTTP 429,
    ``quota_exceeded``); delete sessions first."""


class Unavailable(McapiError):
    """The server cannot serve now: stopping, its queue is full, or the request
    did not finish within its request timeout (HTTP 503, gRPC UNAVAILABLE or
    DEADLINE_EXCEEDED with ``request_timeout``). Worth retrying later."""


class WrongReplica(Unavailable):
    """A replica of a cluster was asked about a session whose shard another
    replica owns (HTTP 421, gRPC UNAVAILABLE, ``wrong_replica``): the router's
    map was stale. Nothing was done; the clients retry it through the router
    (see :class:`~mcapi_client.RetryPolicy`).

    Attributes:
        owner: The replica that owns the shard (the ``x-mcapi-owner`` header
            or trailer), when the server named it.
    """

    owner: str | None = None


class TransportError(Unavailable):
    """The server could not be reached, or the connection broke (client-side
    code ``transport_error``; no status)."""


class Timeout(McapiError):
    """The call did not finish within the client's timeout (client-side code
    ``timeout``; gRPC DEADLINE_EXCEEDED)."""


class InternalError(McapiError):
    """A fault of the server, not the caller's (HTTP 500, gRPC INTERNAL)."""


class SessionFailed(InternalError):
    """An update of the session failed inside the server and the session is
    quarantined (HTTP 500, ``session_failed``): delete it and create it again."""


# The server's stable codes (crates/mcapi-server/src/api/error.rs) with their class and HTTP status.
ERROR_CODES: Final[dict[str, tuple[type[McapiError], int]]] = {
    "bad_request": (BadRequest, 400),
    "column_length": (BadRequest, 400),
    "invalid_mask": (BadRequest, 400),
    "sequence_out_of_order": (BadRequest, 400),
    "invalid_model": (InvalidModel, 400),
    "invalid_basis": (InvalidModel, 400),
    "invalid_parameter": (InvalidParameter, 400),
    "unknown_state": (InvalidObservation, 400),
    "unknown_action": (InvalidObservation, 400),
    "action_not_available": (InvalidObservation, 400),
    "stimulus_length": (InvalidObservation, 400),
    "non_finite_number": (InvalidObservation, 400),
    "stimulus_too_large": (InvalidObservation, 400),
    "first_observation": (InvalidObservation, 400),
    "missing_stimulus": (InvalidObservation, 400),
    "invalid_observation": (InvalidObservation, 400),
    "unauthenticated": (Unauthenticated, 401),
    "forbidden": (Forbidden, 403),
    "move_conflict": (MoveConflict, 409),
    "seq_gap": (SequenceRefused, 409),
    "seq_expired": (SequenceRefused, 409),
    "seq_conflict": (SequenceRefused, 409),
    "not_found": (NotFound, 404),
    "unknown_route": (UnknownRoute, 404),
    "method_not_allowed": (UnknownRoute, 405),
    "limit_exceeded": (LimitExceeded, 413),
    "payload_too_large": (PayloadTooLarge, 413),
    "too_many_sessions": (TooManySessions, 429),
    "too_many_streams": (TooManyStreams, 429),
    "quota_exceeded": (QuotaExceeded, 429),
    "session_failed": (SessionFailed, 500),
    "request_timeout": (Unavailable, 503),
    "unavailable": (Unavailable, 503),
    "storage_unavailable": (Unavailable, 503),
    "wrong_replica": (WrongReplica, 421),
    "shard_moving": (Unavailable, 503),
    "responses_busy": (Unavailable, 503),
    "numerical_failure": (InternalError, 500),
    "internal": (InternalError, 500),
    "internal_panic": (InternalError, 500),
}
"""Each stable error code of the server: the exception class raised for it
and the HTTP status it comes with."""

# Fallbacks for codes this client does not know (a newer server).
_BY_STATUS: Final[dict[int, type[McapiError]]] = {
    400: BadRequest,
    401: Unauthenticated,
    403: Forbidden,
    404: NotFound,
    409: MoveConflict,
    413: LimitExceeded,
    429: TooManySessions,
    503: Unavailable,
}

_BY_GRPC: Final[dict[str, tuple[type[McapiError], int | None]]] = {
    "INVALID_ARGUMENT": (BadRequest, 400),
    "UNAUTHENTICATED": (Unauthenticated, 401),
    "PERMISSION_DENIED": (Forbidden, 403),
    "FAILED_PRECONDITION": (MoveConflict, 409),
    "NOT_FOUND": (NotFound, 404),
    "RESOURCE_EXHAUSTED": (LimitExceeded, 413),
    # gRPC's own message-size limit (tonic refuses an oversized message so).
    "OUT_OF_RANGE": (LimitExceeded, 413),
    "UNAVAILABLE": (Unavailable, 503),
    "DEADLINE_EXCEEDED": (Timeout, None),
    "INTERNAL": (InternalError, 500),
    "UNKNOWN": (InternalError, 500),
}


def error_for(
    code: str | None,
    message: str,
    *,
    status: int | None = None,
    grpc_code: str | None = None,
) -> McapiError:
    """The exception for a server error.

    A known ``code`` decides the class and the HTTP status. An unknown or
    missing code falls back on the HTTP ``status`` (REST) or the gRPC status
    name ``grpc_code``, and the code becomes ``http_<status>`` or the
    lower-cased gRPC name.

    Args:
        code: The stable code the server sent, if any.
        message: The server's message.
        status: The HTTP status of a REST reply.
        grpc_code: The gRPC status name (``"NOT_FOUND"``) of a gRPC reply.
    """
    if code is not None and code in ERROR_CODES:
        cls, known_status = ERROR_CODES[code]
        return cls(message, code=code, status=known_status, grpc_code=grpc_code)
    if grpc_code is not None:
        cls, grpc_status = _BY_GRPC.get(grpc_code, (McapiError, None))
        return cls(
            message,
            code=code or grpc_code.lower(),
            status=status if status is not None else grpc_status,
            grpc_code=grpc_code,
        )
    if status is not None:
        cls = _BY_STATUS.get(status, InternalError if status >= 500 else McapiError)
        return cls(message, code=code or f"http_{status}", status=status)
    return McapiError(message, code=code or "unknown")


def one_line(e: McapiError) -> str:
    """An error as one line for the person running a script: what to do
    about a missing or wrong API key or an unreachable server, else the
    server's stable code and message."""
    if isinstance(e, Unauthenticated):
        return "this server needs an API key: --api-key or MCAPI_API_KEY"
    if isinstance(e, TransportError):
        return f"cannot reach the server ({e.message}); is `mcapi serve` running there?"
    return f"{e.code}: {e.message}"
