#!/usr/bin/env bash
# Every row of the performance targets' table ("Throughput near the wire") in one run, with
# ratios and targets, as a Markdown report on stdout (BENCHMARKS.md §8).
#
#   benches/server.sh                      # full run (about 12 minutes here)
#   QUICK=1 benches/server.sh              # short windows, 10,000 idle sessions
#   MEMORY_SESSIONS=1000000 benches/server.sh   # the memory row at the target's size
#
# Pinning, as the "before" figures of BENCHMARKS.md §8 were measured: the
# server on core $SERVER_CORE (default 0, `taskset -c 0 mcapi serve`), the
# load generator on core $LOADGEN_CORE (default 1,
# `taskset -c 1 mcapi-loadgen --threads 1`). Every server is a
# fresh process with a fresh data directory (mktemp), killed on exit. The
# load generator's own Markdown tables and JSON results (`--json`) go to
# $OUT (default target/bench-server/<time>/), this report to stdout,
# progress to stderr.
#
# Environment:
#   MCAPI            the binary (default target/release/mcapi, built with
#                    `cargo build --release --locked --bin mcapi` if missing)
#   LOADGEN          the load generator (default mcapi-loadgen next to
#                    $MCAPI, built with `cargo build --release --locked
#                    -p mcapi-loadgen` if missing)
#   QUICK=1          1 s warm-up + 3 s windows (default 2 + 10), 10,000 idle
#                    sessions, short criterion run
#   WARMUP, DURATION seconds per measurement (override QUICK's)
#   MEMORY_SESSIONS  idle sessions of the memory row (default 100,000: the
#                    target is 1,000,000, which takes ~10 GiB of RAM and
#                    several minutes here; per-session figures are scaled)
#   SKIP_TICK=1      skip the criterion tick bench (it compiles the bench)
#   OUT              where raw results go
#
# Not part of `make test`: `make bench-server` runs it.
set -euo pipefail
cd "$(dirname "$0")/.."

QUICK=${QUICK:-0}
if [ "$QUICK" = 1 ]; then
  WARMUP=${WARMUP:-1}
  DURATION=${DURATION:-3}
  MEMORY_SESSIONS=${MEMORY_SESSIONS:-10000}
  CRITERION_ARGS=(--warm-up-time 1 --measurement-time 3)
else
  WARMUP=${WARMUP:-2}
  DURATION=${DURATION:-10}
  MEMORY_SESSIONS=${MEMORY_SESSIONS:-100000}
  CRITERION_ARGS=()
fi
SERVER_CORE=${SERVER_CORE:-0}
LOADGEN_CORE=${LOADGEN_CORE:-1}
MCAPI=${MCAPI:-target/release/mcapi}
OUT=${OUT:-target/bench-server/$(date -u +%Y%m%dT%H%M%SZ)}
mkdir -p "$OUT"

for tool in jq curl taskset; do
  command -v "$tool" >/dev/null || { echo "benches/server.sh needs $tool" >&2; exit 1; }
done
if [ ! -x "$MCAPI" ]; then
  echo "building $MCAPI" >&2
  cargo build --release --locked --bin mcapi >&2
fi
LOADGEN=${LOADGEN:-$(dirname "$MCAPI")/mcapi-loadgen}
if [ ! -x "$LOADGEN" ]; then
  echo "building $LOADGEN" >&2
  cargo build --release --locked -p mcapi-loadgen >&2
fi

SERVER_PID=""
SERVER_DIR=""
cleanup() {
  if [ -n "$SERVER_PID" ]; then
    kill "$SERVER_PID" 2>/dev/null || true
    wait "$SERVER_PID" 2>/dev/null || true
  fi
  if [ -n "$SERVER_DIR" ]; then rm -rf "$SERVER_DIR"; fi
}
trap cleanup EXIT
trap 'exit 130' INT TERM

free_port() {
  # A port the kernel hands out for an ephemeral bind, then releases.
  python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'
}

