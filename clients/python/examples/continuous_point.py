#!/usr/bin/env python3
"""An MCA-PI agent moving a point in the unit square between three disc-shaped sources.

A continuous world: the session is created on a ``ContinuousModel`` (the box
[0, 1]^2, four moves, three stimuli) and observes the point's coordinates,
not state numbers. The world is simulated here in a few lines of Python: a
move shifts the point by 0.05 (with a little noise) and stops at the walls;
while the point is inside a disc, that disc's stimulus is delivered.
The server learns the dynamics from the observed transitions and plans on
its default for d = 2, a grid of 64 x 64 cells over the square; the drive
sends the agent to whichever source it received least recently.

This prints, every ``--report-every`` ticks, what the agent seeks and how
often it arrived at each source coming from another one, then the totals,
the same numbers for a random walk on the same seed, and what the session's
model holds (on the grid: the moves kept and the (cell, action) pairs whose
successor it knows).

    mcapi serve                               # in another terminal
    python clients/python/examples/continuous_point.py --steps 3000
"""

from __future__ import annotations

import argparse
import math
import os
import random
import sys
from collections.abc import Sequence

from mcapi_client import Client, models
from mcapi_client.errors import McapiError, one_line

MOVES: dict[str, tuple[float, float]] = {
    "north": (0.0, 0.05),
    "south": (0.0, -0.05),
    "east": (0.05, 0.0),
    "west": (-0.05, 0.0),
}

# name -> (centre, radius)
SOURCES: dict[str, tuple[tuple[float, float], float]] = {
    "food": ((0.15, 0.2), 0.1),
    "water": ((0.85, 0.2), 0.1),
    "rest": ((0.5, 0.85), 0.1),
}

MAGNITUDE = 6.0
"""The stimulus of a source per tick inside it (the paper's source magnitude)."""


class PointWorld:
    """The point, its moves and the discs. ``arrivals`` counts the entries into
    each disc coming from another one (a traversal), not every wobble across
    a disc's edge."""

    def __init__(self, seed: int, noise: float = 0.01) -> None:
        self.rng = random.Random(seed)
        self.noise = noise
        self.x = (0.5, 0.5)
        self.arrivals = dict.fromkeys(SOURCES, 0)
        self.totals = dict.fromkeys(SOURCES, 0.0)
        self.last: str | None = None  # the source visited last

    def source_at(self, x: tuple[float, float]) -> str | None:
        """The source whose disc holds ``x``, if any (the discs do not overlap)."""
        for name, (centre, radius) in SOURCES.items():
            if math.dist(x, centre) <= radius:
                return name
        return None

    def step(self, action: str) -> list[float]:
        """Moves the point; the stimulus received, one value per source."""
        dx, dy = MOVES[action]
        jx, jy = (self.rng.uniform(-self.noise, self.noise) for _ in range(2))
        self.x = (min(1.0, max(0.0, self.x[0] + dx + jx)), min(1.0, max(0.0, self.x[1] + dy + jy)))
        here = self.source_at(self.x)
        if here is not None and here != self.last:
            self.arrivals[here] += 1
            self.last = here
        stimulus = [MAGNITUDE if name == here else 0.0 for name in SOURCES]
        for name, s in zip(SOURCES, stimulus):
            self.totals[name] += s
        return stimulus


def report(world: PointWorld) -> str:
    """Arrivals per source, e.g. ``food 3, water 2, rest 4``."""
    return ", ".join(f"{name} {n}" for name, n in world.arrivals.items())


def balance(world: PointWorld) -> float:
    """min / max of the stimulus received per source (1: perfectly balanced)."""
    got = list(world.totals.values())
    return min(got) / max(max(got), 1e-9)


def random_walk(steps: int, seed: int) -> PointWorld:
    """The same world under uniformly random moves."""
    world = PointWorld(seed)
    moves = random.Random(seed + 1)
    for _ in range(steps):
        world.step(moves.choice(list(MOVES)))
    return world


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the agent in the point world over REST; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8080", help="REST address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--steps", type=int, default=1500, help="ticks to run")
    parser.add_argument("--seed", type=int, default=1, help="seed of the world and the agent")
    parser.add_argument("--report-every", type=int, default=500, help="ticks between reports")
    parser.add_argument("--keep", action="store_true", help="keep the session afterwards")
    args = parser.parse_args(argv)

    model = models.ContinuousModel(
        low=(0.0, 0.0),
        high=(1.0, 1.0),
        actions=tuple(MOVES),
        stimuli=tuple(SOURCES),
    )
    world = PointWorld(args.seed)
    with Client(args.url, api_key=args.api_key) as mc:
        session = mc.create_session(model, seed=args.seed)
        built = session.model.continuous
        basis = built.basis if built is not None else None
        print(
            f"point world: [0, 1]^2, {len(MOVES)} moves, sources {', '.join(SOURCES)}; "
            f"basis {basis}, {session.model.features} features"
        )
        step = mc.observe(session.id, observation=world.x)
        for tick in range(1, args.steps + 1):
            stimulus = world.step(step.action)
            step = mc.observe(session.id, observation=world.x, stimulus=stimulus)
            if args.report_every > 0 and tick % args.report_every == 0:
                seeking = max(range(len(step.drive)), key=lambda i: abs(step.drive[i]))
                print(f"tick {tick:5}: seeking {model.stimuli[seeking]}; arrivals {report(world)}")
        info = mc.get_session(session.id)
        if not args.keep:
            mc.delete_session(session.id)
    walk = random_walk(args.steps, args.seed)
    print(f"agent : {args.steps} ticks, arrivals {report(world)}; balance {balance(world):.2f}")
    print(f"random: {args.steps} ticks, arrivals {report(walk)}; balance {balance(walk):.2f}")
    stats = info.stats.continuous
    if stats is not None:
        on_grid = isinstance(basis, dict) and basis.get("kind") == "grid"
        held = (
            f"grid: {stats.samples} moves kept, {stats.slots} (cell, action) pairs known"
            if on_grid
            else f"sample store: {stats.samples} transitions, {stats.slots} (cell, action) slots"
        )
        print(f"{held}; {stats.clipped} observations clipped")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
