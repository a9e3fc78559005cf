"""Session groups under asyncio (AsyncGrpcClient, AsyncVectorAgents) against
a live server: pipelined steps, masks, refusals, and the same bits as the
blocking stream. The tests run on the shared loop of conftest.run_async."""

from __future__ import annotations

import random

import numpy as np
import pytest
from conftest import Server, async_test

from mcapi_client import AsyncGrpcClient, GrpcClient, InvalidObservation, NotFound, models
from mcapi_client.groups import ADVISED, AsyncVectorAgents, member_seed

N = 6
EVENS, ODDS = [0, 2, 4], [1, 3, 5]


def _walk(world: models.Model, states: np.ndarray, actions: np.ndarray, rng: random.Random) -> np.ndarray:
    return np.array([world.sample_next(int(s), int(a), rng) for s, a in zip(states, actions)])


@async_test
async def test_pipelined_masked_steps_answer_in_order(server: Server) -> None:
    world = models.hallway()
    rng = random.Random(3)
    async with AsyncGrpcClient(server.grpc_target) as mc:
        agents = await mc.create_group(world, N, seed=11, update_mode="lockstep")
        assert isinstance(agents, AsyncVectorAgents)
        async with agents:
            info = agents.info
            assert (info.size, info.seed, info.stimuli, len(info.members)) == (N, 11, 2, N)
            assert await mc.get_group(info.id) == info
            states = np.full(N, 25)
            first = await agents.step(states)
            assert first.seq == 0 and first.actions.shape == (N,) and first.ticks.tolist() == [0] * N
            actions = first.actions.copy()
            # Two batches in flight: the even members and the odd ones.
            for t in range(1, 21):
                states = _walk(world, states, actions, rng)
                stimuli = np.array([world.stimulus(int(s)) for s in states])
                seq_a = agents.send(states[EVENS], stimuli[EVENS], mask=EVENS)
                seq_b = agents.send(states[ODDS], stimuli[ODDS], mask=ODDS)
                assert agents.pending == 2
                a, b = await agents.recv(), await agents.recv()
                assert (a.seq, b.seq) == (seq_a, seq_b) == (2 * t - 1, 2 * t)
                assert not a.errors and not b.errors
                assert a.ticks.tolist() == b.ticks.tolist() == [t] * 3
                actions[EVENS], actions[ODDS] = a.actions, b.actions
            # A member's own refusal: the others step.
            states = _walk(world, states, actions, rng)
            taken = np.full(N, ADVISED, dtype=np.uint32)
            taken[4] = 7  # the hallway has 3 actions
            step = await agents.step(states, np.zeros((N, 2)), action_taken=taken)
            assert [(e.index, e.code) for e in step.errors] == [(4, "unknown_action")]
            assert step.actions[4] == ADVISED and step.drives[4].tolist() == [0.0, 0.0]
            assert step.ticks.tolist() == [21, 21, 21, 21, 0, 21]
            # A column that does not fit: refused before sending; the stream goes on.
            with pytest.raises(ValueError, match="`stimuli` must have shape"):
                agents.send(states, np.zeros((N, 3)))
            assert agents.pending == 0
            # A step the server refuses whole ends the stream.
            bad = states.copy()
            bad[0] = 50
            with pytest.raises(InvalidObservation) as err:
                await agents.step(bad, np.zeros((N, 2)))
            assert err.value.code == "unknown_state"
        # The group outlives its stream: a new one on it goes on.
        again = await mc.vector_agents(info.id)
        async with again:
            step = await again.step(states, np.zeros((N, 2)), mask=list(range(N)))
            assert step.ticks.tolist() == [22, 22, 22, 22, 21, 22]
        await mc.delete_group(info.id)
        with pytest.raises(NotFound):
            await mc.get_group(info.id)
        with pytest.raises(NotFound):
            await mc.get_session(info.members[0])


@async_test
async def test_the_async_stream_gives_the_blocking_streams_bits(server: Server) -> None:
    """One trace fed to a group through AsyncVectorAgents and to a group of
    the same seed through the blocking VectorAgents: the same columns; and
    member 2 alone, as a session of its derived seed, the same drive."""
    world = models.hallway()
    rng = random.Random(8)
    n = 4
    states = np.array([25, 10, 40, 3])
    trace = [(states, None)]
    # The trace: a random walk, independent of the agents' advice.
    for _ in range(30):
        states = np.array([world.sample_next(int(s), rng.randrange(3), rng) for s in states])
        trace.append((states, np.array([world.stimulus(int(s), noise_sd=1.0, rng=rng) for s in states])))
    taken = [None] + [np.array([rng.randrange(3) for _ in range(n)]) for _ in trace[1:]]
    async with AsyncGrpcClient(server.grpc_target) as mc:
        async with await mc.create_group(world, n, seed=99, update_mode="lockstep") as agents:
            async_steps = []
            for (s, xi), a in zip(trace, taken):
                async_steps.append(await agents.step(s, xi, action_taken=a))
        await mc.delete_group(agents.info.id)
    with GrpcClient(server.grpc_target) as sync:
        with sync.create_group(world, n, seed=99, update_mode="lockstep") as twin:
            sync_steps = [twin.step(s, xi, action_taken=a) for (s, xi), a in zip(trace, taken)]
        for x, y in zip(async_steps, sync_steps):
            assert x.actions.tolist() == y.actions.tolist()
            assert x.drives.tobytes() == y.drives.tobytes() and x.rewards.tobytes() == y.rewards.tobytes()
            assert x.policy_versions.tolist() == y.policy_versions.tolist()
        assert async_steps[-1].ticks.tolist() == [30] * n
        alone = sync.create_session(world, seed=member_seed(99, 2), update_mode="lockstep").id
        with sync.interact(alone) as stream:
            for (s, xi), a in zip(trace, taken):
                last = stream.step(int(s[2]), None if xi is None else xi[2], None if a is None else int(a[2]))
        assert last.drive == async_steps[-1].drives[2].tolist()
        assert last.reward == async_steps[-1].rewards[2]
        sync.delete_session(alone)
        sync.delete_group(twin.info.id)
