"""Builders of environment models: the JSON a session is created from.

A :class:`Model` holds the states, named actions, transition table and
stimulus dimensions of an environment, and where its stimuli come from (its
*sources*). Pass it to ``create_session``; it also simulates the world
client-side (:meth:`Model.sample_next`, :meth:`Model.stimulus`), which is how
the examples drive their agents.

- :func:`hallway`: the paper's 50-state hallway (food at 10, rest at 40).
- :func:`grid`: an ASCII map, ``#`` walls and marked source cells.
- :func:`from_transition_table`: any finite model, deterministic or stochastic.
- :func:`from_gymnasium`: a Gymnasium toy-text environment (FrozenLake, Taxi,
  CliffWalking) from its transition table ``env.unwrapped.P``; needs the
  ``gymnasium`` extra only to make the environment, not to build the model.
- :func:`learned`: any of these posted *without* its transitions: the agent
  learns them from its observations (docs/algorithm.md section 8), while the
  client keeps simulating the world with the full model.
- :func:`from_mo_gymnasium`: a discrete multi-objective (MO-Gymnasium)
  environment, its vector reward as the stimulus dimensions, usually with a
  learned transition model; the :class:`MoEnvironment` it returns also steps
  the environment for the session (the ``mo`` extra installs MO-Gymnasium).
- :class:`ContinuousModel`: a continuous world, observations being vectors
  in a box; :func:`from_gymnasium` (without ``sources``) and
  :func:`from_mo_gymnasium` (``observations="continuous"``) make one of an
  environment with a ``Box`` observation space, with the
  :class:`ContinuousEnvironment` that steps it.

Models are checked here by the server's rules (every state has an available
action; probabilities in (0, 1] summing to 1 within 1e-9), so a mistake is a
``ValueError`` naming the place before anything is sent.

Numbers may be numpy scalars and tables numpy arrays (a Gymnasium ``P``
built with numpy, a transition table of ``numpy.int64`` states and
``numpy.float64`` probabilities): a model holds plain ``int`` and ``float``
once built. Next states must be integers (``operator.index``), not floats.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import random
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, SupportsIndex, Union, overload

from ._normalise import as_float, as_int, is_int_like, plain
from .continuous import (
    ContinuousEnvironment,
    ContinuousModel,
    ContinuousStep,
    StimulusOf,
    box_bounds,
)

__all__ = [
    "PROBABILITY_TOLERANCE",
    "GRID_ACTIONS",
    "Source",
    "Successors",
    "Model",
    "GridModel",
    "ModelLike",
    "model_json",
    "hallway",
    "grid",
    "from_transition_table",
    "from_gymnasium",
    "Learned",
    "learned",
    "UnsupportedEnvironment",
    "MoStep",
    "MoEnvironment",
    "from_mo_gymnasium",
    "ContinuousModel",
    "ContinuousStep",
    "ContinuousEnvironment",
]

PROBABILITY_TOLERANCE = 1e-9
"""The server refuses a pair whose probabilities sum further than this from 1."""

GRID_ACTIONS: tuple[str, ...] = ("left", "right", "north", "south", "stay")
"""Action names of grid maps, in index order (as the server's grid form)."""

Successors = tuple[tuple[int, float], ...]
"""The successors of a state-action pair: ``((next_state, probability), ...)``."""

TableEntry = Union[None, SupportsIndex, Mapping[Any, Any], Iterable[Any]]
"""One cell of a transition table: ``None`` (action unavailable), a next
state (deterministic), or successors as ``{next: p}`` or ``[(next, p), ...]``."""


@dataclass(frozen=True, slots=True, init=False)
class Source:
    """A stimulus source: arriving in ``state`` delivers stimulus dimension ``dim``.

    Attributes:
        state: The state where the stimulus is delivered.
        dim: The stimulus dimension (index into the model's stimuli).
    """

    state: int
    dim: int

    def __init__(self, state: SupportsIndex, dim: SupportsIndex) -> None:
        object.__setattr__(self, "state", as_int(state, "source state"))
        object.__setattr__(self, "dim", as_int(dim, "source dimension"))


def _check_names(kind: str, names: Sequence[str]) -> None:
    if not names:
        raise ValueError(f"`{kind}` must not be empty")
    seen: set[str] = set()
    for i, name in enumerate(names):
        if not isinstance(name, str) or not name.strip():
            raise ValueError(f"`{kind}[{i}]` is an empty name")
        if name in seen:
            raise ValueError(f"`{kind}` names `{name}` twice")
        seen.add(name)


@dataclass(frozen=True)
class Model:
    """A finite environment model, validated, ready to post.

    Attributes:
        states: Number of states; states are ``0..states-1``.
        actions: Action names, in index order.
        stimuli: Names of the stimulus dimensions, in the order of the drive.
        table: ``table[s][a]``: the successors of (s, a), ``None`` when the
            action is not available in s.
        sources: Where stimuli are delivered (used by :meth:`stimulus`; the
            server learns them from the observations, not from the model).
        state_names: Optional display names of the states.
        basis: Optional basis for the server, e.g. ``{"kind": "proto_value", "k": 30}``.
    """

    states: int
    actions: tuple[str, ...]
    stimuli: tuple[str, ...]
    table: tuple[tuple[Successors | None, ...], ...]
    sources: tuple[Source, ...] = ()
    state_names: tuple[str, ...] | None = None
    basis: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        # Plain Python values whatever was given (numpy scalars and arrays).
        put = object.__setattr__
        put(self, "states", as_int(self.states, "states"))
        put(self, "actions", tuple(self.actions))
        put(self, "stimuli", tuple(self.stimuli))
        put(self, "table", tuple(
            tuple(None if cell is None else _plain_cell(s, a, cell) for a, cell in enumerate(row))
            for s, row in enumerate(self.table)
        ))
        put(self, "sources", tuple(
            src if isinstance(src, Source) else Source(*src) for src in self.sources
        ))
        if self.state_names is not None:
            put(self, "state_names", tuple(self.state_names))
        if self.basis is not None:
            put(self, "basis", plain(dict(self.basis)))
        if self.states < 1:
            raise ValueError("`states` must be at least 1")
        _check_names("actions", self.actions)
        _check_names("stimuli", self.stimuli)
        if self.state_names is not None and len(self.state_names) != self.states:
            raise ValueError(
                f"`state_names` has {len(self.state_names)} entries, expected {self.states}"
            )
        if len(self.table) != self.states:
            raise ValueError(f"the table has {len(self.table)} rows, expected {self.states}")
        n_actions = len(self.actions)
        for s, row in enumerate(self.table):
            if len(row) != n_actions:
                raise ValueError(
                    f"row {s} of the table has {len(row)} entries, expected {n_actions}"
                )
            if all(cell is None for cell in row):
                raise ValueError(f"state {s} has no available action")
            for a, cell in enumerate(row):
                if cell is not None:
                    self._check_successors(s, a, cell)
        for src in self.sources:
            if not 0 <= src.state < self.states:
                raise ValueError(f"source state {src.state} is out of range (0..{self.states})")
            if not 0 <= src.dim < len(self.stimuli):
                raise ValueError(
                    f"source dimension {src.dim} is out of range ({len(self.stimuli)} stimuli)"
                )

    def _check_successors(self, s: int, a: int, cell: Successors) -> None:
        where = f"state {s}, action `{self.actions[a]}`"
        if not cell:
            raise ValueError(f"{where} has no successor")
        total = 0.0
        seen: set[int] = set()
        for t, p in cell:
            if not 0 <= t < self.states:
                raise ValueError(f"{where}: next state {t} is out of range (0..{self.states})")
            if not (math.isfinite(p) and 0.0 < p <= 1.0):
                raise ValueError(f"{where}: probability {p} is not in (0, 1]")
            if t in seen:
                raise ValueError(f"{where} lists next state {t} twice")
            seen.add(t)
            total += p
        if abs(total - 1.0) > PROBABILITY_TOLERANCE:
            raise ValueError(f"{where}: probabilities sum to {total}, not 1")

    @property
    def deterministic(self) -> bool:
        """Whether every available pair has exactly one successor."""
        return all(cell is None or len(cell) == 1 for row in self.table for cell in row)

    @property
    def pairs(self) -> int:
        """Number of available state-action pairs."""
        return sum(cell is not None for row in self.table for cell in row)

    @property
    def transitions(self) -> int:
        """Number of stored transitions (non-zero entries of P)."""
        return sum(len(cell) for row in self.table for cell in row if cell is not None)

    def available_actions(self, state: SupportsIndex) -> list[int]:
        """Indices of the actions available in ``state``."""
        return [a for a, cell in enumerate(self.table[as_int(state, "state")]) if cell is not None]

    def successors(self, state: SupportsIndex, action: SupportsIndex) -> Successors:
        """The successors of (state, action) as ``((next, p), ...)``.

        Raises:
            ValueError: The action is not available in the state.
        """
        state, action = as_int(state, "state"), as_int(action, "action")
        cell = self.table[state][action]
        if cell is None:
            raise ValueError(f"action `{self.actions[action]}` is not available in state {state}")
        return cell

    def sample_next(self, state: SupportsIndex, action: SupportsIndex, rng: random.Random) -> int:
        """Draws the next state of (state, action) from P(. | state, action)."""
        cell = self.successors(state, action)
        u = rng.random()
        acc = 0.0
        for t, p in cell:
            acc += p
            if u < acc:
                return t
        return cell[-1][0]

    def stimulus(
        self,
        state: SupportsIndex,
        *,
        magnitude: float = 6.0,
        noise_sd: float = 0.0,
        rng: random.Random | None = None,
    ) -> list[float]:
        """The stimulus delivered on arrival in ``state``, as in the paper's
        experiments: ``magnitude`` plus N(0, ``noise_sd``) noise on each
        dimension whose source is ``state``, exactly 0 elsewhere.

        Args:
            state: The state arrived in.
            magnitude: Stimulus of a source on its own dimension (6 in the paper).
            noise_sd: Standard deviation of the Gaussian noise (2 in the paper).
            rng: Random source of the noise (needed when ``noise_sd > 0``).
        """
        state = as_int(state, "state")
        magnitude = as_float(magnitude, "magnitude")
        xi = [0.0] * len(self.stimuli)
        for src in self.sources:
            if src.state == state:
                noise = 0.0
                if noise_sd > 0.0:
                    if rng is None:
                        raise ValueError("pass `rng` to draw noise")
                    noise = float(rng.gauss(0.0, noise_sd))
                xi[src.dim] = magnitude + noise
        return xi

    def source_states(self, stimulus: str | SupportsIndex) -> list[int]:
        """The states delivering a stimulus dimension, given by name or index."""
        dim = (
            self.stimuli.index(stimulus) if isinstance(stimulus, str) else as_int(stimulus, "stimulus")
        )
        return [src.state for src in self.sources if src.dim == dim]

    def with_basis(self, basis: Mapping[str, Any] | None) -> Model:
        """A copy with another basis, e.g. ``{"kind": "proto_value", "k": 30}``."""
        return dataclasses.replace(self, basis=basis)

    def to_json(self) -> dict[str, Any]:
        """The model as the server takes it: deterministic models as ``next``,
        stochastic ones as sparse ``transitions``."""
        out: dict[str, Any] = {"states": self.states, "actions": list(self.actions)}
        if self.state_names is not None:
            out["state_names"] = list(self.state_names)
        if self.deterministic:
            out["next"] = [
                [None if cell is None else cell[0][0] for cell in row] for row in self.table
            ]
        else:
            out["transitions"] = [
                {"state": s, "action": a, "next": [[t, p] for t, p in cell]}
                for s, row in enumerate(self.table)
                for a, cell in enumerate(row)
                if cell is not None
            ]
        out["stimuli"] = list(self.stimuli)
        if self.basis is not None:
            out["basis"] = dict(self.basis)
        return out


@dataclass(frozen=True)
class GridModel(Model):
    """A model built from an ASCII grid map, which also knows its cells.

    Attributes:
        rows: Map height.
        cols: Map width.
        cells: ``(row, col)`` of each state.
        marks: ``(mark, state)`` of every marked cell, in row-major order.
    """

    rows: int = 0
    cols: int = 0
    cells: tuple[tuple[int, int], ...] = ()
    marks: tuple[tuple[str, int], ...] = ()

    def cell_of(self, state: int) -> tuple[int, int]:
        """``(row, col)`` of a state."""
        return self.cells[state]

    def state_at(self, row: int, col: int) -> int | None:
        """The state of a cell; ``None`` for walls and cells off the map."""
        try:
            return self.cells.index((row, col))
        except ValueError:
            return None

    def render(self, marks: Mapping[int, str] | None = None) -> list[str]:
        """The map's rows, walls as ``#``, with ``marks[state]`` drawn over cells."""
        out = [["#"] * self.cols for _ in range(self.rows)]
        for r, c in self.cells:
            out[r][c] = "."
        for mark, s in self.marks:
            r, c = self.cells[s]
            out[r][c] = mark
        for s, ch in (marks or {}).items():
            r, c = self.cells[s]
            out[r][c] = ch
        return ["".join(row) for row in out]


def _plain_cell(s: int, a: int, cell: Iterable[Any]) -> Successors:
    """A table cell of :class:`Model` as ``((int, float), ...)``."""
    where = f"state {s}, action {a}"
    if not isinstance(cell, Iterable) or isinstance(cell, (str, bytes)):
        raise ValueError(f"{where}: {cell!r} is not a tuple of (next_state, probability) pairs")
    out = []
    for pair in cell:
        try:
            t, p = pair
        except (TypeError, ValueError):
            raise ValueError(f"{where}: {pair!r} is not a (next_state, probability) pair") from None
        out.append((_next_state(t, where), _probability(p, where)))
    return tuple(out)


def _next_state(t: object, where: str) -> int:
    try:
        return as_int(t, "next state")
    except TypeError:
        raise ValueError(f"{where}: next state {t!r} is not an integer") from None


def _probability(p: object, where: str) -> float:
    try:
        return as_float(p, "probability")
    except TypeError:
        raise ValueError(f"{where}: probability {p!r} is not a number") from None


StatesLike = Union[SupportsIndex, Iterable[SupportsIndex]]
"""One state, or several (a list, a numpy array)."""


def _sources(
    sources: Mapping[str, StatesLike], stimuli: Sequence[str] | None
) -> tuple[tuple[str, ...], tuple[Source, ...]]:
    """Stimulus names and sources from ``{stimulus name: state(s)}``."""
    names = tuple(stimuli) if stimuli is not None else tuple(sources)
    out = []
    for name, states in sources.items():
        if name not in names:
            raise ValueError(f"source `{name}` is not one of the stimuli {list(names)}")
        dim = names.index(name)
        group: Iterable[Any] = [states] if is_int_like(states) else states  # type: ignore[assignment]
        if not isinstance(group, Iterable) or isinstance(group, (str, bytes)):
            raise TypeError(f"source `{name}`: {states!r} is not a state or a list of states")
        for s in group:
            out.append(Source(state=s, dim=dim))
    return names, tuple(out)


def hallway(
    states: SupportsIndex = 50,
    sources: Mapping[str, StatesLike] | None = None,
    *,
    basis: Mapping[str, Any] | None = None,
) -> Model:
    """The hallway of the paper's Experiment 1: a chain of ``states`` states
    with actions left, right and stay (state 0 has no left, the last no right).

    Args:
        states: Length of the chain (50 in the paper).
        sources: Stimulus name -> source state(s); default food at 10 and
            rest at 40, as in the paper and the server's ``hallway`` preset.
        basis: Optional basis for the server (default: indicator).
    """
    states = as_int(states, "states")
    if states < 1:
        raise ValueError("`states` must be at least 1")
    names, srcs = _sources(sources if sources is not None else {"food": 10, "rest": 40}, None)
    table = tuple(
        (
            None if s == 0 else ((s - 1, 1.0),),
            None if s == states - 1 else ((s + 1, 1.0),),
            ((s, 1.0),),
        )
        for s in range(states)
    )
    return Model(
        states=states,
        actions=("left", "right", "stay"),
        stimuli=names,
        table=table,
        sources=srcs,
        basis=basis,
    )


def grid(
    map_lines: Sequence[str] | str,
    sources: Mapping[str, SupportsIndex],
    *,
    stimuli: Sequence[str] | None = None,
    basis: Mapping[str, Any] | None = None,
) -> GridModel:
    """A grid world from an ASCII map, built as the server builds its grid form.

    ``#`` is a wall, ``.`` a free cell, and any other printable character a
    free cell carrying that mark. Free cells are the states, numbered row by
    row; the actions are left, right, north, south and stay, and moves into
    walls or off the map are not available. Trailing blank lines are ignored;
    rows must have equal width.

    Args:
        map_lines: The map's rows (or one string with a row per line).
        sources: Mark -> stimulus dimension, e.g. ``{"a": 0, "b": 1}``.
        stimuli: Names of the dimensions (default: the marks).
        basis: Optional basis for the server.
    """
    lines = map_lines.splitlines() if isinstance(map_lines, str) else list(map_lines)
    lines = [line.rstrip("\r\n") for line in lines]
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise ValueError("grid map is empty")
    cols = len(lines[0])
    cell_state: dict[tuple[int, int], int] = {}
    cells: list[tuple[int, int]] = []
    marks: list[tuple[str, int]] = []
    for r, line in enumerate(lines):
        if len(line) != cols:
            raise ValueError(f"grid row {r} has {len(line)} columns, expected {cols} like row 0")
        for c, ch in enumerate(line):
            if ch == "#":
                continue
            if ch != "." and not (ch.isascii() and ch.isprintable() and not ch.isspace()):
                raise ValueError(
                    f"grid row {r}, column {c}: unexpected character {ch!r} (use `#`, `.` or a letter)"
                )
            if ch != ".":
                marks.append((ch, len(cells)))
            cell_state[(r, c)] = len(cells)
            cells.append((r, c))
    if not cells:
        raise ValueError("grid map has no free cell")
    if not sources:
        raise ValueError("`sources`: map at least one mark to a stimulus dimension")
    dims_of = {mark: as_int(dim, f"sources[{mark!r}]") for mark, dim in sources.items()}
    n = max(dims_of.values()) + 1
    dims: list[str | None] = [None] * n
    srcs = []
    for mark, dim in dims_of.items():
        if len(mark) != 1:
            raise ValueError(f"`sources`: key `{mark}` must be one character")
        states_of_mark = [s for m, s in marks if m == mark]
        if not states_of_mark:
            raise ValueError(f"`sources`: the map has no cell marked `{mark}`")
        if dim < 0:
            raise ValueError(f"`sources`: dimension {dim} of `{mark}` is negative")
        if dims[dim] is not None:
            raise ValueError(f"`sources`: dimension {dim} is given twice")
        dims[dim] = mark
        # The server's grid form delivers a mark's stimulus at its first cell.
        srcs.append(Source(state=states_of_mark[0], dim=dim))
    if stimuli is not None:
        if len(stimuli) != n:
            raise ValueError(
                f"`stimuli` has {len(stimuli)} names, but `sources` uses {n} dimensions"
            )
        names = tuple(stimuli)
    else:
        names = tuple(m if m is not None else f"dim{d}" for d, m in enumerate(dims))

    def move(r: int, c: int) -> Successors | None:
        s = cell_state.get((r, c))
        return None if s is None else ((s, 1.0),)

    table = tuple(
        (move(r, c - 1), move(r, c + 1), move(r - 1, c), move(r + 1, c), move(r, c))
        for r, c in cells
    )
    return GridModel(
        states=len(cells),
        actions=GRID_ACTIONS,
        stimuli=names,
        table=table,
        sources=tuple(sorted(srcs, key=lambda s: s.dim)),
        basis=basis,
        rows=len(lines),
        cols=cols,
        cells=tuple(cells),
        marks=tuple(marks),
    )


def _successors(entry: TableEntry, where: str) -> Successors | None:
    """Normalises one table cell: merges repeated next states, drops zero probabilities."""
    if entry is None:
        return None
    if is_int_like(entry):
        return ((as_int(entry, "next state"), 1.0),)
    if isinstance(entry, Mapping):
        pairs: Iterable[Any] = entry.items()
    elif isinstance(entry, Iterable) and not isinstance(entry, (str, bytes)):
        pairs = entry
    else:
        raise ValueError(f"{where}: {entry!r} is not a next state or a list of successors")
    merged: dict[int, float] = {}
    for pair in pairs:
        try:
            t, p = pair
        except (TypeError, ValueError):
            raise ValueError(f"{where}: {pair!r} is not a (next_state, probability) pair") from None
        t, p = _next_state(t, where), _probability(p, where)
        if not math.isfinite(p) or p < 0.0:
            raise ValueError(f"{where}: probability {p} is not in (0, 1]")
        if p == 0.0:
            continue
        merged[t] = merged.get(t, 0.0) + p
    if not merged:
        raise ValueError(f"{where} has no successor with a positive probability")
    return tuple(merged.items())


def from_transition_table(
    table: Sequence[Any] | Mapping[Any, Any] | Any,
    actions: Sequence[str],
    sources: Mapping[str, StatesLike],
    *,
    stimuli: Sequence[str] | None = None,
    state_names: Sequence[str] | None = None,
    basis: Mapping[str, Any] | None = None,
) -> Model:
    """A model from a transition table ``table[state][action]``.

    Each row is a sequence with one cell per action, or a mapping from action
    index or name to cell (missing actions are unavailable). A cell is
    ``None`` (unavailable), a next state (deterministic), or the successors as
    ``{next: p}`` or ``[(next, p), ...]``; a next state listed twice has its
    probabilities added, and zero probabilities are dropped. Numbers may be
    numpy scalars and rows numpy arrays (a 2-d array of next states is a
    deterministic table).

    Args:
        table: One row per state (a sequence, or a mapping from 0..n-1).
        actions: Action names, in index order.
        sources: Stimulus name -> source state(s).
        stimuli: Names of all stimulus dimensions, in drive order (default:
            the source names); a dimension may have no source.
        state_names: Optional display names of the states.
        basis: Optional basis for the server.

    Example:
        >>> m = from_transition_table(
        ...     [{"go": {1: 0.5, 0: 0.5}}, {"go": 0}], ["go"], {"food": 1})
        >>> m.to_json()["transitions"][0]
        {'state': 0, 'action': 0, 'next': [[1, 0.5], [0, 0.5]]}
    """
    names, srcs = _sources(sources, stimuli)
    actions = tuple(actions)
    _check_names("actions", actions)
    n = len(table)
    rows = []
    for s in range(n):
        try:
            row = table[s]
        except (KeyError, IndexError):
            raise ValueError(f"the table has no row for state {s}") from None
        cells: list[Successors | None] = [None] * len(actions)
        if isinstance(row, Mapping):
            for key, entry in row.items():
                a = actions.index(key) if isinstance(key, str) and key in actions else key
                if not is_int_like(a) or not 0 <= as_int(a, "action") < len(actions):
                    raise ValueError(f"state {s}: `{key}` is not one of the actions {list(actions)}")
                a = as_int(a, "action")
                cells[a] = _successors(entry, f"state {s}, action `{actions[a]}`")
        else:
            row = list(row)
            if len(row) != len(actions):
                raise ValueError(
                    f"row {s} of the table has {len(row)} entries, expected {len(actions)}"
                )
            for a, entry in enumerate(row):
                cells[a] = _successors(entry, f"state {s}, action `{actions[a]}`")
        rows.append(tuple(cells))
    return Model(
        states=n,
        actions=actions,
        stimuli=names,
        table=tuple(rows),
        sources=srcs,
        state_names=None if state_names is None else tuple(state_names),
        basis=basis,
    )


# Action names of the toy-text and classic-control environments, by class name.
_GYM_ACTIONS: dict[str, tuple[str, ...]] = {
    "FrozenLakeEnv": ("left", "down", "right", "up"),
    "CliffWalkingEnv": ("up", "right", "down", "left"),
    "TaxiEnv": ("south", "north", "east", "west", "pickup", "dropoff"),
    "MountainCarEnv": ("push_left", "none", "push_right"),
    "CartPoleEnv": ("push_left", "push_right"),
    "AcrobotEnv": ("torque_minus", "torque_zero", "torque_plus"),
    "LunarLander": ("none", "fire_left", "fire_main", "fire_right"),
}


@overload
def from_gymnasium(
    env: Any,
    sources: Mapping[str, StatesLike],
    *,
    stimuli: Sequence[str] | None = None,
    actions: Sequence[str] | None = None,
    on_terminated: Literal["restart", "keep"] = "restart",
    basis: Mapping[str, Any] | None = None,
) -> Model: ...


@overload
def from_gymnasium(
    env: Any,
    sources: None = None,
    *,
    stimuli: Sequence[str] | None = None,
    actions: Sequence[str] | None = None,
    basis: Mapping[str, Any] | None = None,
    bounds: Sequence[tuple[float, float] | None] | None = None,
    stimulus_of: StimulusOf | None = None,
    out_of_bounds: Literal["clip", "refuse"] = "clip",
    samples: Mapping[str, int] | None = None,
) -> ContinuousEnvironment: ...


def from_gymnasium(
    env: Any,
    sources: Mapping[str, StatesLike] | None = None,
    *,
    stimuli: Sequence[str] | None = None,
    actions: Sequence[str] | None = None,
    on_terminated: Literal["restart", "keep"] = "restart",
    basis: Mapping[str, Any] | None = None,
    bounds: Sequence[tuple[float, float] | None] | None = None,
    stimulus_of: StimulusOf | None = None,
    out_of_bounds: Literal["clip", "refuse"] = "clip",
    samples: Mapping[str, int] | None = None,
) -> Model | ContinuousEnvironment:
    """A model from a Gymnasium environment.

    **Without** ``sources``: an environment with a 1-d ``Box`` observation
    space and ``Discrete`` actions becomes a continuous world
    (:class:`~mcapi_client.continuous.ContinuousEnvironment`): its box is the
    model's observation space (``bounds`` gives a finite (low, high) per
    component, ``None`` keeping the space's own; an unbounded component
    without one is a ``ValueError`` naming it), and each step's stimulus is
    ``stimulus_of(observation, reward, info)``, one value per name in
    ``stimuli``; without ``stimulus_of``, one stimulus, the positive part of
    the reward (named ``stimuli[0]``, default ``"reward"``). The session
    learns the transitions. Actions are named as the environment's own
    (MountainCar, CartPole, Acrobot, LunarLander) or ``a0``, ``a1``, ...

    **With** ``sources``, the model is read from a toy-text environment's
    transition table:

    Reads ``env.unwrapped.P`` (``P[s][a] = [(p, next, reward, terminated), ...]``),
    so stochastic environments stay stochastic (FrozenLake with
    ``is_slippery=True`` gives three successors per move). Repeated next
    states are merged, zero probabilities dropped, and rounding in the sums
    is corrected so each pair sums to 1. Rewards are ignored: an MCA-PI
    agent's reward comes from its stimuli.

    Episodes end in Gymnasium, but an MCA-PI agent lives on. With
    ``on_terminated="restart"`` (the default) every state entered by a
    terminating transition (FrozenLake's holes and goal) leads, whatever the
    action, to the environment's initial-state distribution: a simulation
    observes the terminal state, then calls ``env.reset()`` and observes the
    start state with the action it was advised. ``"keep"`` takes P as it is
    (toy-text terminal states are absorbing there).

    Args:
        env: The environment (``gymnasium.make("FrozenLake-v1")``), or any
            object with a ``P`` table (and ``initial_state_distrib`` for restarts).
        sources: Stimulus name -> source state(s).
        stimuli: Names of all stimulus dimensions (default: the source names).
        actions: Action names (default: FrozenLake's, Taxi's or CliffWalking's
            own, else ``a0``, ``a1``, ...).
        on_terminated: ``"restart"`` or ``"keep"``, see above.
        basis: Optional basis for the server.

        bounds: Without ``sources``: a finite (low, high) per observation
            component, or ``None`` for a component whose own bounds are finite.
        stimulus_of: Without ``sources``: the stimulus of a step.
        out_of_bounds: Without ``sources``: ``"clip"`` or ``"refuse"``.
        samples: Without ``sources``: the sample store's parameters.

    Raises:
        ValueError: The environment has no transition table, or it does not
            sum to 1, or a restart needs an initial-state distribution it lacks;
            without ``sources``, an unbounded box without ``bounds``.
        TypeError: Without ``sources``, a space that is not a ``Box`` or
            actions that are not ``Discrete``.
    """
    if sources is None:
        space = getattr(env, "observation_space", None)
        if type(space).__name__ == "Discrete":
            raise TypeError(
                f"{type(getattr(env, 'unwrapped', env)).__name__} has Discrete observations: "
                "give `sources` (stimulus name -> source states) to read its transition table"
            )
        names = tuple(stimuli) if stimuli is not None else ("reward",)
        if stimulus_of is None and len(names) != 1:
            raise ValueError(
                f"{len(names)} stimuli {list(names)} without `stimulus_of`: the default stimulus "
                "is one number (the positive part of the reward); give "
                "`stimulus_of(observation, reward, info)` returning one value per stimulus"
            )
        return _continuous_environment(
            env,
            stimuli=names,
            actions=actions,
            basis=basis,
            bounds=bounds,
            stimulus_of=stimulus_of or (lambda _x, r, _i: [max(float(r), 0.0)]),
            out_of_bounds=out_of_bounds,
            samples=samples,
        )
    base = getattr(env, "unwrapped", env)
    P = getattr(base, "P", None)
    if not isinstance(P, Mapping) and not isinstance(P, Sequence):
        raise ValueError(
            f"{type(base).__name__} has no transition table `P` (a toy-text environment has one)"
        )
    n_states = len(P)
    n_actions = len(P[0])
    if actions is None:
        actions = _GYM_ACTIONS.get(type(base).__name__) or tuple(
            f"a{i}" for i in range(n_actions)
        )
    if len(actions) != n_actions:
        raise ValueError(f"{len(actions)} action names for {n_actions} actions")
    rows: list[dict[int, list[tuple[int, float]]]] = []
    terminal: set[int] = set()
    for s in range(n_states):
        row: dict[int, list[tuple[int, float]]] = {}
        for a, outcomes in P[s].items() if isinstance(P[s], Mapping) else enumerate(P[s]):
            pairs = []
            where = f"P[{s}][{a}]"
            for outcome in outcomes:
                p, t, _reward, done = outcome[:4]
                t, p = _next_state(t, where), _probability(p, where)
                pairs.append((t, p))
                if done and p > 0:
                    terminal.add(t)
            row[as_int(a, "action")] = pairs
        rows.append(row)
    if on_terminated == "restart" and terminal:
        dist = getattr(base, "initial_state_distrib", None)
        if dist is None:
            raise ValueError(
                f"{type(base).__name__} has no `initial_state_distrib` to restart from; "
                "pass on_terminated='keep'"
            )
        start = [(s, _probability(p, "initial_state_distrib")) for s, p in enumerate(dist) if p > 0]
        for s in terminal:
            rows[s] = {a: list(start) for a in range(n_actions)}
    elif on_terminated not in ("restart", "keep"):
        raise ValueError(f"on_terminated must be 'restart' or 'keep', not {on_terminated!r}")
    table = []
    for s, row in enumerate(rows):
        cells = []
        for a in range(n_actions):
            where = f"state {s}, action `{actions[a]}`"
            succ = _successors(row.get(a), where)
            if succ is not None:
                total = sum(p for _, p in succ)
                if abs(total - 1.0) > 1e-6:
                    raise ValueError(f"{where}: probabilities sum to {total}, not 1")
                succ = tuple((t, p / total) for t, p in succ)
            cells.append(succ)
        table.append(tuple(cells))
    names, srcs = _sources(sources, stimuli)
    return Model(
        states=n_states,
        actions=tuple(actions),
        stimuli=names,
        table=tuple(table),
        sources=srcs,
        basis=basis,
    )


@dataclass(frozen=True)
class Learned:
    """A model posted without its transitions: the agent learns them from
    the observations it gets (docs/algorithm.md section 8). The client
    still simulates the world with :attr:`model`
    (:meth:`sample_next`, :meth:`stimulus`); the server never sees its P.

    A :class:`GridModel` is posted as the grid form with ``"learn": true``
    (the map gives the states, actions and which moves exist); any other
    model as a full model with ``"transitions": "learn"``, in which every
    action is available in every state, so its table must have no
    unavailable action.

    Attributes:
        model: The world.
        known_after: m: visits after which a pair's estimated row is used
            (1 to 1,000,000; the server's default is 3).
        optimism: ``"absorbing"`` (R-max, the default) or ``"stimulus"``.
    """

    model: Model
    known_after: int | None = None
    optimism: Literal["absorbing", "stimulus"] | None = None

    def __post_init__(self) -> None:
        if self.known_after is not None:
            k = as_int(self.known_after, "known_after")
            if not 1 <= k <= 1_000_000:
                raise ValueError(f"`known_after` {k} is not in 1..=1000000")
            object.__setattr__(self, "known_after", k)
        if self.optimism not in (None, "absorbing", "stimulus"):
            raise ValueError(
                f"`optimism` {self.optimism!r} is not `absorbing` or `stimulus`"
            )
        if not isinstance(self.model, GridModel):
            for s, row in enumerate(self.model.table):
                for a, cell in enumerate(row):
                    if cell is None:
                        raise ValueError(
                            f"action {self.model.actions[a]!r} is unavailable in state {s}: "
                            "a learned full model has every action in every state "
                            "(make the move stay put instead)"
                        )

    def sample_next(self, state: SupportsIndex, action: SupportsIndex, rng: random.Random) -> int:
        """A next state drawn from the world's model."""
        return self.model.sample_next(state, action, rng)

    def stimulus(
        self,
        state: SupportsIndex,
        *,
        magnitude: float = 6.0,
        noise_sd: float = 0.0,
        rng: random.Random | None = None,
    ) -> list[float]:
        """The stimulus on arriving in ``state`` (see :meth:`Model.stimulus`)."""
        return self.model.stimulus(state, magnitude=magnitude, noise_sd=noise_sd, rng=rng)

    def to_json(self) -> dict[str, Any]:
        """The model as the server takes it, without transitions."""
        m = self.model
        out: dict[str, Any]
        if isinstance(m, GridModel):
            mark_of = {state: mark for mark, state in reversed(m.marks)}
            out = {
                "grid": m.render(),
                "sources": {mark_of[src.state]: src.dim for src in m.sources},
                "stimuli": list(m.stimuli),
                "learn": True,
            }
        else:
            out = {"states": m.states, "actions": list(m.actions)}
            if m.state_names is not None:
                out["state_names"] = list(m.state_names)
            out["stimuli"] = list(m.stimuli)
            out["transitions"] = "learn"
        learning: dict[str, Any] = {}
        if self.known_after is not None:
            learning["known_after"] = self.known_after
        if self.optimism is not None:
            learning["optimism"] = self.optimism
        if learning:
            out["learning"] = learning
        if m.basis is not None:
            out["basis"] = dict(m.basis)
        return out


def learned(
    model: Model,
    *,
    known_after: int | None = None,
    optimism: Literal["absorbing", "stimulus"] | None = None,
) -> Learned:
    """``model`` posted without its transitions, for the agent to learn
    (docs/algorithm.md section 8); see :class:`Learned`."""
    return Learned(model, known_after, optimism)


class UnsupportedEnvironment(ValueError):
    """An environment :func:`from_mo_gymnasium` cannot turn into a model: a
    continuous observation or action space, too many states, or a reward
    with no component that can be a stimulus. The message names the problem."""


# What the discrete MO-Gymnasium environments do not say in their spaces, by
# class name: the observation spaces are integer Boxes with loose bounds
# (resource-gathering's is 0..5 for two 0/1 flags too), the objectives and
# actions have no names.
def _mo_preset(base: Any) -> dict[str, Any]:
    name = type(base).__name__
    moves = ("up", "down", "left", "right")
    if name == "ResourceGathering":
        # (row, col, has gold, has gem) on the 5 x 5 map: 100 states, not 6^4.
        return {
            "bounds": ((0, 4), (0, 4), (0, 1), (0, 1)),
            "objectives": ("enemy", "gold", "gem"),
            "actions": moves,
        }
    if name == "DeepSeaTreasure":
        out: dict[str, Any] = {"objectives": ("treasure", "time"), "actions": moves}
        sea = getattr(base, "sea_map", None)
        if sea is not None and not getattr(base, "float_state", False):
            rows, cols = sea.shape
            out["bounds"] = ((0, rows - 1), (0, cols - 1))
        return out
    if name == "FourRoom":
        return {"objectives": ("blue", "green", "red"), "actions": ("left", "up", "right", "down")}
    if name == "Minecart":
        # (x, y, speed, sin, cos, fill of ore 1, fill of ore 2): the space says
        # [-1, 1] for each, the cart's position, speed (at most MAX_SPEED = 1)
        # and the fills (of a capacity of 1) stay in [0, 1].
        unit, signed = (0.0, 1.0), (-1.0, 1.0)
        return {
            "objectives": ("ore1", "ore2", "fuel"),
            "actions": ("mine", "left", "right", "accelerate", "brake", "none"),
            "box": (unit, unit, unit, signed, signed, unit, unit),
        }
    return {}


def _space_leaves(space: Any, where: str) -> list[tuple[int, int]]:
    """The integer components of a discrete space, as inclusive (low, high)."""
    kind = type(space).__name__
    if kind == "Discrete":
        start = as_int(getattr(space, "start", 0), "start")
        return [(start, start + as_int(space.n, "n") - 1)]
    if kind == "MultiDiscrete":
        nvec = _flat_list(space.nvec)
        starts = _flat_list(getattr(space, "start", [0] * len(nvec)))
        firsts = [as_int(b, "start") for b in starts]
        return [(lo, lo + as_int(n, "nvec") - 1) for n, lo in zip(nvec, firsts)]
    if kind == "MultiBinary":
        return [(0, 1)] * math.prod(_flat_list([space.n]))
    if kind == "Box":
        dtype = getattr(space, "dtype", None)
        if getattr(dtype, "kind", "f") not in "iub":
            raise UnsupportedEnvironment(
                f"{where} is continuous ({space}): only discrete observations become states "
                "(Discrete, MultiDiscrete, MultiBinary, an integer Box, or a Tuple or Dict of them); "
                "pass observations='continuous' for a continuous world of observation vectors"
            )
        return [(int(lo), int(hi)) for lo, hi in zip(_flat_list(space.low), _flat_list(space.high))]
    if kind == "Tuple":
        return [leaf for i, sub in enumerate(space.spaces) for leaf in _space_leaves(sub, f"{where}[{i}]")]
    if kind == "Dict":
        return [
            leaf for key, sub in space.spaces.items() for leaf in _space_leaves(sub, f"{where}[{key!r}]")
        ]
    raise UnsupportedEnvironment(
        f"{where} is a {kind} ({space}): only Discrete, MultiDiscrete, MultiBinary, integer Box, "
        "Tuple and Dict spaces become states"
    )


def _flat_list(x: Any) -> list[Any]:
    """The numbers of a scalar, a (nested) list or a numpy array, flattened."""
    x = x.tolist() if hasattr(x, "tolist") else x
    if isinstance(x, (list, tuple)):
        return [y for item in x for y in _flat_list(item)]
    return [x]


def _flat_observation(obs: Any, space: Any) -> list[Any]:
    """An observation's components in the order of :func:`_space_leaves`
    (a Dict space's keys in the space's order, whatever the observation's)."""
    kind = type(space).__name__
    if kind == "Dict" and isinstance(obs, Mapping):
        missing = [key for key in space.spaces if key not in obs]
        if missing:
            raise ValueError(f"observation {obs!r} has no {missing[0]!r}")
        return [y for key, sub in space.spaces.items() for y in _flat_observation(obs[key], sub)]
    if kind == "Tuple" and isinstance(obs, (tuple, list)):
        return [y for item, sub in zip(obs, space.spaces) for y in _flat_observation(item, sub)]
    return _flat_list(obs)


@dataclass(frozen=True)
class MoStep:
    """One step of a :class:`MoEnvironment`, as the session should see it.

    Attributes:
        state: The state to observe: the new observation's index, or the
            start state of the next episode when this step ended one.
        stimulus: The stimulus to observe with it (the kept reward components,
            their negative parts cut to 0, times the scale).
        reward: The environment's raw vector reward, every objective.
        terminated: The environment ended the episode on this step.
        truncated: A wrapper cut the episode short on this step.
        observation: The environment's observation after the step (before
            the reset, when the episode ended).
    """

    state: int
    stimulus: list[float]
    reward: tuple[float, ...]
    terminated: bool
    truncated: bool
    observation: Any

    @property
    def episode_ended(self) -> bool:
        """Whether the environment was reset after this step."""
        return self.terminated or self.truncated


class MoEnvironment:
    """A discrete multi-objective environment as an mcapi model, with the
    adapter that steps it for a session. Made by :func:`from_mo_gymnasium`.

    Pass it to ``create_session`` (it posts ``transitions: "learn"``, or the
    read table in :attr:`known`); then ``reset`` gives the first state to
    observe, and each ``step(action)`` takes the session's action to the
    environment and returns the state and stimulus to observe::

        step = mc.observe(session.id, world.reset(seed=1))
        for _ in range(1000):
            s = world.step(step.action_index)
            step = mc.observe(session.id, s.state, s.stimulus)
        print(world.returns)    # per objective, penalties included

    Attributes:
        env: What is stepped (``env.unwrapped`` unless ``unwrap=False``).
        objectives: Names of all reward components, in the reward's order.
        stimuli: Names of the stimulus dimensions: the kept objectives.
        kept: For each stimulus dimension, the index of its objective.
        dropped: Indices of the objectives that are not stimuli (penalties).
        actions: Action names; index i is the environment's action
            ``action_start + i``.
        observation_space: The space the states come from.
        bounds: Inclusive (low, high) of each observation component.
        states: Number of states: the product of the components' ranges.
        scale: Factor from a reward component to a stimulus amount.
        known: The model read from the environment's transition table, or
            ``None`` when the session learns the transitions.
        returns: Sum of the raw reward per objective since :meth:`reset`.
        stimulus_totals: Sum of the stimulus per dimension since :meth:`reset`.
        ticks: Steps since :meth:`reset`; episodes: episodes ended since.
    """

    def __init__(
        self,
        env: Any,
        *,
        objectives: Sequence[str],
        kept: Sequence[int],
        actions: Sequence[str],
        action_start: int,
        observation_space: Any,
        bounds: Sequence[tuple[int, int]],
        scale: float,
        known: Model | None,
        known_after: int | None,
        optimism: Literal["absorbing", "stimulus"] | None,
        basis: Mapping[str, Any] | None,
    ) -> None:
        self.env = env
        self.objectives = tuple(objectives)
        self.kept = tuple(kept)
        self.stimuli = tuple(self.objectives[i] for i in self.kept)
        self.dropped = tuple(i for i in range(len(self.objectives)) if i not in self.kept)
        self.actions = tuple(actions)
        self.action_start = action_start
        self.observation_space = observation_space
        self.bounds = tuple(bounds)
        self.states = math.prod(hi - lo + 1 for lo, hi in self.bounds)
        self.scale = scale
        self.known = known
        # Validates the learning options as the Learned form does.
        self._learning = Learned(_placeholder(self.actions, self.stimuli), known_after, optimism)
        self.basis = None if basis is None else plain(dict(basis))
        self._ended = False
        self._started = False
        self.returns = [0.0] * len(self.objectives)
        self.stimulus_totals = [0.0] * len(self.stimuli)
        self.ticks = 0
        self.episodes = 0

    def __repr__(self) -> str:
        how = "read transitions" if self.known is not None else "learned transitions"
        return (
            f"MoEnvironment({type(getattr(self.env, 'unwrapped', self.env)).__name__}: {self.states} states, "
            f"actions {list(self.actions)}, stimuli {list(self.stimuli)}, "
            f"dropped {[self.objectives[i] for i in self.dropped]}, {how})"
        )

    def state_of(self, observation: Any) -> int:
        """The state index of an observation (row-major over :attr:`bounds`).

        Raises:
            ValueError: The observation has the wrong number of components,
                a non-integer one, or one outside its bounds.
        """
        flat = _flat_observation(observation, self.observation_space)
        if len(flat) != len(self.bounds):
            raise ValueError(
                f"observation {observation!r} has {len(flat)} components, expected {len(self.bounds)}"
            )
        index = 0
        for i, (x, (lo, hi)) in enumerate(zip(flat, self.bounds)):
            try:
                v = int(x)
            except (TypeError, ValueError):
                v = lo - 1  # reported below
            if isinstance(x, str) or v != x or not lo <= v <= hi:
                raise ValueError(
                    f"observation {observation!r}: component {i} is {x!r}, not an integer in {lo}..{hi} "
                    "(pass `observation_bounds` to from_mo_gymnasium if the bounds are too tight)"
                )
            index = index * (hi - lo + 1) + (v - lo)
        return index

    def observation_of(self, state: SupportsIndex) -> tuple[int, ...]:
        """The observation components of a state index (inverse of :meth:`state_of`)."""
        s = as_int(state, "state")
        if not 0 <= s < self.states:
            raise ValueError(f"state {s} is out of range (0..{self.states})")
        out = []
        for lo, hi in reversed(self.bounds):
            s, r = divmod(s, hi - lo + 1)
            out.append(lo + r)
        return tuple(reversed(out))

    def stimulus_of(self, reward: Any) -> list[float]:
        """The stimulus of a vector reward: the kept components, negative
        parts cut to 0, times :attr:`scale`."""
        r = [float(x) for x in _flat_list(reward)]
        if len(r) != len(self.objectives):
            raise ValueError(f"reward {reward!r} has {len(r)} components, expected {len(self.objectives)}")
        return [max(r[i], 0.0) * self.scale for i in self.kept]

    def env_action(self, action: Any) -> int:
        """The environment's action of a session's action: an index, a name,
        or a ``Step`` (its ``action_index``)."""
        if hasattr(action, "action_index"):
            action = action.action_index
        if isinstance(action, str):
            if action not in self.actions:
                raise ValueError(f"`{action}` is not one of the actions {list(self.actions)}")
            a = self.actions.index(action)
        else:
            a = as_int(action, "action")
            if not 0 <= a < len(self.actions):
                raise ValueError(f"action {a} is out of range (0..{len(self.actions)})")
        return self.action_start + a

    def reset(self, seed: int | None = None) -> int:
        """Resets the environment and the totals; returns the start state,
        the session's first observation."""
        obs, _info = self.env.reset(seed=seed)
        self._ended = False
        self._started = True
        self.returns = [0.0] * len(self.objectives)
        self.stimulus_totals = [0.0] * len(self.stimuli)
        self.ticks = 0
        self.episodes = 0
        return self.state_of(obs)

    def step(self, action: Any) -> MoStep:
        """Takes the session's action in the environment.

        When the step ends an episode (terminated, or truncated by a
        wrapper), the environment is reset at once and the returned state is
        the next episode's start, with this step's stimulus: the session's
        stimulus estimate is per state-action pair, so the stimulus is
        credited to the move that earned it, and the agent's life goes on
        without a tick spent in a terminal state.
        """
        if not self._started:
            raise RuntimeError("call reset() before step()")
        obs, reward, terminated, truncated, _info = self.env.step(self.env_action(action))
        raw = tuple(float(x) for x in _flat_list(reward))
        stimulus = self.stimulus_of(raw)
        self.ticks += 1
        for i, x in enumerate(raw):
            self.returns[i] += x
        for j, x in enumerate(stimulus):
            self.stimulus_totals[j] += x
        state_obs = obs
        if terminated or truncated:
            self.episodes += 1
            state_obs, _info = self.env.reset()
        return MoStep(self.state_of(state_obs), stimulus, raw, bool(terminated), bool(truncated), obs)

    def to_json(self) -> dict[str, Any]:
        """The model as the server takes it: ``transitions: "learn"``, or the read table."""
        if self.known is not None:
            out = self.known.to_json()
        else:
            out = {
                "states": self.states,
                "actions": list(self.actions),
                "stimuli": list(self.stimuli),
                "transitions": "learn",
            }
            learning = self._learning.to_json().get("learning")
            if learning:
                out["learning"] = learning
        if self.basis is not None:
            out["basis"] = dict(self.basis)
        return out


def _placeholder(actions: Sequence[str], stimuli: Sequence[str]) -> Model:
    """A one-state model, only to check the learning options with :class:`Learned`."""
    return Model(1, tuple(actions), tuple(stimuli), ((((0, 1.0),),) * len(actions),))


@overload
def from_mo_gymnasium(
    env: Any,
    *,
    observations: Literal["discrete"] = "discrete",
    penalties: Literal["drop", "error"] = "drop",
    scale: float = 1.0,
    transitions: Literal["auto", "learn", "table"] = "auto",
    observation_bounds: Sequence[tuple[int, int]] | None = None,
    objectives: Sequence[str] | None = None,
    actions: Sequence[str] | None = None,
    max_states: int = 10_000,
    unwrap: bool = True,
    known_after: int | None = None,
    optimism: Literal["absorbing", "stimulus"] | None = None,
    basis: Mapping[str, Any] | None = None,
) -> MoEnvironment: ...


@overload
def from_mo_gymnasium(
    env: Any,
    *,
    observations: Literal["continuous"],
    penalties: Literal["drop", "error"] = "drop",
    scale: float = 1.0,
    objectives: Sequence[str] | None = None,
    actions: Sequence[str] | None = None,
    unwrap: bool = True,
    basis: Mapping[str, Any] | None = None,
    observation_bounds: Sequence[tuple[float, float] | None] | None = None,
    out_of_bounds: Literal["clip", "refuse"] = "clip",
    samples: Mapping[str, int] | None = None,
) -> ContinuousEnvironment: ...


def from_mo_gymnasium(
    env: Any,
    *,
    observations: Literal["discrete", "continuous"] = "discrete",
    penalties: Literal["drop", "error"] = "drop",
    scale: float = 1.0,
    transitions: Literal["auto", "learn", "table"] = "auto",
    observation_bounds: Sequence[Any] | None = None,
    objectives: Sequence[str] | None = None,
    actions: Sequence[str] | None = None,
    max_states: int = 10_000,
    unwrap: bool = True,
    known_after: int | None = None,
    optimism: Literal["absorbing", "stimulus"] | None = None,
    basis: Mapping[str, Any] | None = None,
    out_of_bounds: Literal["clip", "refuse"] = "clip",
    samples: Mapping[str, int] | None = None,
) -> MoEnvironment | ContinuousEnvironment:
    """A multi-objective environment (MO-Gymnasium's API: ``step`` returns a
    vector reward) as an mcapi model and a step adapter.

    **Continuous observations** (``observations="continuous"``, e.g.
    ``minecart-v0``): a 1-d ``Box`` observation space becomes a continuous
    world (:class:`~mcapi_client.continuous.ContinuousEnvironment`;
    ``observation_bounds`` gives a (low, high) per component, ``None``
    keeping the space's own, and must replace unbounded ones), the stimuli
    are the kept reward components as below, and the session learns the
    transitions. The options about states and tables below do not apply.
    Minecart declares [-1, 1] for all 7 components while position, speed
    and the two fills never go below 0: its box here is the one it reaches,
    [0, 1] for those and [-1, 1] for the heading's sine and cosine, so the
    basis does not spend half its resolution on values never seen.

    **States.** The observation space must be discrete: Discrete,
    MultiDiscrete, MultiBinary, a Box of an integer dtype with finite
    bounds, or a Tuple or Dict of these. Its components are flattened
    row-major into one index (:meth:`MoEnvironment.state_of`). MO-Gymnasium's
    grid worlds declare integer Boxes with loose bounds; the known ones get
    tight bounds here (resource-gathering: row, column and two flags, 100
    states; deep-sea-treasure: the map's cells, 121). More than
    ``max_states`` states (four-room: 169 cells x 2^12 collected-shape flags)
    is refused: abstract the observation with a ``gymnasium.ObservationWrapper``
    and pass ``unwrap=False``, or give ``observation_bounds``.

    **Actions.** The action space must be Discrete; action i of the session
    is the environment's ``start + i``.

    **Stimuli.** Each reward component (objective) is a stimulus dimension
    unless the reward space says it is never positive (a time or damage
    penalty, ``high <= 0``): those are dropped (``penalties="drop"``) or
    refused (``"error"``). A stimulus is an amount received, and MCA-PI has no
    aversion: the reward is ``|Xi(s, a) . Lambda D|``, so a penalty posted as
    a negative stimulus would attract like a positive one, and a penalty
    split off as its own positive dimension would be sought whenever the
    drive turns to it (the drive turns to what was received least). The
    penalties are still counted in :attr:`MoEnvironment.returns`, and a
    death or a time cost still shapes behaviour through the dynamics (a
    killed agent restarts and loses what it carried). A component that can
    be both positive and negative keeps its positive part, and so does every
    component of an environment without a ``reward_space`` (then none is
    dropped). Stimuli are the kept components times ``scale``.

    **Transitions.** With ``transitions="auto"`` the environment's own table
    is read when it has one (``env.unwrapped.P`` in the toy-text form
    ``P[s][a] = [(p, next, reward, terminated), ...]`` over a Discrete
    observation space; a terminating outcome leads to the
    ``initial_state_distrib``, as the adapter's reset does); otherwise, and
    with ``"learn"``, the session learns them (``transitions: "learn"``,
    docs/algorithm.md section 8). MO-Gymnasium's environments keep their
    dynamics in ``step()`` (resource-gathering's enemies are random), so
    they are learned. ``"table"`` requires the table.

    Args:
        env: The environment, e.g. ``mo_gymnasium.make("resource-gathering-v0")``.
        penalties: ``"drop"`` or ``"error"`` for never-positive objectives.
        scale: Stimulus per unit of reward (positive).
        transitions: ``"auto"``, ``"learn"`` or ``"table"``, see above.
        observation_bounds: Inclusive (low, high) per observation component,
            instead of the space's (or the preset's) bounds.
        objectives: Names of the reward components (default: the known
            environments' own, else ``r0``, ``r1``, ...).
        actions: Action names (default: the known environments' own, else
            ``a0``, ``a1``, ...).
        max_states: The most states accepted (the server has its own limits).
        unwrap: Step ``env.unwrapped`` (the default: an agent's life has no
            time limit, so the TimeLimit wrapper is skipped); ``False`` steps
            ``env`` with its wrappers, and a truncation ends the episode too.
        known_after: m of a learned model (see :class:`Learned`).
        optimism: ``"absorbing"`` or ``"stimulus"`` (see :class:`Learned`).
        basis: Optional basis for the server.

    Raises:
        UnsupportedEnvironment: A continuous or otherwise unsupported space,
            more than ``max_states`` states, or no objective left as a stimulus.
        ValueError: A bad option, or a transition table that does not sum to 1.
    """
    base = getattr(env, "unwrapped", env)
    stepped = base if unwrap else env
    name = type(base).__name__
    preset = _mo_preset(base)

    action_space: Any = getattr(stepped, "action_space", None)
    if type(action_space).__name__ != "Discrete":
        raise UnsupportedEnvironment(
            f"{name}'s action space is {action_space}: only a Discrete action space maps to mcapi actions"
        )
    n_actions = as_int(action_space.n, "action_space.n")
    action_start = as_int(getattr(action_space, "start", 0), "action_space.start")
    if actions is None:
        actions = preset.get("actions") if len(preset.get("actions", ())) == n_actions else None
        actions = actions or tuple(f"a{i}" for i in range(n_actions))
    actions = tuple(actions)
    if len(actions) != n_actions:
        raise ValueError(f"{len(actions)} action names for {n_actions} actions")
    _check_names("actions", actions)

    if observations not in ("discrete", "continuous"):
        raise ValueError(f"observations must be 'discrete' or 'continuous', not {observations!r}")
    continuous = observations == "continuous"
    if not continuous:
        obs_space = getattr(stepped, "observation_space", None)
        if obs_space is None:
            raise UnsupportedEnvironment(f"{name} has no observation_space")
        leaves = _space_leaves(obs_space, f"{name}'s observation space")
        if observation_bounds is not None:
            bounds = [(as_int(lo, "low"), as_int(hi, "high")) for lo, hi in observation_bounds]
            if len(bounds) != len(leaves):
                raise ValueError(
                    f"`observation_bounds` has {len(bounds)} entries; "
                    f"the observation has {len(leaves)} components"
                )
        elif (
            "bounds" in preset
            and obs_space == base.observation_space
            and len(preset["bounds"]) == len(leaves)
        ):
            bounds = list(preset["bounds"])
        else:
            bounds = leaves
        for i, (lo, hi) in enumerate(bounds):
            if hi < lo:
                raise ValueError(f"observation component {i}: bounds {lo}..{hi} are empty")
        states = math.prod(hi - lo + 1 for lo, hi in bounds)
        if states > max_states:
            raise UnsupportedEnvironment(
                f"{name}'s observation space {obs_space} gives {states:,} states "
                f"({' x '.join(str(hi - lo + 1) for lo, hi in bounds)}), "
                f"more than max_states = {max_states:,}: "
                "abstract the observation (a gymnasium.ObservationWrapper, with unwrap=False), "
                "give tighter `observation_bounds`, or raise `max_states`"
            )

    reward_space = getattr(base, "reward_space", None)
    if reward_space is None and hasattr(env, "get_wrapper_attr"):
        with contextlib.suppress(AttributeError):
            reward_space = env.get_wrapper_attr("reward_space")
    if reward_space is not None:
        highs = [float(x) for x in _flat_list(reward_space.high)]
    else:
        n_obj = getattr(base, "reward_dim", None)
        if n_obj is None:
            raise UnsupportedEnvironment(
                f"{name} has neither `reward_space` nor `reward_dim`: is it a multi-objective environment?"
            )
        highs = [math.inf] * as_int(n_obj, "reward_dim")
    if objectives is None:
        objectives = preset.get("objectives") if len(preset.get("objectives", ())) == len(highs) else None
        objectives = objectives or tuple(f"r{i}" for i in range(len(highs)))
    objectives = tuple(objectives)
    if len(objectives) != len(highs):
        raise ValueError(f"{len(objectives)} objective names for {len(highs)} reward components")
    _check_names("objectives", objectives)
    penalty = [i for i, hi in enumerate(highs) if hi <= 0.0]
    if penalty and penalties == "error":
        raise UnsupportedEnvironment(
            f"{name}'s objectives {[objectives[i] for i in penalty]} are never positive (penalties); "
            "a stimulus is an amount received: pass penalties='drop' to leave them out"
        )
    if penalties not in ("drop", "error"):
        raise ValueError(f"penalties must be 'drop' or 'error', not {penalties!r}")
    kept = [i for i in range(len(highs)) if i not in penalty]
    if not kept:
        raise UnsupportedEnvironment(
            f"{name}'s objectives {list(objectives)} are all penalties: no stimulus left"
        )
    scale = as_float(scale, "scale")
    if not (math.isfinite(scale) and scale > 0.0):
        raise ValueError(f"`scale` {scale} is not a positive number")
    if continuous:
        # Observation vectors: the session learns the transitions.
        box = observation_bounds
        if box is None and "box" in preset:
            space = getattr(stepped, "observation_space", None)
            if tuple(getattr(space, "shape", ())) == (len(preset["box"]),):
                box = preset["box"]

        def stimulus_of(_x: list[float], reward: Any, _info: Mapping[str, Any]) -> list[float]:
            r = _flat_list(reward)
            return [max(float(r[i]), 0.0) * scale for i in kept]

        return _continuous_environment(
            env,
            stimuli=[objectives[i] for i in kept],
            actions=actions,
            basis=basis,
            bounds=box,
            stimulus_of=stimulus_of,
            out_of_bounds=out_of_bounds,
            samples=samples,
            stepped=stepped,
        )

    if transitions not in ("auto", "learn", "table"):
        raise ValueError(f"transitions must be 'auto', 'learn' or 'table', not {transitions!r}")
    table = getattr(base, "P", None)
    readable = table is not None and type(obs_space).__name__ == "Discrete" and observation_bounds is None
    if transitions == "table" and not readable:
        raise ValueError(
            f"{name} has no transition table `P` over a Discrete observation space: use transitions='learn'"
        )
    known = None
    if readable and transitions != "learn":
        known = _mo_table(base, table, states, bounds[0][0], actions, tuple(objectives[i] for i in kept))
    return MoEnvironment(
        stepped,
        objectives=objectives,
        kept=kept,
        actions=actions,
        action_start=action_start,
        observation_space=obs_space,
        bounds=bounds,
        scale=scale,
        known=known,
        known_after=known_after,
        optimism=optimism,
        basis=basis,
    )


def _mo_table(
    base: Any, P: Any, states: int, start: int, actions: Sequence[str], stimuli: Sequence[str]
) -> Model:
    """A toy-text table ``P[s][a] = [(p, next, reward, terminated), ...]`` with
    each terminating outcome leading to the initial-state distribution."""
    init: list[tuple[int, float]] | None = None
    dist = getattr(base, "initial_state_distrib", None)
    if dist is not None:
        weights = enumerate(_flat_list(dist))
        init = [(s, _probability(p, "initial_state_distrib")) for s, p in weights if p > 0]
    rows = []
    for s in range(states):
        row: dict[int, dict[int, float]] = {}
        outcomes_of = P[s + start]
        pairs = outcomes_of.items() if isinstance(outcomes_of, Mapping) else enumerate(outcomes_of)
        for a, outcomes in pairs:
            where = f"P[{s + start}][{a}]"
            succ: dict[int, float] = {}
            for outcome in outcomes:
                p, t, _reward, done = outcome[:4]
                p = _probability(p, where)
                targets = [(_next_state(t, where) - start, 1.0)]
                if done:
                    if init is None:
                        raise ValueError(
                            f"{type(base).__name__} has no `initial_state_distrib` to restart from: "
                            "use transitions='learn'"
                        )
                    targets = init
                for u, q in targets:
                    if p * q > 0:
                        succ[u] = succ.get(u, 0.0) + p * q
            total = sum(succ.values())
            if abs(total - 1.0) > 1e-6:
                raise ValueError(f"{where}: probabilities sum to {total}, not 1")
            row[as_int(a, "action")] = {u: q / total for u, q in succ.items()}
        rows.append(row)
    return from_transition_table(rows, actions, {}, stimuli=stimuli)


ModelLike = Union[
    Model, Learned, MoEnvironment, ContinuousModel, ContinuousEnvironment, Mapping[str, Any], str
]
"""A model to create a session from: a :class:`Model`, a :class:`Learned`, a
:class:`MoEnvironment`, a :class:`ContinuousModel` or a
:class:`ContinuousEnvironment` (posted by their ``to_json``), the model's JSON as a
mapping (a full model, ``{"preset": "hallway"}`` or ``{"grid": [...],
"sources": {...}}``; numpy values allowed), or a preset name
(``"hallway"``, ``"three_room"``)."""


def model_json(model: ModelLike) -> dict[str, Any]:
    """The ``model`` JSON of a create request (REST's body; gRPC sends it as the typed ``Model``)."""
    if isinstance(model, (Model, Learned, MoEnvironment, ContinuousModel, ContinuousEnvironment)):
        return model.to_json()
    if isinstance(model, str):
        return {"preset": model}
    if isinstance(model, Mapping):
        out: dict[str, Any] = plain(dict(model))
        return out
    raise TypeError(f"not a model: {type(model).__name__}")


def _continuous_environment(
    env: Any,
    *,
    stimuli: Sequence[str],
    actions: Sequence[str] | None,
    basis: Mapping[str, Any] | None,
    bounds: Sequence[tuple[float, float] | None] | None,
    stimulus_of: StimulusOf,
    out_of_bounds: Literal["clip", "refuse"],
    samples: Mapping[str, int] | None,
    stepped: Any = None,
) -> ContinuousEnvironment:
    """A ``Box``-observation, ``Discrete``-action environment as a continuous world."""
    base = getattr(env, "unwrapped", env)
    name = type(base).__name__
    stepped = env if stepped is None else stepped
    action_space: Any = getattr(stepped, "action_space", None)
    if type(action_space).__name__ != "Discrete":
        raise TypeError(
            f"{name}'s action space is {action_space}: only Discrete actions map to mcapi actions"
        )
    n_actions = as_int(action_space.n, "action_space.n")
    if actions is None:
        known = _GYM_ACTIONS.get(name, ())
        actions = known if len(known) == n_actions else None
    names = tuple(actions) if actions is not None else tuple(f"a{i}" for i in range(n_actions))
    if len(names) != n_actions:
        raise ValueError(f"{len(names)} action names for {n_actions} actions")
    low, high = box_bounds(getattr(stepped, "observation_space", None), bounds, name)
    model = ContinuousModel(
        low=tuple(low),
        high=tuple(high),
        actions=names,
        stimuli=tuple(stimuli),
        basis=basis,
        out_of_bounds=out_of_bounds,
        samples=samples,
    )
    start = as_int(getattr(action_space, "start", 0), "action_space.start")
    return ContinuousEnvironment(stepped, model, stimulus_of, start)
