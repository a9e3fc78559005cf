"""The high-rate loop: thousands of ticks over one Interact stream, with the
agent alternating between the hallway's two sources as in the paper."""

from __future__ import annotations

import random
import time

from mcapi_client import GrpcClient, models

TICKS = 4000


def test_thousands_of_ticks_alternate_between_the_sources(grpc_client: GrpcClient) -> None:
    world = models.hallway()
    rng = random.Random(2024)
    sid = grpc_client.create_session(world, seed=2024).id
    state = rng.randrange(world.states)
    visits = {10: 0, 40: 0}
    trips: list[int] = []  # the sequence of distinct sources reached
    dominant: list[int] = []
    started = time.perf_counter()
    with grpc_client.interact(sid) as stream:
        step = stream.step(state)
        for i in range(TICKS):
            state = world.sample_next(state, step.action_index, rng)
            step = stream.step(state, world.stimulus(state, noise_sd=2.0, rng=rng))
            assert step.tick == i + 1
            if state in visits:
                visits[state] += 1
                if not trips or trips[-1] != state:
                    trips.append(state)
            dominant.append(max((0, 1), key=lambda j: abs(step.drive[j])))
    elapsed = time.perf_counter() - started
    # The paper's behaviour: food, then rest, then food... many times over.
    assert len(trips) >= 20, f"only {len(trips)} legs between the sources: {trips}"
    assert min(visits.values()) >= 0.3 * max(visits.values()), visits
    switches = sum(1 for a, b in zip(dominant, dominant[1:]) if a != b)
    assert switches >= 20, "the dominant drive switches back and forth"
    info = grpc_client.get_session(sid)
    assert info.tick == TICKS and info.state == state
    # Not a benchmark, but the stream must not degenerate into seconds per tick.
    assert TICKS / elapsed > 100, f"{TICKS / elapsed:.0f} ticks/s"
