"""The blocking REST client against the real server: every method."""

from __future__ import annotations

import random

import httpx
import pytest

from mcapi_client import Client, NotFound, Observation, models
from mcapi_client.types import SessionInfo


def test_ready(client: Client) -> None:
    assert client.ready()
    with Client("http://127.0.0.1:9", timeout=0.5) as dead:
        assert not dead.ready()


def test_create_from_a_built_model_returns_its_summary_and_config(client: Client) -> None:
    info = client.create_session(
        models.hallway(), seed=11, eta=0.02, gamma=0.9, priorities=[1.0, 0.5],
        stimulus_rate=0.5, optimistic_sd=0.2, ridge=1e-5, epsilon=0.1,
        update_mode="async", history=64,
    )
    assert isinstance(info, SessionInfo)
    assert info.id.startswith("s") and "." in info.id
    assert info.tick == 0 and info.state is None and info.policy_version == 0
    assert info.model.states == 50
    assert info.model.actions == ["left", "right", "stay"]
    assert info.model.stimuli == ["food", "rest"]
    assert info.model.pairs == 148 and info.model.deterministic
    assert info.model.basis.kind == "indicator"
    cfg = info.agent
    assert (cfg.seed, cfg.eta, cfg.gamma, cfg.priorities) == (11, 0.02, 0.9, [1.0, 0.5])
    assert (cfg.stimulus_rate, cfg.optimistic_sd, cfg.ridge, cfg.epsilon) == (0.5, 0.2, 1e-5, 0.1)
    assert (cfg.update_mode, cfg.history) == ("async", 64)
    assert len(info.drive) == 2 and all(isinstance(d, float) for d in info.drive)
    assert abs(sum(d * d for d in info.drive) - 1.0) < 1e-9, "the drive is a unit vector"
    assert set(info.drive_by_stimulus()) == {"food", "rest"}
    assert info.dominant_stimulus() in ("food", "rest")


def test_create_from_preset_name_and_server_forms(client: Client) -> None:
    preset = client.create_session("hallway", seed=1)
    assert preset.model.states == 50 and preset.agent.stimulus_rate == "sample_mean"
    assert preset.agent.update_mode == "lockstep"
    grid = client.create_session({"grid": ["#####", "#a.b#", "#####"], "sources": {"a": 0, "b": 1}})
    assert grid.model.states == 3 and grid.model.stimuli == ["a", "b"]
    pvf = client.create_session(models.hallway(basis={"kind": "proto_value", "k": 10}))
    assert (pvf.model.basis.kind, pvf.model.basis.k, pvf.model.features) == ("proto_value", 10, 30)


def test_get_reflects_observations(client: Client) -> None:
    sid = client.create_session("hallway", seed=3).id
    client.observe(sid, 25)
    client.observe(sid, 26, [0.0, 0.0])
    info = client.get_session(sid)
    assert (info.id, info.tick, info.state) == (sid, 1, 26)
    assert info.policy_version >= 1
    assert info.stats.factorisations + info.stats.factorisation_reuses >= 1
    assert isinstance(info.stats.condition_1_holds, bool)


def test_observe_first_then_with_stimulus_and_action_taken(client: Client) -> None:
    world = models.hallway()
    sid = client.create_session(world, seed=5).id
    first = client.observe(sid, 25)
    assert first.tick == 0 and first.reward == 0.0
    assert first.action in world.actions and world.actions[first.action_index] == first.action
    # Report that the agent went right whatever it was told, by name then by index.
    step = client.observe(sid, 26, [0.0, 0.0], action_taken="right")
    assert step.tick == 1
    step = client.observe(sid, 27, [0.0, 0.0], action_taken=1)
    assert step.tick == 2
    # Arriving at the food source moves the drive.
    before = client.get_session(sid).drive
    for s in range(26, 9, -1):
        step = client.observe(sid, s, world.stimulus(s))
    assert step.drive != before
    assert step.reward >= 0.0


def test_observe_batch_replays_in_order_and_matches_single_observations(client: Client) -> None:
    world = models.hallway()
    rng = random.Random(4)
    a = client.create_session(world, seed=9).id
    b = client.create_session(world, seed=9).id
    state = 20
    log = [Observation(state)]
    singles = [client.observe(a, state)]
    for _ in range(60):
        state = world.sample_next(state, singles[-1].action_index, rng)
        obs = Observation(state, world.stimulus(state, noise_sd=2.0, rng=rng))
        log.append(obs)
        singles.append(client.observe(a, obs.state, obs.stimulus))
    # The same log as one batch, in the three accepted shapes.
    mixed = [log[0], {"state": log[1].state, "stimulus": log[1].stimulus}] + [
        (o.state, o.stimulus) for o in log[2:]
    ]
    batch = client.observe_batch(b, mixed)
    assert batch == singles, "same seed and observations give the same steps"
    assert [s.tick for s in batch] == list(range(61))


