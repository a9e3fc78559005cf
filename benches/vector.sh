#!/usr/bin/env bash
# Vectorised stepping in one run (BENCHMARKS.md, "Vectorised stepping"): one
# Python process drives 10,000 hallway agents as a training loop would
# (benches/vector.py), over each path, and the single-observation gRPC paths
# are measured beside it by the load generator. A Markdown report on stdout,
# progress on stderr, raw results in $OUT.
#
#   benches/vector.sh                 # about 4 minutes here
#   QUICK=1 benches/vector.sh         # 1 s warm-up + 3 s windows
#
# Pinning: the server on core $SERVER_CORE (default 0), the Python process
# (and the load generator) on core $CLIENT_CORE (default 1). Every server is
# a fresh process with a fresh data directory, killed on exit.
#
# Rows:
#   group, async, memory       StepGroup, 2 steps in flight (two masks of 5,000)
#   group, lockstep, memory    the same, lockstep sessions
#   group, async, durable      the same on the default store (--durability sync)
#   batch, async, memory       the same loop through today's InteractBatch client
#                              (one (session_id, observation) pair per member)
#   rest-group, async, memory  POST /v1/groups/{id}/steps with JSON columns,
#                              2 connections, one step in flight on each
#   Interact / InteractBatch   mcapi-loadgen's gRPC scenario: 64 sessions over
#                              4 connections, one observation per message;
#                              over TCP, then over the server's Unix socket
#                              (--grpc-socket)
#   tick alone                 criterion: tick/hallway_indicator (the core's
#                              step of one hallway agent; SKIP_TICK=1 skips it)
#
# Environment: MCAPI, LOADGEN (default target/release/...; built if
# missing), PYTHON (default clients/python/.venv/bin/python, made by
# `make python-venv`), MEMBERS (default 10000), OUT.
set -euo pipefail
cd "$(dirname "$0")/.."

QUICK=${QUICK:-0}
if [ "$QUICK" = 1 ]; then WARMUP=1 DURATION=3; else WARMUP=${WARMUP:-3} DURATION=${DURATION:-10}; fi
SERVER_CORE=${SERVER_CORE:-0}
CLIENT_CORE=${CLIENT_CORE:-1}
MEMBERS=${MEMBERS:-10000}
MCAPI=${MCAPI:-target/release/mcapi}
LOADGEN=${LOADGEN:-$(dirname "$MCAPI")/mcapi-loadgen}
PYTHON=${PYTHON:-clients/python/.venv/bin/python}
OUT=${OUT:-target/bench-vector/$(date -u +%Y%m%dT%H%M%SZ)}
mkdir -p "$OUT"

for tool in jq curl taskset; do
  command -v "$tool" >/dev/null || { echo "benches/vector.sh needs $tool" >&2; exit 1; }
done
[ -x "$MCAPI" ] || cargo build --release --locked --bin mcapi >&2
[ -x "$LOADGEN" ] || cargo build --release --locked -p mcapi-loadgen >&2
[ -x "$PYTHON" ] || make python-venv >&2

SERVER_PID=""
SERVER_DIR=""
cleanup() {
  if [ -n "$SERVER_PID" ]; then
    kill "$SERVER_PID" 2>/dev/null || true
    wait "$SERVER_PID" 2>/dev/null || true
  fi
  if [ -n "$SERVER_DIR" ]; then rm -rf "$SERVER_DIR"; fi
  SERVER_PID=""
  SERVER_DIR=""
}
trap cleanup EXIT
trap 'exit 130' INT TERM

free_port() {
  python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'
}

# start_server NAME ARGS...: a fresh server on $SERVER_CORE with a fresh
# data directory; sets HP, GP, SERVER_PID.
start_server() {
  local name=$1
  shift
  cleanup
  SERVER_DIR=$(mktemp -d "${TMPDIR:-/tmp}/mcapi-vector.XXXXXX")
  HP=$(free_port)
  GP=$(free_port)
  taskset -c "$SERVER_CORE" "$MCAPI" serve --http "127.0.0.1:$HP" --grpc "127.0.0.1:$GP" \
    --data-dir "$SERVER_DIR/data" "$@" >"$OUT/$name.serve.log" 2>&1 &
  SERVER_PID=$!
  for _ in $(seq 1 300); do
    if curl -fsS "http://127.0.0.1:$HP/readyz" >/dev/null 2>&1; then return 0; fi
    if ! kill -0 "$SERVER_PID" 2>/dev/null; then
      echo "the server ($name) exited; see $OUT/$name.serve.log" >&2
      exit 1
    fi
    sleep 0.1
  done
  echo "the server ($name) was not ready in 30 s" >&2
  exit 1
}

# drive NAME PATH MODE SERVER-ARGS...: one row of benches/vector.py on a
# fresh server; its JSON to $OUT/NAME.json.
drive() {
  local name=$1 path=$2 mode=$3
  shift 3
  echo "== $name" >&2
  start_server "$name" "$@"
  taskset -c "$CLIENT_CORE" "$PYTHON" benches/vector.py --grpc "127.0.0.1:$GP" \
    --http "http://127.0.0.1:$HP" --server-pid "$SERVER_PID" --path "$path" --mode "$mode" \
    --members "$MEMBERS" --in-flight 2 --warmup "$WARMUP" --duration "$DURATION" >"$OUT/$name.json"
  cleanup
}

