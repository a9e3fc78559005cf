"""Retrying what a cluster refuses without doing anything (docs/cluster.md):
a replica asked about a shard it does not own (HTTP 421 / gRPC UNAVAILABLE,
``wrong_replica``), a shard being moved (503 ``shard_moving``), a replica
that is starting, stopping or whose queue is full (503 ``unavailable``), a
store that could not commit (503 ``storage_unavailable``, rolled back), and,
over REST, a router that found no replica to send the request to (a 503
without mcapi's error body). Each of these means the request had no effect,
so every call, observations included, is retried, with jittered exponential
backoff, until the policy's deadline; the last error is then raised.

Observations the clients number (``seq``, the default: see the README's
"Delivery") are safe to send again whatever happened to the first send, as
the server answers a resent seq with its recorded reply and applies nothing.
So those calls, and an ``interact`` stream that breaks, are also retried on
what may have taken effect (:data:`RESEND_CODES`): no answer, a connection
refused or reset (``transport_error``; over gRPC ``UNAVAILABLE`` without
mcapi's trailer), the client's ``timeout`` if the deadline leaves room,
``request_timeout``, a stream that ended without a reply, a router's 502 or
504. Every other call keeps the rule above: not retried on those, as the
request may have taken effect; nor on any other error.

Each retry is counted in the client's :class:`RetryCounter` (``client.retries``,
by reason: the error code) and logged at DEBUG on the ``mcapi_client`` logger.

    from mcapi_client import Client, RetryPolicy

    Client(url, retry=RetryPolicy(deadline=30.0))   # longer shard moves
    Client(url, retry=None)                          # no retries
    mc = Client(url); ...; print(mc.retries.total, mc.retries.by_reason())
"""

from __future__ import annotations

import logging
import random
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field

from .errors import McapiError

__all__ = ["RetryPolicy", "RetryCounter", "DEFAULT_RETRY", "RETRYABLE_CODES", "RESEND_CODES"]

log = logging.getLogger("mcapi_client")

RETRYABLE_CODES: frozenset[str] = frozenset(
    {"wrong_replica", "shard_moving", "unavailable", "storage_unavailable", "http_503", "http_421"}
)
"""Error codes that mean "nothing was done, try again": the server's, and
``http_503`` / ``http_421`` for a router's reply without mcapi's error body."""

RESEND_CODES: frozenset[str] = frozenset(
    {"transport_error", "timeout", "request_timeout", "stream_closed", "http_502", "http_504"}
)
"""Error codes after which the request may or may not have taken effect:
retried only for numbered observations (``seq``), which the server applies
at most once however often they arrive."""


@dataclass(frozen=True)
class RetryPolicy:
    """When and how long to retry a refused call.

    Attributes:
        deadline: Seconds from the first attempt after which no retry starts.
        initial_backoff: The first wait's upper bound, in seconds.
        max_backoff: The largest upper bound of a wait.
        multiplier: Growth of the bound per attempt.
        codes: The error codes retried for every call.
        resend_codes: The error codes also retried for numbered
            observations (and broken ``interact`` streams, reopened).
        rng: The source of jitter (seed it for reproducible tests).
    """

    deadline: float = 10.0
    initial_backoff: float = 0.05
    max_backoff: float = 1.0
    multiplier: float = 2.0
    codes: frozenset[str] = RETRYABLE_CODES
    resend_codes: frozenset[str] = RESEND_CODES
    rng: random.Random = field(default_factory=random.Random, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not (self.deadline >= 0 and self.initial_backoff > 0 and self.max_backoff > 0):
            raise ValueError("deadline must be >= 0 and the backoffs > 0")
        if self.multiplier < 1:
            raise ValueError("multiplier must be >= 1")

    def retries(self, error: McapiError, resend: bool = False) -> bool:
        """Whether ``error`` is one this policy retries; ``resend``: the call
        is a numbered observation, safe to send again."""
        return error.code in self.codes or (resend and error.code in self.resend_codes)

    def waits(self) -> Iterator[float]:
        """The waits before each retry: "full jitter", uniform in [0, bound]
        with the bound growing from ``initial_backoff`` to ``max_backoff``."""
        bound = self.initial_backoff
        while True:
            yield self.rng.uniform(0.0, bound)
            bound = min(self.max_backoff, bound * self.multiplier)


DEFAULT_RETRY = RetryPolicy()
"""The clients' default: retries for up to 10 seconds."""


class RetryCounter:
    """The retries a client made, by reason (the code of the error retried:
    ``transport_error``, ``unavailable``, ...). Thread-safe; ``client.retries``.

        mc.retries.total                 # 3
        mc.retries["transport_error"]    # 2
        mc.retries.by_reason()           # {"transport_error": 2, "unavailable": 1}
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_reason: dict[str, int] = {}

    @property
    def total(self) -> int:
        """Retries of every reason."""
        with self._lock:
            return sum(self._by_reason.values())

    def __getitem__(self, reason: str) -> int:
        with self._lock:
            return self._by_reason.get(reason, 0)

    def by_reason(self) -> dict[str, int]:
        """A copy of the counts per reason."""
        with self._lock:
            return dict(self._by_reason)

    def record(self, reason: str, what: str, attempt: int, wait: float) -> None:
        """Counts one retry and logs it (DEBUG, logger ``mcapi_client``)."""
        with self._lock:
            self._by_reason[reason] = self._by_reason.get(reason, 0) + 1
        log.debug("mcapi_client: retry %d of %s after %s, in %.3f s", attempt, what, reason, wait)

    def __repr__(self) -> str:
        return f"RetryCounter({self.by_reason()!r})"


class Attempts:
    """The retry loop's state for one call: call :meth:`next_wait` with each
    refusal; it returns the seconds to wait, or ``None`` to give up.

    Args:
        policy: The policy; ``None``: never retry.
        now: The time of the first attempt (``time.monotonic()``).
        counter: Where each retry is counted and logged.
        what: The call, for the log line.
    """

    def __init__(
        self,
        policy: RetryPolicy | None,
        now: float,
        counter: RetryCounter | None = None,
        what: str = "",
    ) -> None:
        self._policy = policy
        self._end = now + (policy.deadline if policy is not None else 0.0)
        self._waits = policy.waits() if policy is not None else iter(())
        self._counter = counter
        self._what = what
        self.count = 0

    def next_wait(
        self,
        error: McapiError,
        now: float,
        retry_after: float | None = None,
        resend: bool = False,
    ) -> float | None:
        """The wait before the next attempt after ``error``; ``None``: raise it.
        ``resend``: the call may be sent again after any error of
        ``policy.resend_codes`` (a numbered observation)."""
        if self._policy is None or not self._policy.retries(error, resend):
            return None
        wait = next(self._waits)
        if retry_after is not None:
            wait = max(wait, min(retry_after, self._policy.max_backoff))
        if now + wait > self._end:
            return None
        self.count += 1
        if self._counter is not None:
            self._counter.record(error.code, self._what, self.count, wait)
        return wait
