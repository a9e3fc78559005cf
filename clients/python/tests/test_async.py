"""The asyncio REST client: every method, concurrency, and parity with the blocking one."""

from __future__ import annotations

import asyncio
import random

import pytest

from mcapi_client import AsyncClient, Client, InvalidObservation, NotFound, models

pytestmark = pytest.mark.anyio


async def test_every_method(server: object) -> None:
    world = models.hallway()
    async with AsyncClient(server.http_url) as mc:  # type: ignore[attr-defined]
        assert await mc.ready()
        info = await mc.create_session(world, seed=21, history=10)
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
        with pytest.raises(NotFound):
            await mc.get_session(sid)
        with pytest.raises(InvalidObservation) as e:
            await mc.observe((await mc.create_session("hallway")).id, 99)
        assert e.value.code == "unknown_state" and e.value.status == 400


async def test_concurrent_sessions_match_sequential_runs(server: object) -> None:
    """Eight sessions driven at once over one AsyncClient give the same steps
    as the same runs one after another over the blocking client."""
    world = models.hallway()

    Walk = list[tuple[int, "list[float] | None", "str | None"]]

    def plan(seed: int) -> Walk:
        # A fixed random walk (not the agent's choices), so the runs are comparable.
        rng = random.Random(seed)
        state = rng.randrange(50)
        out: Walk = [(state, None, None)]
        for _ in range(40):
            action = rng.choice(world.available_actions(state))
            state = world.sample_next(state, action, rng)
            out.append((state, world.stimulus(state), world.actions[action]))
        return out

    async def run(mc: AsyncClient, seed: int) -> list[object]:
        sid = (await mc.create_session(world, seed=seed)).id
        return [await mc.observe(sid, s, xi, action_taken=a) for s, xi, a in plan(seed)]

    async with AsyncClient(server.http_url) as mc:  # type: ignore[attr-defined]
        together = await asyncio.gather(*(run(mc, seed) for seed in range(8)))
    with Client(server.http_url) as blocking:  # type: ignore[attr-defined]
        for seed in range(8):
            sid = blocking.create_session(world, seed=seed).id
            alone = [blocking.observe(sid, s, xi, action_taken=a) for s, xi, a in plan(seed)]
            assert together[seed] == alone
