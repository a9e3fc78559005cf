#!/usr/bin/env python3
"""Many hallway agents at once: one session group, stepped by columns.

The paper's hallway (50 states, food at 10, rest at 40, stimulus 6 + N(0, 2))
for every member of a group, simulated with numpy arrays (no Python object
per agent) and stepped over the group's gRPC ``StepGroup`` stream. With
``--in-flight 2`` (the default) the members are split in two halves, each
stepped by its own mask, so that one half's step is on the wire while the
other half's next states are computed. Prints the rate as it goes: agent
steps per second (one member's observation each) and group steps per second
(messages: one per slice and step).

    pip install './clients/python[grpc,vector]'
    cargo run --release -- serve          # in another terminal
    python examples/hallway_group.py --agents 256 --steps 2000
    python examples/hallway_group.py --transport rest --agents 64   # REST: one POST per step
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from mcapi_client import Client, GrpcClient, models
from mcapi_client.errors import McapiError, one_line
from mcapi_client.groups import GroupStep, VectorAgents

if TYPE_CHECKING:
    import numpy.typing as npt

MOVES = np.array([-1, 1, 0])  # the hallway's actions: left, right, stay


class Hallways:
    """N hallways stepped together: states, moves and stimuli as arrays."""

    def __init__(self, world: models.Model, n: int, noise_sd: float, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.noise_sd = noise_sd
        self.sources = [(src.state, src.dim) for src in world.sources]
        self.n_stimuli = len(world.stimuli)
        self.states = self.rng.integers(0, world.states, n)
        self.visits = np.zeros(self.n_stimuli, dtype=np.int64)

    def move(self, rows: slice, actions: npt.NDArray[np.uint32]) -> npt.NDArray[np.float64]:
        """Moves the agents of ``rows`` by their actions; their stimuli."""
        states = self.states[rows] + MOVES[actions]
        self.states[rows] = states
        stimuli = np.zeros((len(states), self.n_stimuli))
        for state, dim in self.sources:
            here = states == state
            count = int(here.sum())
            if count:
                stimuli[here, dim] = 6.0 + self.rng.normal(0.0, self.noise_sd, count)
                self.visits[dim] += count
        return stimuli


def refused(step: GroupStep) -> None:
    """Stops at the first member refused (a bug in this simulation if any)."""
    if step.errors:
        e = step.errors[0]
        raise SystemExit(f"member {e.index} refused: {e.code}: {e.message}")


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the group of hallway agents; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transport", choices=["grpc", "rest"], default="grpc", help="how to step the group")
    parser.add_argument("--target", default="127.0.0.1:50051", help="gRPC address of mcapi")
    parser.add_argument("--url", default="http://127.0.0.1:8080", help="REST address of mcapi")
    parser.add_argument(
        "--api-key",
        default=os.environ.get("MCAPI_API_KEY"),
        help="API key, if the server has keys (default: $MCAPI_API_KEY)",
    )
    parser.add_argument("--agents", type=int, default=256, help="members of the group")
    parser.add_argument("--steps", type=int, default=2000, help="steps of every member")
    parser.add_argument("--in-flight", type=int, default=2, help="gRPC: member slices stepped in flight")
    parser.add_argument("--seed", type=int, default=1, help="seed of the world and the group")
    parser.add_argument("--noise-sd", type=float, default=2.0, help="sd of the source noise")
    parser.add_argument(
        "--update-mode",
        choices=["lockstep", "async"],
        default="lockstep",
        help="lockstep: one policy update per tick; async: the server plans behind the stream",
    )
    parser.add_argument("--report-every", type=float, default=1.0, help="seconds between rate lines")
    parser.add_argument("--keep", action="store_true", help="keep the group afterwards")
    args = parser.parse_args(argv)
    if args.agents < 1 or args.steps < 1:
        parser.error("--agents and --steps must be at least 1")
    slices = 1 if args.transport == "rest" else args.in_flight
    if not 1 <= slices <= min(8, args.agents):
        parser.error(f"--in-flight must be 1 to {min(8, args.agents)} (the server reads 8 ahead)")

    world = models.hallway()
    sim = Hallways(world, args.agents, args.noise_sd, args.seed)
    bounds = np.linspace(0, args.agents, slices + 1).astype(int)
    rows = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
    masks = [np.arange(r.start, r.stop) for r in rows]

    client: GrpcClient | Client = (
        GrpcClient(args.target, api_key=args.api_key)
        if args.transport == "grpc"
        else Client(args.url, api_key=args.api_key)
    )
    with client as mc:
        agents = mc.create_group(world, args.agents, seed=args.seed, update_mode=args.update_mode)
        print(
            f"group {agents.info.id}: {args.agents} hallway agents ({args.update_mode}), "
            f"{args.transport}, {slices} step(s) in flight"
        )
        with agents:
            first = agents.step(sim.states)
            refused(first)
            actions = [first.actions[r] for r in rows]
            started = last_report = time.perf_counter()
            done = last_done = 0  # agent steps
            group_steps = 0
            if slices == 1:
                for _ in range(args.steps):
                    stimuli = sim.move(rows[0], actions[0])
                    step = agents.step(sim.states, stimuli)
                    refused(step)
                    actions[0] = step.actions
                    done += args.agents
                    group_steps += 1
                    t = time.perf_counter()
                    if t - last_report >= args.report_every:
                        print(f"  {(done - last_done) / (t - last_report):10.0f} agent steps/s")
                        last_report, last_done = t, done
            else:
                stream = agents
                assert isinstance(stream, VectorAgents)  # gRPC: send and recv
                for k, r in enumerate(rows):  # one step of each slice in flight
                    stimuli = sim.move(r, actions[k])
                    stream.send(sim.states[r], stimuli, mask=masks[k])
                sent = 1
                while True:
                    for k, r in enumerate(rows):
                        step = stream.recv()  # the oldest: slice k's
                        refused(step)
                        done += len(masks[k])
                        group_steps += 1
                        if sent < args.steps:
                            stimuli = sim.move(r, step.actions)
                            stream.send(sim.states[r], stimuli, mask=masks[k])
                    t = time.perf_counter()
                    if t - last_report >= args.report_every:
                        print(f"  {(done - last_done) / (t - last_report):10.0f} agent steps/s")
                        last_report, last_done = t, done
                    if sent >= args.steps:
                        break
                    sent += 1
            elapsed = time.perf_counter() - started
        rate = done / elapsed if elapsed > 0 else float("inf")
        print(
            f"{args.agents} agents x {args.steps} steps in {elapsed:.2f} s: {rate:.0f} agent steps/s, "
            f"{group_steps / elapsed if elapsed > 0 else 0:.0f} group steps/s; visits: "
            + ", ".join(f"{name} {int(v)}" for name, v in zip(world.stimuli, sim.visits))
        )
        if not args.keep:
            mc.delete_group(agents.info.id)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except McapiError as e:
        sys.exit(f"mcapi: {one_line(e)}")
