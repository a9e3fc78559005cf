"""Applied exactly once under a live rebalance and a SIGKILL, through the
Python client with its default settings (BENCHMARKS.md §13, "Exactly once
under a live rebalance and a SIGKILL"; docs/sessions.md, "Delivery
guarantees").

Each run, on a fresh temporary data directory:

1. starts ``mcapi cluster local --replicas 3`` (HAProxy in front, the
   replicas' default durable store) and waits for its banner;
2. creates 150 hallway sessions through the router over REST and drives
   each from its own thread with one shared ``Client(url)``: default retry
   policy, default timeout, observations numbered by the client (``seq``).
   Each thread counts the observations acknowledged to its session.
   An observation whose call finally fails is sent again, with the same
   content, until it is acknowledged (the client then resends the same
   ``seq``), so that every observation the thread made is acknowledged once;
3. while the load runs: ``mcapi cluster rebalance --replicas 4`` (256
   shards move to ``mcapi-3``), then SIGKILL of one replica (``mcapi-(run %
   4)``; the supervisor starts it again), and the load goes on for
   ``--after-kill`` seconds. With ``--kill-during`` the replica is killed
   while shards move instead (after 1 to 200 of the 256 moves, drawn per
   run), and the rebalance, which the kill interrupts, is run again until
   it completes;
4. stops the load (each thread finishes the observation it is sending), then
   reads every session through the router: its ``next_seq`` must equal the
   observations acknowledged to it, and its ``tick`` that number less one
   (the first observation is no tick).

Per run it prints the sessions, the acknowledged observations, the retries
the client made (``client.retries``, by reason), the replays it saw (steps
with ``replayed``), the mismatches, and the calls that failed for good (to
the caller, after the client's own retries). Exits 1 if any run has a
mismatch, 2 if a run could not be carried out.

    clients/python/.venv/bin/python benches/exactly_once.py --runs 20 [--kill-during]
    make bench-exactly-once RUNS=20 [KILL_DURING=1]

The client is imported from this tree (clients/python), not from the venv's
installed copy, so the code measured is the code checked out.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "clients" / "python"))

from mcapi_client import Client, McapiError  # noqa: E402

BANNER = "Ctrl-C or SIGTERM stops everything."


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def observation(i: int) -> dict[str, Any]:
    """The i-th observation of every session: a function of i alone, so a
    resend carries the same content. The first puts the agent in state 25;
    then it steps right and left in turn, with stimuli that vary."""
    if i == 0:
        return {"state": 25}
    right = i % 2 == 1
    return {
        "state": 26 if right else 25,
        "stimulus": [(i % 7) / 10, (i % 5) / 10],
        "action_taken": "right" if right else "left",
    }


@dataclass
class Session:
    id: str
    acked: int = 0  # observations acknowledged (the next one's index)
    replays: int = 0
    failed: int = 0  # calls that raised to us (the observation then sent again)
    unsettled: bool = False  # still not acknowledged when the run gave up on it
    errors: list[str] = field(default_factory=list)


class Cluster:
    """A running ``mcapi cluster local`` on a fresh directory."""

    def __init__(self, mcapi: str, work: Path, replicas: int, serve_args: list[str]) -> None:
        self.mcapi = mcapi
        self.dir = work / "cluster"
        self.http, self.grpc = free_port(), free_port()
        self.out = work / "local.out"
        self.err = work / "local.err"
        args = [
            mcapi, "cluster", "local", "--replicas", str(replicas),
            "--http", f"127.0.0.1:{self.http}", "--grpc", f"127.0.0.1:{self.grpc}",
            "--data-dir", str(self.dir),
        ]
        if serve_args:
            args += ["--", *serve_args]
        env = {k: v for k, v in os.environ.items() if k not in ("MCAPI_SHARD_MAP", "MCAPI_REPLICA")}
        self.proc = subprocess.Popen(
            args, stdin=subprocess.DEVNULL, stdout=open(self.out, "wb"),
            stderr=open(self.err, "wb"), env=env,
        )
        deadline = time.monotonic() + 120
        while BANNER not in self.out.read_text(errors="replace"):
            if self.proc.poll() is not None:
                raise RuntimeError(f"cluster local exited ({self.proc.returncode}):\n{self.tail()}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"cluster local not up in 120 s:\n{self.tail()}")
            time.sleep(0.05)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http}"

    def tail(self) -> str:
        return "\n".join(self.err.read_text(errors="replace").splitlines()[-20:])

    def state(self) -> dict[str, Any]:
        for _ in range(50):  # read again if caught while the supervisor writes it
            try:
                state: dict[str, Any] = json.loads((self.dir / "cluster.json").read_text())
                return state
            except (OSError, ValueError):
                time.sleep(0.02)
        raise RuntimeError("cluster.json unreadable")

    def process(self, name: str) -> dict[str, Any] | None:
        return next((p for p in self.state()["processes"] if p["name"] == name), None)

    def ready(self, name: str) -> bool:
        p = self.process(name)
        if p is None or p.get("pid") is None or p.get("http") is None:
            return False
        try:
            with urllib.request.urlopen(f"http://{p['http']}/readyz", timeout=2) as r:
                return bool(r.status == 200)
        except OSError:
            return False

    def epoch(self) -> int:
        for line in (self.dir / "shards.map").read_text().splitlines():
            if line.startswith("epoch "):
                return int(line.split()[1])
        return 0

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def kill(cluster: Cluster, name: str) -> tuple[dict[str, Any], float]:
    """SIGKILL of a replica: its process entry then, and when."""
    victim = cluster.process(name)
    assert victim is not None and victim.get("pid"), f"{name} not running"
    os.kill(int(victim["pid"]), signal.SIGKILL)
    return victim, time.monotonic()


def wait_back(
    cluster: Cluster, name: str, victim: dict[str, Any], killed_at: float, back: float | None
) -> float:
    """Seconds from the kill until the supervisor had the replica running
    again and it answered ``/readyz``."""
    while back is None:
        p = cluster.process(name)
        if p and p.get("pid") not in (None, victim["pid"]) and cluster.ready(name):
            back = time.monotonic() - killed_at
        elif time.monotonic() - killed_at > 60:
            raise RuntimeError(f"{name} not back in 60 s:\n{cluster.tail()}")
        else:
            time.sleep(0.05)
    return back


@dataclass
class Run:
    run: int
    sessions: int = 0
    acked: int = 0
    retries: int = 0
    retries_by: dict[str, int] = field(default_factory=dict)
    replays: int = 0
    failed: int = 0
    failed_by: dict[str, int] = field(default_factory=dict)
    unsettled: int = 0
    mismatches: int = 0
    details: list[str] = field(default_factory=list)
    victim: str = ""
    moves: int = 0
    moves_at_kill: int | None = None
    rebalance_s: float = 0.0
    rebalance_tries: int = 0
    back_s: float | None = None
    seconds: float = 0.0


def one_run(args: argparse.Namespace, run_no: int) -> Run:
    result = Run(run_no)
    started = time.monotonic()
    work = Path(tempfile.mkdtemp(prefix="mcapi-exactly-once."))
    keep = False
    cluster = Cluster(args.mcapi, work, 3, args.serve_args)
    try:
        mc = Client(cluster.url)  # every setting at its default
        try:
            sessions = [
                Session((mc.create_session("hallway", seed=run_no * 1000 + k)).id)
                for k in range(args.sessions)
            ]
            result.sessions = len(sessions)
            stop = threading.Event()

            def drive(s: Session) -> None:
                give_up: float | None = None
                while True:
                    if stop.is_set():
                        if give_up is None:
                            give_up = time.monotonic() + args.settle
                        if time.monotonic() > give_up:
                            s.unsettled = True  # its last observation's fate is unknown
                            return
                    sent = time.monotonic()
                    try:
                        step = mc.observe(s.id, **observation(s.acked))
                    except (McapiError, OSError) as e:
                        s.failed += 1
                        code = getattr(e, "code", type(e).__name__)
                        result.failed_by[code] = result.failed_by.get(code, 0) + 1
                        took = time.monotonic() - sent
                        s.errors.append(f"observation {s.acked} after {took:.1f} s: {code}: {e}"[:300])
                        time.sleep(0.05 + random.random() * 0.05)
                        continue  # the same observation again: same content, same seq
                    s.acked += 1
                    if step.replayed:
                        s.replays += 1
                    if stop.is_set():
                        return
                    if args.pause:
                        time.sleep(args.pause)

            threads = [threading.Thread(target=drive, args=(s,), daemon=True) for s in sessions]
            for t in threads:
                t.start()
            time.sleep(args.before)

            # The rebalance to 4 replicas under load, and SIGKILL of one
            # replica (the supervisor starts it again): after the rebalance,
            # or with --kill-during while shards move (then the rebalance,
            # which the kill may interrupt, is run again until it completes).
            result.victim = f"mcapi-{run_no % 4}"
            epoch0 = cluster.epoch()
            rebalance = [args.mcapi, "cluster", "rebalance", "--data-dir", str(cluster.dir)]
            rebalance += ["--replicas", "4"]
            t0 = time.monotonic()
            # Its output goes to a file: a pipe nobody reads while it runs
            # would fill up (a line per move) and stop it.
            log = work / "rebalance.log"

            def start_rebalance() -> subprocess.Popen[bytes]:
                with open(log, "ab") as out:
                    return subprocess.Popen(rebalance, stdout=out, stderr=subprocess.STDOUT)

            reb = start_rebalance()
            if args.kill_during:
                # After a number of moves drawn per run, from 1 to 200 of 256.
                at = epoch0 + random.Random(run_no).randint(1, 200)
                while reb.poll() is None and cluster.epoch() < at:
                    if time.monotonic() - t0 > 180:
                        raise RuntimeError(f"no {at - epoch0} moves in 180 s:\n{log.read_text()[-2000:]}")
                    time.sleep(0.005)
                result.moves_at_kill = cluster.epoch() - epoch0
                victim, killed_at = kill(cluster, result.victim)
            reb.wait(300)
            tries = 1
            while reb.returncode != 0:
                if not args.kill_during or tries >= 5:
                    tail = log.read_text(errors="replace")[-2000:]
                    raise RuntimeError(f"rebalance failed ({reb.returncode}):\n{tail}")
                result.back_s = wait_back(cluster, result.victim, victim, killed_at, result.back_s)
                reb = start_rebalance()
                reb.wait(300)
                tries += 1
            result.rebalance_s = time.monotonic() - t0
            result.rebalance_tries = tries
            result.moves = cluster.epoch() - epoch0
            if not args.kill_during:
                victim, killed_at = kill(cluster, result.victim)
            result.back_s = wait_back(cluster, result.victim, victim, killed_at, result.back_s)
            while time.monotonic() - killed_at < args.after_kill:
                time.sleep(0.05)

            stop.set()
            for t in threads:
                t.join()

            # Every session: applied = acknowledged.
            for s in sessions:
                info = mc.get_session(s.id)
                result.acked += s.acked
                result.replays += s.replays
                result.failed += s.failed
                want_tick = max(s.acked - 1, 0)
                ok = info.next_seq == s.acked and info.tick == want_tick
                if s.unsettled:
                    result.unsettled += 1
                    # Its last observation may or may not have been applied.
                    ok = info.next_seq in (s.acked, s.acked + 1)
                if not ok:
                    result.mismatches += 1
                    result.details.append(
                        f"{s.id}: {s.acked} acknowledged, next_seq {info.next_seq}, tick {info.tick}, "
                        f"{s.replays} replays, {s.failed} failed calls {s.errors[-3:]}"
                    )
            for s in sessions:
                for e in s.errors:
                    result.details.append(f"{s.id} failed for good: {e}")
            result.retries = mc.retries.total
            result.retries_by = mc.retries.by_reason()
        finally:
            mc.close()
        keep = result.mismatches > 0 and args.keep_failed
    finally:
        cluster.stop()
        if keep:
            result.details.append(f"data directory and logs kept in {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    result.seconds = time.monotonic() - started
    return result


def fmt_counts(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(d.items(), key=lambda kv: -kv[1])) or "-"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mcapi", default=str(ROOT / "target" / "debug" / "mcapi"))
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--sessions", type=int, default=150)
    p.add_argument("--before", type=float, default=1.5, help="seconds of load before the rebalance")
    p.add_argument("--after-kill", type=float, default=4.0, help="seconds of load after the kill")
    p.add_argument("--pause", type=float, default=0.0, help="seconds each session waits between observations")
    p.add_argument("--settle", type=float, default=30.0,
                   help="seconds a session may take to get its last observation acked once the load stops")
    p.add_argument("--kill-during", action="store_true",
                   help="kill the replica while shards move (after 1 to 200 moves), not after the rebalance")
    p.add_argument("--json", type=Path, help="write every run's numbers here")
    p.add_argument("--keep-failed", action="store_true",
                   help="keep the data directory of a run with a mismatch")
    p.add_argument("serve_args", nargs="*", help="after --: extra `mcapi serve` flags for every replica")
    args = p.parse_args()
    if shutil.which("haproxy") is None and not Path("/usr/sbin/haproxy").exists():
        print("exactly_once.py needs haproxy (apt-get install haproxy)", file=sys.stderr)
        return 2

    when = "during the rebalance" if args.kill_during else "after the rebalance"
    print(f"# exactly once: {args.runs} runs, {args.sessions} sessions, SIGKILL {when}, {args.mcapi}",
          flush=True)
    print("| run | sessions | acked | client retries (by reason) | replays | mismatches | failed for good "
          "| victim, back after | rebalance | run |", flush=True)
    print("|---|---|---|---|---|---|---|---|---|---|", flush=True)
    results: list[Run] = []
    for n in range(1, args.runs + 1):
        try:
            r = one_run(args, n)
        except Exception as e:  # a run that could not be carried out
            print(f"run {n} could not be carried out: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
            return 2
        results.append(r)
        back = f"{r.back_s:.1f} s" if r.back_s is not None else "?"
        if r.moves_at_kill is not None:
            back += f", killed after move {r.moves_at_kill}"
        tries = f" in {r.rebalance_tries} tries" if r.rebalance_tries > 1 else ""
        print(
            f"| {n} | {r.sessions} | {r.acked} | {r.retries} ({fmt_counts(r.retries_by)}) | {r.replays} "
            f"| **{r.mismatches}** | {r.failed} ({fmt_counts(r.failed_by)}) | {r.victim}, {back} "
            f"| {r.moves} moves{tries}, {r.rebalance_s:.1f} s | {r.seconds:.0f} s |",
            flush=True,
        )
        if r.unsettled:
            print(f"  {r.unsettled} sessions with an unsettled last observation", flush=True)
        for d in r.details:
            print(f"  {d}", flush=True)
    bad = [r.run for r in results if r.mismatches]
    print(
        f"\ntotal: {sum(r.acked for r in results)} acknowledged observations, "
        f"{sum(r.retries for r in results)} client retries, {sum(r.replays for r in results)} replays, "
        f"{sum(r.mismatches for r in results)} mismatches (runs with one: {bad or 'none'}), "
        f"{sum(r.failed for r in results)} calls failed for good, "
        f"{sum(r.unsettled for r in results)} unsettled",
        flush=True,
    )
    if args.json:
        args.json.write_text(json.dumps([r.__dict__ for r in results], indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
