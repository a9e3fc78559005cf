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

Models are checked here by the server's rules (every state has an available
action; probabilities in (0, 1] summing to 1 within 1e-9), so a mistake is a
``ValueError`` naming the place before anything is sent.

Numbers may be numpy scalars and tables numpy arrays (a Gymnasium ``P``
built with numpy, a transition table of ``numpy.int64`` states and
``numpy.float64`` probabilities): a model holds plain ``int`` and ``float``
once built. Next states must be integers (``operator.index``), not floats.
"""

from __future__ import annotations

import dataclasses
import math
import random
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, SupportsIndex, Union

from ._normalise import as_float, as_int, is_int_like, plain

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


# Action names of the toy-text environments, by class name.
_GYM_ACTIONS: dict[str, tuple[str, ...]] = {
    "FrozenLakeEnv": ("left", "down", "right", "up"),
    "CliffWalkingEnv": ("up", "right", "down", "left"),
    "TaxiEnv": ("south", "north", "east", "west", "pickup", "dropoff"),
}


def from_gymnasium(
    env: Any,
    sources: Mapping[str, StatesLike],
    *,
    stimuli: Sequence[str] | None = None,
    actions: Sequence[str] | None = None,
    on_terminated: Literal["restart", "keep"] = "restart",
    basis: Mapping[str, Any] | None = None,
) -> Model:
    """A model from a Gymnasium toy-text environment's transition table.

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

    Raises:
        ValueError: The environment has no transition table, or it does not
            sum to 1, or a restart needs an initial-state distribution it lacks.
    """
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


ModelLike = Union[Model, Learned, Mapping[str, Any], str]
"""A model to create a session from: a :class:`Model`, the model's JSON as a
mapping (a full model, ``{"preset": "hallway"}`` or ``{"grid": [...],
"sources": {...}}``; numpy values allowed), or a preset name
(``"hallway"``, ``"three_room"``)."""


def model_json(model: ModelLike) -> dict[str, Any]:
    """The ``model`` JSON of a create request (REST's body; gRPC sends it as the typed ``Model``)."""
    if isinstance(model, (Model, Learned)):
        return model.to_json()
    if isinstance(model, str):
        return {"preset": model}
    if isinstance(model, Mapping):
        out: dict[str, Any] = plain(dict(model))
        return out
    raise TypeError(f"not a model: {type(model).__name__}")
