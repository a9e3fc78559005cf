"""Continuous worlds: observations are vectors in a box, not state numbers.

A :class:`ContinuousModel` is posted as the server's continuous model form
(docs/sessions.md, "Continuous worlds"); the session then takes
``observation=[x1, ..., xd]`` instead of ``state``, and learns the
transitions from what it observes. :class:`ContinuousEnvironment` adapts a
Gymnasium (or MO-Gymnasium) environment with a ``Box`` observation space and
``Discrete`` actions: it holds the model and steps the environment with the
session's actions, returning the observation and stimulus to report::

    world = models.from_gymnasium(env, stimuli=["goal"])
    step = mc.observe(session.id, observation=world.reset(seed=1))
    for _ in range(1000):
        s = world.step(step.action_index)
        step = mc.observe(session.id, observation=s.observation, stimulus=s.stimulus)

Made by :func:`mcapi_client.models.from_gymnasium` (without ``sources``) and
:func:`mcapi_client.models.from_mo_gymnasium` (``observations="continuous"``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from ._normalise import as_float, as_floats, as_int, plain

__all__ = [
    "MAX_DIM",
    "MAX_ACTIONS",
    "BASIS_KEYS",
    "SAMPLE_KEYS",
    "ContinuousModel",
    "ContinuousStep",
    "ContinuousEnvironment",
]

MAX_DIM = 64
"""The most dimensions of an observation space (the server's bound)."""

MAX_ACTIONS = 64
"""The most actions of a continuous world (the server's bound)."""

MAX_COORDINATE = 1e12
"""The largest magnitude of a box corner (the server's bound)."""


def _floats(values: Any, what: str) -> tuple[float, ...]:
    out = tuple(as_floats(values, what))
    for i, v in enumerate(out):
        if not math.isfinite(v) or abs(v) > MAX_COORDINATE:
            raise ValueError(
                f"`{what}[{i}]` is {v}: a bound must be finite and at most 1e12 in magnitude"
            )
    return out


BASIS_KEYS: dict[str, tuple[str, ...]] = {
    "fourier": ("order", "max_coupling"),
    "rbf": ("centres_per_dim", "width"),
    "tiles": ("tilings", "tiles_per_dim", "table"),
    "pvf": ("k", "nodes", "neighbours"),
    "grid": ("cells_per_dim", "neighbours", "reach"),
}
"""The bases of a continuous world, by ``kind``, and the fields each takes
(the server checks their values: docs/sessions.md, "Continuous worlds")."""

SAMPLE_KEYS = ("cells_per_dim", "per_cell", "max", "known_after")
"""The fields of ``samples``, every one optional."""


def _basis(basis: Any) -> dict[str, Any]:
    if not isinstance(basis, Mapping):
        raise TypeError(f"`basis` must be a mapping such as {{'kind': 'fourier', 'order': 5}}, not {basis!r}")
    out: dict[str, Any] = plain(dict(basis))
    kind = out.get("kind")
    if kind not in BASIS_KEYS:
        raise ValueError(f"`basis.kind` is {kind!r}; a continuous world takes {', '.join(BASIS_KEYS)}")
    unknown = sorted(set(out) - {"kind", *BASIS_KEYS[kind]})
    if unknown:
        raise ValueError(
            f"`basis` of kind {kind!r} has no field {unknown[0]!r} (it takes {', '.join(BASIS_KEYS[kind])})"
        )
    return out


def _samples(samples: Any) -> dict[str, int]:
    if not isinstance(samples, Mapping):
        raise TypeError(f"`samples` must be a mapping such as {{'max': 2048}}, not {samples!r}")
    out: dict[str, int] = {}
    for key, value in samples.items():
        if key not in SAMPLE_KEYS:
            raise ValueError(f"`samples` has no field {key!r} (it takes {', '.join(SAMPLE_KEYS)})")
        n = as_int(value, f"samples.{key}")
        if n < 0:
            raise ValueError(f"`samples.{key}` is {n}, not a count")
        out[key] = n
    return out


@dataclass(frozen=True)
class ContinuousModel:
    """A continuous world as the server takes it.

    Attributes:
        low: Lower corner of the box, one coordinate per dimension (1 to 64).
        high: Upper corner; each coordinate strictly above ``low``'s.
        actions: Action names, distinct (1 to 64).
        stimuli: Stimulus names, distinct (at least one).
        basis: The basis, e.g. ``{"kind": "fourier", "order": 5}``; ``None``
            for the server's default by dimension.
        out_of_bounds: ``"clip"`` (the server clips an observation outside
            the box and counts it) or ``"refuse"`` (400 ``invalid_observation``).
        samples: How the sample store is cut (``cells_per_dim``, ``per_cell``,
            ``max``, ``known_after``); ``None`` for the defaults.
    """

    low: tuple[float, ...]
    high: tuple[float, ...]
    actions: tuple[str, ...]
    stimuli: tuple[str, ...]
    basis: Mapping[str, Any] | None = None
    out_of_bounds: Literal["clip", "refuse"] = "clip"
    samples: Mapping[str, int] | None = None

    def __post_init__(self) -> None:
        put = object.__setattr__
        put(self, "low", _floats(self.low, "low"))
        put(self, "high", _floats(self.high, "high"))
        put(self, "actions", tuple(self.actions))
        put(self, "stimuli", tuple(self.stimuli))
        if self.basis is not None:
            put(self, "basis", _basis(self.basis))
        if self.samples is not None:
            put(self, "samples", _samples(self.samples))
        d = len(self.low)
        if not 1 <= d <= MAX_DIM:
            raise ValueError(f"the observation space has {d} dimensions; 1 to {MAX_DIM} are allowed")
        if len(self.high) != d:
            raise ValueError(f"`high` has {len(self.high)} coordinates, `low` {d}")
        for i, (lo, hi) in enumerate(zip(self.low, self.high)):
            if not lo < hi:
                raise ValueError(f"dimension {i}: `low` {lo} is not below `high` {hi}")
        if not 1 <= len(self.actions) <= MAX_ACTIONS:
            raise ValueError(f"{len(self.actions)} actions; 1 to {MAX_ACTIONS} are allowed")
        if not self.stimuli:
            raise ValueError("a continuous world needs at least one stimulus")
        for what, names in (("action", self.actions), ("stimulus", self.stimuli)):
            for i, n in enumerate(names):
                if not isinstance(n, str) or not n.strip():
                    raise ValueError(f"{what} {i} is {n!r}, not a name")
            if len(set(names)) != len(names):
                raise ValueError(f"duplicate {what} names: {list(names)}")
        if self.out_of_bounds not in ("clip", "refuse"):
            raise ValueError(f"`out_of_bounds` is {self.out_of_bounds!r}, not 'clip' or 'refuse'")

    @property
    def dim(self) -> int:
        """The dimension d of the observation space."""
        return len(self.low)

    @classmethod
    def from_json(cls, d: Mapping[str, Any], *, check: bool = True) -> ContinuousModel:
        """A model from its REST JSON (what :meth:`to_json` writes, and what a
        session's ``model.continuous`` holds: the model as the server built
        it, its basis and sample store filled in). ``check=False`` takes a
        server's reply as it is (a basis field this client does not know yet
        is kept, not refused)."""
        space = d["observation_space"]
        basis, samples = d.get("basis"), d.get("samples")
        fields: dict[str, Any] = {
            "low": tuple(as_floats(space["low"], "low")),
            "high": tuple(as_floats(space["high"], "high")),
            "actions": tuple(str(a) for a in d["actions"]),
            "stimuli": tuple(str(s) for s in d["stimuli"]),
            "basis": None if basis is None else plain(dict(basis)),
            "out_of_bounds": d.get("out_of_bounds", "clip"),
            "samples": None if samples is None else {str(k): int(v) for k, v in samples.items()},
        }
        if check:
            return cls(**fields)
        model = object.__new__(cls)
        for name, value in fields.items():
            object.__setattr__(model, name, value)
        return model

    def contains(self, observation: Any) -> bool:
        """Whether ``observation`` (a vector of d numbers) lies in the box;
        outside it, the server clips it (``"clip"``) or refuses it (``"refuse"``)."""
        x = as_floats(observation, "observation")
        return len(x) == self.dim and all(lo <= v <= hi for lo, v, hi in zip(self.low, x, self.high))

    def to_json(self) -> dict[str, Any]:
        """The model as the REST API takes it."""
        out: dict[str, Any] = {
            "observation_space": {"low": list(self.low), "high": list(self.high)},
            "actions": list(self.actions),
            "stimuli": list(self.stimuli),
            "out_of_bounds": self.out_of_bounds,
        }
        if self.basis is not None:
            out["basis"] = dict(self.basis)
        if self.samples is not None:
            out["samples"] = dict(self.samples)
        return out


@dataclass(frozen=True)
class ContinuousStep:
    """One step of a :class:`ContinuousEnvironment`, as the session should see it.

    Attributes:
        observation: The observation to report: the environment's after the
            step, or the first of the next episode when this step ended one.
        stimulus: The stimulus to report with it.
        reward: The environment's raw reward (a vector for MO-Gymnasium).
        terminated: The environment ended the episode on this step.
        truncated: A wrapper cut the episode short on this step.
    """

    observation: list[float]
    stimulus: list[float]
    reward: Any
    terminated: bool
    truncated: bool

    @property
    def episode_ended(self) -> bool:
        """Whether the environment was reset after this step."""
        return self.terminated or self.truncated


StimulusOf = Callable[[list[float], Any, Mapping[str, Any]], Sequence[float]]
"""``stimulus_of(observation, reward, info)``: the stimulus a step delivered."""


class ContinuousEnvironment:
    """A Gymnasium environment with a ``Box`` observation space and
    ``Discrete`` actions, as a continuous mcapi model with the adapter that
    steps it. Pass it to ``create_session`` (it posts :attr:`model`).

    Attributes:
        env: What is stepped.
        model: The continuous model posted for it.
        returns: Sum of the raw reward since :meth:`reset` (per component for
            a vector reward).
        stimulus_totals: Sum of the stimulus per dimension since :meth:`reset`.
        ticks: Steps since :meth:`reset`; episodes: episodes ended since.
    """

    def __init__(
        self,
        env: Any,
        model: ContinuousModel,
        stimulus_of: StimulusOf,
        action_start: int = 0,
    ) -> None:
        self.env = env
        self.model = model
        self._stimulus_of = stimulus_of
        self._action_start = action_start
        self._seed: int | None = None
        self.returns: Any = 0.0
        self.stimulus_totals = [0.0] * len(model.stimuli)
        self.ticks = 0
        self.episodes = 0

    def to_json(self) -> dict[str, Any]:
        """The model's JSON (what ``create_session`` posts)."""
        return self.model.to_json()

    @staticmethod
    def _vector(observation: Any) -> list[float]:
        flat = observation.ravel().tolist() if hasattr(observation, "ravel") else list(observation)
        return [float(x) for x in flat]

    def reset(self, seed: int | None = None) -> list[float]:
        """Resets the environment and the totals; the first observation."""
        self._seed = seed
        observation, _ = self.env.reset(seed=seed)
        self.returns = 0.0
        self.stimulus_totals = [0.0] * len(self.model.stimuli)
        self.ticks = 0
        self.episodes = 0
        return self._vector(observation)

    def step(self, action_index: int) -> ContinuousStep:
        """Takes the session's action; what to report next. An episode that
        ends is reset at once (an agent's life goes on), and the step then
        carries the next episode's first observation."""
        n = len(self.model.actions)
        a = as_int(action_index, "action_index")
        if not 0 <= a < n:
            raise ValueError(f"action {a} is not in 0..{n}")
        observation, reward, terminated, truncated, info = self.env.step(self._action_start + a)
        seen = self._vector(observation)
        stimulus = [float(x) for x in self._stimulus_of(seen, reward, info)]
        if len(stimulus) != len(self.model.stimuli):
            raise ValueError(
                f"stimulus_of gave {len(stimulus)} components for {len(self.model.stimuli)} stimuli"
            )
        raw = reward.tolist() if hasattr(reward, "tolist") else reward
        if isinstance(raw, list):
            base = self.returns if isinstance(self.returns, list) else [0.0] * len(raw)
            self.returns = [r + float(x) for r, x in zip(base, raw)]
        else:
            self.returns = float(self.returns) + float(raw)
        self.stimulus_totals = [t + s for t, s in zip(self.stimulus_totals, stimulus)]
        self.ticks += 1
        if terminated or truncated:
            self.episodes += 1
            observation, _ = self.env.reset()
            seen = self._vector(observation)
        return ContinuousStep(seen, stimulus, raw, bool(terminated), bool(truncated))


def box_bounds(
    space: Any, bounds: Sequence[tuple[float, float] | None] | None, name: str
) -> tuple[list[float], list[float]]:
    """The box of a 1-d ``Box`` space, with ``bounds`` replacing its own: a
    (low, high) per component, or ``None`` to keep the space's. A bound that
    is infinite, or beyond 1e12 in magnitude (``numpy.finfo(float32).max``
    stands for "unbounded" in some environments), must be replaced."""
    if type(space).__name__ != "Box":
        raise TypeError(f"{name}'s observation space is {space}, not a Box")
    shape = tuple(getattr(space, "shape", ()) or ())
    if len(shape) != 1:
        raise TypeError(
            f"{name}'s observation space {space} has shape {shape}: only a 1-d Box is an "
            "observation vector (flatten it with gymnasium.wrappers.FlattenObservation)"
        )
    low = [float(x) for x in space.low.ravel().tolist()]
    high = [float(x) for x in space.high.ravel().tolist()]
    if bounds is not None:
        if len(bounds) != len(low):
            raise ValueError(f"{len(bounds)} bounds for {len(low)} observation components")
        for i, b in enumerate(bounds):
            if b is not None:
                lo, hi = b
                low[i], high[i] = as_float(lo, f"bounds[{i}]"), as_float(hi, f"bounds[{i}]")
    for i, (lo, hi) in enumerate(zip(low, high)):
        if not (math.isfinite(lo) and math.isfinite(hi)) or max(abs(lo), abs(hi)) > MAX_COORDINATE:
            raise ValueError(
                f"{name}'s observation component {i} is unbounded ({lo}, {hi}): "
                f"give `bounds` with a finite (low, high) for component {i} "
                "(None keeps a component's own bounds)"
            )
    return low, high
