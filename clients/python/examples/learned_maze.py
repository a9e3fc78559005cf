#!/usr/bin/env python3
"""The paper's three-room maze with a transition model the server never sees.

The maze (three rooms joined by doorways, sources a, b and c) is simulated
here and posted with ``models.learned``: the server gets the map's states,
actions and stimuli but not where the moves lead, and the agent learns that
from the observations (docs/algorithm.md section 8). Pairs it has tried
fewer than ``known_after`` times are optimistic, so it explores first, then
balances its drives. This prints how much of the model is known as it
goes, the tick each source was first reached, and the visits per source.

    cargo run --release -- serve          # in another terminal
    python examples/learned_maze.py --steps 5000
"""

from __future__ import annotations

import argparse
import os
import random
import sys
from collections.abc import Sequence

from mcapi_client import Client, models
from mcapi_client.errors import McapiError, one_line

THREE_ROOM = """\
##########################
#.......#........#.......#
#.......#........#....c..#
#................#.......#
#.......#........#.......#
#.......#........#.......#
#.......#........#.......#
#.......#................#
#.a.....#........#.......#
#.......#....b...#.......#
##########################
"""


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the learned maze over REST; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--url", default="http://127.0.0.1:8080", help="REST address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--steps", type=int, default=5000, help="ticks to run")
    parser.add_argument("--seed", type=int, default=1, help="seed of the world and the agent")
    parser.add_argument("--known-after", type=int, default=3, help="visits before a pair is known (m)")
    parser.add_argument("--report-every", type=int, default=500, help="ticks between reports")
    parser.add_argument("--keep", action="store_true", help="keep the session afterwards")
    args = parser.parse_args(argv)

    maze = models.grid(THREE_ROOM, {"a": 0, "b": 1, "c": 2})
    world = models.learned(maze, known_after=args.known_after)
    sources = {name: set(maze.source_states(name)) for name in maze.stimuli}
    rng = random.Random(args.seed)
    with Client(args.url, api_key=args.api_key) as mc:
        session = mc.create_session(world, seed=args.seed)
        learned = session.model.learned
        if learned is None:
            print("the server did not take the model as learned", file=sys.stderr)
            return 1
        print(
            f"session {session.id}: {session.model.states} states, {session.model.pairs} pairs, "
            f"m = {learned.known_after}, {learned.optimism} optimism, "
            f"at most {learned.max_transitions} stored transitions"
        )
        state = rng.randrange(session.model.states)
        step = mc.observe(session.id, state)
        found: dict[str, int] = {}
        visits = {name: 0 for name in maze.stimuli}
        for tick in range(1, args.steps + 1):
            state = maze.sample_next(state, step.action_index, rng)
            step = mc.observe(session.id, state, maze.stimulus(state))
            for name, states in sources.items():
                if state in states:
                    visits[name] += 1
                    if name not in found:
                        found[name] = tick
                        print(f"tick {tick:5}: first reached source {name}")
            if tick % args.report_every == 0:
                known = mc.values(session.id).known_fraction or 0.0
                print(f"tick {tick:5}: {known:.3f} of the model known")
        print("visits: " + ", ".join(f"{name} {n}" for name, n in visits.items()))
        if not args.keep:
            mc.delete_session(session.id)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