def test_values_tables(client: Client) -> None:
    world = models.hallway()
    sid = client.create_session(world, seed=2).id
    step = client.observe(sid, 25)
    client.observe(sid, world.sample_next(25, step.action_index, random.Random(0)), [0.0, 0.0])
    default = client.values(sid)
    assert default.tick == 1
    assert default.v is not None and len(default.v) == 50
    assert default.policy is not None and set(default.policy) <= set(world.actions)
    assert default.q is None and default.r is None and default.xi is None
    everything = client.values(sid, "all")
    assert everything.q is not None and everything.r is not None and everything.xi is not None
    assert everything.q[0][0] is None, "state 0 has no left"
    assert everything.q[49][1] is None, "state 49 has no right"
    assert isinstance(everything.q[10][2], float)
    assert everything.xi[10][2] is not None and len(everything.xi[10][2]) == 2
    # V(s) is Q of the greedy action.
    for s in (0, 10, 25, 49):
        a = world.actions.index(everything.policy[s])  # type: ignore[index]
        assert everything.v[s] == pytest.approx(everything.q[s][a])  # type: ignore[index]
    some = client.values(sid, ["q", "r"])
    assert some.q == everything.q and some.r == everything.r and some.v is None


def test_history_names_actions_and_honours_limit(client: Client, server: object) -> None:
    world = models.hallway()
    sid = client.create_session(world, seed=8, history=5).id
    step = client.observe(sid, 25)
    rng = random.Random(1)
    state = 25
    for _ in range(8):
        state = world.sample_next(state, step.action_index, rng)
        step = client.observe(sid, state, world.stimulus(state))
    hist = client.history(sid)
    assert len(hist) == 5, "the session keeps `history` ticks"
    assert [h.tick for h in hist] == list(range(4, 9))
    assert all(h.action == world.actions[h.action_index] for h in hist)
    assert hist[-1].state == state and hist[-1].drive == step.drive
    assert [h.tick for h in client.history(sid, limit=2)] == [7, 8]
    # A client that never saw the session still names the actions.
    with Client(client.base_url) as fresh:
        assert fresh.history(sid, limit=1)[0].action == hist[-1].action


def test_list_pages_and_iterates_every_session(client: Client) -> None:
    ids = {client.create_session("hallway").id for _ in range(5)}
    listed = [s.id for s in client.iter_sessions(page_size=2)]
    assert ids <= set(listed)
    assert listed == sorted(listed), "sessions come in id order"
    assert len(listed) == len(set(listed)), "no session twice across pages"
    first = client.list_sessions(limit=2)
    assert len(first.sessions) == 2 and first.next == first.sessions[-1].id
    second = client.list_sessions(after=first.next, limit=2)
    assert second.sessions[0].id > first.sessions[-1].id
    summary = next(s for s in client.iter_sessions() if s.id in ids)
    assert summary.states == 50 and summary.update_mode == "lockstep" and summary.tick == 0
    assert summary.idle_ms is None, "no observation yet"
    client.observe(summary.id, 3)
    observed = next(s for s in client.iter_sessions() if s.id == summary.id)
    assert observed.idle_ms is not None and 0 <= observed.idle_ms < 60_000


def test_delete(client: Client) -> None:
    sid = client.create_session("hallway").id
    client.delete_session(sid)
    with pytest.raises(NotFound):
        client.get_session(sid)
    with pytest.raises(NotFound):
        client.delete_session(sid)
    assert sid not in {s.id for s in client.iter_sessions()}


def test_api_key_and_extra_headers_are_sent() -> None:
    seen: list[httpx.Request] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(204)

    with Client("http://mcapi.test", api_key="k-1", headers={"x-trace": "t"},
                transport=httpx.MockTransport(handler)) as c:
        c.delete_session("s0001.ABC/../x")
    (req,) = seen
    assert req.headers["authorization"] == "Bearer k-1"
    assert req.headers["x-trace"] == "t"
    # The id is one path segment, whatever it contains.
    assert req.url.raw_path == b"/v1/sessions/s0001.ABC%2F..%2Fx"
