#!/usr/bin/env python3
"""/healthz latency while the most expensive legal requests, hostile ones
and hundreds of half-open connections are in flight (BENCHMARKS.md section 5).

    python3 benches/hostile_load.py [--bin target/release/mcapi] [--seconds 20]
        [--only half-open|pvf|curiosity|values|builds|numerics|ids|groups]

Starts `mcapi serve` (redb in a temporary directory, default limits), then:

1. idle: probes /healthz every 20 ms on a fresh connection for a few seconds
   (the baseline of the same run);
2. load: keeps 400 half-open connections (a request line and one header,
   never finished; reopened when the server drops one), and workers that
   loop over the most expensive requests the default limits allow:
   - `pvf`: creating sessions on distinct 760-800-state chains with a
     30-PVF basis (a dense eigendecomposition each; distinct models defeat
     the cache), then deleting them (4 clients);
   - `curiosity`: batches of curiosity signal samples on a session with
     `signal_dim` 16 (the largest whose estimated tick fits `--max-tick-us`):
     an eigendecomposition of a 152x152 matrix per sample;
   - `values`: `values?include=all` and full history on a 200,000-pair
     session;
   and over the requests the server's defences refuse or cut short:
   - `builds`: creates on distinct 1,950-2,050-state rings (one action) with
     150 PVFs, 2.5-3 s of sparse eigensolver each on an idle server, from a
     client that gives up after 0.5 s (the server stops the abandoned build:
     `mcapi_builds_stopped_total{reason="abandoned"}`); and creates on a
     10,000-state ring with 550 PVFs, estimated past `--max-build-ms`, which
     must be refused at once with 413 `limit_exceeded`;
   - `numerics`: creates with numbers a session cannot compute with
     (priorities 5e-324, `optimistic_sd` 1e308, ridge 5e-324 or 1e308,
     curiosity `gain`/`clip` 1e308, custom bases such as [[1e200, 0], [0, 1]]
     or linearly dependent ones, 1e309, NaN, -Infinity): each must be 400;
   - `ids`: every session and group route on ids of a foreign shard
     (`s0400.…`, `sffff.…`) or malformed (`sffff.x`, `%00%ff`, a 3,000-byte
     ULID, ...): each must be 404 or 400 with a JSON `{code, message}`;
   - `groups`: creating a hallway group of 1,000 members, one columnar step,
     21 malformed steps (wrong column lengths, ragged rows, NaN as a string
     and as a bare token, 1e309, bad masks, unknown states, ...; each must be
     4xx), a second step, deleting the group; and malformed group creations
     (n = 0, -1, 10,001, 10^30, `agent.seed`, priorities 5e-324);
   while the prober goes on.

Prints p50/p99/max of /healthz for both phases, their ratio, the work done
(answers counted by kind and status, and the slowest refusal of each hostile
kind as this process saw it), the server's RSS at start, under load and
after, the `mcapi_builds_stopped_total` and `mcapi_panics_total` counters,
the server's own latency histogram of the refused creates and group steps
(this process's GIL inflates what its threads measure), and, loudly
(`!!!`), every 5xx count and every wrong answer with the request that
reproduces it. Only the standard library is used.
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
    """`body` is JSON-encoded, or sent as it is when it is bytes."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        data = body if body is None or isinstance(body, bytes) else json.dumps(body).encode()
        headers = {"content-type": "application/json"} if data else {}
        conn.request(method, path, body=data, headers=headers)
        resp = conn.getresponse()
        text = resp.read()
        if text.startswith((b"{", b"[")):
            try:
                return resp.status, json.loads(text)
            except ValueError:
                pass
        return resp.status, text
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


LOCK = threading.Lock()


def bump(counts: dict, key: str, by: int = 1) -> None:
    with LOCK:
        counts[key] = counts.get(key, 0) + by


def slowest(counts: dict, key: str, seconds: float) -> None:
    """Keeps the slowest answer of a kind of refusal, in ms."""
    with LOCK:
        counts[key] = max(counts.get(key, 0.0), round(seconds * 1000, 1))


