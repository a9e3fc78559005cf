#!/usr/bin/env python3
"""An MCA-PI agent in MO-Gymnasium's resource-gathering, fetching gold and gems in turn.

``models.from_mo_gymnasium`` turns the environment into a session's model:
100 states (row, column, carrying gold, carrying a gem), the four moves, and
one stimulus per objective that can be received: gold and gem, delivered on
coming home with them. The third objective, -1 when an enemy kills the
agent, is a penalty, not an amount received, and is left out of the
stimuli (the agent still loses what it carried and restarts at home). The
server never sees the dynamics: it learns them from the observations
(``transitions: "learn"``), explores until the pairs are known, then its
drive sends it for whichever resource it received least recently.

This prints how much of the model is known as it goes, then the totals per
objective (the raw returns, the enemy penalty included) and the balance.

    pip install './clients/python[mo]'
    cargo run --release -- serve          # in another terminal
    python examples/mo_resource_gathering.py --steps 5000
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Sequence

from mcapi_client import Client, models
from mcapi_client.errors import McapiError, one_line


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the agent in resource-gathering over REST; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8080", help="REST address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--steps", type=int, default=5000, help="ticks to run")
    parser.add_argument("--seed", type=int, default=1, help="seed of the environment and the agent")
    parser.add_argument("--scale", type=float, default=6.0, help="stimulus per unit of reward")
    parser.add_argument("--known-after", type=int, default=1, help="visits before a pair is known (m)")
    parser.add_argument("--report-every", type=int, default=1000, help="ticks between reports")
    parser.add_argument("--keep", action="store_true", help="keep the session afterwards")
    args = parser.parse_args(argv)

    try:
        import mo_gymnasium
    except ImportError:
        print("this example needs MO-Gymnasium: pip install './clients/python[mo]'")
        return 2

    # MO-Gymnasium builds its reward spaces from float64 bounds: gymnasium warns.
    warnings.filterwarnings("ignore", message=".*precision lowered", category=UserWarning)
    world = models.from_mo_gymnasium(
        mo_gymnasium.make("resource-gathering-v0"),  # type: ignore[attr-defined]
        scale=args.scale,
        known_after=args.known_after,
    )
    dropped = ", ".join(world.objectives[i] for i in world.dropped) or "none"
    print(
        f"resource-gathering: {world.states} states, actions {', '.join(world.actions)}; "
        f"stimuli {', '.join(world.stimuli)}; penalties left out: {dropped}"
    )
    with Client(args.url, api_key=args.api_key) as mc:
        session = mc.create_session(world, seed=args.seed)
        step = mc.observe(session.id, world.reset(seed=args.seed))
        for tick in range(1, args.steps + 1):
            s = world.step(step.action_index)
            step = mc.observe(session.id, s.state, s.stimulus)
            if tick % args.report_every == 0:
                known = mc.values(session.id).known_fraction or 0.0
                amounts = zip(world.stimuli, world.stimulus_totals)
                got = ", ".join(f"{n} {x / args.scale:.0f}" for n, x in amounts)
                print(f"tick {tick:5}: {known:.3f} of the model known; {world.episodes} episodes; {got}")
        totals = ", ".join(f"{n} {x:+.0f}" for n, x in zip(world.objectives, world.returns))
        kept = [world.returns[i] for i in world.kept]
        balance = min(kept) / max(1.0, max(kept))
        print(
            f"{args.steps} ticks, {world.episodes} episodes: per objective {totals}; "
            f"balance (fewer/more) {balance:.2f}"
        )
        if not args.keep:
            mc.delete_session(session.id)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
