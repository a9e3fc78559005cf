#!/usr/bin/env python3
"""The paper's hallway (Experiment 1), simulated here and driven over REST.

A 50-state chain with actions left, right and stay; arriving at state 10
delivers food, at state 40 rest: 6 plus N(0, 2) noise on that stimulus, 0 on
the other. The agent starts at a random state. Each tick this program applies
the advised action, reports the new state and its stimulus, and gets the
next action. The drive D turns towards the stimulus received least
recently, so the agent walks to one source, then the other, and back: this
prints each switch of the dominant drive and saves a plot of D over time
(when matplotlib is installed).

    cargo run --release -- serve          # in another terminal
    python examples/hallway_rest.py --steps 3000 --plot hallway_drive.png
"""

from __future__ import annotations

import argparse
import os
import random
import sys
from collections.abc import Sequence

from mcapi_client import Client, models
from mcapi_client.errors import McapiError, one_line

# A drive component takes over when |D_j| >= SWITCH_RATIO |D_current| (the
# hysteresis the server's experiments use to count switches).
SWITCH_RATIO = 1.5


def dominant(drive: Sequence[float], current: int | None = None) -> int:
    """The dominant drive component, with hysteresis around ``current``."""
    best = max(range(len(drive)), key=lambda j: abs(drive[j]))
    if current is None or best == current:
        return best
    return best if abs(drive[best]) >= SWITCH_RATIO * abs(drive[current]) else current


def save_plot(path: str, drives: list[list[float]], states: list[int], names: Sequence[str]) -> bool:
    """Plots D over time and the agent's state; False when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, (ax_d, ax_s) = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    ticks = range(len(drives))
    for j, name in enumerate(names):
        ax_d.plot(ticks, [d[j] for d in drives], label=f"D[{name}]", linewidth=1)
    ax_d.set_ylabel("drive")
    ax_d.legend(loc="upper right")
    ax_d.set_title("MCA-PI agent in the hallway (over REST)")
    ax_s.plot(range(len(states)), states, color="0.3", linewidth=0.7)
    ax_s.axhline(10, color="tab:blue", linestyle=":", label="food (10)")
    ax_s.axhline(40, color="tab:orange", linestyle=":", label="rest (40)")
    ax_s.set_ylabel("state")
    ax_s.set_xlabel("tick")
    ax_s.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the hallway over REST; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--url", default="http://127.0.0.1:8080", help="REST address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--steps", type=int, default=3000, help="ticks to run")
    parser.add_argument("--seed", type=int, default=1, help="seed of the world and the agent")
    parser.add_argument("--noise-sd", type=float, default=2.0, help="sd of the source noise")
    parser.add_argument("--plot", default="hallway_drive.png", help="where to save the plot")
    parser.add_argument("--no-plot", action="store_true", help="do not plot")
    parser.add_argument("--keep", action="store_true", help="keep the session afterwards")
    args = parser.parse_args(argv)

    world = models.hallway()
    rng = random.Random(args.seed)
    with Client(args.url, api_key=args.api_key) as mc:
        session = mc.create_session(world, seed=args.seed, eta=0.01, gamma=0.95)
        names = session.model.stimuli
        state = rng.randrange(world.states)
        print(f"session {session.id}: {world.states} states, food at 10, rest at 40; start at {state}")
        step = mc.observe(session.id, state)  # the first observation: the state only
        drives, states = [step.drive], [state]
        current = dominant(step.drive)
        visits = {name: 0 for name in names}
        print(f"tick {step.tick:6d}: seeking {names[current]:<5} D={_fmt(step.drive)}")
        for _ in range(args.steps):
            state = world.sample_next(state, step.action_index, rng)
            stimulus = world.stimulus(state, noise_sd=args.noise_sd, rng=rng)
            step = mc.observe(session.id, state, stimulus)
            drives.append(step.drive)
            states.append(state)
            for j, x in enumerate(stimulus):
                if x != 0.0:
                    visits[names[j]] += 1
            now = dominant(step.drive, current)
            if now != current:
                current = now
                print(
                    f"tick {step.tick:6d}: seeking {names[current]:<5} D={_fmt(step.drive)} "
                    f"(agent at state {state})"
                )
        print("visits: " + ", ".join(f"{k} {v}" for k, v in visits.items()))
        if not args.no_plot:
            if save_plot(args.plot, drives, states, names):
                print(f"saved the plot of D over time to {args.plot}")
            else:
                print("matplotlib is not installed: no plot (pip install './clients/python[plot]')")
        if not args.keep:
            mc.delete_session(session.id)
    return 0


def _fmt(drive: Sequence[float]) -> str:
    return "[" + ", ".join(f"{d:+.3f}" for d in drive) + "]"


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
