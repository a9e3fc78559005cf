#!/usr/bin/env python3
"""One Python process drives N hallway agents as a vectorised training loop
would, and reports the rate it counts and the server's CPU per observation.

    benches/vector.py --grpc 127.0.0.1:50051 --http http://127.0.0.1:8080 \
        --server-pid PID --path group --members 10000 --in-flight 2

The world is simulated here, in numpy: the hallway of the paper (50 states,
left / right / stay, food at 10, rest at 40), every agent in its own copy.
The members are split into ``--in-flight`` slices of equal size; each slice
is one message, and the loop keeps every slice's message in flight: it
takes the oldest reply, moves that slice's worlds by the advised actions and
sends the slice's next step before it reads the next reply (the pattern of
EnvPool's and PufferLib's asynchronous stepping). A step counted is one
member's observation answered.

Paths:
  group        ``StepGroup`` with :class:`mcapi_client.groups.VectorAgents`
               (numpy columns, ``send``/``recv``)
  batch        ``InteractBatch`` with :meth:`GrpcClient.interact_batch`
               (one ``(session_id, observation)`` pair per member; one
               message in flight, as the client's ``step`` is synchronous)
  rest-group   ``POST /v1/groups/{id}/steps`` with JSON columns (standard
               library ``http.client``, one message in flight per
               connection, one connection per slice)

Server CPU is read from ``/proc/PID/stat`` (user + system) over the
measured window, so it counts everything the server did, the agents'
ticks included. The group path also reports the time between consecutive
replies in the window (``reply_gap_p99_ms``, ``reply_gap_max_ms``): a
stall of the server, such as every member writing its snapshot in the same
step, shows in that tail. Prints one JSON object on stdout; progress on
stderr.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import sys
import threading
import time
import urllib.parse
from collections.abc import Callable
from typing import Any

import numpy as np

from mcapi_client import GrpcClient, models
from mcapi_client.groups import ADVISED

STATES = 50
FOOD, REST = 10, 40
TICKS_PER_SECOND = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User plus system CPU of a process, in seconds."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS_PER_SECOND


class Worlds:
    """N hallways, moved by actions in numpy."""

    def __init__(self, n: int, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.states = self.rng.integers(0, STATES, size=n, dtype=np.int64)

    def move(self, index: slice, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Applies each member's action (0 left, 1 right, 2 stay; an unknown
        one stays) and returns the new states and their stimuli (N × 2)."""
        delta = np.where(actions == 0, -1, np.where(actions == 1, 1, 0))
        states = np.clip(self.states[index] + delta, 0, STATES - 1)
        self.states[index] = states
        stimuli = np.zeros((len(states), 2))
        stimuli[:, 0] = states == FOOD
        stimuli[:, 1] = states == REST
        return states, stimuli


def slices(n: int, parts: int) -> list[slice]:
    bounds = np.linspace(0, n, parts + 1).astype(int)
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def measure(
    run_for: Callable[[float], int], warmup: float, duration: float, pid: int | None
) -> dict[str, float]:
    """Runs `run_for` for the warm-up, then for the window, reading the
    server's CPU around the window."""
    run_for(warmup)
    gaps: list[float] | None = getattr(run_for, "gaps", None)
    if gaps is not None:
        gaps.clear()
    cpu0 = cpu_seconds(pid) if pid else 0.0
    t0 = time.perf_counter()
    steps = run_for(duration)
    elapsed = time.perf_counter() - t0
    cpu = (cpu_seconds(pid) - cpu0) if pid else float("nan")
    out = {"steps": steps, "seconds": elapsed, "steps_per_s": steps / elapsed}
    if pid:
        out["server_cpu_s"] = cpu
        out["server_us_per_step"] = cpu / steps * 1e6
    if gaps:
        ordered = sorted(gaps)
        out["reply_gap_p99_ms"] = ordered[int(0.99 * (len(ordered) - 1))] * 1e3
        out["reply_gap_max_ms"] = ordered[-1] * 1e3
    return out


def group_path(args: argparse.Namespace) -> Callable[[float], int]:
    client = GrpcClient(args.grpc)
    agents = client.create_group(models.hallway(), args.members, seed=1, update_mode=args.mode)
    worlds = Worlds(args.members, 2)
    parts = slices(args.members, args.in_flight)
    masks = [None if len(parts) == 1 else np.arange(p.start, p.stop, dtype=np.uint32) for p in parts]
    queue: list[int] = []
    for i, p in enumerate(parts):  # every member's first observation
        agents.send(worlds.states[p], mask=masks[i])
        queue.append(i)

    def run_for(seconds: float) -> int:
        steps = 0
        end = time.perf_counter() + seconds
        last = time.perf_counter()
        while time.perf_counter() < end:
            i = queue.pop(0)
            reply = agents.recv()
            now = time.perf_counter()
            run_for.gaps.append(now - last)  # type: ignore[attr-defined]
            last = now
            if reply.errors:
                sys.exit(f"refused members: {reply.errors[:3]}")
            steps += len(reply.actions)
            states, stimuli = worlds.move(parts[i], reply.actions)
            agents.send(states, stimuli, mask=masks[i])
            queue.append(i)
        return steps

    # The time between consecutive replies, in the window: a stall of the
    # server (every member snapshotting at once, say) shows in its tail.
    run_for.gaps = []  # type: ignore[attr-defined]
    return run_for


