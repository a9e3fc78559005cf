"""A Gymnasium vector environment driven by a group (VectorEnvAdapter), over
gRPC and REST, with sub-environments that terminate, so that Gymnasium's
next-step autoreset is exercised: a tiny line world registered here."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from conftest import Server

from mcapi_client import Client, GrpcClient, models
from mcapi_client.vector_env import VectorEnvAdapter

gymnasium = pytest.importorskip("gymnasium", reason="the gymnasium extra is not installed")

LENGTH, START, FOOD, WATER = 8, 3, 0, 7
ENV_ID = "mcapi-test/Line-v0"


class Line(gymnasium.Env):  # type: ignore[misc]
    """States 0..7 on a line, actions left and right (Discrete(2, start=1):
    the environment's action 1 is left). Arriving at 0 is food (``info["food"]``),
    arriving at 7 is water (``info["water"]``, reward 1) and ends the episode;
    every episode starts at 3."""

    def __init__(self) -> None:
        self.observation_space = gymnasium.spaces.Discrete(LENGTH)
        self.action_space = gymnasium.spaces.Discrete(2, start=1)
        self.state = START

    def reset(self, *, seed: int | None = None, options: Any = None) -> tuple[int, dict[str, Any]]:
        super().reset(seed=seed)
        self.state = START
        return self.state, {}

    def step(self, action: int) -> tuple[int, float, bool, bool, dict[str, Any]]:
        assert action in (1, 2), action
        self.state = max(self.state - 1, 0) if action == 1 else min(self.state + 1, LENGTH - 1)
        info: dict[str, Any] = {}
        if self.state == FOOD:
            info["food"] = 1.0
        if self.state == WATER:
            info["water"] = 1.0
        return self.state, float(self.state == WATER), self.state == WATER, False, info


gymnasium.register(ENV_ID, entry_point=Line)


def line_model() -> models.Model:
    """The line, its terminal state leading back to the start whatever the action."""
    table = []
    for s in range(LENGTH):
        table.append([START, START] if s == WATER else [max(s - 1, 0), min(s + 1, LENGTH - 1)])
    return models.from_transition_table(table, ["left", "right"], {"food": FOOD, "water": WATER})


def drive_line(agents: Any, n: int, ticks: int) -> tuple[list[Any], VectorEnvAdapter]:
    envs = gymnasium.make_vec(ENV_ID, num_envs=n, vectorization_mode="sync")
    world = VectorEnvAdapter(envs, agents, stimuli=["food", "water"])
    first = world.reset(seed=1)
    assert first.actions.shape == (n,)
    steps = [world.step() for _ in range(ticks)]
    envs.close()
    return steps, world


def test_a_group_drives_the_vector_env_through_autoresets(grpc_client: GrpcClient) -> None:
    model, n, ticks = line_model(), 8, 300
    with grpc_client.create_group(model, n, seed=3, update_mode="lockstep") as agents:
        steps, world = drive_line(agents, n, ticks)
        info = agents.info
    prev_states = np.full(n, START)
    prev_actions = None
    for t, s in enumerate(steps):
        # Every move reported is one the model allows: an autoreset is the
        # terminal state's restart row, never a jump the model does not know.
        if prev_actions is not None:
            expected = [model.successors(a, b)[0][0] for a, b in zip(prev_states, prev_actions)]
            assert s.states.tolist() == expected, f"tick {t}"
        # Reset by this step exactly when the step before ended the episode.
        was_ended = steps[t - 1].episode_ended if t else np.zeros(n, dtype=bool)
        assert s.reset.tolist() == was_ended.tolist()
        assert (s.states[s.reset] == START).all() and (s.stimuli[s.reset] == 0.0).all()
        assert (s.states[s.terminated] == WATER).all()
        assert s.stimuli[s.terminated].tolist() == [[0.0, 1.0]] * int(s.terminated.sum())
        assert (s.stimuli[:, 0] == (s.states == FOOD)).all()
        assert not s.agents.errors
        prev_states, prev_actions = s.states, s.agents.actions
    ended = np.sum([s.terminated for s in steps], axis=0)
    assert ended.sum() >= n and (ended > 0).sum() >= n // 2, f"sub-environments restart: {ended}"
    assert (world.episodes == ended).all() and (world.returns == ended).all()
    assert world.stimulus_totals[:, 0].sum() > 0, "members find the food too"
    assert world.ticks == ticks
    # The server saw every step of every member, and where each is now.
    for k, sid in enumerate(info.members):
        session = grpc_client.get_session(sid)
        assert (session.tick, session.state) == (ticks, int(steps[-1].states[k]))
    grpc_client.delete_group(info.id)


def test_over_rest_the_same_run(grpc_client: GrpcClient, server: Server) -> None:
    model, n, ticks = line_model(), 4, 150
    with grpc_client.create_group(model, n, seed=9, update_mode="lockstep") as agents:
        over_grpc, _ = drive_line(agents, n, ticks)
    with Client(server.http_url) as rest, rest.create_group(model, n, seed=9, update_mode="lockstep") as ra:
        over_rest, _ = drive_line(ra, n, ticks)
        rest.delete_group(ra.info.id)
    assert any(s.terminated.any() for s in over_rest)
    for x, y in zip(over_grpc, over_rest):
        assert x.states.tolist() == y.states.tolist()
        assert x.agents.drives.tolist() == y.agents.drives.tolist()
    grpc_client.delete_group(agents.info.id)


def test_stimulus_of_and_the_reward_default(grpc_client: GrpcClient) -> None:
    model, n = line_model(), 2
    envs = gymnasium.vector.SyncVectorEnv([Line, Line])
    seen: list[tuple[Any, Any]] = []

    def stimulus_of(obs: Any, rewards: Any, infos: Any) -> Any:
        seen.append((obs.copy(), rewards.copy()))
        return np.stack([(obs == START) * 2.0, rewards * 3.0], axis=1)  # 2 at the start, too

    with grpc_client.create_group(model, n, seed=4) as agents:
        world = VectorEnvAdapter(envs, agents, stimulus_of=stimulus_of)
        assert world.stimuli == ("stimulus0", "stimulus1")
        world.reset(seed=0)
        resets = 0
        for _ in range(100):
            step = world.step()
            # A sub-environment reset by this step is at the start with a zero stimulus.
            assert step.stimuli.tolist() == np.where(
                step.reset[:, None], 0.0, np.stack([(step.states == START) * 2.0, step.rewards * 3.0], axis=1)
            ).tolist()
            resets += int(step.reset.sum())
        assert len(seen) == 100 and resets > 0 and world.stimulus_totals.sum(axis=0).min() > 0
    grpc_client.delete_group(agents.info.id)
    one = models.from_transition_table(
        [[START, START] if s == WATER else [max(s - 1, 0), min(s + 1, LENGTH - 1)] for s in range(LENGTH)],
        ["left", "right"],
        {"water": WATER},
    )
    with grpc_client.create_group(one, n, seed=4) as agents:
        world = VectorEnvAdapter(envs, agents)
        assert world.stimuli == ("reward",)
        world.reset(seed=0)
        steps = [world.step() for _ in range(100)]
        assert all(s.stimuli[:, 0].tolist() == np.where(s.reset, 0.0, s.rewards).tolist() for s in steps)
        assert world.stimulus_totals.sum() > 0
    grpc_client.delete_group(agents.info.id)
    envs.close()


def test_what_the_adapter_refuses(grpc_client: GrpcClient) -> None:
    model = line_model()
    with grpc_client.create_group(model, 2, seed=1) as agents:
        envs = gymnasium.vector.SyncVectorEnv([Line] * 3)
        with pytest.raises(ValueError, match="3 sub-environments for a group of 2 members"):
            VectorEnvAdapter(envs, agents, stimuli=["food", "water"])
        same = gymnasium.vector.SyncVectorEnv(
            [Line] * 2, autoreset_mode=gymnasium.vector.AutoresetMode.SAME_STEP
        )
        with pytest.raises(ValueError, match="autoreset mode is SameStep"):
            VectorEnvAdapter(same, agents, stimuli=["food", "water"])
        ok = gymnasium.vector.SyncVectorEnv([Line] * 2)
        with pytest.raises(ValueError, match="1 stimulus names"):
            VectorEnvAdapter(ok, agents, stimuli=["food"])
        with pytest.raises(ValueError, match="needs `stimuli`"):
            VectorEnvAdapter(ok, agents)
        boxed = gymnasium.vector.SyncVectorEnv(
            [lambda: gymnasium.wrappers.TransformObservation(
                Line(), lambda o: np.array([o], dtype=np.float32),
                gymnasium.spaces.Box(0, 7, (1,), dtype=np.float32))] * 2
        )
        with pytest.raises(TypeError, match="observation space is Box"):
            VectorEnvAdapter(boxed, agents, stimuli=["food", "water"])
        world = VectorEnvAdapter(ok, agents, stimuli=["food", "water"])
        with pytest.raises(RuntimeError, match="reset"):
            world.step()
        for e in (envs, same, ok, boxed):
            e.close()
    grpc_client.delete_group(agents.info.id)