STARTED=$(date -u '+%Y-%m-%d %H:%M:%S UTC')
COMMIT=$(git rev-parse --short HEAD 2>/dev/null || echo unknown)

drive group-async group async --store memory
drive group-lockstep group lockstep --store memory
drive group-durable group async --durability sync
drive batch-async batch async --store memory --max-batch "$MEMBERS"
drive rest-group-async rest-group async --store memory

echo "== Interact / InteractBatch (mcapi-loadgen)" >&2
start_server loadgen --store memory
taskset -c "$CLIENT_CORE" "$LOADGEN" --threads 1 --http "http://127.0.0.1:$HP" \
  --grpc "http://127.0.0.1:$GP" --server-pid "$SERVER_PID" --warmup-secs "$WARMUP" \
  --duration-secs "$DURATION" --json "$OUT/loadgen.json" --scenario grpc --modes async \
  --grpc-streams 64 --grpc-connections 4 --grpc-batch 16 --no-paced >"$OUT/loadgen.md"
cleanup

echo "== Interact / InteractBatch over a Unix socket (mcapi-loadgen)" >&2
SOCKET_DIR=$(mktemp -d "${TMPDIR:-/tmp}/mcapi-sock.XXXXXX")
start_server loadgen-socket --store memory --grpc-socket "$SOCKET_DIR/grpc.sock"
taskset -c "$CLIENT_CORE" "$LOADGEN" --threads 1 --http "http://127.0.0.1:$HP" \
  --grpc "unix:$SOCKET_DIR/grpc.sock" --server-pid "$SERVER_PID" --warmup-secs "$WARMUP" \
  --duration-secs "$DURATION" --json "$OUT/loadgen-socket.json" --scenario grpc --modes async \
  --grpc-streams 64 --grpc-connections 4 --grpc-batch 16 --no-paced >"$OUT/loadgen-socket.md"
cleanup
rmdir "$SOCKET_DIR" 2>/dev/null || true

TICK="not measured (SKIP_TICK=1)"
if [ "${SKIP_TICK:-0}" != 1 ]; then
  echo "== tick alone (criterion)" >&2
  taskset -c "$SERVER_CORE" cargo bench --locked -p mcapi-experiments --bench tick -- \
    'tick/hallway_indicator$' --warm-up-time 1 --measurement-time 3 >"$OUT/tick.txt" 2>&1
  TICK=$(grep -A1 'tick/hallway_indicator' "$OUT/tick.txt" | grep -o 'time: *\[[^]]*\]' | head -1)
fi

row() {
  jq -r --arg what "$2" '"| \($what) | \(.steps_per_s | floor) | \(.server_us_per_step * 100 | round / 100) | \(.reply_gap_max_ms // null | if . == null then "–" else round end) |"' "$OUT/$1.json"
}
rate() { jq -r '.steps_per_s' "$OUT/$1.json"; }
ratio() { python3 -c "print(f'{$1 / $2:.2f}')"; }

cat <<EOF
# Vectorised stepping

$STARTED, commit $COMMIT; server on core $SERVER_CORE, the Python process on core
$CLIENT_CORE; $MEMBERS hallway sessions; ${WARMUP} s warm-up + ${DURATION} s windows.
Raw results: $OUT.

| path (one Python process) | steps/s | server CPU µs/step | longest wait for a reply, ms |
|---|---|---|---|
$(row group-async "StepGroup, async, memory store, 2 in flight")
$(row group-lockstep "StepGroup, lockstep, memory store, 2 in flight")
$(row group-durable "StepGroup, async, durable store (sync), 2 in flight")
$(row batch-async "InteractBatch client, async, memory store")
$(row rest-group-async "REST group steps (JSON), async, memory store, 2 in flight")

- StepGroup over InteractBatch: **$(ratio "$(rate group-async)" "$(rate batch-async)")×**; over REST group steps: **$(ratio "$(rate group-async)" "$(rate rest-group-async)")×**
- durable / memory: **$(ratio "$(rate group-durable)" "$(rate group-async)")**; lockstep / async: **$(ratio "$(rate group-lockstep)" "$(rate group-async)")**

Single observations (mcapi-loadgen, 64 sessions over 4 connections, over
TCP on loopback and over the server's Unix socket, \`--grpc-socket\`):

| method | observations/s | server CPU µs/obs |
|---|---|---|
$(jq -r '.grpc[] | "| \(.method) (\(.streams) × \(.batch)) | \(.summary.rate | floor) | \(.server_cpu_us_per_observation * 100 | round / 100) |"' "$OUT/loadgen.json")
$(jq -r '.grpc[] | "| \(.method) (\(.streams) × \(.batch)), Unix socket | \(.summary.rate | floor) | \(.server_cpu_us_per_observation * 100 | round / 100) |"' "$OUT/loadgen-socket.json")

The core's hallway tick alone (criterion tick/hallway_indicator): $TICK
EOF
