"""The asyncio gRPC client (grpc.aio) against the real server: every method,
the Interact and Watch streams, the error mapping, and the same answers as
the blocking client. The tests run on the shared loop of conftest.run_async."""

from __future__ import annotations

import asyncio
import random
import socket

import pytest
from conftest import Server, async_test

from mcapi_client import (
    AsyncGrpcClient,
    GrpcClient,
    InvalidObservation,
    NotFound,
    Observation,
    Timeout,
    TransportError,
    models,
)

UNKNOWN_ID = "s0000.01AAAAAAAAAAAAAAAAAAAAAAAA"


@async_test
async def test_every_method(server: Server) -> None:
    world = models.hallway()
    async with AsyncGrpcClient(server.grpc_target) as mc:
        assert await mc.ready(timeout=5)
        info = await mc.create_session(world, seed=21, history=10, update_mode="lockstep")
        sid = info.id
        assert info.model.stimuli == ["food", "rest"] and info.agent.seed == 21
        step = await mc.observe(sid, 12)
        state = world.sample_next(12, step.action_index, random.Random(0))
        step = await mc.observe(sid, state, world.stimulus(state), action_taken=step.action)
        assert step.tick == 1
        steps = await mc.observe_batch(sid, [(state, [0.0, 0.0]), {"state": state, "stimulus": [0.0, 0.0]}])
        assert [s.tick for s in steps] == [2, 3]
        got = await mc.get_session(sid)
        assert got.tick == 3 and got.state == state
        values = await mc.values(sid, ["v", "q"])
        assert values.v is not None and values.q is not None and values.policy is None
        hist = await mc.history(sid, limit=2)
        assert [h.tick for h in hist] == [2, 3] and hist[0].action in world.actions
        page = await mc.list_sessions(limit=1)
        assert len(page.sessions) == 1
        assert sid in [s.id async for s in mc.iter_sessions(page_size=3)]
        await mc.delete_session(sid)
        with pytest.raises(NotFound) as e:
            await mc.get_session(sid)
        assert (e.value.code, e.value.status, e.value.grpc_code) == ("not_found", 404, "NOT_FOUND")
        with pytest.raises(InvalidObservation) as bad:
            await mc.observe((await mc.create_session("hallway")).id, 99)
        assert (bad.value.code, bad.value.grpc_code) == ("unknown_state", "INVALID_ARGUMENT")
    async with AsyncGrpcClient("127.0.0.1:9") as dead:
        assert not await dead.ready(timeout=0.3)


@async_test
async def test_same_answers_as_the_blocking_client(server: Server) -> None:
    """Twin sessions, one per client, fed the same observations, agree on every
    step, value table and history entry; a fresh async client (no cached
    shapes) reads the same tables."""
    world = models.hallway()
    rng = random.Random(11)
    with GrpcClient(server.grpc_target) as blocking:
        async with AsyncGrpcClient(server.grpc_target) as mc:
            a_id = blocking.create_session(world, seed=4, history=100).id
            b_id = (await mc.create_session(world, seed=4, history=100)).id
            state = 30
            a, b = blocking.observe(a_id, state), await mc.observe(b_id, state)
            assert a == b
            for i in range(60):
                state = world.sample_next(state, a.action_index, rng)
                xi = world.stimulus(state, noise_sd=2.0, rng=rng)
                taken = None if i % 7 else a.action
                a = blocking.observe(a_id, state, xi, action_taken=taken)
                b = await mc.observe(b_id, state, xi, action_taken=taken)
                assert a == b
            assert blocking.values(a_id, "all") == await mc.values(b_id, "all")
            assert blocking.history(a_id) == await mc.history(b_id)
        async with AsyncGrpcClient(server.grpc_target) as fresh:
            assert (await fresh.values(b_id, "xi")).xi == blocking.values(a_id, "xi").xi
            assert (await fresh.history(b_id, limit=3)) == blocking.history(a_id, limit=3)


@async_test
async def test_interact_step_loop_and_pipelined_replay(server: Server) -> None:
    world = models.hallway()
    rng = random.Random(5)
    log = [Observation(rng.randrange(50))]
    for _ in range(299):
        prev = log[-1].state
        action = rng.choice(world.available_actions(prev))
        nxt = world.sample_next(prev, action, rng)
        log.append(Observation(nxt, world.stimulus(nxt, noise_sd=2.0, rng=rng), world.actions[action]))
    async with AsyncGrpcClient(server.grpc_target) as mc:
        looped_id = (await mc.create_session(world, seed=44)).id
        piped_id = (await mc.create_session(world, seed=44)).id
        batch_id = (await mc.create_session(world, seed=44)).id
        async with mc.interact(looped_id) as stream:
            looped = [await stream.step(o.state, o.stimulus, o.action_taken) for o in log]
            assert stream.pending == 0
        async with mc.interact(piped_id) as stream:
            for obs in log:  # all queued before any reply is read
                stream.send(obs.state, obs.stimulus, obs.action_taken)
            assert stream.pending == 300
            piped = [s async for s in stream]
            assert stream.pending == 0 and [s async for s in stream] == []
        batch = await mc.observe_batch(batch_id, log)
        assert looped == piped == batch
        assert [s.tick for s in looped] == list(range(300))
        assert (await mc.get_session(looped_id)).tick == 299


