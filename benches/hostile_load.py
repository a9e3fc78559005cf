#!/usr/bin/env python3
"""/healthz latency while the most expensive legal requests and hundreds of
half-open connections are in flight (BENCHMARKS.md section 6).

    python3 benches/hostile_load.py [--bin target/release/mcapi] [--seconds 20]

Starts `mcapi serve` (redb in a temporary directory, default limits), then:

1. idle: probes /healthz every 20 ms on a fresh connection for a few seconds
   (the baseline of the same run);
2. load: keeps 400 half-open connections (a request line and one header,
   never finished; reopened when the server drops one), and workers that
   loop over the most expensive requests the default limits allow:
   - creating sessions on distinct 800-state chains with a 30-PVF basis
     (a dense eigendecomposition each; distinct models defeat the cache),
     then deleting them;
   - batches of curiosity signal samples on a session with `signal_dim` 16
     (the largest whose estimated tick fits `--max-tick-us`): an
     eigendecomposition of a 152x152 matrix per sample;
   - `values?include=all` and full history on a 200,000-pair session;
   while the prober goes on.

Prints p50/p99/max of /healthz for both phases, their ratio, the work done,
and the server's RSS before and after. Only the standard library is used.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def request(port: int, method: str, path: str, body=None, timeout=120.0):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        data = None if body is None else json.dumps(body).encode()
        headers = {"content-type": "application/json"} if data else {}
        conn.request(method, path, body=data, headers=headers)
        resp = conn.getresponse()
        text = resp.read()
        return resp.status, (json.loads(text) if text.startswith((b"{", b"[")) else text)
    finally:
        conn.close()


def rss(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


def chain(states: int, k: int | None = None) -> dict:
    nxt = [[max(s - 1, 0), min(s + 1, states - 1)] for s in range(states)]
    model = {"states": states, "actions": ["left", "right"], "stimuli": ["a", "b"], "next": nxt}
    model["basis"] = {"kind": "proto_value", "k": k} if k else {"kind": "indicator"}
    return model


def probe(port: int, seconds: float) -> None:
    """The prober's own process (`--probe`): the load's threads hold this
    process's GIL while they decode large answers, which would show up as
    /healthz latency if the prober ran among them. Prints the samples."""
    samples, failures = [], 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t = time.perf_counter()
        try:
            status, _ = request(port, "GET", "/healthz", timeout=10)
            if status == 200:
                samples.append(time.perf_counter() - t)
            else:
                failures += 1
        except OSError:
            failures += 1
        time.sleep(0.02)
    print(json.dumps({"samples": samples, "failures": failures}))


def run_probe(port: int, seconds: float) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, __file__, "--probe", str(port), "--seconds", str(seconds)],
        stdout=subprocess.PIPE, text=True)


def probe_result(proc: subprocess.Popen) -> tuple[list[float], int]:
    out, _ = proc.communicate(timeout=600)
    d = json.loads(out)
    return d["samples"], d["failures"]


def half_open(port: int, n: int, stop: threading.Event, counts: dict):
    socks: list[socket.socket] = []

    def one():
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.sendall(b"GET /v1/sessions HTTP/1.1\r\nHost: slow\r\n")
        s.setblocking(False)
        return s

    while not stop.is_set():
        alive = []
        for s in socks:
            try:
                # Readable means the server answered (a timeout) or closed.
                s.recv(1, socket.MSG_PEEK)
                counts["dropped"] += 1
                s.close()
            except BlockingIOError:
                alive.append(s)
            except OSError:
                counts["dropped"] += 1
                s.close()
        socks = alive
        while len(socks) < n and not stop.is_set():
            try:
                socks.append(one())
                counts["opened"] += 1
            except OSError:
                counts["refused"] += 1
                break
        counts["open_now"] = len(socks)
        time.sleep(0.2)
    for s in socks:
        s.close()


def pvf_worker(port: int, stop: threading.Event, counts: dict, seed: int):
    rng = random.Random(seed)
    while not stop.is_set():
        states = rng.randint(760, 800)
        status, body = request(port, "POST", "/v1/sessions", {"model": chain(states, 30)})
        counts[f"pvf create {status}"] = counts.get(f"pvf create {status}", 0) + 1
        if status == 201:
            request(port, "DELETE", f"/v1/sessions/{body['id']}")


def curiosity_worker(port: int, stop: threading.Event, counts: dict):
    status, body = request(port, "POST", "/v1/sessions",
                           {"model": {"preset": "hallway"},
                            "agent": {"seed": 1, "curiosity": {"signal_dim": 16}}})
    assert status == 201, body
    sid = body["id"]
    request(port, "POST", f"/v1/sessions/{sid}/observations", {"state": 0})
    rng = random.Random(2)
    state = 0
    while not stop.is_set():
        batch = []
        for _ in range(50):
            state = min(max(state + rng.choice([-1, 1]), 0), 49)
            batch.append({"state": state, "stimulus": [0.0, 0.0],
                          "signal": [rng.uniform(-1, 1) for _ in range(16)]})
        status, _ = request(port, "POST", f"/v1/sessions/{sid}/observations", {"observations": batch})
        counts[f"curious batch {status}"] = counts.get(f"curious batch {status}", 0) + 1
        if status != 200:
            break


def values_worker(port: int, stop: threading.Event, counts: dict):
    status, body = request(port, "POST", "/v1/sessions", {"model": chain(100_000)})
    assert status == 201, body
    sid = body["id"]
    request(port, "POST", f"/v1/sessions/{sid}/observations", {"state": 0})
    while not stop.is_set():
        status, _ = request(port, "GET", f"/v1/sessions/{sid}/values?include=all")
        counts[f"values all {status}"] = counts.get(f"values all {status}", 0) + 1
        request(port, "GET", f"/v1/sessions/{sid}/history")


def pct(xs: list[float], p: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(p / 100 * (len(xs) - 1))))] * 1000


def summary(name: str, xs: list[float]) -> str:
    return (f"{name}: n={len(xs)} p50={pct(xs, 50):.2f} ms p99={pct(xs, 99):.2f} ms "
            f"max={max(xs) * 1000:.2f} ms mean={statistics.mean(xs) * 1000:.2f} ms")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default=str(ROOT / "target/release/mcapi"))
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--idle-seconds", type=float, default=5.0)
    ap.add_argument("--half-open", type=int, default=400)
    ap.add_argument("--only", choices=["half-open", "pvf", "curiosity", "values"],
                    help="run one kind of load only (to find what slows /healthz)")
    ap.add_argument("--probe", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.probe:
        probe(args.probe, args.seconds)
        return
    port, grpc = free_port(), free_port()
    with tempfile.TemporaryDirectory() as data:
        server = subprocess.Popen(
            [args.bin, "serve", "--http", f"127.0.0.1:{port}", "--grpc", f"127.0.0.1:{grpc}",
             "--data-dir", data, "--log-format", "json"],
            stdout=subprocess.DEVNULL, stderr=open(os.path.join(data, "log"), "w"))
        try:
            for _ in range(500):
                try:
                    if request(port, "GET", "/readyz", timeout=1)[0] == 200:
                        break
                except OSError:
                    pass
                time.sleep(0.02)
            rss_start = rss(server.pid)
            idle, idle_failures = probe_result(run_probe(port, args.idle_seconds))

            stop = threading.Event()
            counts = {"opened": 0, "dropped": 0, "refused": 0, "open_now": 0}
            kinds = {
                "half-open": [(half_open, (port, args.half_open, stop, counts))],
                "pvf": [(pvf_worker, (port, stop, counts, i)) for i in range(4)],
                "curiosity": [(curiosity_worker, (port, stop, counts))],
                "values": [(values_worker, (port, stop, counts))],
            }
            threads = [threading.Thread(target=f, args=a, daemon=True)
                       for kind, work in kinds.items() if args.only in (None, kind)
                       for f, a in work]
            for t in threads:
                t.start()
            time.sleep(2)  # the half-open connections are open, the work under way
            loaded, failures = probe_result(run_probe(port, args.seconds))
            rss_peak = rss(server.pid)
            stop.set()
            for t in threads:
                t.join(timeout=180)
            rss_end = rss(server.pid)
        finally:
            server.terminate()
            server.wait(timeout=60)
    print(summary("healthz idle  ", idle))
    print(summary("healthz loaded", loaded))
    print(f"p99 loaded / idle: {pct(loaded, 99) / pct(idle, 99):.1f}x; "
          f"probe failures: {idle_failures} idle, {failures} loaded")
    print("work:", json.dumps(counts, sort_keys=True))
    print(f"RSS: start {rss_start >> 20} MiB, under load {rss_peak >> 20} MiB, after {rss_end >> 20} MiB")


if __name__ == "__main__":
    main()
