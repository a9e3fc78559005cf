#!/usr/bin/env python3
"""Recovery time of a continuous world's session after kill -9, with and
without snapshots, on the same binary.

One lockstep session on the unit square (four moves, three stimuli, 8 x 8
RBFs x 4 actions, the default basis of d = 2 before the grid planner, named
here so that the numbers stay comparable) takes OBS observations over REST in
batches, the server is killed with SIGKILL, and a new server on the same
data directory recovers it. The time reported is the server's own
("sessions recovered" line, `seconds`), beside the entries it replayed.
Two rows, interleaved over ROUNDS rounds:

- `--snapshot-every 1000` (the default): a snapshot every 1000 observations;
  recovery restores the newest and replays the log after it;
- `--snapshot-every 1000000000`: no snapshot before the kill, so recovery
  replays the whole log, as every continuous session did before snapshots.

    python3 benches/continuous_recovery.py target/release/mcapi [--obs N] [--rounds R]

Used by BENCHMARKS.md section 12 ("Snapshots of continuous sessions").
"""

import argparse
import json
import math
import os
import signal
import socket
import subprocess
import tempfile
import time
import urllib.request


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def call(base: str, method: str, path: str, body: object | None = None) -> object:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        base + path, data=data, method=method, headers={"content-type": "application/json"}
    )
    with urllib.request.urlopen(req, timeout=600) as r:
        return json.loads(r.read() or b"null")


def start(binary: str, data: str, every: int, log: str) -> tuple[subprocess.Popen, str]:
    http, grpc = free_port(), free_port()
    proc = subprocess.Popen(
        [binary, "serve", "--http", f"127.0.0.1:{http}", "--grpc", f"127.0.0.1:{grpc}",
         "--data-dir", data, "--snapshot-every", str(every), "--log-format", "json"],
        stdout=open(log, "w"), stderr=subprocess.STDOUT,
    )
    base = f"http://127.0.0.1:{http}"
    deadline = time.time() + 900
    while time.time() < deadline:
        try:
            urllib.request.urlopen(base + "/readyz", timeout=5)
            return proc, base
        except OSError:
            time.sleep(0.05)
    proc.kill()
    raise SystemExit(f"the server on {data} did not get ready; see {log}")


def recovered(log: str) -> dict:
    for line in open(log):
        if "sessions recovered" in line:
            return json.loads(line)["fields"]
    raise SystemExit(f"no 'sessions recovered' line in {log}")


def drive(base: str, n: int) -> None:
    model = {
        "observation_space": {"low": [0, 0], "high": [1, 1]},
        "actions": ["north", "south", "east", "west"],
        "stimuli": ["a", "b", "c"],
        "basis": {"kind": "rbf", "centres_per_dim": 8},
    }
    sid = call(base, "POST", "/v1/sessions", {"model": model, "agent": {"seed": 1}})["id"]
    x, action, sent = [0.5, 0.5], None, 0
    sources = [(0.1, 0.1), (0.9, 0.1), (0.5, 0.9)]
    while sent < n:
        # One observation at a time: lockstep's next action depends on the reply.
        if action is not None:
            dx, dy = [(0, 0.02), (0, -0.02), (0.02, 0), (-0.02, 0)][action]
            x = [min(1.0, max(0.0, x[0] + dx)), min(1.0, max(0.0, x[1] + dy))]
        obs: dict = {"observation": x}
        if sent > 0:
            obs["stimulus"] = [6.0 if math.dist(x, s) < 0.04 else 0.0 for s in sources]
        step = call(base, "POST", f"/v1/sessions/{sid}/observations", obs)
        action = step["action_index"]
        sent += 1


def row(binary: str, every: int, n: int, tmp: str, tag: str) -> dict:
    data = tempfile.mkdtemp(dir=tmp, prefix=f"{tag}-")
    proc, base = start(binary, data, every, os.path.join(tmp, f"{tag}-first.log"))
    drive(base, n)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    log = os.path.join(tmp, f"{tag}-second.log")
    proc, _ = start(binary, data, every, log)
    out = recovered(log)
    proc.send_signal(signal.SIGTERM)
    proc.wait()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("binary")
    ap.add_argument("--obs", type=int, default=6000, help="observations before the kill")
    ap.add_argument("--rounds", type=int, default=2)
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="mcapi-continuous-recovery-")
    print(f"{a.obs} observations, then kill -9 and a recovery; logs in {tmp}\n")
    print("| round | `--snapshot-every` | entries replayed | recovery (s) |")
    print("|---|---|---|---|")
    for r in range(1, a.rounds + 1):
        for every in [1000, 1_000_000_000]:
            out = row(a.binary, every, a.obs, tmp, f"r{r}-{every}")
            print(f"| {r} | {every} | {out['replayed']} | {out['seconds']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
