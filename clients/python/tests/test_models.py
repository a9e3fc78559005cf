"""Model builders: their rules, and that the server builds the same models."""

from __future__ import annotations

import dataclasses
import random
from collections import Counter
from typing import Any

import pytest

from mcapi_client import Client, models
from mcapi_client.models import Source

GRID = [
    "#######",
    "#a..#.#",
    "#.#...#",
    "#...#b#",
    "#######",
    "",
]


def test_hallway_is_the_papers_chain() -> None:
    h = models.hallway()
    assert (h.states, h.actions, h.stimuli) == (50, ("left", "right", "stay"), ("food", "rest"))
    assert h.sources == (Source(10, 0), Source(40, 1))
    assert h.pairs == 148 and h.deterministic
    assert h.available_actions(0) == [1, 2] and h.available_actions(49) == [0, 2]
    assert h.successors(10, 1) == ((11, 1.0),)
    assert h.stimulus(10) == [6.0, 0.0] and h.stimulus(40) == [0.0, 6.0] and h.stimulus(11) == [0.0, 0.0]
    rng = random.Random(0)
    noisy = [h.stimulus(40, noise_sd=2.0, rng=rng)[1] for _ in range(2000)]
    assert abs(sum(noisy) / len(noisy) - 6.0) < 0.2
    spec = h.to_json()
    assert spec["next"][0] == [None, 1, 0] and spec["next"][49] == [48, None, 49]
    assert "transitions" not in spec
    short = models.hallway(5, {"x": [0, 4]})
    assert short.source_states("x") == [0, 4] and short.stimuli == ("x",)


def test_grid_numbers_free_cells_and_blocks_walls() -> None:
    g = models.grid(GRID, {"a": 0, "b": 1}, stimuli=["food", "water"])
    assert g.states == 12 and g.actions == models.GRID_ACTIONS
    assert (g.rows, g.cols) == (5, 7)
    assert g.cell_of(0) == (1, 1) and g.state_at(1, 1) == 0 and g.state_at(0, 0) is None
    assert g.marks == (("a", 0), ("b", 11))
    assert g.sources == (Source(0, 0), Source(11, 1))
    left, right, north, south, stay = range(5)
    assert g.successors(0, right) == ((1, 1.0),)
    assert g.table[0][left] is None and g.table[0][north] is None
    assert g.successors(0, south) == ((g.state_at(2, 1), 1.0),)  # type: ignore[arg-type]
    assert g.successors(0, stay) == ((0, 1.0),)
    assert g.render() == [line for line in GRID if line]
    assert models.grid("\n".join(GRID), {"a": 0}).stimuli == ("a",)


