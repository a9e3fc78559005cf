"""A Gymnasium environment whose states arrive as numpy scalars, over real
sockets on every transport: slippery FrozenLake in a vector environment
(``obs`` is an ``int64`` array, so each state is a ``numpy.int64``), its model
posted from a transition table built with numpy out of ``P``, stimuli as
numpy arrays, and each session fed by ``env.step``."""

from __future__ import annotations

from typing import Any

import pytest
from conftest import Server, open_client

from mcapi_client import Client, Step, models

gymnasium = pytest.importorskip("gymnasium", reason="the gymnasium extra is not installed")
np = pytest.importorskip("numpy")

SOURCES = {"food": 3, "water": 8}  # free cells of the 4x4 map, a few slippery steps from the start
ACTIONS = ["left", "down", "right", "up"]
ENVS = 2
TICKS = 200


def make_lake() -> Any:
    # Unwrapped: an agent's life has no time limit (a truncation would move
    # it to the start in a way the model does not know).
    return gymnasium.make("FrozenLake-v1", map_name="4x4", is_slippery=True).unwrapped


def numpy_table(lake: Any) -> list[list[dict[Any, Any]]]:
    """``P`` as a dense array T[s, a, s'], terminal states (holes, goal)
    restarting at the initial distribution, read back as cells of
    ``{numpy.int64 next state: numpy.float64 probability}``."""
    n_states, n_actions = lake.observation_space.n, lake.action_space.n
    T = np.zeros((n_states, n_actions, n_states))
    terminal = np.zeros(n_states, dtype=bool)
    for s in range(n_states):
        for a in range(n_actions):
            for p, t, _reward, done in lake.P[s][a]:
                T[s, a, t] += p
                terminal[t] |= bool(done) and p > 0
    T[terminal] = lake.initial_state_distrib
    return [
        [{t: T[s, a, t] for t in np.flatnonzero(T[s, a])} for a in range(n_actions)]
        for s in range(n_states)
    ]


def stimulus(state: Any, rng: Any) -> Any:
    """6 plus N(0, 2) noise on the dimension of a source state, else zeros (a numpy array)."""
    xi = np.zeros(len(SOURCES))
    for dim, source in enumerate(SOURCES.values()):
        if state == source:
            xi[dim] = 6.0 + rng.normal(0.0, 2.0)
    return xi


def test_the_numpy_table_is_the_model_from_gymnasium() -> None:
    lake = make_lake()
    built = models.from_transition_table(
        numpy_table(lake), ACTIONS, {name: np.int64(s) for name, s in SOURCES.items()}
    )
    reference = models.from_gymnasium(lake, sources=SOURCES)
    assert (built.states, built.actions, built.stimuli, built.sources) == (
        reference.states, reference.actions, reference.stimuli, reference.sources,
    )
    for s in range(built.states):
        for a in range(len(ACTIONS)):
            assert dict(built.successors(s, a)) == pytest.approx(dict(reference.successors(s, a)))
    assert all(type(t) is int and type(p) is float for row in built.table for c in row if c for t, p in c)


@pytest.mark.parametrize("kind", ["rest", "grpc", "grpc-stream", "async-rest", "async-grpc"])
def test_frozenlake_with_numpy_states(kind: str, server: Server) -> None:
    envs = gymnasium.vector.SyncVectorEnv([make_lake for _ in range(ENVS)])
    lake = envs.envs[0]
    model = models.from_transition_table(numpy_table(lake), ACTIONS, SOURCES)
    rng = np.random.default_rng(5)
    with open_client("grpc" if kind == "grpc-stream" else kind, server) as mc:
        sessions = [
            mc.create_session(model, seed=np.int64(k), gamma=np.float64(0.9), priorities=np.ones(2)).id
            for k in range(ENVS)
        ]
        streams = [mc.interact(sid) for sid in sessions] if kind == "grpc-stream" else []

        def observe(k: int, state: Any, xi: Any) -> Step:
            if streams:
                return streams[k].step(state, xi)  # type: ignore[no-any-return]
            return mc.observe(sessions[k], state, xi)  # type: ignore[no-any-return]

        obs, _ = envs.reset(seed=11)
        assert obs.dtype == np.int64 and isinstance(obs[0], np.integer) and not isinstance(obs[0], int)
        log: list[list[tuple[Any, Any]]] = [[(obs[k], None)] for k in range(ENVS)]
        steps = [observe(k, obs[k], None) for k in range(ENVS)]
        got: list[list[Step]] = [[s] for s in steps]
        visits = np.zeros(len(SOURCES), dtype=int)
        for _ in range(TICKS):
            # A terminated sub-environment resets on this step whatever the
            # action: what the model's restart rows say.
            obs, _reward, _terminated, truncated, _ = envs.step(np.array([s.action_index for s in steps]))
            assert not truncated.any()
            for k in range(ENVS):
                xi = stimulus(obs[k], rng)
                steps[k] = observe(k, obs[k], xi)
                got[k].append(steps[k])
                log[k].append((obs[k], xi))
                visits += xi != 0
        for stream in streams:
            stream.close()
        for k in range(ENVS):
            info = mc.get_session(sessions[k])
            assert (info.tick, info.state) == (TICKS, int(obs[k]))
            assert info.model.transitions == model.transitions and not info.model.deterministic
    envs.close()
    assert visits.min() > 0, f"the agents reach both sources: {visits}"

    # The same observations as plain Python numbers, to twin sessions of the
    # same seeds: the same steps, tick by tick.
    with Client(server.http_url) as plain:
        for k in range(ENVS):
            twin = plain.create_session(model, seed=k, gamma=0.9, priorities=[1.0, 1.0]).id
            replay = [(int(s),) if xi is None else (int(s), [float(x) for x in xi]) for s, xi in log[k]]
            assert plain.observe_batch(twin, replay) == got[k]
