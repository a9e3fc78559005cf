#!/usr/bin/env bash
# `make container-bench`: start-to-ready time of the mcapi container with
# SESSIONS (default 10,000) stored sessions on its volume, against the same
# container on an empty volume in the same run, and the image's size.
# Start-to-ready: from `podman start` to the first 200 of /readyz (the
# server answers /readyz only after every stored session is recovered).
# Needs the image built by `make container-test` (IMAGE, default
# localhost/mcapi:test), root and the Python client's venv.
set -euo pipefail
cd "$(dirname "$0")/.."
source tools/podman.sh

PY=${PY:-clients/python/.venv/bin/python}
IMAGE=${IMAGE:-localhost/mcapi:test}
SESSIONS=${SESSIONS:-10000}
STEPS=${STEPS:-3}
RUNS=${RUNS:-5}
NAME=mcapi-bench-$$
OUT=target/container
mkdir -p "$OUT"

cleanup() {
  for v in empty full; do
    podman_ rm -f -t 0 "$NAME-$v" >/dev/null 2>&1 || true
    podman_ volume rm -f "$NAME-$v" >/dev/null 2>&1 || true
  done
}
trap cleanup EXIT
podman_ image exists "$IMAGE" || { echo "no image $IMAGE: run make container-test first" >&2; exit 1; }

read -r PORT < <("$PY" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
HTTP=http://127.0.0.1:$PORT
wait_ready() { "$PY" tools/container_drive.py wait-ready --http "$HTTP" --timeout 600; }

for v in empty full; do
  podman_ create --name "$NAME-$v" "${PODMAN_ULIMITS[@]}" --read-only --read-only-tmpfs=false \
    -v "$NAME-$v:/data" -p "127.0.0.1:$PORT:8080" "$IMAGE" >/dev/null
done
podman_ start "$NAME-full" >/dev/null 2>>"$OUT/podman.log"
wait_ready >/dev/null
"$PY" tools/container_drive.py populate --http "$HTTP" --sessions "$SESSIONS" --steps "$STEPS"
podman_ stop -t 30 "$NAME-full" >/dev/null 2>>"$OUT/podman.log"
size=$(du -sh "$(podman_ volume inspect --format '{{.Mountpoint}}' "$NAME-full")" | cut -f1)
echo "volume with $SESSIONS sessions: $size"

# Interleaved pairs: empty volume, then the full one, RUNS times.
for i in $(seq "$RUNS"); do
  for v in empty full; do
    t0=$(date +%s.%N)
    podman_ start "$NAME-$v" >/dev/null 2>>"$OUT/podman.log"
    wait_ready >/dev/null
    t1=$(date +%s.%N)
    awk -v v="$v" -v a="$t0" -v b="$t1" 'BEGIN { printf "%s %.3f\n", v, b - a }'
    podman_ stop -t 30 "$NAME-$v" >/dev/null 2>>"$OUT/podman.log"
  done
done | tee "$OUT/start_to_ready.txt"
"$PY" - "$OUT/start_to_ready.txt" <<'PYEOF'
import statistics, sys
runs = {}
for line in open(sys.argv[1]):
    kind, secs = line.split()
    runs.setdefault(kind, []).append(float(secs))
e, f = statistics.median(runs["empty"]), statistics.median(runs["full"])
print(f"start-to-ready, median of {len(runs['full'])}: empty volume {e:.2f} s, "
      f"with the sessions {f:.2f} s ({f / e:.1f}x)")
PYEOF
podman_ image inspect --format '{{.Size}}' "$IMAGE" | awk '{printf "image size: %.1f MB\n", $1 / 1e6}'
