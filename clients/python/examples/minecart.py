#!/usr/bin/env python3
"""An MCA-PI agent in MO-Gymnasium's minecart, mining both ores in turn, against a random policy.

``models.from_mo_gymnasium(env, observations="continuous")`` turns the
environment into a continuous world: its 7 observation components (the
cart's position, speed, heading and the fill of its two ore slots, in the
box the cart reaches: [0, 1], and [-1, 1] for the heading's sine and cosine)
are the observation vector, its 6 actions the session's, and the two ore
components of its reward (ore delivered at home) the stimuli. Fuel, a cost,
is no stimulus. The server learns the dynamics from the observations and
plans on them; its drive turns to whichever ore it received least recently.

This runs the agent, then a uniformly random policy on the same seeds, and
prints each one's ore totals and balance (fewer/more). Minecart's mines draw
their yield from numpy's global generator, not the environment's, so each
run seeds it too: the agent and the random policy meet the same mines.

    pip install './clients/python[mo]'
    mcapi serve                           # in another terminal
    python clients/python/examples/minecart.py --steps 3000 --seeds 1
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import warnings
from collections.abc import Sequence

from mcapi_client import Client, models
from mcapi_client.errors import McapiError, one_line


def run(args: argparse.Namespace, seed: int, agent: bool) -> list[float]:
    """One run of ``args.steps`` ticks; the ore delivered, per ore."""
    import mo_gymnasium
    import numpy

    env = mo_gymnasium.make("minecart-v0")  # type: ignore[attr-defined]
    scale: float = args.scale
    basis = json.loads(args.basis) if args.basis else None
    world = models.from_mo_gymnasium(env, observations="continuous", scale=scale, basis=basis)
    numpy.random.seed(seed)  # the mines' yields (see above)
    observation = world.reset(seed=seed)
    if not agent:
        rng = random.Random(seed)
        for _ in range(args.steps):
            world.step(rng.randrange(len(world.model.actions)))
        return [x / args.scale for x in world.stimulus_totals]
    with Client(args.url, api_key=args.api_key) as mc:
        session = mc.create_session(world, seed=seed)
        step = mc.observe(session.id, observation=observation)
        for _ in range(args.steps):
            s = world.step(step.action_index)
            step = mc.observe(session.id, observation=s.observation, stimulus=s.stimulus)
        if not args.keep:
            mc.delete_session(session.id)
    return [x / args.scale for x in world.stimulus_totals]


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the agent and the random policy; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--url", default="http://127.0.0.1:8080", help="REST address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--steps", type=int, default=3000, help="ticks per run")
    parser.add_argument("--seeds", type=int, default=1, help="runs, seeds 1..N")
    parser.add_argument("--scale", type=float, default=6.0, help="stimulus per unit of ore")
    parser.add_argument(
        "--basis",
        default=None,
        help='the basis as JSON, e.g. \'{"kind": "fourier", "order": 2}\' (default: the server\'s)',
    )
    parser.add_argument("--keep", action="store_true", help="keep the sessions afterwards")
    args = parser.parse_args(argv)
    try:
        import mo_gymnasium  # noqa: F401
    except ImportError:
        print("this example needs MO-Gymnasium: pip install './clients/python[mo]'")
        return 2
    # MO-Gymnasium builds its reward spaces from float64 bounds: gymnasium warns.
    warnings.filterwarnings("ignore", message=".*precision lowered", category=UserWarning)
    runs: dict[str, list[list[float]]] = {"agent": [], "random": []}
    for seed in range(1, args.seeds + 1):
        try:
            runs["agent"].append(run(args, seed, agent=True))
        except McapiError as e:
            print(f"mcapi: {e}")
            return 1
        runs["random"].append(run(args, seed, agent=False))
        (a1, a2), (r1, r2) = runs["agent"][-1], runs["random"][-1]
        print(f"seed {seed}: agent ore1 {a1:.2f}, ore2 {a2:.2f}; random ore1 {r1:.2f}, ore2 {r2:.2f}")
    for name, rows in runs.items():
        totals = [sum(r[i] for r in rows) / len(rows) for i in range(2)]
        balances = [min(r) / max(max(r), 1e-9) for r in rows]
        print(
            f"{name:6}: ore1 {totals[0]:.2f}, ore2 {totals[1]:.2f} per run of {args.steps} ticks "
            f"(mean of {len(rows)}); balance {sum(balances) / len(balances):.2f}"
        )
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