@pytest.mark.parametrize(
    ("lines", "sources", "message"),
    [
        (["###", "#.", "###"], {"a": 0}, "grid row 1 has 2 columns"),
        (["#\t#"], {"a": 0}, "unexpected character"),
        (["###"], {"a": 0}, "no free cell"),
        (["#a#"], {}, "map at least one mark"),
        (["#a#"], {"z": 0}, "no cell marked `z`"),
        (["#ab#"], {"a": 0, "b": 0}, "dimension 0 is given twice"),
    ],
)
def test_grid_errors(lines: list[str], sources: dict[str, int], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        models.grid(lines, sources)


def test_transition_table_forms_merging_and_encoding() -> None:
    m = models.from_transition_table(
        [
            {"go": [(1, 0.25), (1, 0.25), (0, 0.5), (2, 0.0)], "wait": 0},
            [None, {1: 1.0}],
            [2, None],
        ],
        actions=["go", "wait"],
        sources={"food": 2},
        stimuli=["food", "water"],
    )
    assert m.successors(0, 0) == ((1, 0.5), (0, 0.5)), "repeats merged, zeros dropped"
    assert m.available_actions(1) == [1] and m.available_actions(2) == [0]
    assert not m.deterministic and m.transitions == 5 and m.pairs == 4
    spec = m.to_json()
    assert spec["transitions"][0] == {"state": 0, "action": 0, "next": [[1, 0.5], [0, 0.5]]}
    assert spec["stimuli"] == ["food", "water"] and "next" not in spec
    det = models.from_transition_table([[1], [0]], ["flip"], {"x": 0})
    assert det.deterministic and det.to_json()["next"] == [[1], [0]]
    rng = random.Random(1)
    counts = Counter(m.sample_next(0, 0, rng) for _ in range(4000))
    assert abs(counts[1] / 4000 - 0.5) < 0.05


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ([[{0: 0.5}]], "probabilities sum to 0.5"),
        ([[None]], "state 0 has no available action"),
        ([[3]], "next state 3 is out of range"),
        ([[{0: -0.1, 1: 1.1}], [0]], "probability -0.1"),
        ([[0, 0]], "row 0 of the table has 2 entries"),
        ([{"jump": 0}], "`jump` is not one of the actions"),
        ([[{0: 0.0}]], "no successor with a positive probability"),
    ],
)
def test_transition_table_errors(table: Any, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        models.from_transition_table(table, ["go"], {"x": 0})


class FakeToyText:
    """The shape of a toy-text environment without Gymnasium: P and a start."""

    def __init__(self) -> None:
        # 0 -> 1 (slips back to 0 half the time); 1 -> 2, terminal (absorbing in P).
        self.P = {
            0: {0: [(0.5, 1, 0.0, False), (0.5, 0, 0.0, False)], 1: [(1.0, 0, 0.0, False)]},
            1: {0: [(1.0, 2, 1.0, True)], 1: [(1.0, 0, 0.0, False)]},
            2: {0: [(1.0, 2, 0.0, True)], 1: [(1.0, 2, 0.0, True)]},
        }
        self.initial_state_distrib = [1.0, 0.0, 0.0]

    @property
    def unwrapped(self) -> FakeToyText:
        return self


def test_from_gymnasium_table_restart_and_keep() -> None:
    env = FakeToyText()
    m = models.from_gymnasium(env, sources={"food": 2})
    assert m.actions == ("a0", "a1")
    assert m.successors(0, 0) == ((1, 0.5), (0, 0.5))
    assert m.successors(2, 0) == ((0, 1.0),) and m.successors(2, 1) == ((0, 1.0),), "terminal restarts"
    kept = models.from_gymnasium(env, sources={"food": 2}, on_terminated="keep", actions=["l", "r"])
    assert kept.successors(2, 0) == ((2, 1.0),)
    del env.initial_state_distrib
    with pytest.raises(ValueError, match="initial_state_distrib"):
        models.from_gymnasium(env, sources={"food": 2})
    with pytest.raises(ValueError, match="no transition table"):
        models.from_gymnasium(object(), sources={"food": 0})


def test_from_gymnasium_frozenlake_slippery() -> None:
    gymnasium = pytest.importorskip("gymnasium", reason="the gymnasium extra is not installed")
    env = gymnasium.make("FrozenLake-v1", map_name="4x4", is_slippery=True)
    m = models.from_gymnasium(env, sources={"food": 3, "water": 8})
    assert (m.states, m.actions) == (16, ("left", "down", "right", "up"))
    assert not m.deterministic
    # Corner state 0, "left": stays with 2/3 (left and up both bump), goes down with 1/3.
    assert dict(m.successors(0, 0)) == pytest.approx({0: 2 / 3, 4: 1 / 3})
    for s in range(16):
        for a in m.available_actions(s):
            assert sum(p for _, p in m.successors(s, a)) == pytest.approx(1.0, abs=1e-12)
    # Holes (5, 7, 11, 12) and the goal (15) restart at the start cell.
    for s in (5, 7, 11, 12, 15):
        assert all(m.successors(s, a) == ((0, 1.0),) for a in range(4))
    # Non-slippery FrozenLake is deterministic.
    assert models.from_gymnasium(
        gymnasium.make("FrozenLake-v1", is_slippery=False), sources={"g": 15}
    ).deterministic


def test_the_server_accepts_the_built_models(client: Client) -> None:
    h = client.create_session(models.hallway(), seed=1)
    preset = client.create_session("hallway", seed=1)
    assert h.model == preset.model
    g = models.grid(GRID, {"a": 0, "b": 1})
    built = client.create_session(g, seed=2)
    server_grid = client.create_session({"grid": GRID, "sources": {"a": 0, "b": 1}}, seed=2)
    # The same model; only the map form carries a layout (the client posts
    # its grid as a full transition model).
    assert built.model.layout is None and server_grid.model.layout is not None
    assert built.model == dataclasses.replace(server_grid.model, layout=None)
    # The same model, the same seed and the same observations: the same agent.
    rng = random.Random(3)
    state = 5
    a = client.observe(built.id, state)
    b = client.observe(server_grid.id, state)
    for _ in range(40):
        assert a == b
        state = g.sample_next(state, a.action_index, rng)
        a = client.observe(built.id, state, g.stimulus(state))
        b = client.observe(server_grid.id, state, g.stimulus(state))
    assert client.values(built.id, "q").q == client.values(server_grid.id, "q").q
    stochastic = models.from_gymnasium(FakeToyText(), sources={"food": 2})
    info = client.create_session(stochastic)
    assert (info.model.states, info.model.pairs) == (3, stochastic.pairs)
    assert info.model.transitions == stochastic.transitions and not info.model.deterministic


def test_learned_models_are_explored_through_every_client(any_client: Any) -> None:
    """A grid posted with ``learn`` (docs/algorithm.md section 8): the server
    never sees the moves, the agent learns them from the observations, and
    ``known_fraction`` rises from 0; the same seed and observations give the
    same agent as the full-model form."""
    g = models.grid(GRID, {"a": 0, "b": 1})
    world = models.learned(g, known_after=1)
    assert world.to_json() == {
        "grid": [line for line in GRID if line],
        "sources": {"a": 0, "b": 1},
        "stimuli": ["a", "b"],
        "learn": True,
        "learning": {"known_after": 1},
    }
    info = any_client.create_session(world, seed=4)
    learned = info.model.learned
    assert learned is not None and (learned.known_after, learned.optimism) == (1, "absorbing")
    assert learned.max_transitions == info.model.pairs * info.model.states
    known = any_client.create_session(g, seed=4)
    assert known.model.learned is None
    assert any_client.values(known.id).known_fraction is None
    rng = random.Random(5)
    state = 0
    step = any_client.observe(info.id, state)
    fractions = [any_client.values(info.id).known_fraction]
    seen = {state}
    for t in range(1, 301):
        state = world.sample_next(state, step.action_index, rng)
        seen.add(state)
        step = any_client.observe(info.id, state, world.stimulus(state))
        if t % 100 == 0:
            fractions.append(any_client.values(info.id).known_fraction)
    assert fractions[0] == 0.0
    assert fractions == sorted(fractions) and fractions[-1] > 0.5, fractions
    history = any_client.history(info.id, 1)
    assert history[-1].known_fraction == fractions[-1]
    assert len(any_client.history(known.id)) == 0
    assert set(g.source_states("a") + g.source_states("b")) <= seen, "both sources found"
    # A full model posted with "transitions": "learn" needs every action in
    # every state; the hallway's ends have none to the wall.
    with pytest.raises(ValueError, match="unavailable in state 0"):
        models.learned(models.hallway())
    with pytest.raises(ValueError, match="known_after"):
        models.learned(g, known_after=0)
    chain = models.from_transition_table(
        [[1, 0], [0, 1]], ["go", "stay"], {"x": [1]}
    )
    full = any_client.create_session(models.learned(chain, optimism="stimulus"), seed=1)
    assert full.model.learned is not None and full.model.learned.optimism == "stimulus"
    assert models.learned(chain).to_json()["transitions"] == "learn"
