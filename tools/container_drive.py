#!/usr/bin/env python3
"""Drives hallway sessions in a running mcapi (the container test's client).

Half the sessions are created and driven over REST, half over gRPC (the
``Interact`` stream, one observation in flight). After every acknowledged
observation the session's tick, drive and state are written to a ledger
(a JSON file, replaced atomically), so a test can kill the server at any
moment and then ask ``verify`` whether everything acknowledged survived.

    container_drive.py create --http URL --grpc HOST:PORT --ledger F --sessions 4
    container_drive.py drive  --http URL --grpc HOST:PORT --ledger F --steps 20
    container_drive.py drive  ... --until-error     # until the server goes away
    container_drive.py verify --http URL --grpc HOST:PORT --ledger F [--exact]

``verify`` reads every session over both transports: its tick must equal the
ledger's (``--exact``, after a clean stop) or exceed it by at most the one
observation that may have been applied but not yet acknowledged when the
server was killed; when the ticks are equal the drive must be bit-identical.
It then takes the server's tick, drive and state into the ledger, so a later
``drive`` goes on from there. Exit 0 on success, 1 with a message per
failing session otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import time
from typing import Any

from mcapi_client import Client, GrpcClient, McapiError, Observation, models

WORLD = models.hallway()


def load(path: str) -> dict[str, Any]:
    with open(path) as f:
        data: dict[str, Any] = json.load(f)
    return data


def save(path: str, ledger: dict[str, Any]) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(ledger, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def create(args: argparse.Namespace) -> int:
    ledger: dict[str, Any] = {"sessions": {}}
    with Client(args.http) as rest, GrpcClient(args.grpc) as grpc:
        for i in range(args.sessions):
            transport = "rest" if i % 2 == 0 else "grpc"
            client: Any = rest if transport == "rest" else grpc
            info = client.create_session(WORLD, seed=100 + i, eta=0.01, gamma=0.95)
            ledger["sessions"][info.id] = {
                "transport": transport,
                "tick": info.tick,
                "drive": info.drive,
                "state": None,
                "rng": 100 + i,
            }
    save(args.ledger, ledger)
    print(f"created {args.sessions} sessions (REST and gRPC alternately)")
    return 0


def drive(args: argparse.Namespace) -> int:
    ledger = load(args.ledger)
    sessions = ledger["sessions"]
    done = 0
    with Client(args.http, timeout=10.0) as rest, GrpcClient(args.grpc, timeout=10.0) as grpc:
        streams = {
            sid: grpc.interact(sid) for sid, s in sessions.items() if s["transport"] == "grpc"
        }
        rngs = {sid: random.Random(s["rng"] * 1_000_003 + s["tick"]) for sid, s in sessions.items()}
        try:
            step_no = 0
            while args.until_error or step_no < args.steps:
                for sid, s in sessions.items():
                    rng = rngs[sid]
                    if s["state"] is None:
                        state, stimulus = rng.randrange(WORLD.states), None
                    else:
                        action = s.get("action")
                        if action is None:  # resynced from the server: any action
                            action = rng.randrange(len(WORLD.actions))
                        state = WORLD.sample_next(s["state"], action, rng)
                        stimulus = WORLD.stimulus(state, noise_sd=2.0, rng=rng)
                    if s["transport"] == "rest":
                        step = rest.observe(sid, state, stimulus)
                    else:
                        step = streams[sid].step(state, stimulus)
                    # The first observation (the state alone) is no tick.
                    expected = s["tick"] + (0 if s["state"] is None else 1)
                    if step.tick != expected:
                        print(f"{sid}: acknowledged tick {step.tick}, expected {expected}")
                        return 1
                    s.update(tick=step.tick, drive=step.drive, state=state, action=step.action_index)
                    save(args.ledger, ledger)
                    done += 1
                step_no += 1
        except McapiError as e:
            if not args.until_error:
                raise
            print(f"stopped by the server going away after {done} acknowledged observations: {e}")
            return 0
        finally:
            for stream in streams.values():
                stream.close()
    print(f"{done} observations acknowledged ({len(sessions)} sessions)")
    return 0


def verify(args: argparse.Namespace) -> int:
    ledger = load(args.ledger)
    failures = []
    with Client(args.http) as rest, GrpcClient(args.grpc) as grpc:
        for sid, s in ledger["sessions"].items():
            for name, client in (("REST", rest), ("gRPC", grpc)):
                info = client.get_session(sid)
                slack = 0 if args.exact else 1
                if not s["tick"] <= info.tick <= s["tick"] + slack:
                    failures.append(f"{sid} over {name}: tick {info.tick}, acknowledged {s['tick']}")
                elif info.tick == s["tick"] and info.drive != s["drive"]:
                    failures.append(
                        f"{sid} over {name}: drive {info.drive} != acknowledged {s['drive']}"
                    )
                # The server is the truth from here on (it may hold one
                # observation more than was acknowledged).
                s.update(tick=info.tick, drive=info.drive, state=info.state, action=None)
    save(args.ledger, ledger)
    for f in failures:
        print("FAIL", f)
    ticks = sum(s["tick"] for s in ledger["sessions"].values())
    print(f"verified {len(ledger['sessions'])} sessions, {ticks} acknowledged ticks in all"
          + ("" if failures else ": all present"))
    return 1 if failures else 0


def populate(args: argparse.Namespace) -> int:
    """Creates ``--sessions`` hallway sessions with ``--steps`` observations
    each, over REST from 16 threads (for the start-to-ready benchmark)."""
    from concurrent.futures import ThreadPoolExecutor

    def one(i: int) -> int:
        rng = random.Random(i)
        with Client(args.http) as rest:
            info = rest.create_session(WORLD, seed=i)
            state = rng.randrange(WORLD.states)
            step = rest.observe(info.id, state)
            batch = []
            for _ in range(args.steps):  # a walk, ignoring the advice after the first
                state = WORLD.sample_next(state, step.action_index, rng)
                batch.append(Observation(state=state, stimulus=WORLD.stimulus(state)))
            steps = rest.observe_batch(info.id, batch)
            return steps[-1].tick if steps else step.tick

    start = time.monotonic()
    with ThreadPoolExecutor(16) as pool:
        ticks = sum(pool.map(one, range(args.sessions)))
    print(f"created {args.sessions} sessions ({ticks} ticks) in {time.monotonic() - start:.1f} s")
    return 0


def wait_ready(args: argparse.Namespace) -> int:
    """Polls /readyz until 200 (or the deadline); prints the seconds taken."""
    import httpx

    start = time.monotonic()
    while time.monotonic() - start < args.timeout:
        try:
            if httpx.get(args.http + "/readyz", timeout=1.0).status_code == 200:
                print(f"{time.monotonic() - start:.3f}")
                return 0
        except httpx.HTTPError:
            pass
        time.sleep(0.05)
    print(f"not ready after {args.timeout} s", file=sys.stderr)
    return 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("create", "drive", "verify", "populate", "wait-ready"):
        p = sub.add_parser(name)
        p.add_argument("--http", default="http://127.0.0.1:8080")
        p.add_argument("--grpc", default="127.0.0.1:50051")
        p.add_argument("--ledger", default="ledger.json")
        p.add_argument("--sessions", type=int, default=4)
        p.add_argument("--steps", type=int, default=20)
        p.add_argument("--until-error", action="store_true")
        p.add_argument("--exact", action="store_true")
        p.add_argument("--timeout", type=float, default=60.0)
    args = parser.parse_args()
    run = {
        "create": create,
        "drive": drive,
        "verify": verify,
        "populate": populate,
        "wait-ready": wait_ready,
    }
    return run[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