def finding(findings: list, what: str, method: str, path: str, body, status, reply) -> None:
    """A request the server answered wrongly: kept with what reproduces it."""
    sent = body if isinstance(body, bytes) else json.dumps(body).encode() if body is not None else b""
    with LOCK:
        if len(findings) < 50:
            findings.append({"what": what, "request": f"{method} {path}",
                             "body": sent[:300].decode("utf-8", "replace") + ("..." if len(sent) > 300 else ""),
                             "status": status, "reply": str(reply)[:300]})


def ring(states: int, k: int) -> dict:
    """A ring of one action with `k` proto-value functions: its eigenvalues
    crowd together, so the sparse eigensolver takes long on it."""
    return {"states": states, "actions": ["go"], "stimuli": ["x"],
            "next": [[(s + 1) % states] for s in range(states)],
            "basis": {"kind": "proto_value", "k": k}}


def is_error_json(reply) -> bool:
    return (isinstance(reply, dict) and isinstance(reply.get("code"), str)
            and isinstance(reply.get("message"), str))


def abandon_worker(port: int, stop: threading.Event, counts: dict, findings: list, seed: int):
    """Creates on distinct 1,950-2,050-state rings with 150 PVFs (about a
    second of eigensolver each) and gives up after 0.5 s: the server must
    stop the abandoned build (`mcapi_builds_stopped_total{reason="abandoned"}`)."""
    rng = random.Random(seed)
    while not stop.is_set():
        body = json.dumps({"model": ring(rng.randint(1950, 2050), 150)}).encode()
        try:
            status, reply = request(port, "POST", "/v1/sessions", body, timeout=0.5)
        except TimeoutError:
            bump(counts, "abandoned create gave up")
            continue
        except OSError as e:
            bump(counts, f"abandoned create {type(e).__name__}")
            continue
        bump(counts, f"abandoned create {status}")
        if status == 201:
            request(port, "DELETE", f"/v1/sessions/{reply['id']}")
        elif status >= 500 and not (status == 503 and is_error_json(reply)
                                     and reply["code"] == "unavailable"):
            finding(findings, "abandoned-build create", "POST", "/v1/sessions", body, status, reply)


def over_budget_worker(port: int, stop: threading.Event, counts: dict, findings: list):
    """Creates on a 10,000-state ring with 550 PVFs (estimated past
    `--max-build-ms`): each must be refused at once, 413 `limit_exceeded`
    naming the flag."""
    body = json.dumps({"model": ring(10_000, 550)}).encode()
    while not stop.is_set():
        t = time.perf_counter()
        try:
            status, reply = request(port, "POST", "/v1/sessions", body, timeout=60)
        except OSError as e:
            bump(counts, f"over-budget create {type(e).__name__}")
            continue
        slowest(counts, "over-budget slowest ms", time.perf_counter() - t)
        bump(counts, f"over-budget create {status}")
        if status == 201:
            request(port, "DELETE", f"/v1/sessions/{reply['id']}")
        if not (status == 413 and is_error_json(reply) and reply["code"] == "limit_exceeded"
                and "--max-build-ms" in reply["message"]):
            finding(findings, "over-budget create not refused by --max-build-ms",
                    "POST", "/v1/sessions", body, status, reply)
        time.sleep(0.05)


def custom_model(rows) -> dict:
    return {"states": 2, "actions": ["go", "stay"], "stimuli": ["x"], "next": [[1, 0], [0, 1]],
            "basis": {"kind": "custom", "state_features": rows}}