@async_test
async def test_interact_errors_end_the_stream(server: Server) -> None:
    async with AsyncGrpcClient(server.grpc_target) as mc:
        sid = (await mc.create_session("hallway")).id
        async with mc.interact(sid) as stream:
            await stream.step(3)
            await stream.step(4, [0.0, 0.0])
            with pytest.raises(InvalidObservation) as e:
                await stream.step(5, [0.0])
            assert (e.value.code, e.value.grpc_code) == ("stimulus_length", "INVALID_ARGUMENT")
            with pytest.raises(InvalidObservation):
                await stream.recv()  # the stream has ended: its error again
        assert (await mc.get_session(sid)).tick == 1, "the observations before the error stay applied"
        async with mc.interact(UNKNOWN_ID) as stream:
            with pytest.raises(NotFound) as nf:
                await stream.step(0)
        assert nf.value.status == 404
        stream = mc.interact(sid)
        stream.close()
        with pytest.raises(RuntimeError):
            stream.send(1)


@async_test
async def test_interact_batch_matches_interact(server: Server) -> None:
    world = models.hallway()
    async with AsyncGrpcClient(server.grpc_target) as mc:
        batched = [(await mc.create_session(world, seed=s)).id for s in (1, 2)]
        single = [(await mc.create_session(world, seed=s)).id for s in (1, 2)]
        log = [Observation(25)] + [Observation(s, world.stimulus(s)) for s in range(24, 0, -1)]
        async with mc.interact_batch() as stream:
            steps = [await stream.step([(b, o) for b in batched]) for o in log]
            errors = await stream.step([(batched[0], (1, [0.0])), (UNKNOWN_ID, (1,))])
        assert [type(e) for e in errors] == [InvalidObservation, NotFound]
        for k, sid in enumerate(single):
            async with mc.interact(sid) as one:
                assert [await one.step(o.state, o.stimulus) for o in log] == [s[k] for s in steps]
        stream.close()
        with pytest.raises(RuntimeError):
            await stream.step([])


@async_test
async def test_watch_snapshots_until_deleted_or_cancelled(server: Server) -> None:
    async with AsyncGrpcClient(server.grpc_target) as mc:
        sid = (await mc.create_session("hallway", seed=1)).id
        async with mc.watch(sid, interval=0.02) as watch:
            first = await watch.__anext__()
            assert first.id == sid and first.tick == 0 and first.state is None
            await mc.observe(sid, 7)
            await mc.observe(sid, 8, [0.0, 0.0])
            last = first
            async for snap in watch:
                last = snap
                if snap.tick == 1:
                    break
            assert (last.tick, last.state) == (1, 8)

        # Deleting the session ends the iteration (not an error).
        seen: list[int] = []

        async def read() -> None:
            async with mc.watch(sid, interval=0.02) as w:
                async for snap in w:
                    seen.append(snap.tick)

        reader = asyncio.create_task(read())
        while not seen:
            await asyncio.sleep(0.01)
        await mc.delete_session(sid)
        await asyncio.wait_for(reader, 10)

        other = (await mc.create_session("hallway")).id
        watch = mc.watch(other, interval=10)
        assert (await watch.__anext__()).id == other
        watch.cancel()
        assert [s async for s in watch] == []
        with pytest.raises(NotFound):
            await mc.watch(UNKNOWN_ID).__anext__()
        with pytest.raises(ValueError):
            mc.watch(other, interval=0.001)


@async_test
async def test_concurrent_sessions_over_one_channel(server: Server) -> None:
    """Eight sessions driven at once over one channel give the steps of the
    same runs one after another over the blocking client."""
    world = models.hallway()

    def plan(seed: int) -> list[Observation]:
        rng = random.Random(seed)
        out = [Observation(rng.randrange(50))]
        for _ in range(30):
            action = rng.choice(world.available_actions(out[-1].state))
            state = world.sample_next(out[-1].state, action, rng)
            out.append(Observation(state, world.stimulus(state), world.actions[action]))
        return out

    async def run(mc: AsyncGrpcClient, seed: int) -> list[object]:
        sid = (await mc.create_session(world, seed=seed)).id
        return [await mc.observe(sid, o.state, o.stimulus, o.action_taken) for o in plan(seed)]

    async with AsyncGrpcClient(server.grpc_target) as mc:
        together = await asyncio.gather(*(run(mc, seed) for seed in range(8)))
    with GrpcClient(server.grpc_target) as blocking:
        for seed in range(8):
            sid = blocking.create_session(world, seed=seed).id
            assert together[seed] == blocking.observe_batch(sid, plan(seed))


@async_test
async def test_unreachable_server_and_timeouts() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    async with AsyncGrpcClient(f"127.0.0.1:{port}", timeout=2) as mc:
        with pytest.raises(TransportError) as e:
            await mc.get_session("x")
        assert (e.value.code, e.value.status, e.value.grpc_code) == ("transport_error", None, "UNAVAILABLE")
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        async with AsyncGrpcClient(f"127.0.0.1:{silent.getsockname()[1]}", timeout=0.3) as mc:
            with pytest.raises(Timeout) as t:
                await mc.get_session("x")
        assert (t.value.code, t.value.grpc_code) == ("timeout", "DEADLINE_EXCEEDED")
