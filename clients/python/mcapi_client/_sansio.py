"""What the four clients share without doing any I/O: operations written once
as generators, the drivers that run them blocking or under asyncio, and the
per-session cache of model shapes.

An operation is a generator that yields the requests it needs (a REST
:class:`~mcapi_client._protocol.Request` or a gRPC
:class:`~mcapi_client._pb.Call`), is sent each reply, and returns the typed
result; an operation that needs another one first (``history`` of a
session whose action names are not known yet) delegates with ``yield
from``. A client's method only builds the operation and hands it to its
driver with the function that does the I/O:

    def observe(self, session_id, state, ...):          # Client
        return drive(self._protocol.observe(...), self._send)

    async def observe(self, session_id, state, ...):    # AsyncClient
        return await adrive(self._protocol.observe(...), self._send)

So request building, reply decoding, error mapping and caching are one code
path for the blocking and the asyncio client of a transport, and a test can
step an operation by hand without a server.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Generator
from typing import Any, Generic, TypeVar

from .errors import McapiError

__all__ = ["Op", "drive", "adrive", "SessionCache"]

R = TypeVar("R")
T = TypeVar("T")
V = TypeVar("V")

Op = Generator[R, Any, T]
"""An operation: yields requests of type ``R``, is sent their replies, returns a ``T``."""


def drive(op: Generator[R, Any, T], send: Callable[[R], Any]) -> T:
    """Runs ``op`` to its result, ``send`` doing each request's I/O (blocking).
    A request's :class:`~mcapi_client.McapiError` is thrown into ``op`` (which
    may handle it, as numbered observations do, or let it through)."""
    try:
        request = next(op)
        while True:
            try:
                reply = send(request)
            except McapiError as e:
                request = op.throw(e)
            else:
                request = op.send(reply)
    except StopIteration as done:
        result: T = done.value
        return result
    finally:
        op.close()


async def adrive(op: Generator[R, Any, T], send: Callable[[R], Awaitable[Any]]) -> T:
    """Runs ``op`` to its result, awaiting ``send`` for each request's I/O
    (errors thrown into ``op`` as by :func:`drive`)."""
    try:
        request = next(op)
        while True:
            try:
                reply = await send(request)
            except McapiError as e:
                request = op.throw(e)
            else:
                request = op.send(reply)
    except StopIteration as done:
        result: T = done.value
        return result
    finally:
        op.close()


class SessionCache(Generic[V]):
    """What a client remembers per session (its action names, its shape),
    for the most recent ``capacity`` sessions it saw."""

    def __init__(self, capacity: int = 1024) -> None:
        self._capacity = capacity
        self._items: dict[str, V] = {}

    def get(self, session_id: str) -> V | None:
        """The entry of a session, if remembered."""
        return self._items.get(session_id)

    def put(self, session_id: str, value: V) -> None:
        """Remembers a session's entry (the newest), forgetting the oldest beyond capacity."""
        self._items.pop(session_id, None)
        self._items[session_id] = value
        while len(self._items) > self._capacity:
            del self._items[next(iter(self._items))]

    def drop(self, session_id: str) -> None:
        """Forgets a session (deleted)."""
        self._items.pop(session_id, None)
