"""Session groups over gRPC: VectorAgents against a live server."""

from __future__ import annotations

import random

import numpy as np
import pytest

from mcapi_client import GrpcClient, McapiError, models
from mcapi_client.groups import ADVISED, member_seed


def _walk(world: models.Model, states: list[int], actions: np.ndarray, rng: random.Random) -> list[int]:
    return [world.sample_next(s, int(a), rng) for s, a in zip(states, actions)]


def test_member_seed_is_the_servers_formula() -> None:
    assert member_seed(1234567, 0) == 6457827717110365317


def test_a_group_steps_as_its_members_would_alone(grpc_client: GrpcClient) -> None:
    world = models.hallway()
    n = 4
    rng = random.Random(11)
    with grpc_client.create_group(world, n, seed=7, update_mode="lockstep") as agents:
        info = agents.info
        assert info.size == n and len(info.members) == n and info.stimuli == 2
        states = [25, 10, 40, 3]
        trace: list[tuple[list[int], np.ndarray | None]] = [(list(states), None)]
        step = agents.step(states)
        assert step.actions.shape == (n,) and step.drives.shape == (n, 2)
        for _ in range(60):
            states = _walk(world, states, step.actions, rng)
            stimuli = np.array([world.stimulus(s) for s in states])
            trace.append((list(states), stimuli))
            step = agents.step(states, stimuli)
            assert not step.errors
        group_drives = step.drives.copy()
        group_ticks = step.ticks.copy()
    assert (group_ticks == 60).all()

    # Member i, replayed alone with its derived seed, gives the same bits.
    for i in range(n):
        sid = grpc_client.create_session(world, seed=member_seed(info.seed, i), update_mode="lockstep").id
        with grpc_client.interact(sid) as stream:
            alone = stream.step(trace[0][0][i])
            for states_t, stimuli_t in trace[1:]:
                assert stimuli_t is not None
                alone = stream.step(states_t[i], stimuli_t[i])
        assert alone.drive == group_drives[i].tolist()
        grpc_client.delete_session(sid)
    grpc_client.delete_group(info.id)
    with pytest.raises(McapiError):
        grpc_client.get_session(info.members[0])


def test_pipelined_steps_answer_in_order_and_refusals_are_per_member(grpc_client: GrpcClient) -> None:
    world = models.hallway()
    with grpc_client.create_group(world, 3, seed=3) as agents:
        seqs = [agents.send([25, 25, 25])]
        seqs.append(agents.send([26, 24, 25], np.zeros((3, 2)), action_taken=[ADVISED, ADVISED, ADVISED]))
        # Member 1 names an action the model does not have: its own refusal.
        seqs.append(agents.send([27, 23, 25], np.zeros((3, 2)), action_taken=[ADVISED, 99, ADVISED]))
        assert agents.pending == 3
        replies = [agents.recv() for _ in seqs]
        assert [r.seq for r in replies] == seqs == [0, 1, 2]
        last = replies[-1]
        assert [e.index for e in last.errors] == [1]
        assert last.errors[0].code == "unknown_action"
        assert last.actions[1] == ADVISED
        assert last.drives[1].tolist() == [0.0, 0.0] and last.rewards[1] == 0.0
        # The others went on.
        assert last.ticks[0] == 2 and last.ticks[2] == 2
        # A mask steps some members only.
        masked = agents.step([28], np.zeros((1, 2)), mask=[0])
        assert masked.actions.shape == (1,) and masked.ticks[0] == 3
    grpc_client.delete_group(agents.info.id)


def test_columns_that_do_not_fit_are_refused_before_sending(grpc_client: GrpcClient) -> None:
    with grpc_client.create_group(models.hallway(), 2, seed=5) as agents:
        agents.step([25, 25])
        bad = [
            (([25, 25, 25], np.zeros((3, 2))), {}, "`states` has 3 entries; 2 expected"),
            (([25, 25], np.zeros((2, 3))), {}, "`stimuli` must have shape (2, 2)"),
            (([25, -1], np.zeros((2, 2))), {}, "`states` holds -1"),
            (([25.0, 26.0], np.zeros((2, 2))), {}, "`states` must hold integers"),
            (([25], np.zeros((1, 2))), {"mask": [1, 0]}, "`mask` must be strictly increasing"),
            (([25], np.zeros((1, 2))), {"mask": [2]}, "`mask` names member 2; the group has 2"),
            (([25, 25], np.zeros((2, 2))), {"action_taken": [0]}, "`action_taken` has 1 entries"),
            (([25, 25],), {"observations": np.zeros((2, 1))}, "pass `states`, not `observations`"),
        ]
        for args, kw, message in bad:
            with pytest.raises(ValueError) as err:
                agents.step(*args, **kw)
            assert message in str(err.value)
        assert agents.pending == 0
        # Nothing was sent: the stream goes on at the next seq.
        ok = agents.step([26, 24], np.zeros((2, 2)))
        assert ok.seq == 1 and ok.ticks.tolist() == [1, 1]


def test_a_step_the_server_refuses_whole_ends_the_stream(grpc_client: GrpcClient) -> None:
    with grpc_client.create_group(models.hallway(), 2, seed=5) as agents:
        agents.step([25, 25])
        with pytest.raises(McapiError) as err:
            agents.step([25, 50], np.zeros((2, 2)))  # the hallway has 50 states
        assert (err.value.code, err.value.grpc_code) == ("unknown_state", "INVALID_ARGUMENT")
    # Nothing of it was applied.
    ticks = [grpc_client.get_session(m).tick for m in agents.info.members]
    assert ticks == [0, 0]
    grpc_client.delete_group(agents.info.id)
