#!/usr/bin/env python3
"""Resident memory of sessions whose history rings are full (BENCHMARKS.md §3).

Starts `mcapi serve --store memory`, creates N hallway sessions (async) and
sends each 301 observations in one batch, so every 256-tick history ring is
full, then reads the server's VmRSS from /proc.

    python3 benches/history_memory.py target/debug/mcapi 19100 3000
"""

binary, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
p = subprocess.Popen([binary, "serve", "--store", "memory", "--http", f"127.0.0.1:{port}", "--grpc", f"127.0.0.1:{port+1}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
def post(path, body):
    req = urllib.request.Request(f"http://127.0.0.1:{port}{path}", data=json.dumps(body).encode(), headers={"content-type": "application/json"})
    return json.load(urllib.request.urlopen(req))
for _ in range(100):
    try:
        urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz"); break
    except Exception: time.sleep(0.1)
def rss():
    for line in open(f"/proc/{p.pid}/status"):
        if line.startswith("VmRSS"): return int(line.split()[1]) / 1024
base = rss()
obs = [{"state": 25}] + [{"state": 5 + (i % 40), "stimulus": [6.0 if (5 + i % 40) == 10 else 0.0, 6.0 if (5 + i % 40) == 40 else 0.0]} for i in range(300)]
for i in range(n):
    sid = post("/v1/sessions", {"model": {"preset": "hallway"}, "agent": {"seed": i, "update_mode": "async"}})["id"]
    post(f"/v1/sessions/{sid}/observations", {"observations": obs})
time.sleep(0.5)
print(f"{binary}: {n} sessions with full 256-tick rings: VmRSS {rss():.0f} MiB (fresh {base:.0f} MiB), {(rss()-base)*1024/n:.1f} KiB per session")
p.terminate(); p.wait()
