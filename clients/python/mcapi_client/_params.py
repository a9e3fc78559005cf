"""The agent options of a session, one per parameter of the server's table.

Generated from the parameter tables of mcapi-core and mcapi-server by
`make generate`; do not edit by hand (a test fails when it differs).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final, TypedDict

if TYPE_CHECKING:
    from ._inputs import CuriosityLike, StimulusRate, UpdateMode
    from ._normalise import FloatLike, FloatsLike, IntLike


class AgentKwargs(TypedDict, total=False):
    """The agent options of ``create_session``; one left out takes the server's default."""

    eta: FloatLike | None
    """MCA learning rate eta of Eq. 1, in (0, 0.5]; default 0.01."""
    gamma: FloatLike | None
    """Discount gamma, in [0, 1); default 0.95."""
    priorities: FloatsLike | None
    """Priorities rho, one per stimulus dimension, a curiosity dimension included (Lambda =
    diag(1/rho)), in [1e-6, 1]; default all 1."""
    stimulus_rate: StimulusRate | FloatLike | None
    """How Xi learns: the sample mean of each pair, or a constant rate; default "sample_mean"."""
    optimistic_sd: FloatLike | None
    """Sigma of the optimistic initial draw of Xi, in [0, 1e12]; default 0.3."""
    ridge: FloatLike | None
    """Ridge lambda added to A only when A is singular, in [1e-12, 1e6]; default 1e-6."""
    epsilon: FloatLike | None
    """Epsilon of epsilon-greedy exploration, in [0, 1]; default 0."""
    seed: IntLike | None
    """Seed of the session's RNG (returned, so a session can be made again); default drawn by the
    server."""
    update_mode: UpdateMode | None
    """"lockstep": the reply follows exactly one policy update; "async": the reply comes at once and
    the tick loop updates behind it; default "lockstep"."""
    history: IntLike | None
    """Recent ticks kept for /history; default 256."""
    curiosity: CuriosityLike | None
    """A curiosity channel: the server appends a stimulus dimension "curiosity", last, and computes
    it from the raw "signal" of observations; default none."""


AGENT_OPTIONS: Final[tuple[str, ...]] = (
    "eta",
    "gamma",
    "priorities",
    "stimulus_rate",
    "optimistic_sd",
    "ridge",
    "epsilon",
    "seed",
    "update_mode",
    "history",
    "curiosity",
)
"""The keys of :class:`AgentKwargs`, in the server's order."""

AGENT_KINDS: Final[dict[str, str]] = {
    "eta": "real",
    "gamma": "real",
    "priorities": "per_stimulus",
    "stimulus_rate": "real_or_name",
    "optimistic_sd": "real",
    "ridge": "real",
    "epsilon": "real",
    "seed": "integer",
    "update_mode": "choice",
    "history": "integer",
    "curiosity": "object",
}
"""What each option holds: "real", "integer", "per_stimulus", "real_or_name",
"choice" or "object" (the readers of a session's configuration follow it)."""

CURIOSITY_PARAMS: Final[tuple[str, ...]] = (
    "max_centres",
    "beta",
    "tau",
    "lag",
    "eta_c",
    "gain",
    "clip",
    "delta",
    "freeze_after",
    "explain_below",
    "explain_min_samples",
    "dt",
    "floor_rel",
    "floor_abs",
    "initial_error",
    "max_sources",
)
"""The constants of a curiosity channel (the keys of ``CuriosityConfig.params``)."""
