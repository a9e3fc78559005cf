"""Exactly-once delivery: the ``seq`` of each observation a client sends,
per session, without I/O (docs/sessions.md, "Delivery guarantees").

A client numbers the observations it sends to a session 0, 1, 2, ... in the
order it sends them: :class:`Sequences` remembers, per session, the seq of
the next one. It learns where a session stands from the session it created
(``next_seq`` 0) or, for one it did not create, from ``next_seq`` of
``GetSession`` before its first observation (one round trip per session);
a server without sequence numbers (no ``next_seq``) gets unnumbered
observations. A numbered observation can be sent again after any failure:
the server applies a seq once and answers a resend with the recorded reply
(``replayed``), so the clients retry numbered calls on a lost answer too
(:data:`mcapi_client.retry.RESEND_CODES`).

What the client believes after a call that finally failed, for the
observations ``[seq, seq + n)`` it carried:

- **No answer** (the retries ran out on a broken connection or a timeout):
  they may or may not have been applied. The next call takes ``seq`` again:
  the same observation sent again is then applied once (or replayed); another
  one is refused with ``seq_conflict`` if the lost one was applied after
  all, and then the client reads ``next_seq`` and sends it with that (the
  lost one stays applied, as if its reply had arrived).
- **Refused** (a 4xx, a 5xx with mcapi's body: nothing applied): one
  observation's seq is taken again; a batch's (whose first observations may
  have been applied before an invalid one) is read from the server on next use.
- **``seq_gap``** (the server has applied fewer than the client believes:
  it lost acknowledged observations, e.g. an in-memory store restarted under
  the same id, or ``--durability os`` after a power cut): raised, and the
  next call goes on from the ``expected_seq`` the server named.
- **``seq_conflict``, ``seq_expired``** (another writer numbered this
  session's observations, or a resend came too late): raised; the next call
  reads ``next_seq`` again.

A session must have one numbering writer: a client that observes a session
also stepped elsewhere (another client, a group) at the same time would
number its observations from a stale count (refused as ``seq_conflict``
unless the content happens to match). A client's own ``InteractBatch``
steps are unnumbered and make it forget the count of each session they
step, so it is read again before that session's next numbered observation.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from ._sansio import Op, SessionCache
from .errors import McapiError, SequenceRefused
from .retry import RESEND_CODES

__all__ = ["Sequences", "numbered"]

R = TypeVar("R")


class _Entry:
    __slots__ = ("next", "uncertain")

    def __init__(self, next_seq: int | None) -> None:
        self.next = next_seq
        self.uncertain: int | None = None  # the first seq of a call that got no answer


class Sequences:
    """Per session, the seq of the next observation this client sends
    (thread-safe; the most recent sessions are remembered, the others read
    again from the server when next used)."""

    def __init__(self, capacity: int = 4096) -> None:
        self._lock = threading.Lock()
        self._entries: SessionCache[_Entry] = SessionCache(capacity)

    def learn(self, session_id: str, next_seq: int | None, *, force: bool = False) -> None:
        """What the server says of a session (``next_seq`` of a creation or a
        read); kept only if nothing is known yet, or ``force``."""
        with self._lock:
            if force or self._entries.get(session_id) is None:
                self._entries.put(session_id, _Entry(next_seq))

    def forget(self, session_id: str) -> None:
        """Forgets a session: its count is read again before its next
        numbered observation."""
        with self._lock:
            self._entries.drop(session_id)

    def next_seq(self, session_id: str) -> int | None:
        """The seq the next observation would take, if known."""
        with self._lock:
            entry = self._entries.get(session_id)
            return entry.next if entry is not None else None

    def take(self, session_id: str, n: int) -> tuple[bool, int | None]:
        """Reserves ``n`` consecutive seqs: ``(known, first)``; ``known``
        false: read the session first; ``first`` ``None``: the server does
        not number observations."""
        with self._lock:
            entry = self._entries.get(session_id)
            if entry is None:
                return False, None
            first = entry.next
            if first is not None:
                entry.next = first + n
            return True, first

    def answered(self, session_id: str, first: int, n: int) -> None:
        """``[first, first + n)`` were applied (or replayed)."""
        with self._lock:
            entry = self._entries.get(session_id)
            if entry is None:
                self._entries.put(session_id, _Entry(first + n))
                return
            entry.uncertain = None
            if entry.next is None or entry.next < first + n:
                entry.next = first + n

    def failed(self, session_id: str, first: int, n: int, error: McapiError) -> bool:
        """A numbered call of ``[first, first + n)`` finally failed with
        ``error``: what to believe next (see the module's text). Returns
        ``True`` when the call should be numbered again and resent: a
        ``seq_conflict`` on the seq of an earlier call that got no answer,
        which was therefore applied."""
        with self._lock:
            entry = self._entries.get(session_id)
            if entry is None:
                return False
            last = entry.next == first + n  # no later seq was taken meanwhile
            if error.code == "seq_conflict" and entry.uncertain == first:
                self._entries.drop(session_id)
                return True
            if error.code in RESEND_CODES or error.code == "cancelled":
                if last:
                    entry.next, entry.uncertain = first, first
                else:
                    self._entries.drop(session_id)
            elif error.code == "seq_gap" and isinstance(error, SequenceRefused):
                if last and error.expected_seq is not None:
                    entry.next, entry.uncertain = error.expected_seq, None
                else:
                    self._entries.drop(session_id)
            elif error.code in ("seq_conflict", "seq_expired") or n != 1 or not last:
                self._entries.drop(session_id)
            else:
                entry.next = first
            return False


def numbered(
    seqs: Sequences | None,
    session_id: str,
    encoded: Sequence[Any],
    given: int | None,
    set_seq: Callable[[Any, int], None],
    request: Callable[[bool], R],
    learn: Callable[[], Op[R, Any]],
) -> Op[R, Any]:
    """Sends observations numbered: the operation of ``observe`` and
    ``observe_batch`` over both transports, returning the raw reply.

    Args:
        seqs: The client's counts; ``None``: send unnumbered (at least once).
        session_id: The session.
        encoded: The observations as sent (JSON objects or messages), each
            given its seq by ``set_seq`` in place.
        given: The first observation's own seq, if the caller gave one:
            sent as given (and the count follows it).
        set_seq: Sets one encoded observation's seq.
        request: The request of the encoded observations; its argument:
            whether it may be sent again after a lost answer.
        learn: The operation that reads the session (its ``next_seq``) into ``seqs``.
    """
    n = len(encoded)
    if seqs is None or n == 0 or given is not None:
        try:
            reply = yield request(given is not None)
        except SequenceRefused as e:
            e.seq = given
            raise
        if given is not None and seqs is not None:
            seqs.answered(session_id, given, n)
        return reply
    for attempt in range(2):
        known, first = seqs.take(session_id, n)
        if not known:
            yield from learn()
            known, first = seqs.take(session_id, n)
        if first is None:  # a server without sequence numbers
            return (yield request(False))
        for i, obs in enumerate(encoded):
            set_seq(obs, first + i)
        try:
            reply = yield request(True)
        except McapiError as e:
            if isinstance(e, SequenceRefused):
                e.seq = first
            if seqs.failed(session_id, first, n, e) and attempt == 0:
                continue
            raise
        seqs.answered(session_id, first, n)
        return reply
    raise AssertionError("unreachable")  # pragma: no cover
