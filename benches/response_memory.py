#!/usr/bin/env python3
"""Peak memory of the server under concurrent maximal value-table responses
(BENCHMARKS.md section 5).

    python3 benches/response_memory.py [--bin target/release/mcapi] [--clients 20]

For each configuration, in one run: starts `mcapi serve` (redb in a temporary
directory), creates one session whose `values?include=all` is tens of MB
(a 100 x 100 open grid with 40 sources, on a one-feature custom basis so it
is cheap to build), then has `--clients` threads each GET it at once,
retrying a 503 `responses_busy` after its Retry-After, until every client has
read one whole response. Prints the response size, the server's peak RSS
(VmHWM) above its RSS before the load, the number of 503s and the wall time.

Configurations: the default budget (`--max-response-bytes-total`, 256 MiB)
and, as the baseline, a budget so large that it never refuses (the server
before the budget existed). Only the standard library is used.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MARKS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMN"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def status_kib(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def model() -> dict:
    width, height = 100, 100
    rows = ["#" * (width + 2)]
    for r in range(height):
        row = ["."] * width
        if r % 10 == 0:
            for j in range(4):
                i = r // 10 * 4 + j
                row[j * 25] = MARKS[i]
        rows.append("#" + "".join(row) + "#")
    rows.append("#" * (width + 2))
    return {
        "grid": rows,
        "sources": {m: i for i, m in enumerate(MARKS)},
        "basis": {"kind": "custom", "state_features": [[1.0]] * (width * height)},
    }


def call(port: int, method: str, path: str, body=None, timeout=300.0):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        data = None if body is None else json.dumps(body).encode()
        headers = {"content-type": "application/json"} if data else {}
        conn.request(method, path, body=data, headers=headers)
        r = conn.getresponse()
        return r.status, r.getheader("retry-after"), r.read()
    finally:
        conn.close()


def run(binary: str, clients: int, extra: list[str]) -> dict:
    port, grpc = free_port(), free_port()
    with tempfile.TemporaryDirectory() as data:
        server = subprocess.Popen(
            [binary, "serve", "--http", f"127.0.0.1:{port}", "--grpc", f"127.0.0.1:{grpc}",
             "--data-dir", data, "--log-format", "json", *extra],
            stdout=subprocess.DEVNULL, stderr=open(os.path.join(data, "log"), "w"))
        try:
            for _ in range(500):
                try:
                    if call(port, "GET", "/readyz", timeout=1)[0] == 200:
                        break
                except OSError:
                    pass
                time.sleep(0.02)
            status, _, body = call(port, "POST", "/v1/sessions", {"model": model()})
            assert status == 201, body[:300]
            sid = json.loads(body)["id"]
            path = f"/v1/sessions/{sid}/values?include=all"
            status, _, body = call(port, "GET", path)
            assert status == 200, body[:300]
            size = len(body)
            del body
            before = status_kib(server.pid, "VmRSS")
            busy = [0]
            lock = threading.Lock()
            go = threading.Barrier(clients)

            def client() -> None:
                go.wait()
                while True:
                    status, retry, body = call(port, "GET", path)
                    if status == 200:
                        assert len(body) == size
                        return
                    assert status == 503, (status, body[:300])
                    with lock:
                        busy[0] += 1
                    time.sleep(float(retry or 1))

            start = time.perf_counter()
            threads = [threading.Thread(target=client) for _ in range(clients)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            wall = time.perf_counter() - start
            peak = status_kib(server.pid, "VmHWM")
            return {"size": size, "before_kib": before, "peak_kib": peak,
                    "busy": busy[0], "wall": wall}
        finally:
            server.terminate()
            server.wait(timeout=30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", default=str(ROOT / "target/release/mcapi"))
    ap.add_argument("--clients", type=int, default=20)
    args = ap.parse_args()
    configs = [
        ("unbounded (--max-response-bytes-total 1 TiB)", ["--max-response-bytes-total", str(1 << 40)]),
        ("default budget (256 MiB)", []),
    ]
    print(f"{args.clients} clients, each reading one whole values?include=all")
    print("| configuration | response | RSS before | peak RSS (VmHWM) | peak above before | 503 responses_busy | wall |")
    print("|---|---|---|---|---|---|---|")
    for name, extra in configs:
        r = run(args.bin, args.clients, extra)
        mib = lambda kib: f"{kib / 1024:.0f} MiB"  # noqa: E731
        print(f"| {name} | {r['size'] / 2**20:.1f} MiB | {mib(r['before_kib'])} | "
              f"{mib(r['peak_kib'])} | {mib(r['peak_kib'] - r['before_kib'])} | "
              f"{r['busy']} | {r['wall']:.1f} s |", flush=True)


if __name__ == "__main__":
    sys.exit(main())
