#!/usr/bin/env bash
# Two mcapi binaries against each other on the durable store, interleaved
# pair by pair (BENCHMARKS.md §8, "Zero-filled log segments"): REST observe,
# closed loop, at (32 connections, 100 sessions) and (256, 1,000), each run
# on a fresh server with a fresh data directory, the server pinned to core 0
# and the load generator to core 1; a memory-store run of AFTER opens each
# round as the reference. Then one connection and one session, for the
# latency of a commit alone.
#
#   BEFORE=/tmp/mcapi-old AFTER=target/release/mcapi benches/store-ab.sh
#
# The load generator is the `mcapi-loadgen` next to AFTER in every run
# (LOADGEN to choose another), so only the server differs within a pair.
#
# Environment: ROUNDS (3), WARMUP (2), DURATION (8), OUT (raw JSON,
# default target/bench-store-ab/<time>/). One line per run on stdout.
set -euo pipefail
cd "$(dirname "$0")/.."
: "${BEFORE:?set BEFORE to the baseline binary}"
AFTER=${AFTER:-target/release/mcapi}
LOADGEN=${LOADGEN:-$(dirname "$AFTER")/mcapi-loadgen}
ROUNDS=${ROUNDS:-3}
WARMUP=${WARMUP:-2}
DURATION=${DURATION:-8}
OUT=${OUT:-target/bench-store-ab/$(date -u +%Y%m%dT%H%M%SZ)}
mkdir -p "$OUT"
for tool in jq curl taskset python3; do
  command -v "$tool" >/dev/null || { echo "benches/store-ab.sh needs $tool" >&2; exit 1; }
done

free_port() {
  python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'
}

PID=""
DIR=""
cleanup() {
  if [ -n "$PID" ]; then kill "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; fi
  if [ -n "$DIR" ]; then rm -rf "$DIR"; fi
  PID=""
  DIR=""
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# run NAME BINARY SESSIONS CONNECTIONS SERVE-ARGS...
run() {
  local name=$1 bin=$2 sessions=$3 conns=$4
  shift 4
  DIR=$(mktemp -d "${TMPDIR:-/tmp}/mcapi-ab.XXXXXX")
  local hp gp
  hp=$(free_port)
  gp=$(free_port)
  taskset -c 0 "$bin" serve --http "127.0.0.1:$hp" --grpc "127.0.0.1:$gp" \
    --data-dir "$DIR/data" "$@" >"$OUT/$name.serve.log" 2>&1 &
  PID=$!
  for _ in $(seq 1 300); do
    curl -fsS "http://127.0.0.1:$hp/readyz" >/dev/null 2>&1 && break
    sleep 0.1
  done
  taskset -c 1 "$LOADGEN" --threads 1 --http "http://127.0.0.1:$hp" \
    --grpc "http://127.0.0.1:$gp" --server-pid "$PID" --warmup-secs "$WARMUP" \
    --duration-secs "$DURATION" --no-paced --scenario rest --sessions "$sessions" \
    --max-connections "$conns" --modes async --json "$OUT/$name.json" >"$OUT/$name.md"
  cleanup
  jq -r --arg n "$name" '.rest[0].observe as $o |
    "\($n)\tobserve \($o.summary.rate | floor) req/s\tp50 \($o.summary.p50_us | floor) µs\tp99 \($o.summary.p99_us | floor) µs\tserver CPU \($o.window.server_cpu_us_per_request * 10 | floor / 10) µs/req\tother \($o.window.cpu_other * 100 | floor / 100) cores"' \
    "$OUT/$name.json"
}

for round in $(seq 1 "$ROUNDS"); do
  for size in "100 32" "1000 256"; do
    read -r sessions conns <<<"$size"
    run "r$round-memory-$sessions" "$AFTER" "$sessions" "$conns" --store memory
    run "r$round-before-$sessions" "$BEFORE" "$sessions" "$conns"
    run "r$round-after-$sessions" "$AFTER" "$sessions" "$conns"
  done
done
for round in $(seq 1 "$ROUNDS"); do
  run "r$round-before-1" "$BEFORE" 1 1
  run "r$round-after-1" "$AFTER" 1 1
done