# start_server NAME ARGS...: a fresh server on $SERVER_CORE with a fresh
# data directory; sets HTTP_URL, GRPC_URL, SERVER_PID.
start_server() {
  local name=$1
  shift
  cleanup
  SERVER_DIR=$(mktemp -d "${TMPDIR:-/tmp}/mcapi-bench.XXXXXX")
  local hp gp
  hp=$(free_port)
  gp=$(free_port)
  HTTP_URL=http://127.0.0.1:$hp
  GRPC_URL=http://127.0.0.1:$gp
  taskset -c "$SERVER_CORE" "$MCAPI" serve --http "127.0.0.1:$hp" --grpc "127.0.0.1:$gp" \
    --data-dir "$SERVER_DIR/data" "$@" >"$OUT/$name.serve.log" 2>&1 &
  SERVER_PID=$!
  for _ in $(seq 1 300); do
    if curl -fsS "$HTTP_URL/readyz" >/dev/null 2>&1; then return 0; fi
    if ! kill -0 "$SERVER_PID" 2>/dev/null; then
      echo "the server ($name) exited; see $OUT/$name.serve.log" >&2
      tail -5 "$OUT/$name.serve.log" >&2
      exit 1
    fi
    sleep 0.1
  done
  echo "the server ($name) was not ready in 30 s" >&2
  exit 1
}

stop_server() {
  cleanup
  SERVER_PID=""
  SERVER_DIR=""
}

# loadgen NAME ARGS...: the load generator on $LOADGEN_CORE against the
# running server; Markdown to $OUT/NAME.md, JSON to $OUT/NAME.json.
loadgen() {
  local name=$1
  shift
  echo "== $name" >&2
  taskset -c "$LOADGEN_CORE" "$LOADGEN" --threads 1 \
    --http "$HTTP_URL" --grpc "$GRPC_URL" --server-pid "$SERVER_PID" \
    --warmup-secs "$WARMUP" --duration-secs "$DURATION" \
    --json "$OUT/$name.json" "$@" >"$OUT/$name.md"
}

# rest_pair NAME SERVER-ARGS...: REST at (32 connections, 100 sessions) and
# (256 connections, 1,000 sessions), async, each on its own fresh server.
rest_pair() {
  local name=$1
  shift
  start_server "$name-100" "$@"
  loadgen "$name-100" --scenario rest --sessions 100 --max-connections 32 --modes async
  stop_server
  start_server "$name-1000" "$@"
  loadgen "$name-1000" --scenario rest --sessions 1000 --max-connections 256 --modes async
  stop_server
}

STARTED=$(date -u '+%Y-%m-%d %H:%M:%S UTC')
COMMIT=$(git rev-parse --short HEAD 2>/dev/null || echo unknown)
DIRTY=$(git status --porcelain --untracked-files=no 2>/dev/null | grep -q . && echo " (with uncommitted changes)" || true)

# Rows 1, 2 and 4: REST on the memory store and the default (durable) store.
rest_pair memory --store memory
rest_pair durable
HAS_DURABILITY=0
if "$MCAPI" serve --help 2>/dev/null | grep -q -- '--durability'; then
  HAS_DURABILITY=1
  rest_pair durable-os --durability os
fi

# Row 3: gRPC Interact, 64 streams over 1 and 4 HTTP/2 connections, then
# the same 64 sessions as vectorised worlds: InteractBatch, 4 streams of 16.
start_server grpc --store memory
loadgen grpc-1 --scenario grpc --modes async --grpc-streams 64 --grpc-connections 1 --grpc-batch 16
loadgen grpc-4 --scenario grpc --modes async --grpc-streams 64 --grpc-connections 4 --grpc-batch 16
stop_server

# Row 5: idle hallway sessions, then all deleted. Limits raised so the count
# fits (the per-key byte budget counts each session's estimated worst case).
start_server memory-sessions --store memory \
  --max-sessions "$MEMORY_SESSIONS" --max-key-sessions "$MEMORY_SESSIONS" \
  --max-key-bytes 1099511627776
