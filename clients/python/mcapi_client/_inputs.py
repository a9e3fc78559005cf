"""The inputs an agent option may take beyond plain numbers: the update
mode, the stimulus rate and a curiosity channel.

They live below :mod:`mcapi_client.types` (which re-exports them) so that
the generated options of :mod:`mcapi_client._params` can name them without
importing the module that imports the options.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, SupportsIndex, Union

from ._normalise import IntLike, as_int, is_int_like, plain

UpdateMode = Literal["lockstep", "async"]
"""``"lockstep"``: each reply comes after exactly one policy update (the
paper's Algorithm 1, reproducible for a seed); ``"async"``: the reply comes at
once and the server's tick loop improves the policy behind it."""

StimulusRate = Union[Literal["sample_mean"], float]
"""The learning rate of the stimulus function: the named rule
``"sample_mean"`` (rate 1/n(s, a)) or a constant in (0, 1]."""


@dataclass(frozen=True, slots=True, init=False)
class CuriosityConfig:
    """A session's curiosity channel (the paper's section on curiosity-driven
    learning; docs/algorithm.md section 7 of the server).

    A session created with one gets an extra stimulus dimension named
    ``"curiosity"``, last in ``model.stimuli``: the server computes it, as
    xi_cur, from raw signal samples the client sends with observations
    (``signal=``). The client sends only the extrinsic stimulus components.

    Attributes:
        signal_dim: Dimension m of the raw signal x(t), at least 1 (2 for
            the paper's Eq. 6).
        params: The channel's constants, every key optional (e.g.
            ``{"gain": 800, "delta": 0.3}``); ``None`` or ``{}`` take the
            server's defaults. In a session's effective configuration every
            constant is filled in.
    """

    signal_dim: int
    params: dict[str, Any] | None

    def __init__(self, signal_dim: IntLike, params: Mapping[str, Any] | None = None) -> None:
        object.__setattr__(self, "signal_dim", as_int(signal_dim, "curiosity.signal_dim"))
        object.__setattr__(self, "params", None if params is None else plain(dict(params)))

    def to_json(self) -> dict[str, object]:
        """The ``agent.curiosity`` object of a REST create request."""
        out: dict[str, object] = {"signal_dim": self.signal_dim}
        if self.params is not None:
            out["params"] = dict(self.params)
        return out


CuriosityLike = Union[CuriosityConfig, Mapping[str, Any], SupportsIndex]
"""A curiosity channel to create a session with: a :class:`CuriosityConfig`,
its JSON (``{"signal_dim": 2, "params": {...}}``), or just the signal
dimension (every constant at its default)."""


def as_curiosity(c: CuriosityLike) -> CuriosityConfig:
    """Normalises a ``curiosity=`` argument to a :class:`CuriosityConfig`."""
    if isinstance(c, CuriosityConfig):
        return c
    if isinstance(c, bool):
        raise TypeError("curiosity: give the signal dimension or a CuriosityConfig, not a bool")
    if is_int_like(c):
        return CuriosityConfig(signal_dim=c)  # type: ignore[arg-type]
    if isinstance(c, Mapping):
        unknown = set(c) - {"signal_dim", "params"}
        if unknown:
            raise TypeError(f"unknown curiosity keys: {sorted(unknown)}")
        return CuriosityConfig(signal_dim=c["signal_dim"], params=c.get("params"))
    raise TypeError(f"not a curiosity channel: {c!r}")
