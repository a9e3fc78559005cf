"""Session groups over REST (Client, AsyncClient, RestVectorAgents) against a
live server: the calls, refusals per member and whole, and the same columns
as over gRPC."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from conftest import Blocking, Server, run_async

from mcapi_client import AsyncClient, BadRequest, Client, GrpcClient, InvalidObservation, NotFound, models
from mcapi_client.groups import ADVISED, AsyncRestVectorAgents, GroupStep, RestVectorAgents, member_seed


def test_create_step_get_delete(client: Client) -> None:
    world = models.hallway()
    with client.create_group(world, 3, seed=7, update_mode="lockstep") as agents:
        assert isinstance(agents, RestVectorAgents)
        info = agents.info
        assert (info.size, info.seed, info.update_mode, info.stimuli, info.observation_dim) == (
            3, 7, "lockstep", 2, 0,
        )
        assert client.get_group(info.id) == info
        seeds = [client.get_session(m).agent.seed for m in info.members]
        assert seeds == [member_seed(7, i) for i in range(3)]
        first = agents.step([25, 25, 25])
        assert first.seq == 0 and first.actions.dtype == np.uint32 and first.drives.shape == (3, 2)
        assert first.ticks.tolist() == [0, 0, 0] and not first.errors
        # Member 1 names an action the model does not have: refused alone.
        step = agents.step([26, 24, 25], np.zeros((3, 2)), action_taken=[None, 99, ADVISED])
        assert step.seq == 1
        assert [(e.index, e.code) for e in step.errors] == [(1, "unknown_action")]
        assert "out of range" in step.errors[0].message
        assert step.actions[1] == ADVISED and step.drives[1].tolist() == [0.0, 0.0]
        assert step.rewards[1] == 0.0 and step.policy_versions[1] == 0 and step.ticks[1] == 0
        assert step.ticks.tolist() == [1, 0, 1] and step.actions[0] < 3 and step.actions[2] < 3
        # step_group by id, a mask: member 2 only.
        masked = client.step_group(info.id, [27], [[1.0, 0.0]], mask=[2])
        assert masked.ticks.tolist() == [2] and masked.drives.shape == (1, 2)
        assert client.get_session(info.members[2]).tick == 2
    client.delete_group(info.id)
    with pytest.raises(NotFound):
        client.get_group(info.id)
    with pytest.raises(NotFound):
        client.get_session(info.members[0])


def test_columns_are_checked_before_sending_and_the_server_refuses_the_rest(
    client: Client, server: Server
) -> None:
    with client.create_group(models.hallway(), 2, seed=5) as agents:
        gid = agents.info.id
        agents.step([25, 25])
        with pytest.raises(ValueError, match="`states` has 3 entries; 2 expected"):
            agents.step([25, 25, 25], np.zeros((3, 2)))
        with pytest.raises(ValueError, match=r"`stimuli` must have shape \(2, 2\)"):
            client.step_group(gid, [25, 25], np.zeros((2, 1)))
        # A client that has not seen the group reads its shape first.
        with Client(server.http_url) as fresh, pytest.raises(ValueError, match="`mask` names member 5"):
            fresh.step_group(gid, [25], np.zeros((1, 2)), mask=[5])
        # NaN cannot travel as JSON: refused with the server's code.
        with pytest.raises(BadRequest) as nan:
            agents.step([25, 25], [[0.0, float("nan")], [0.0, 0.0]])
        assert nan.value.code == "non_finite_number"
        # What only the server knows: a state beyond the model's.
        with pytest.raises(InvalidObservation) as unknown:
            agents.step([25, 50], np.zeros((2, 2)))
        assert (unknown.value.code, unknown.value.status) == ("unknown_state", 400)
        # The server's own length check, the body sent as is.
        body = {"states": [25, 25, 25], "stimuli": [[0, 0]] * 3}
        raw = httpx.post(f"{server.http_url}/v1/groups/{gid}/steps", json=body)
        assert raw.status_code == 400 and raw.json()["code"] == "column_length"
        assert [client.get_session(m).tick for m in agents.info.members] == [0, 0]
    client.delete_group(gid)
    with pytest.raises(NotFound):
        client.step_group(gid, [25, 25], np.zeros((2, 2)))


def _run(agents: object, trace: list[tuple[list[int], np.ndarray | None]]) -> list[GroupStep]:
    return [agents.step(s, xi) for s, xi in trace]  # type: ignore[attr-defined]


def test_rest_and_grpc_give_the_same_columns(server: Server) -> None:
    world = models.hallway()
    rng = np.random.default_rng(4)
    states = [25, 12, 38, 0]
    trace: list[tuple[list[int], np.ndarray | None]] = [(states, None)]
    for _ in range(20):
        states = [int(np.clip(s + rng.integers(-1, 2), 0, 49)) for s in states]
        trace.append((states, np.array([world.stimulus(s) for s in states]) + rng.random((4, 2))))
    with Client(server.http_url) as rest, GrpcClient(server.grpc_target) as grpc:
        with rest.create_group(world, 4, seed=21, update_mode="lockstep") as a:
            over_rest = _run(a, trace)
        with grpc.create_group(world, 4, seed=21, update_mode="lockstep") as b:
            over_grpc = _run(b, trace)
        for x, y in zip(over_rest, over_grpc):
            assert x.actions.tolist() == y.actions.tolist()
            assert x.drives.tolist() == y.drives.tolist() and x.rewards.tolist() == y.rewards.tolist()
            assert x.ticks.tolist() == y.ticks.tolist()
        assert over_rest[-1].ticks.tolist() == [20] * 4
        # The async REST client: the same calls, awaited.
        mc = Blocking(lambda: AsyncClient(server.http_url))
        try:
            agents = mc.create_group(world, 4, seed=21, update_mode="lockstep")
            steps = [mc.step_group(agents.info.id, s, xi) for s, xi in trace[:10]]
            again = mc.vector_agents(agents.info.id)
            assert isinstance(again, AsyncRestVectorAgents)
            steps += [run_async(again.step(s, xi)) for s, xi in trace[10:]]
            assert steps[-1].drives.tolist() == over_rest[-1].drives.tolist()
            assert [s.seq for s in steps[9:12]] == [0, 0, 1]
            assert mc.get_group(agents.info.id) == agents.info
            mc.delete_group(agents.info.id)
            rest.delete_group(a.info.id)
            grpc.delete_group(b.info.id)
        finally:
            mc.close()