loadgen memory-sessions --scenario memory --memory-sessions "$MEMORY_SESSIONS" --settle-secs 2
stop_server
# Row 5 on the default durable store with idle sessions evicted after 1 s
# (docs/sessions.md, "Idle sessions"): RSS once all are evicted, then after
# one observation each (every one loaded back) and evicted again.
if "$MCAPI" serve --help | grep -q -- '--evict-idle-secs'; then
  start_server memory-evicted --evict-idle-secs 1 \
    --max-sessions "$MEMORY_SESSIONS" --max-key-sessions "$MEMORY_SESSIONS" \
    --max-key-bytes 1099511627776
  loadgen memory-evicted --scenario memory --memory-sessions "$MEMORY_SESSIONS" \
    --settle-secs 2 --evicted-wait-secs 600
  stop_server
fi

# Row 6: the three-room 30-PVF tick (criterion), on the server's core.
TICK_US=""
if [ "${SKIP_TICK:-0}" != 1 ]; then
  echo "== tick (cargo bench)" >&2
  cargo bench --locked -p mcapi-experiments --bench tick --no-run >"$OUT/tick.build.txt" 2>&1
  taskset -c "$SERVER_CORE" cargo bench --locked -p mcapi-experiments --bench tick -- \
    'tick/three_room_pvf30$' "${CRITERION_ARGS[@]}" >"$OUT/tick.txt" 2>&1
  # "time:   [lo unit mid unit hi unit]": the middle estimate, in µs.
  TICK_US=$(awk '/time:/ { gsub(/\[|\]/, "");
      for (i = 1; i <= NF; i++) if ($i == "time:") break;
      v = $(i + 3); u = $(i + 4);
      if (u == "ns") v /= 1000; else if (u == "ms") v *= 1000; else if (u == "s") v *= 1e6;
      if (v > 0) printf "%.2f", v; exit }' "$OUT/tick.txt")
fi
FINISHED=$(date -u '+%H:%M:%S UTC')

# ------------------------------------------------------------------ report

num() { jq -r "$2 // empty" "$OUT/$1.json"; }
fmt() { awk -v x="$1" -v d="${2:-0}" 'BEGIN { if (x == "") print "—"; else printf "%.*f", d, x }'; }
ratio() { awk -v a="$1" -v b="$2" 'BEGIN { if (a == "" || b == "" || b == 0) print ""; else printf "%.2f", a / b }'; }
# met VALUE OP TARGET: yes / **no** / n/a
met() { awk -v x="$1" -v op="$2" -v t="$3" 'BEGIN {
  if (x == "") { print "n/a"; exit }
  ok = (op == ">=") ? (x >= t) : (x <= t)
  print ok ? "yes" : "**no**" }'; }

row() { printf '| %s | %s | %s | %s |\n' "$1" "$2" "$3" "$4"; }