def numeric_cases() -> list:
    hallway = {"preset": "hallway"}

    def curious(params):
        return {"curiosity": {"signal_dim": 2, "params": params}}

    cases = [{"model": hallway, "agent": agent} for agent in (
        {"priorities": [5e-324, 1]},
        {"priorities": [1e-200, 1]},
        {"priorities": [-0.0, 1]},
        {"optimistic_sd": 1e308},
        {"optimistic_sd": 1e13},
        {"ridge": 5e-324},
        {"ridge": 1e308},
        {"gamma": 1.0},
        curious({"gain": 1e308}),
        curious({"gain": 1e308, "clip": 1e308}),
        curious({"clip": 1e308}),
        curious({"gain": 0.0}),
    )]
    cases += [{"model": custom_model(rows)} for rows in (
        [[1e200, 0], [0, 1]],
        [[1e100, 1], [1, 1e-100]],
        [[1e6, 0], [0, 1]],
        [[1, 2], [2, 4]],
        [[5e-324, 0], [0, 5e-324]],
    )]
    # Conditioned well enough, but its first policy update fails at this discount.
    cases.append({"model": custom_model([[1e6, 0], [0, 1e2]]), "agent": {"gamma": 0.999999, "seed": 1}})
    bodies = [json.dumps(c).encode() for c in cases]
    # Numbers JSON can write but a double cannot hold, and JSON that is not.
    bodies += [b'{"model": {"preset": "hallway"}, "agent": {"optimistic_sd": 1e309}}',
               b'{"model": {"preset": "hallway"}, "agent": {"priorities": [1e-400, 1]}}',
               b'{"model": {"preset": "hallway"}, "agent": {"eta": NaN}}',
               b'{"model": {"preset": "hallway"}, "agent": {"ridge": -Infinity}}',
               b'{"model": {"preset": "hallway"}, "agent": {"optimistic_sd": "1e308"}}']
    return bodies


def numerics_worker(port: int, stop: threading.Event, counts: dict, findings: list):
    """Creates whose numbers a session cannot compute with: each must be
    400 at once."""
    bodies = numeric_cases()
    while not stop.is_set():
        for body in bodies:
            t = time.perf_counter()
            try:
                status, reply = request(port, "POST", "/v1/sessions", body, timeout=60)
            except OSError as e:
                bump(counts, f"numeric create {type(e).__name__}")
                continue
            kind = "custom-basis" if b'"custom"' in body else "agent"
            slowest(counts, f"numeric {kind} slowest ms", time.perf_counter() - t)
            bump(counts, f"numeric create {status}")
            if status == 201:
                request(port, "DELETE", f"/v1/sessions/{reply['id']}")
            if status != 400 or not is_error_json(reply):
                finding(findings, "numeric edge case not refused 400", "POST", "/v1/sessions",
                        body, status, reply)
        time.sleep(0.02)


FOREIGN_IDS = [
    "s0400.01J0000000000000000000000",   # shard 1024: beyond the 1024 shards
    "sffff.01J0000000000000000000000",
    "sffff.x",
    "s03ff.01J0000000000000000000000",   # a shard of this server, no such session
    "s0000.g01J0000000000000000000000",  # a group's id on a session's route
    "%00%ff",
    "%ff%fe%fd",
    "s0001.%2e%2e%2f%2e%2e",
    "s-001.01J0000000000000000000000",
    "S0001.01J0000000000000000000000",
    "s0001." + "Z" * 3000,
    "s0400.g01J0000000000000000000000",
]


def ids_worker(port: int, stop: threading.Event, counts: dict, findings: list):
    """Every route of sessions and groups on ids of a foreign shard or
    malformed: each must be 404 or 400 with a JSON `{code, message}`."""
    routes = [("GET", "/v1/sessions/{}", None),
              ("POST", "/v1/sessions/{}/observations", {"state": 0}),
              ("POST", "/v1/sessions/{}/observations", {"observations": [{"state": 0}]}),
              ("GET", "/v1/sessions/{}/values?include=all", None),
              ("GET", "/v1/sessions/{}/history", None),
              ("DELETE", "/v1/sessions/{}", None),
              ("GET", "/v1/groups/{}", None),
              ("POST", "/v1/groups/{}/steps", {"states": [0]}),
              ("DELETE", "/v1/groups/{}", None)]
    while not stop.is_set():
        for sid in FOREIGN_IDS:
            for method, route, body in routes:
                path = route.format(sid)
                try:
                    status, reply = request(port, method, path, body, timeout=60)
                except OSError as e:
                    bump(counts, f"ids {type(e).__name__}")
                    finding(findings, f"foreign/malformed id: {e!r}", method, path, body, None, None)
                    continue
                bump(counts, f"ids {status}")
                if status not in (400, 404) or not is_error_json(reply):
                    bump(counts, "ids wrong answer")
                    finding(findings, "foreign/malformed id not 404/400 with a JSON error",
                            method, path, body, status, reply)
        time.sleep(0.02)


