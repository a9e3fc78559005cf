#!/usr/bin/env python3
"""The paper's hallway over the gRPC Interact stream, at full speed.

The same world as hallway_rest.py (50 states, food at 10, rest at 40,
stimulus 6 + N(0, 2)), but every tick travels over one bidirectional stream:
no call set-up per observation. Prints the ticks per second as it goes and
each switch of the dominant drive.

    cargo run --release -- serve          # in another terminal
    python examples/hallway_stream.py --steps 20000
"""

from __future__ import annotations

import argparse
import os
import random
import sys
import time
from collections.abc import Sequence

from mcapi_client import GrpcClient, models
from mcapi_client.errors import McapiError, one_line

SWITCH_RATIO = 1.5  # hysteresis of a drive switch, as in hallway_rest.py


def dominant(drive: Sequence[float], current: int | None = None) -> int:
    """The dominant drive component, with hysteresis around ``current``."""
    best = max(range(len(drive)), key=lambda j: abs(drive[j]))
    if current is None or best == current:
        return best
    return best if abs(drive[best]) >= SWITCH_RATIO * abs(drive[current]) else current


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the hallway over the Interact stream; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--target", default="127.0.0.1:50051", help="gRPC address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--steps", type=int, default=20000, help="ticks to run")
    parser.add_argument("--seed", type=int, default=1, help="seed of the world and the agent")
    parser.add_argument("--noise-sd", type=float, default=2.0, help="sd of the source noise")
    parser.add_argument(
        "--update-mode",
        choices=["lockstep", "async"],
        default="lockstep",
        help="lockstep: one policy update per tick; async: the server plans behind the stream",
    )
    parser.add_argument("--report-every", type=float, default=1.0, help="seconds between rate lines")
    parser.add_argument("--keep", action="store_true", help="keep the session afterwards")
    args = parser.parse_args(argv)

    world = models.hallway()
    rng = random.Random(args.seed)
    with GrpcClient(args.target, api_key=args.api_key) as mc:
        session = mc.create_session(world, seed=args.seed, update_mode=args.update_mode)
        names = session.model.stimuli
        state = rng.randrange(world.states)
        print(f"session {session.id} ({args.update_mode}); start at {state}")
        visits = dict.fromkeys(names, 0)
        switches = 0
        with mc.interact(session.id) as stream:
            step = stream.step(state)
            current = dominant(step.drive)
            started = last_report = time.perf_counter()
            last_ticks = 0
            for i in range(1, args.steps + 1):
                state = world.sample_next(state, step.action_index, rng)
                stimulus = world.stimulus(state, noise_sd=args.noise_sd, rng=rng)
                step = stream.step(state, stimulus)
                for j, x in enumerate(stimulus):
                    if x != 0.0:
                        visits[names[j]] += 1
                now = dominant(step.drive, current)
                if now != current:
                    current, switches = now, switches + 1
                    print(f"tick {step.tick:7d}: seeking {names[current]} (agent at state {state})")
                t = time.perf_counter()
                if t - last_report >= args.report_every:
                    print(f"  {(i - last_ticks) / (t - last_report):8.0f} ticks/s")
                    last_report, last_ticks = t, i
            elapsed = time.perf_counter() - started
        rate = args.steps / elapsed if elapsed > 0 else float("inf")
        print(
            f"{args.steps} ticks in {elapsed:.2f} s: {rate:.0f} ticks/s; "
            f"{switches} drive switches; visits: "
            + ", ".join(f"{k} {v}" for k, v in visits.items())
        )
        if not args.keep:
            mc.delete_session(session.id)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