def batch_path(args: argparse.Namespace) -> Callable[[float], int]:
    client = GrpcClient(args.grpc)
    ids = [
        client.create_session(models.hallway(), seed=1 + i, update_mode=args.mode).id
        for i in range(args.members)
    ]
    worlds = Worlds(args.members, 2)
    stream = client.interact_batch()
    results = stream.step([(sid, (int(s),)) for sid, s in zip(ids, worlds.states)])
    everyone = slice(0, args.members)
    state = {"actions": np.array([r.action_index for r in results])}  # type: ignore[union-attr]

    def run_for(seconds: float) -> int:
        steps = 0
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            states, stimuli = worlds.move(everyone, state["actions"])
            entries = [
                (sid, (int(s), x.tolist())) for sid, s, x in zip(ids, states, stimuli)
            ]
            results = stream.step(entries)
            state["actions"] = np.array([getattr(r, "action_index", ADVISED) for r in results])
            steps += len(results)
        return steps

    return run_for


def rest_group_path(args: argparse.Namespace) -> Callable[[float], int]:
    url = urllib.parse.urlsplit(args.http)
    conns = [http.client.HTTPConnection(url.hostname, url.port) for _ in range(args.in_flight)]

    def call(conn: http.client.HTTPConnection, method: str, path: str, body: Any = None) -> Any:
        data = json.dumps(body).encode() if body is not None else None
        conn.request(method, path, body=data, headers={"content-type": "application/json"})
        resp = conn.getresponse()
        payload = resp.read()
        if resp.status >= 300:
            sys.exit(f"{method} {path}: {resp.status} {payload[:300]!r}")
        return json.loads(payload)

    group = call(
        conns[0],
        "POST",
        "/v1/groups",
        {"model": {"preset": "hallway"}, "agent": {"update_mode": args.mode}, "n": args.members, "seed": 1},
    )
    path = f"/v1/groups/{group['id']}/steps"
    worlds = Worlds(args.members, 2)
    parts = slices(args.members, args.in_flight)
    actions: list[np.ndarray] = [np.zeros(0)] * len(parts)

    def first(i: int) -> None:
        p = parts[i]
        body: dict[str, Any] = {"states": worlds.states[p].tolist()}
        if len(parts) > 1:
            body["mask"] = list(range(p.start, p.stop))
        actions[i] = np.array(call(conns[i], "POST", path, body)["actions"])

    for i in range(len(parts)):
        first(i)

    def run_slice(i: int, end: float, counts: list[int]) -> None:
        p = parts[i]
        mask = list(range(p.start, p.stop)) if len(parts) > 1 else None
        while time.perf_counter() < end:
            states, stimuli = worlds.move(p, actions[i])
            body: dict[str, Any] = {"states": states.tolist(), "stimuli": stimuli.tolist()}
            if mask is not None:
                body["mask"] = mask
            reply = call(conns[i], "POST", path, body)
            actions[i] = np.array([ADVISED if a is None else a for a in reply["actions"]])
            counts[i] += len(reply["actions"])

    def run_for(seconds: float) -> int:
        end = time.perf_counter() + seconds
        counts = [0] * len(parts)
        threads = [threading.Thread(target=run_slice, args=(i, end, counts)) for i in range(len(parts))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return sum(counts)

    return run_for


PATHS = {"group": group_path, "batch": batch_path, "rest-group": rest_group_path}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grpc", default="127.0.0.1:50051")
    parser.add_argument("--http", default="http://127.0.0.1:8080")
    parser.add_argument("--server-pid", type=int)
    parser.add_argument("--path", choices=sorted(PATHS), default="group")
    parser.add_argument("--members", type=int, default=10_000)
    parser.add_argument("--in-flight", type=int, default=2)
    parser.add_argument("--mode", choices=["async", "lockstep"], default="async")
    parser.add_argument("--warmup", type=float, default=2.0)
    parser.add_argument("--duration", type=float, default=10.0)
    args = parser.parse_args()
    print(f"== {args.path}, {args.members} members, {args.mode}, {args.in_flight} in flight", file=sys.stderr)
    run_for = PATHS[args.path](args)
    result = measure(run_for, args.warmup, args.duration, args.server_pid)
    result.update(path=args.path, members=args.members, mode=args.mode, in_flight=args.in_flight)
    print(json.dumps(result))
    os._exit(0)  # the gRPC channel's threads need not be joined


if __name__ == "__main__":
    main()
