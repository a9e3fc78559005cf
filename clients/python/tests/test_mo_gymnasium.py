"""``models.from_mo_gymnasium``: discrete multi-objective environments as
models with a step adapter. The checks of spaces, penalties and tables run
on small hand-made environments (gymnasium's spaces only); the end-to-end
tests drive MO-Gymnasium's resource-gathering through a real server over
REST and gRPC with the session's own actions."""

from __future__ import annotations

from typing import Any

import pytest
from conftest import Server, open_client

from mcapi_client import Client, models
from mcapi_client.models import MoEnvironment, UnsupportedEnvironment

gymnasium = pytest.importorskip("gymnasium", reason="the gymnasium extra is not installed")
np = pytest.importorskip("numpy")
spaces = gymnasium.spaces
# MO-Gymnasium's reward spaces are float64 Boxes cast to float32.
pytestmark = pytest.mark.filterwarnings("ignore:.*precision lowered:UserWarning")


class Chain:
    """A hand-made multi-objective environment: a chain of ``n`` cells; action
    1 moves right, 0 left. Arriving in the last cell pays ``reward`` and ends
    the episode; every step costs the time penalty of the last component."""

    def __init__(
        self,
        n: int = 4,
        observation_space: Any = None,
        reward_space: Any = None,
        reward: tuple[float, ...] = (1.0, 0.5, -1.0),
    ) -> None:
        self.n = n
        self.observation_space = observation_space or spaces.Discrete(n)
        self.action_space = spaces.Discrete(2)
        self.reward = np.array(reward, dtype=np.float32)
        self.reward_space = reward_space or spaces.Box(
            low=np.array([0.0, -1.0, -1.0], dtype=np.float32),
            high=np.array([1.0, 1.0, -1.0], dtype=np.float32),
            dtype=np.float32,
        )
        self.pos = 0
        self.actions_seen: list[int] = []

    @property
    def unwrapped(self) -> Chain:
        return self

    def reset(self, seed: int | None = None, **_: Any) -> tuple[Any, dict[str, Any]]:
        self.pos = 0
        return np.int64(self.pos), {}

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        self.actions_seen.append(int(action))
        self.pos = max(0, min(self.n - 1, self.pos + (1 if int(action) == 1 else -1)))
        done = self.pos == self.n - 1
        r = self.reward.copy() if done else np.array([0.0, 0.0, -1.0], dtype=np.float32)
        return np.int64(self.pos), r, done, False, {}


class Fixed(Chain):
    """A chain whose observation space and observations are given."""

    def __init__(self, observation_space: Any, observation: Any) -> None:
        super().__init__(observation_space=observation_space)
        self.observation = observation

    def reset(self, seed: int | None = None, **_: Any) -> tuple[Any, dict[str, Any]]:
        return self.observation, {}


def test_composite_spaces_flatten_row_major_and_back() -> None:
    space = spaces.Dict(
        {
            "cell": spaces.MultiDiscrete([3, 4]),
            "flags": spaces.MultiBinary(2),
            "level": spaces.Tuple((spaces.Discrete(2, start=5),)),
        }
    )
    world = models.from_mo_gymnasium(Fixed(space, None))
    assert world.bounds == ((0, 2), (0, 3), (0, 1), (0, 1), (5, 6))
    assert world.states == 3 * 4 * 2 * 2 * 2
    seen = set()
    for s in range(world.states):
        cell0, cell1, f0, f1, level = world.observation_of(s)
        flags = np.array([f0, f1], dtype=np.int8)
        obs = {"cell": np.array([cell0, cell1]), "flags": flags, "level": (level,)}
        assert world.state_of(obs) == s
        seen.add(s)
    assert len(seen) == world.states
    assert world.state_of({"cell": [2, 3], "flags": [1, 1], "level": (6,)}) == world.states - 1
    # The space's key order, whatever the observation's.
    assert world.state_of({"level": (5,), "flags": [0, 1], "cell": [0, 0]}) == 2
    with pytest.raises(ValueError, match=r"component 4 is 7, not an integer in 5\.\.6"):
        world.state_of({"cell": [0, 0], "flags": [0, 0], "level": (7,)})
    with pytest.raises(ValueError, match="has no 'cell'"):
        world.state_of({"level": (5,), "flags": [0, 1]})
    with pytest.raises(ValueError, match="component 1 is 1.5, not an integer"):
        world.state_of({"cell": [0, 1.5], "flags": [0, 0], "level": (5,)})
    with pytest.raises(ValueError, match="has 2 components, expected 5"):
        world.state_of([0, 0])


def test_refuses_continuous_and_oversized_spaces() -> None:
    box = spaces.Box(low=0.0, high=1.0, shape=(2,), dtype=np.float32)
    with pytest.raises(UnsupportedEnvironment, match="observation space is continuous"):
        models.from_mo_gymnasium(Fixed(box, None))
    chain = Chain()
    chain.action_space = spaces.Box(low=-1.0, high=1.0, shape=(1,))
    with pytest.raises(UnsupportedEnvironment, match="only a Discrete action space"):
        models.from_mo_gymnasium(chain)
    big = spaces.MultiDiscrete([100, 100, 2])
    too_many = r"gives 20,000 states \(100 x 100 x 2\), more than max_states"
    with pytest.raises(UnsupportedEnvironment, match=too_many):
        models.from_mo_gymnasium(Fixed(big, None))
    assert models.from_mo_gymnasium(Fixed(big, None), max_states=20_000).states == 20_000
    text = spaces.Text(5)
    with pytest.raises(UnsupportedEnvironment, match="is a Text"):
        models.from_mo_gymnasium(Fixed(text, None))


