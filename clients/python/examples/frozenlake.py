#!/usr/bin/env python3
"""An MCA-PI agent on Gymnasium's slippery FrozenLake, balancing two needs.

The model comes from FrozenLake's own transition table
(``models.from_gymnasium``): with ``is_slippery=True`` each move goes where it
was meant to with probability 1/3 and to either side otherwise, and the
server plans with those probabilities. Two stimulus sources sit on the map,
food in the top row's far corner and water down the left edge, each a few
slippery steps from the start past the holes. Falling into a hole or
reaching the goal ends Gymnasium's episode; the agent lives on: the next
observation is the start cell after ``env.reset()``, which is what the model
says (``on_terminated="restart"``).

The drive turns towards whichever stimulus the agent received least
recently, so it fetches food, then water, then food again, despite the ice.
This prints the visits to each source per window of ticks and the drive.

    pip install './clients/python[gymnasium]'
    cargo run --release -- serve          # in another terminal
    python examples/frozenlake.py --steps 3000
"""

from __future__ import annotations

import argparse
import os
import random
import sys
from collections.abc import Sequence
from typing import Any

from mcapi_client import Client, models
from mcapi_client.errors import McapiError, one_line

# Source cells per map (FrozenLake numbers cells row by row): food in the top
# row's far corner, water on the left edge; both are free cells ("F").
SOURCES = {
    "4x4": {"food": 3, "water": 8},
    "8x8": {"food": 7, "water": 56},
}


def draw(desc: Sequence[Sequence[bytes]], sources: dict[str, int]) -> str:
    """The map, with each source drawn as the index of its stimulus dimension."""
    cols = len(desc[0])
    rows = [[ch.decode() for ch in row] for row in desc]
    for dim, s in enumerate(sources.values()):
        rows[s // cols][s % cols] = str(dim)
    legend = ", ".join(f"{dim} = {name} (state {s})" for dim, (name, s) in enumerate(sources.items()))
    return "\n".join("  " + "".join(row) for row in rows) + f"\n  S start, H hole, G goal; {legend}"


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the agent on FrozenLake; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8080", help="REST address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--steps", type=int, default=3000, help="ticks to run")
    parser.add_argument("--seed", type=int, default=1, help="seed of the world and the agent")
    parser.add_argument("--map", choices=["4x4", "8x8"], default="4x4", help="FrozenLake map")
    parser.add_argument("--noise-sd", type=float, default=2.0, help="sd of the source noise")
    parser.add_argument("--window", type=int, default=500, help="ticks per summary line")
    parser.add_argument("--keep", action="store_true", help="keep the session afterwards")
    args = parser.parse_args(argv)

    try:
        import gymnasium
    except ImportError:
        print("this example needs gymnasium: pip install './clients/python[gymnasium]'")
        return 2

    env = gymnasium.make("FrozenLake-v1", map_name=args.map, is_slippery=True)
    lake: Any = env.unwrapped  # stepped directly: an agent's life has no time limit
    sources = SOURCES[args.map]
    model = models.from_gymnasium(env, sources=sources)
    print(f"FrozenLake {args.map}, slippery: {model.states} states, {model.transitions} transitions")
    print(draw(lake.desc, sources))

    rng = random.Random(args.seed)
    names = list(model.stimuli)
    with Client(args.url, api_key=args.api_key) as mc:
        session = mc.create_session(model, seed=args.seed)
        obs, _ = lake.reset(seed=args.seed)
        state = int(obs)
        step = mc.observe(session.id, state)
        ended = False
        window = dict.fromkeys(names, 0)
        total = dict.fromkeys(names, 0)
        falls = 0
        for t in range(1, args.steps + 1):
            if ended:
                obs, _ = lake.reset()  # what the model's restart rows say
                ended = False
            else:
                obs, _reward, ended, _truncated, _ = lake.step(step.action_index)
                if ended and lake.desc.flat[int(obs)] == b"H":
                    falls += 1
            state = int(obs)
            stimulus = model.stimulus(state, noise_sd=args.noise_sd, rng=rng)
            step = mc.observe(session.id, state, stimulus)
            for j, x in enumerate(stimulus):
                if x != 0.0:
                    window[names[j]] += 1
                    total[names[j]] += 1
            if t % args.window == 0 or t == args.steps:
                drive = ", ".join(f"{n} {d:+.2f}" for n, d in zip(names, step.drive))
                seen = ", ".join(f"{n} {c:3d}" for n, c in window.items())
                print(f"ticks {t:6d}: visits {seen}; drive {drive}")
                window = dict.fromkeys(names, 0)
        balance = min(total.values()) / max(1, max(total.values()))
        print(
            "total visits: "
            + ", ".join(f"{n} {c}" for n, c in total.items())
            + f"; holes fallen into: {falls}; balance (fewer/more): {balance:.2f}"
        )
        if not args.keep:
            mc.delete_session(session.id)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