cat <<EOF
Command: \`$([ "$QUICK" = 1 ] && echo "QUICK=1 ")$([ "$MCAPI" != target/release/mcapi ] && echo "MCAPI=$MCAPI ")MEMORY_SESSIONS=$MEMORY_SESSIONS benches/server.sh\`
(warm-up $WARMUP s + window $DURATION s per measurement), commit $COMMIT$DIRTY,
$STARTED to $FINISHED, $(nproc) cores ($(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ *//')).
Server on core $SERVER_CORE, \`mcapi-loadgen --threads 1\` on core $LOADGEN_CORE; async hallway sessions.
Raw results: \`$OUT\`.

| row | measured | target | met? |
|---|---|---|---|
EOF

# Row 1.
h=$(num memory-100 '.rest[0].healthz.summary.rate')
o=$(num memory-100 '.rest[0].observe.summary.rate')
r=$(ratio "$o" "$h")
row "1. REST observe / \`/healthz\`, memory store (32 conn., 100 sessions)" \
  "$(fmt "$o") / $(fmt "$h") req/s = **$(fmt "$r" 2)**" "≥ 0.70" "$(met "$r" '>=' 0.70)"

# Row 2.
for pair in "durable:default durable store" "durable-os:\`--durability os\`"; do
  name=${pair%%:*}
  label=${pair#*:}
  if [ "$name" = durable-os ] && [ "$HAS_DURABILITY" = 0 ]; then continue; fi
  for n in 100 1000; do
    conns=$([ "$n" = 100 ] && echo 32 || echo 256)
    d=$(num "$name-$n" '.rest[0].observe.summary.rate')
    m=$(num "memory-$n" '.rest[0].observe.summary.rate')
    r=$(ratio "$d" "$m")
    row "2. REST observe, $label / memory store ($conns conn., $n sessions)" \
      "$(fmt "$d") / $(fmt "$m") req/s = **$(fmt "$r" 2)**" "≥ 0.60" "$(met "$r" '>=' 0.60)"
  done
done
if [ "$HAS_DURABILITY" = 0 ]; then
  row "2. (\`--durability os\`)" "not measured: this \`mcapi serve\` has no \`--durability\`" "—" "n/a"
fi

# Row 3.
for c in 1 4; do
  us=$(num "grpc-$c" '.grpc[0].server_cpu_us_per_observation')
  rate=$(num "grpc-$c" '.grpc[0].summary.rate')
  row "3. gRPC \`Interact\` server CPU per observation, memory store ($c conn., 64 streams)" \
    "**$(fmt "$us" 1) µs** ($(fmt "$rate") obs/s)" "≤ 5 µs" "$(met "$us" '<=' 5)"
done
for c in 1 4; do
  us=$(num "grpc-$c" '.grpc[] | select(.method == "InteractBatch") | .server_cpu_us_per_observation')
  rate=$(num "grpc-$c" '.grpc[] | select(.method == "InteractBatch") | .summary.rate')
  single=$(num "grpc-$c" '.grpc[] | select(.method == "Interact") | .server_cpu_us_per_observation')
  row "3. gRPC \`InteractBatch\` server CPU per observation, memory store ($c conn., 4 streams × 16 sessions)" \
    "**$(fmt "$us" 1) µs** ($(fmt "$rate") obs/s; $(fmt "$(ratio "$us" "$single")" 2)× \`Interact\`'s)" "≤ 5 µs" "$(met "$us" '<=' 5)"
done

# Row 4.
for name in memory durable; do
  for n in 100 1000; do
    conns=$([ "$n" = 100 ] && echo 32 || echo 256)
    p99=$(num "$name-$n" '.rest[0].paced.summary.p99_us')
    p99ms=$(awk -v x="$p99" 'BEGIN { if (x != "") printf "%.3f", x / 1000 }')
    target=$(num "$name-$n" '.rest[0].paced.target_rate')
    got=$(num "$name-$n" '.rest[0].paced.summary.rate')
    row "4. REST p99 at half the closed-loop peak, $name store ($conns conn., $n sessions)" \
      "**$(fmt "$p99ms" 2) ms** at $(fmt "$got") of $(fmt "$target") req/s" "≤ 2 ms" "$(met "$p99ms" '<=' 2)"
  done
done

# Row 5.
kib=$(num memory-sessions '.memory.kib_per_idle_session')
gib=$(awk -v k="$kib" 'BEGIN { if (k != "") printf "%.2f", k * 1e6 / 1048576 }')
row "5. idle hallway sessions ($(fmt "$MEMORY_SESSIONS") created)" \
  "**$(fmt "$kib" 2) KiB** each → $(fmt "$gib" 2) GiB per 1,000,000" "1,000,000 in ≤ 4 GiB (≤ 4.19 KiB each)" "$(met "$gib" '<=' 4)"
base=$(num memory-sessions '.memory.baseline_rss_bytes')
peak=$(num memory-sessions '.memory.observed_rss_bytes')
after=$(num memory-sessions '.memory.settled_rss_bytes')
back=$(num memory-sessions '.memory.returned_after_settle')
mib() { awk -v x="$1" 'BEGIN { if (x == "") print "—"; else printf "%.0f MiB", x / 1048576 }'; }
row "5. RSS after deleting them all (2 s later)" \
  "**$(mib "$after")** (fresh $(mib "$base"), with sessions $(mib "$peak"); $(awk -v r="$back" 'BEGIN { printf "%.0f%%", 100 * r }') returned)" \
  "returned (≥ 90% of what they took)" "$(met "$back" '>=' 0.90)"

if [ -f "$OUT/memory-evicted.json" ]; then
  kib=$(num memory-evicted '.memory.kib_per_idle_session')
  gib=$(awk -v k="$kib" 'BEGIN { if (k != "") printf "%.2f", k * 1e6 / 1048576 }')
  row "5. idle hallway sessions, default durable store, evicted after 1 s ($(fmt "$MEMORY_SESSIONS") created)" \
    "**$(fmt "$kib" 2) KiB** each → $(fmt "$gib" 2) GiB per 1,000,000" "1,000,000 in ≤ 4 GiB (≤ 4.19 KiB each)" "$(met "$gib" '<=' 4)"
  kib=$(num memory-evicted '.memory.kib_per_observed_evicted_session')
  gib=$(awk -v k="$kib" 'BEGIN { if (k != "") printf "%.2f", k * 1e6 / 1048576 }')
  row "5. the same after one observation each (each loaded back), evicted again" \
    "**$(fmt "$kib" 2) KiB** each → $(fmt "$gib" 2) GiB per 1,000,000" "1,000,000 in ≤ 4 GiB (≤ 4.19 KiB each)" "$(met "$gib" '<=' 4)"
fi

# Row 6.
if [ -n "$TICK_US" ]; then
  row "6. three-room 30-PVF tick (\`cargo bench -p mcapi-experiments --bench tick -- 'tick/three_room_pvf30\$'\`)" \
    "**$TICK_US µs**" "≤ 8 µs" "$(met "$TICK_US" '<=' 8)"
else
  row "6. three-room 30-PVF tick" "not measured (SKIP_TICK=1, or no estimate in $OUT/tick.txt)" "≤ 8 µs" "n/a"
fi

# How busy the rest of the machine was: the windows mean little if others
# were using the cores.
others=$(cat "$OUT"/*.json | jq -r '.. | objects | .cpu_other? // empty' | sort -n)
if [ -n "$others" ]; then
  echo
  echo "Cores kept busy by other processes (and steal) during the measurement windows: \
$(echo "$others" | head -1 | xargs printf '%.2f') to $(echo "$others" | tail -1 | xargs printf '%.2f') \
of $(nproc). Above ~0.1 the REST and gRPC rows are disturbed."
fi

# Context: CPU beside the REST rows (the two share a 2-core machine).
echo
echo "REST rows in detail (closed loop; server / loadgen / other cores busy during the observe window):"
echo
echo "| store | sessions | conn. | /healthz req/s | observe req/s | observe p99 | server CPU µs/req | CPU server / loadgen / other |"
echo "|---|---|---|---|---|---|---|---|"
for name in memory durable durable-os; do
  [ -f "$OUT/$name-100.json" ] || continue
  for n in 100 1000; do
    f="$name-$n"
    printf '| %s | %s | %s | %s | %s | %s ms | %s | %s / %s / %s |\n' "$name" "$n" \
      "$(num "$f" '.rest[0].connections')" \
      "$(fmt "$(num "$f" '.rest[0].healthz.summary.rate')")" \
      "$(fmt "$(num "$f" '.rest[0].observe.summary.rate')")" \
      "$(fmt "$(awk -v x="$(num "$f" '.rest[0].observe.summary.p99_us')" 'BEGIN { print x / 1000 }')" 2)" \
      "$(fmt "$(num "$f" '.rest[0].observe.window.server_cpu_us_per_request')" 1)" \
      "$(fmt "$(num "$f" '.rest[0].observe.window.cpu_server')" 2)" \
      "$(fmt "$(num "$f" '.rest[0].observe.window.cpu_loadgen')" 2)" \
      "$(fmt "$(num "$f" '.rest[0].observe.window.cpu_other')" 2)"
  done
done