def test_penalties_are_dropped_or_refused_and_mixed_components_cut_at_zero() -> None:
    world = models.from_mo_gymnasium(Chain(), objectives=("gold", "mixed", "time"), scale=6)
    assert world.stimuli == ("gold", "mixed") and world.kept == (0, 1) and world.dropped == (2,)
    assert world.stimulus_of([1.0, -0.5, -1.0]) == [6.0, 0.0]
    assert world.stimulus_of(np.array([0.5, 0.25, -1.0])) == [3.0, 1.5]
    with pytest.raises(UnsupportedEnvironment, match=r"objectives \['time'\] are never positive"):
        models.from_mo_gymnasium(Chain(), objectives=("gold", "mixed", "time"), penalties="error")
    low, high = np.array([-1.0, -5.0], dtype=np.float32), np.array([0.0, -1.0], dtype=np.float32)
    only_costs = spaces.Box(low=low, high=high, dtype=np.float32)
    with pytest.raises(UnsupportedEnvironment, match="are all penalties"):
        models.from_mo_gymnasium(Chain(reward_space=only_costs))
    with pytest.raises(ValueError, match="`scale` -1.0 is not a positive number"):
        models.from_mo_gymnasium(Chain(), scale=-1)


def test_learned_json_and_options() -> None:
    world = models.from_mo_gymnasium(
        Chain(), known_after=2, optimism="stimulus", basis={"kind": "indicator"}, actions=("left", "right")
    )
    assert world.known is None
    assert models.model_json(world) == {
        "states": 4,
        "actions": ["left", "right"],
        "stimuli": ["r0", "r1"],
        "transitions": "learn",
        "learning": {"known_after": 2, "optimism": "stimulus"},
        "basis": {"kind": "indicator"},
    }
    with pytest.raises(ValueError, match="`known_after` 0 is not in"):
        models.from_mo_gymnasium(Chain(), known_after=0)
    assert world.env_action("right") == 1 and world.env_action(0) == 0
    with pytest.raises(ValueError, match="action 2 is out of range"):
        world.env_action(2)


def test_steps_fold_the_episode_end_into_the_reset_state() -> None:
    chain = Chain(n=3)
    world = models.from_mo_gymnasium(chain, scale=2)
    with pytest.raises(RuntimeError, match="reset"):
        world.step(1)
    assert world.reset() == 0
    first = world.step(1)
    assert (first.state, first.stimulus, first.episode_ended) == (1, [0.0, 0.0], False)
    last = world.step(1)  # arrives in cell 2: the episode ends, and the state is the reset one
    assert last.terminated and last.episode_ended and int(last.observation) == 2
    assert (last.state, last.stimulus, last.reward) == (0, [2.0, 1.0], (1.0, 0.5, -1.0))
    assert world.returns == [1.0, 0.5, -2.0] and world.stimulus_totals == [2.0, 1.0]
    assert (world.ticks, world.episodes) == (2, 1) and chain.actions_seen == [1, 1]


class Table(Chain):
    """The chain with a toy-text transition table ``P`` and vector rewards."""

    def __init__(self) -> None:
        super().__init__(n=3)
        self.initial_state_distrib = np.array([0.5, 0.5, 0.0])
        def outcome(s: int, a: int) -> list[tuple[float, int, Any, bool]]:
            t = min(2, max(0, s + (1 if a else -1)))
            return [(1.0, t, np.zeros(3), t == 2)]

        self.P = {s: {a: outcome(s, a) for a in range(2)} for s in range(3)}


def test_a_transition_table_is_read_with_terminal_outcomes_restarting() -> None:
    world = models.from_mo_gymnasium(Table())
    assert world.known is not None
    out = models.model_json(world)
    assert "learn" not in str(out.get("transitions"))
    # State 1, right: terminates, so it leads to the initial distribution.
    assert dict(world.known.successors(1, 1)) == {0: 0.5, 1: 0.5}
    assert world.known.successors(1, 0) == ((0, 1.0),)
    assert models.model_json(models.from_mo_gymnasium(Table(), transitions="learn"))["transitions"] == "learn"
    with pytest.raises(ValueError, match="no transition table"):
        models.from_mo_gymnasium(Chain(), transitions="table")


def test_a_read_table_is_posted_as_a_known_model(client: Client) -> None:
    world = models.from_mo_gymnasium(Table(), scale=6)
    session = client.create_session(world, seed=1)
    try:
        assert session.model.learned is None and session.model.states == 3
        step = client.observe(session.id, world.reset())
        for _ in range(30):
            s = world.step(step)
            step = client.observe(session.id, s.state, s.stimulus)
        assert world.episodes >= 2 and world.stimulus_totals[0] == 6 * world.episodes
    finally:
        client.delete_session(session.id)


