"""Retrying what a cluster refuses without doing anything (docs/cluster.md):
a replica asked about a shard it does not own (HTTP 421 / gRPC UNAVAILABLE,
``wrong_replica``), a shard being moved (503 ``shard_moving``), a replica
that is starting, stopping or whose queue is full (503 ``unavailable``), a
store that could not commit (503 ``storage_unavailable``, rolled back), and,
over REST, a router that found no replica to send the request to (a 503
without mcapi's error body). Each of these means the request had no effect,
so every call, observations included, is retried, with jittered exponential
backoff, until the policy's deadline; the last error is then raised.

Not retried: ``request_timeout`` (the request may have taken effect), a
connection that could not be made or broke (``transport_error``: over gRPC a
router's own 503 arrives as one), and every other error. A refused
``interact`` or ``watch`` stream is not reopened: the caller opens it again.

    from mcapi_client import Client, RetryPolicy

    Client(url, retry=RetryPolicy(deadline=30.0))   # longer shard moves
    Client(url, retry=None)                          # no retries
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from dataclasses import dataclass, field

from .errors import McapiError

__all__ = ["RetryPolicy", "DEFAULT_RETRY", "RETRYABLE_CODES"]

RETRYABLE_CODES: frozenset[str] = frozenset(
    {"wrong_replica", "shard_moving", "unavailable", "storage_unavailable", "http_503", "http_421"}
)
"""Error codes that mean "nothing was done, try again": the server's, and
``http_503`` / ``http_421`` for a router's reply without mcapi's error body."""


@dataclass(frozen=True)
class RetryPolicy:
    """When and how long to retry a refused call.

    Attributes:
        deadline: Seconds from the first attempt after which no retry starts.
        initial_backoff: The first wait's upper bound, in seconds.
        max_backoff: The largest upper bound of a wait.
        multiplier: Growth of the bound per attempt.
        codes: The error codes retried.
        rng: The source of jitter (seed it for reproducible tests).
    """

    deadline: float = 10.0
    initial_backoff: float = 0.05
    max_backoff: float = 1.0
    multiplier: float = 2.0
    codes: frozenset[str] = RETRYABLE_CODES
    rng: random.Random = field(default_factory=random.Random, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not (self.deadline >= 0 and self.initial_backoff > 0 and self.max_backoff > 0):
            raise ValueError("deadline must be >= 0 and the backoffs > 0")
        if self.multiplier < 1:
            raise ValueError("multiplier must be >= 1")

    def retries(self, error: McapiError) -> bool:
        """Whether ``error`` is one this policy retries."""
        return error.code in self.codes

    def waits(self) -> Iterator[float]:
        """The waits before each retry: "full jitter", uniform in [0, bound]
        with the bound growing from ``initial_backoff`` to ``max_backoff``."""
        bound = self.initial_backoff
        while True:
            yield self.rng.uniform(0.0, bound)
            bound = min(self.max_backoff, bound * self.multiplier)


DEFAULT_RETRY = RetryPolicy()
"""The clients' default: retries for up to 10 seconds."""


class Attempts:
    """The retry loop's state for one call: call :meth:`next_wait` with each
    refusal; it returns the seconds to wait, or ``None`` to give up."""

    def __init__(self, policy: RetryPolicy | None, now: float) -> None:
        self._policy = policy
        self._end = now + (policy.deadline if policy is not None else 0.0)
        self._waits = policy.waits() if policy is not None else iter(())
        self.count = 0

    def next_wait(self, error: McapiError, now: float, retry_after: float | None = None) -> float | None:
        """The wait before the next attempt after ``error``; ``None``: raise it."""
        if self._policy is None or not self._policy.retries(error):
            return None
        wait = next(self._waits)
        if retry_after is not None:
            wait = max(wait, min(retry_after, self._policy.max_backoff))
        if now + wait > self._end:
            return None
        self.count += 1
        return wait
