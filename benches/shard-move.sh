#!/usr/bin/env bash
# Shard moves measured on `mcapi cluster local` (BENCHMARKS.md §10):
#   1. the time to move one shard of 1,000 sessions (each with 10
#      observations), `mcapi cluster move`, idle;
#   2. the pause clients see while `mcapi cluster rebalance` moves 3 -> 4
#      replicas under load: a Python client observes 6,000 sessions through
#      HAProxy in a loop, retrying 503/421 every 5 ms; a request's pause is
#      the time from its first refusal to its acknowledgement.
# Usage: benches/shard-move.sh [path/to/mcapi]   (default: target/release/mcapi)
# Needs haproxy and python3. Everything runs on loopback and stops by itself.
set -euo pipefail
MCAPI=${1:-target/release/mcapi}
MCAPI=$(realpath "$MCAPI")
WORK=$(mktemp -d)
trap 'kill $(cat "$WORK"/*.pid 2>/dev/null) 2>/dev/null || true; sleep 1; rm -rf "$WORK"' EXIT

start() { # dir http grpc
  "$MCAPI" cluster local --data-dir "$1" --http "127.0.0.1:$2" --grpc "127.0.0.1:$3" -- --workers 2 \
    > "$1.out" 2> "$1.err" &
  echo $! > "$1.pid"
  for _ in $(seq 600); do grep -q "stops everything" "$1.out" 2>/dev/null && return; sleep 0.1; done
  echo "cluster did not start: $(tail "$1.err")" >&2; exit 1
}
stop() { kill "$(cat "$1.pid")"; while kill -0 "$(cat "$1.pid")" 2>/dev/null; do sleep 0.1; done; rm "$1.pid"; }

echo "== 1. one shard of 1,000 sessions"
C1="$WORK/one"; mkdir -p "$C1"
{ echo "epoch 1"; echo "s0000 mcapi-0"; for s in $(seq 1 1023); do printf 's%04x mcapi-1\n' "$s"; done; } > "$C1/shards.map"
start "$C1" 28080 28051
python3 - "$C1/cluster.json" <<'PY'
import http.client, json, sys
state = json.load(open(sys.argv[1]))
addr = next(p["http"] for p in state["processes"] if p["name"] == "mcapi-0")
host, port = addr.split(":")
c = http.client.HTTPConnection(host, int(port))
def post(path, body):
    c.request("POST", path, json.dumps(body), {"content-type": "application/json"})
    r = c.getresponse(); data = r.read()
    assert r.status in (200, 201), (r.status, data)
    return json.loads(data)
for i in range(1000):
    sid = post("/v1/sessions", {"model": {"preset": "hallway"}, "agent": {"seed": i}})["id"]
    assert sid.startswith("s0000."), sid
    post(f"/v1/sessions/{sid}/observations", {"state": 25})
    for k in range(10):
        post(f"/v1/sessions/{sid}/observations", {"state": 25, "stimulus": [0.1, 0.2], "action_taken": "stay"})
print("1,000 sessions with 10 observations each in s0000 on mcapi-0")
PY
for run in 1 2 3; do
  to=$([ $((run % 2)) = 1 ] && echo mcapi-1 || echo mcapi-0)
  "$MCAPI" cluster move --data-dir "$C1" --shard s0000 --to "$to" 2>/dev/null
done
stop "$C1"

echo "== 2. rebalance 3 -> 4 under load"
C2="$WORK/four"; mkdir -p "$C2"
"$MCAPI" cluster plan --replicas 3 --out "$C2/shards.map" 2>/dev/null
start "$C2" 28180 28151
python3 - 28180 "$MCAPI" "$C2" <<'PY'
import http.client, json, subprocess, sys, threading, time
port, mcapi, data = int(sys.argv[1]), sys.argv[2], sys.argv[3]
def conn(): return http.client.HTTPConnection("127.0.0.1", port, timeout=30)
c = conn()
def call(c, method, path, body=None):
    c.request(method, path, json.dumps(body) if body is not None else None, {"content-type": "application/json"})
    r = c.getresponse(); return r.status, r.read()
ids = []
for i in range(6000):
    s, b = call(c, "POST", "/v1/sessions", {"model": {"preset": "hallway"}, "agent": {"seed": i}})
    sid = json.loads(b)["id"]; ids.append(sid)
    call(c, "POST", f"/v1/sessions/{sid}/observations", {"state": 25})
pauses, cuts, done, stop = [], [], [0], [False]
def drive(part):
    c = conn()
    while not stop[0]:
        for sid in part:
            if stop[0]: break
            first, cut = None, False
            while True:
                try:
                    s, _ = call(c, "POST", f"/v1/sessions/{sid}/observations",
                                {"state": 25, "stimulus": [0.1, 0.2], "action_taken": "stay"})
                except Exception:
                    # The router's restart (new replicas) cuts connections.
                    c = conn(); s = 0; cut = True
                if s == 200: break
                first = first or time.perf_counter()
                time.sleep(0.005)
            if first: (cuts if cut else pauses).append(time.perf_counter() - first)
            done[0] += 1
threads = [threading.Thread(target=drive, args=(ids[k::4],)) for k in range(4)]
for t in threads: t.start()
time.sleep(1)
t0 = time.perf_counter()
out = subprocess.run([mcapi, "cluster", "rebalance", "--data-dir", data, "--replicas", "4"],
                     capture_output=True, text=True, check=True).stdout
took = time.perf_counter() - t0
time.sleep(1); stop[0] = True
for t in threads: t.join()
print(out.strip())
p = sorted(x * 1e3 for x in pauses)
q = lambda f: p[min(len(p) - 1, int(round((len(p) - 1) * f)))] if p else 0.0
print(f"rebalance took {took:.1f} s; {done[0]} observations acknowledged by the clients; "
      f"{len(p)} of them paused by a move (503/421, retried every 5 ms): p50 {q(0.5):.1f} ms, "
      f"p99 {q(0.99):.1f} ms, max {p[-1] if p else 0:.1f} ms; {len(cuts)} cut by the router's restart "
      f"(longest {max(cuts, default=0) * 1e3:.0f} ms)")
PY
stop "$C2"
