#!/usr/bin/env python3
"""A curious agent in the paper's hallway: a book at one state, over REST.

The hallway of Experiment 1 (food at 10, rest at 40) with a curiosity
channel: the session gets a third stimulus dimension, ``curiosity``, which
the server computes as xi_cur (the paper's Eq. 7) from raw signal samples.
Arriving at the book's state (25 by default) delivers one sample of the
paper's Eq. 6 book signal, x1 = sin t + cos^2(11t), x2 = cos 11t, on the
book's own clock, which advances by dt = 0.08 per delivered sample. While a
module learns the signal, xi_cur is positive and draws the agent back to
the book; once its estimation error stays below delta the module freezes,
the book is explained and the agent returns to balancing food and rest.
This prints the ticks where a module freezes and a summary of the visits.

    cargo run --release -- serve          # in another terminal
    python examples/curiosity.py --steps 6000
"""

from __future__ import annotations

import argparse
import math
import os
import random
import sys
from collections.abc import Sequence

from mcapi_client import Client, CuriosityConfig, models
from mcapi_client.errors import McapiError, one_line

DT = 0.08
"""The signal clock's step per delivered sample (the server's default ``dt``)."""


def book(t: float) -> list[float]:
    """The paper's Eq. 6 book signal at time t."""
    return [math.sin(t) + math.cos(11 * t) ** 2, math.cos(11 * t)]


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the curious hallway over REST; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--url", default="http://127.0.0.1:8080", help="REST address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--steps", type=int, default=6000, help="ticks to run")
    parser.add_argument("--seed", type=int, default=1, help="seed of the world and the agent")
    parser.add_argument("--book", type=int, default=25, help="the state where the book is")
    parser.add_argument("--noise-sd", type=float, default=2.0, help="sd of the food/rest noise")
    parser.add_argument("--keep", action="store_true", help="keep the session afterwards")
    args = parser.parse_args(argv)

    world = models.hallway()
    rng = random.Random(args.seed)
    with Client(args.url, api_key=args.api_key) as mc:
        session = mc.create_session(
            world, seed=args.seed, gamma=0.85, curiosity=CuriosityConfig(signal_dim=2)
        )
        names = session.model.stimuli  # food, rest, curiosity (appended by the server)
        state = rng.randrange(world.states)
        print(
            f"session {session.id}: stimuli {', '.join(names)}; "
            f"book at {args.book}, start at {state}"
        )
        step = mc.observe(session.id, state)  # the first observation: the state only
        samples = 0  # book samples delivered: the book's clock is samples * DT
        visits = {"food": 0, "rest": 0, "book": 0}
        modules = 0
        for _ in range(args.steps):
            state = world.sample_next(state, step.action_index, rng)
            stimulus = world.stimulus(state, noise_sd=args.noise_sd, rng=rng)  # the extrinsic part
            signal = None
            if state == args.book:
                signal = book(samples * DT)
                samples += 1
                visits["book"] += 1
            for name, x in zip(names, stimulus):
                if x != 0.0:
                    visits[name] += 1
            step = mc.observe(session.id, state, stimulus, signal=signal)
            assert step.curiosity is not None  # a session with a channel
            if step.curiosity.modules > modules:
                modules = step.curiosity.modules
                frozen = mc.get_session(session.id).curiosity
                assert frozen is not None
                m = frozen.modules[-1]
                print(
                    f"tick {step.tick:6d}: a module froze after learning source {m.source} "
                    f"from {m.learned_samples} book samples; modules: {modules}"
                )
        info = mc.get_session(session.id)
        assert info.curiosity is not None
        explained = "explained" if info.curiosity.all_explained else "not explained yet"
        print(
            f"{info.tick} ticks: {info.curiosity.samples} book samples, "
            f"{len(info.curiosity.modules)} frozen module(s), the book {explained}"
        )
        print("visits: " + ", ".join(f"{k} {v}" for k, v in visits.items()))
        if not args.keep:
            mc.delete_session(session.id)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