# End to end: resource-gathering through a real server.

mo_gymnasium = pytest.importorskip("mo_gymnasium", reason="the mo extra is not installed")


def test_known_mo_gymnasium_environments() -> None:
    world = models.from_mo_gymnasium(mo_gymnasium.make("resource-gathering-v0"))
    assert (world.states, world.actions) == (100, ("up", "down", "left", "right"))
    assert world.objectives == ("enemy", "gold", "gem") and world.stimuli == ("gold", "gem")
    assert world.observation_of(world.reset(seed=0)) == (4, 2, 0, 0)  # home, carrying nothing
    dst = models.from_mo_gymnasium(mo_gymnasium.make("deep-sea-treasure-v0"))
    assert (dst.states, dst.stimuli, dst.dropped) == (121, ("treasure",), (1,))
    with pytest.raises(UnsupportedEnvironment, match="FourRoom's observation space .* more than max_states"):
        models.from_mo_gymnasium(mo_gymnasium.make("four-room-v0"))
    with pytest.raises(UnsupportedEnvironment, match="continuous"):
        models.from_mo_gymnasium(mo_gymnasium.make("mo-mountaincar-v0"))


class CellOnly(gymnasium.ObservationWrapper):  # type: ignore[misc]
    """four-room's observation without its collected-shape flags: the cell."""

    def __init__(self, env: Any) -> None:
        super().__init__(env)
        self.observation_space = spaces.MultiDiscrete([13, 13])

    def observation(self, obs: Any) -> Any:
        return obs[:2]


def test_an_observation_wrapper_makes_four_room_small_enough() -> None:
    world = models.from_mo_gymnasium(CellOnly(mo_gymnasium.make("four-room-v0").unwrapped), unwrap=False)
    assert (world.states, world.stimuli, world.dropped) == (169, ("blue", "green", "red"), ())
    assert world.observation_of(world.reset(seed=0)) == (12, 0)  # the start, lower left
    assert world.step("up").state == world.state_of([11, 0])


class Recorder(gymnasium.Wrapper):  # type: ignore[misc]
    """Records each action and observation (reset ones as ``None`` actions)."""

    def __init__(self, env: Any) -> None:
        super().__init__(env)
        self.log: list[tuple[int | None, Any]] = []

    def reset(self, **kw: Any) -> Any:
        obs, info = self.env.reset(**kw)
        self.log.append((None, obs))
        return obs, info

    def step(self, action: Any) -> Any:
        out = self.env.step(action)
        self.log.append((int(action), out[0]))
        return out


@pytest.mark.parametrize("kind", ["rest", "grpc"])
def test_resource_gathering_end_to_end(server: Server, kind: str) -> None:
    ticks = 600
    # The recorder is stepped (unwrap=False) and wraps the unwrapped
    # environment, so there is no time limit either way.
    env = Recorder(mo_gymnasium.make("resource-gathering-v0").unwrapped)
    world = models.from_mo_gymnasium(env, scale=6, known_after=1, unwrap=False)
    assert isinstance(world, MoEnvironment) and world.states == 100
    with open_client(kind, server) as mc:
        session = mc.create_session(world, seed=3)
        assert session.model.states == 100 and session.model.stimuli == ["gold", "gem"]
        assert session.model.learned is not None and session.model.learned.known_after == 1
        start = world.reset(seed=3)
        step = mc.observe(session.id, start)
        advised, sent, stimuli = [], [start], []
        for _ in range(ticks):
            advised.append(step.action_index)
            s = world.step(step.action_index)
            step = mc.observe(session.id, s.state, s.stimulus)
            sent.append(s.state)
            stimuli.append(s.stimulus)
        known = mc.values(session.id).known_fraction
        history = mc.history(session.id, limit=ticks)
        mc.delete_session(session.id)

    # The adapter's mapping: each advised action went to the environment as
    # that action, and each state observed is the index of the observation
    # the environment returned (or of its reset observation after an episode end).
    stepped = [a for a, _ in env.log if a is not None]
    assert stepped == advised
    log = env.log
    kept = [obs for k, (_, obs) in enumerate(log) if k + 1 == len(log) or log[k + 1][0] is not None]
    assert sent == [world.state_of(obs) for obs in kept]
    assert len(history) >= 100  # the newest ticks the server keeps
    assert [h.state for h in history] == sent[-len(history) :]
    assert [h.stimulus for h in history] == stimuli[-len(history) :]

    # The agent explores, learns the model (all but the 28 pairs of states
    # never observed: home while carrying, which the reset replaces, and a
    # resource's cell before picking it up) and brings both resources home:
    # 8 to 12 of each over seeds 0-11, where moving at random brings about 3.
    gold, gem = (x / 6 for x in world.stimulus_totals)
    assert world.episodes >= 10, world.episodes
    assert gold >= 5 and gem >= 5, world.stimulus_totals
    assert world.returns[1:] == [gold, gem]
    assert known is not None and 0.85 <= known <= 0.93, known