def bad_group_steps(n: int) -> list:
    zero = [[0, 0]] * n
    states = [25] * n
    nan_rows = ", ".join(["[NaN, 0]"] * n).encode()
    return [
        {"states": [25] * (n - 1), "stimuli": zero},                     # short column
        {"states": states, "stimuli": [[0, 0]] * (n - 1) + [[0]]},       # ragged row
        {"states": states, "stimuli": [[0, 0, 0]] * n},                  # too many dimensions
        {"states": states, "stimuli": [["NaN", 0]] * n},                 # NaN as a string
        b'{"states": [' + b", ".join([b"25"] * n) + b'], "stimuli": [' + nan_rows + b"]}",  # NaN token
        b'{"states": [25], "stimuli": [[1e309, 0]], "mask": [0]}',       # overflows a double
        {"states": states, "stimuli": [[1e13, 0]] * n},                  # beyond the stimulus limit
        {"mask": [5, 3], "states": [25, 25], "stimuli": [[0, 0]] * 2},    # mask goes down
        {"mask": [0, 0], "states": [25, 25], "stimuli": [[0, 0]] * 2},    # mask repeats
        {"mask": [n], "states": [25], "stimuli": [[0, 0]]},              # mask beyond N
        {"mask": [2 ** 32], "states": [25], "stimuli": [[0, 0]]},
        {"states": [50] * n, "stimuli": zero},                           # unknown state
        {"states": [-1] * n, "stimuli": zero},
        {"states": [2.5] * n, "stimuli": zero},
        {"states": states, "stimuli": zero, "action_taken": [4294967295] * n},
        {"states": states, "stimuli": zero, "action_taken": [0] * (n + 1)},
        {"states": states, "stimuli": zero, "seqs": [0, 1, 2]},
        {"states": states, "stimuli": zero, "seqs": [2 ** 64] * n},
        {"states": states, "stimuli": zero, "extra": 1},
        {"states": "25"},
        {"observations": [[0.0]] * n},                                   # continuous column, discrete model
    ]


def groups_worker(port: int, stop: threading.Event, counts: dict, findings: list, seed: int):
    """Creates a hallway group of 1,000 members, steps it by columns, sends
    it malformed steps (each must be 4xx, nothing applied), steps it again
    and deletes it; and a few malformed creations."""
    n = 1000
    bad = bad_group_steps(n)
    bad_creates = [{"model": {"preset": "hallway"}, "n": 0},
                   {"model": {"preset": "hallway"}, "n": 10 ** 30},
                   {"model": {"preset": "hallway"}, "n": 10_001},
                   {"model": {"preset": "hallway"}, "n": 2, "agent": {"seed": 1}},
                   {"model": {"preset": "hallway"}, "n": 2, "agent": {"priorities": [5e-324, 1]}},
                   {"model": {"preset": "hallway"}, "n": -1}]
    rng = random.Random(seed)

    def call(method, path, body, kind, ok):
        try:
            status, reply = request(port, method, path, body, timeout=120)
        except OSError as e:
            bump(counts, f"{kind} {type(e).__name__}")
            finding(findings, f"{kind}: {e!r}", method, path, body, None, None)
            return None, None
        bump(counts, f"{kind} {status}")
        if not ok(status, reply):
            finding(findings, f"{kind}: unexpected answer", method, path, body, status, reply)
        return status, reply

    while not stop.is_set():
        status, group = call("POST", "/v1/groups", {"model": {"preset": "hallway"}, "n": n,
                                                    "seed": rng.randrange(2 ** 32)},
                             "group create", lambda s, r: s == 201)
        if status != 201:
            time.sleep(0.5)
            continue
        gid = group["id"]
        steps = f"/v1/groups/{gid}/steps"
        call("POST", steps, {"states": [25] * n}, "group step", lambda s, r: s == 200)
        for body in bad:
            call("POST", steps, body, "group bad step",
                 lambda s, r: 400 <= s < 500 and is_error_json(r))
        call("POST", steps, {"states": [rng.choice([24, 26]) for _ in range(n)],
                             "stimuli": [[rng.random(), 0.0] for _ in range(n)]},
             "group step", lambda s, r: s == 200 and isinstance(r, dict) and not r.get("errors"))
        call("DELETE", f"/v1/groups/{gid}", None, "group delete", lambda s, r: s == 204)
        for body in bad_creates:
            call("POST", "/v1/groups", body, "group bad create",
                 lambda s, r: 400 <= s < 500 and is_error_json(r))


