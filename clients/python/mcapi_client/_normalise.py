"""Numbers at the boundary: numpy scalars and arrays (and anything else that
speaks Python's number protocols) become plain ``int``, ``float`` and
``list`` before they reach JSON or protobuf.

Nothing here imports numpy. The rules, by duck typing:

- an integer is anything :func:`operator.index` takes (``int``,
  ``numpy.int64``, a 0-d integer array); ``bool`` and ``numpy.bool_`` are
  refused, since a flag is not a state or a count, and so are floats, even
  integral ones (``2.0`` is not a state);
- a float is a ``float``, an integer as above, or anything with
  ``__float__`` (``numpy.float32``, ``decimal.Decimal``); ``bool`` and
  strings are refused. NaN and infinity pass: the server answers them (the
  REST observation path refuses them before sending, JSON having no way to
  carry them);
- a vector is any iterable of those (a list, a tuple, a 1-d array), an
  object with ``tolist()`` (numpy) being read through it; strings, bytes
  and mappings are refused.

Objects with ``tolist()`` (numpy scalars and arrays, torch tensors) are read
through it: it returns plain Python values, so a ``numpy.bool_`` shows up as
a ``bool`` and is refused like one.
"""

from __future__ import annotations

import operator
from collections.abc import Iterable, Mapping
from typing import Any, Protocol, SupportsFloat, SupportsIndex, Union, runtime_checkable

__all__ = [
    "IntLike",
    "FloatLike",
    "FloatsLike",
    "SupportsToList",
    "as_int",
    "as_opt_int",
    "as_float",
    "as_opt_float",
    "as_floats",
    "as_opt_floats",
    "is_int_like",
    "plain",
]


@runtime_checkable
class SupportsToList(Protocol):
    """An array-like with ``tolist()`` (a numpy array, a torch tensor)."""

    def tolist(self) -> Any: ...


IntLike = SupportsIndex
"""An integer: ``int``, ``numpy.int64``, ... (what :func:`operator.index` takes)."""

FloatLike = Union[SupportsFloat, SupportsIndex]
"""A real number: ``float``, ``int``, ``numpy.float32``, ``numpy.int64``, ..."""

FloatsLike = Union[Iterable[FloatLike], SupportsToList]
"""A vector of real numbers: a list or tuple of them, or a 1-d numpy array."""


def _kind(x: object) -> str:
    return type(x).__name__


def _through_tolist(x: object) -> object:
    """``x.tolist()`` for numpy-likes (scalars give a plain scalar), else ``x``."""
    if isinstance(x, (int, float, str, bytes)):
        return x
    tolist = getattr(type(x), "tolist", None)
    return tolist(x) if callable(tolist) else x


def as_int(x: object, name: str) -> int:
    """``x`` as a plain ``int``.

    Raises:
        TypeError: ``x`` is a bool, a float or not a number; the message names ``name``.
    """
    if isinstance(x, bool):
        raise TypeError(f"`{name}` must be an integer, not a bool ({x!r})")
    if isinstance(x, int):
        return int(x)
    y = _through_tolist(x)
    if isinstance(y, bool):
        raise TypeError(f"`{name}` must be an integer, not a bool ({x!r})")
    try:
        return operator.index(y)  # type: ignore[arg-type]
    except TypeError:
        raise TypeError(f"`{name}` must be an integer, not {_kind(x)} ({x!r})") from None


def as_opt_int(x: object, name: str) -> int | None:
    """:func:`as_int`, ``None`` kept."""
    return None if x is None else as_int(x, name)


def is_int_like(x: object) -> bool:
    """Whether :func:`as_int` takes ``x`` (an integer, not a bool)."""
    try:
        as_int(x, "")
    except TypeError:
        return False
    return True


def as_float(x: object, name: str) -> float:
    """``x`` as a plain ``float`` (NaN and infinity included).

    Raises:
        TypeError: ``x`` is a bool, a string or not a number; the message names ``name``.
    """
    if isinstance(x, bool):
        raise TypeError(f"`{name}` must be a number, not a bool ({x!r})")
    if isinstance(x, (float, int)):
        return float(x)
    if isinstance(x, (str, bytes)):
        raise TypeError(f"`{name}` must be a number, not {_kind(x)} ({x!r})")
    y = _through_tolist(x)
    if isinstance(y, bool):
        raise TypeError(f"`{name}` must be a number, not a bool ({x!r})")
    if isinstance(y, (float, int)):
        return float(y)
    if isinstance(y, SupportsFloat):
        return float(y)
    if isinstance(y, SupportsIndex):
        return float(operator.index(y))
    raise TypeError(f"`{name}` must be a number, not {_kind(x)} ({x!r})")


def as_opt_float(x: object, name: str) -> float | None:
    """:func:`as_float`, ``None`` kept."""
    return None if x is None else as_float(x, name)


def as_floats(xs: object, name: str) -> list[float]:
    """``xs`` as a plain ``list[float]``, element by element.

    Raises:
        TypeError: ``xs`` is not a vector, or an element is not a number
            (the message names it as ``name[i]``).
    """
    if isinstance(xs, (str, bytes, Mapping)):
        raise TypeError(f"`{name}` must be a sequence of numbers, not {_kind(xs)}")
    ys = _through_tolist(xs)
    if not isinstance(ys, Iterable) or isinstance(ys, (str, bytes, Mapping)):
        raise TypeError(f"`{name}` must be a sequence of numbers, not {_kind(xs)} ({xs!r})")
    return [as_float(x, f"{name}[{i}]") for i, x in enumerate(ys)]


def as_opt_floats(xs: object, name: str) -> list[float] | None:
    """:func:`as_floats`, ``None`` kept."""
    return None if xs is None else as_floats(xs, name)


def plain(value: Any) -> Any:
    """A JSON value made of plain Python types: mappings become dicts (keys
    that are integers become ``int``), sequences and arrays lists, numpy
    scalars their Python equivalent; bools stay bools. Anything else is left
    for the JSON encoder to refuse."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value)
    if isinstance(value, Mapping):
        return {plain(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    y = _through_tolist(value)
    if y is not value:
        return plain(y)
    if isinstance(value, SupportsIndex):
        return operator.index(value)
    if isinstance(value, SupportsFloat):
        return float(value)
    return value