def metrics_text(port: int) -> str:
    try:
        _, text = request(port, "GET", "/metrics", timeout=10)
    except OSError as e:
        return f"# /metrics: {e!r}"
    return text.decode("utf-8", "replace") if isinstance(text, bytes) else str(text)


def server_latency(text: str, method: str, route: str, status: int) -> str | None:
    """The server's own latency histogram of one route and status (the load
    process's GIL inflates what its threads measure): how many answers, and
    how many within 10 ms, 100 ms and 1 s."""
    labels = f'method="{method}",route="{route}",status="{status}"'
    buckets = {}
    for line in text.splitlines():
        if line.startswith("mcapi_http_request_duration_seconds_bucket{" + labels + ",le="):
            le = line.split('le="')[1].split('"')[0]
            buckets[le] = int(float(line.rsplit(" ", 1)[1]))
    if not buckets:
        return None
    top = max((float(le), le) for le in buckets if le != "+Inf")
    worst = min((float(le) for le in buckets if le != "+Inf" and buckets[le] == buckets["+Inf"]),
                default=float("inf"))
    return (f"{method} {route} {status}: n={buckets['+Inf']}, "
            f"{buckets.get('0.01', '?')} within 10 ms, {buckets.get('0.1', '?')} within 100 ms, "
            f"{buckets.get('1', '?')} within 1 s, all within {worst:g} s"
            if worst != float("inf") else
            f"{method} {route} {status}: n={buckets['+Inf']}, {buckets[top[1]]} within {top[0]:g} s")


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
    ap.add_argument("--only", choices=["half-open", "pvf", "curiosity", "values",
                                       "builds", "numerics", "ids", "groups"],
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
            findings: list[dict] = []
            kinds = {
                "half-open": [(half_open, (port, args.half_open, stop, counts))],
                "pvf": [(pvf_worker, (port, stop, counts, i)) for i in range(4)],
                "curiosity": [(curiosity_worker, (port, stop, counts))],
                "values": [(values_worker, (port, stop, counts))],
                "builds": [(abandon_worker, (port, stop, counts, findings, 10)),
                           (over_budget_worker, (port, stop, counts, findings))],
                "numerics": [(numerics_worker, (port, stop, counts, findings))],
                "ids": [(ids_worker, (port, stop, counts, findings))],
                "groups": [(groups_worker, (port, stop, counts, findings, 20))],
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
            crashed = server.poll()
            text = metrics_text(port)
            metrics = [line for line in text.splitlines()
                       if line.startswith(("mcapi_builds_stopped_total", "mcapi_panics_total"))]
            latencies = [x for x in (server_latency(text, "POST", "/v1/sessions", 400),
                                     server_latency(text, "POST", "/v1/sessions", 413),
                                     server_latency(text, "POST", "/v1/groups/{id}/steps", 400))
                         if x]
        finally:
            server.terminate()
            server.wait(timeout=60)
    print(summary("healthz idle  ", idle))
    print(summary("healthz loaded", loaded))
    print(f"p99 loaded / idle: {pct(loaded, 99) / pct(idle, 99):.1f}x; "
          f"probe failures: {idle_failures} idle, {failures} loaded")
    print("work:", json.dumps(counts, sort_keys=True))
    print(f"RSS: start {rss_start >> 20} MiB, under load {rss_peak >> 20} MiB, after {rss_end >> 20} MiB")
    print("metrics:", "; ".join(metrics) or "no builds stopped, no panics")
    for line in latencies:
        print("server-side latency,", line)
    if crashed is not None:
        print(f"!!! FINDING: the server exited with status {crashed} during the load")
    fives = sorted(k for k, v in counts.items() if v and k.split()[-1].startswith("5"))
    if fives:
        print("!!! 5xx answers:", ", ".join(f"{k}: {counts[k]}" for k in fives))
    for f in findings:
        print("!!! FINDING:", json.dumps(f))
    if findings:
        print(f"!!! {len(findings)} findings (at most 50 kept)")


if __name__ == "__main__":
    main()
