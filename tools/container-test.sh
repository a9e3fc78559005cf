#!/usr/bin/env bash
# `make container-test`: builds the image from the real Dockerfile with podman
# and proves it works as deployed:
#
#  1. base images: made locally when missing (tools/container-base.sh);
#  2. build: `podman build --format docker` (keeps HEALTHCHECK), with the
#     commit time as SOURCE_DATE_EPOCH and the version/revision as labels;
#  3. the image: user 10001, a health check, labels that match
#     `mcapi --version` and `git rev-parse HEAD`, its creation time equal to
#     SOURCE_DATE_EPOCH, no compiler or cargo inside, its size (bounded by
#     MAX_IMAGE_MB);
#  4. a container with a read-only root filesystem (only the /data volume
#     writable) and REST and gRPC published on loopback ports: sessions
#     created and driven over both transports (tools/container_drive.py);
#     `podman healthcheck run`; the process runs as 10001 and cannot write /;
#  5. SIGTERM (podman stop): a clean exit, code 0, well before the timeout;
#     a restart on the same volume has every tick and drive bit for bit;
#  6. SIGKILL while clients are mid-stream: after a restart every
#     acknowledged observation is there, and the sessions go on;
#  7. compose.yaml with podman-compose: API keys from the env file, the
#     named volume kept over `down` and `up`.
#
# Needs root and podman, runc, debootstrap (.ci/run installs them) and the
# Python client's venv (`make python-venv`). Logs and the ledger of
# acknowledged observations go to target/container/.
set -euo pipefail
cd "$(dirname "$0")/.."
source tools/podman.sh

PY=${PY:-clients/python/.venv/bin/python}
IMAGE=${IMAGE:-localhost/mcapi:test}
MAX_IMAGE_MB=${MAX_IMAGE_MB:-120}
PODMAN_COMPOSE_VERSION=1.6.0
OUT=target/container
NAME=mcapi-ct-$$
VOL=mcapi-ct-$$
mkdir -p "$OUT"
rm -f "$OUT"/ledger.json "$OUT"/podman.log "$OUT"/compose.log

log() { printf '[container-test %4ds] %s\n' "$SECONDS" "$*"; }
fail() {
  log "FAIL: $*"
  exit 1
}
drive() { "$PY" tools/container_drive.py "$1" --http "$HTTP" --grpc "$GRPC" --ledger "$OUT/ledger.json" "${@:2}"; }
# Ticks acknowledged so far, summed over the ledger's sessions.
acknowledged() {
  "$PY" -c 'import json,sys; print(sum(s["tick"] for s in json.load(open(sys.argv[1]))["sessions"].values()))' "$OUT/ledger.json"
}

cleanup() {
  status=$?
  if [ "$status" -ne 0 ] && podman_ container exists "$NAME" 2>/dev/null; then
    echo "--- container log (last 40 lines) ---"
    podman_ logs --tail 40 "$NAME" 2>&1 || true
  fi
  podman_ rm -f -t 0 "$NAME" >/dev/null 2>&1 || true
  podman_ volume rm -f "$VOL" >/dev/null 2>&1 || true
  exit "$status"
}
trap cleanup EXIT

[ "$(id -u)" -eq 0 ] || fail "needs root (rootful podman); run as root or with sudo"
[ -x "$PY" ] || fail "no Python client venv at $PY (make python-venv)"

# ---------------------------------------------------------------------------
log "base images"
bash tools/container-base.sh

SOURCE_DATE_EPOCH=${SOURCE_DATE_EPOCH:-$(git log -1 --format=%ct 2>/dev/null || echo 0)}
REVISION=${REVISION:-$(git rev-parse HEAD 2>/dev/null || echo unknown)}
VERSION=$(cargo metadata --no-deps --format-version 1 --locked \
  | "$PY" -c 'import json,sys; print(next(p["version"] for p in json.load(sys.stdin)["packages"] if p["name"] == "mcapi"))')
log "build $IMAGE (mcapi $VERSION, revision $REVISION, SOURCE_DATE_EPOCH=$SOURCE_DATE_EPOCH)"
build_start=$SECONDS
# The machine's CA bundle is mounted into RUN steps so cargo trusts the
# network's TLS (a proxy's CA on some CI machines). The labels are passed
# both ways: as build arguments (what the Dockerfile's LABEL uses, and all
# Docker needs) and as --label, because buildah's layer cache ignores ARG
# values in LABEL: after a commit that changes no compiled input (the
# binary is byte-identical), it would reuse the previous image, labels,
# creation time and all.
if ! podman_ build --format docker --network host \
    -v /etc/ssl/certs:/etc/ssl/certs:ro "${PODMAN_ULIMITS[@]}" \
    --timestamp "$SOURCE_DATE_EPOCH" \
    --build-arg SOURCE_DATE_EPOCH="$SOURCE_DATE_EPOCH" \
    --build-arg VERSION="$VERSION" --build-arg REVISION="$REVISION" \
    --label org.opencontainers.image.version="$VERSION" \
    --label org.opencontainers.image.revision="$REVISION" \
    -t "$IMAGE" . >"$OUT/build.log" 2>&1; then
  tail -40 "$OUT/build.log"
  fail "podman build (full log: $OUT/build.log)"
fi
log "built in $((SECONDS - build_start)) s"

# ---------------------------------------------------------------------------
log "image checks"
podman_ image inspect "$IMAGE" >"$OUT/image.json"
# (podman logs that it cannot reach systemd to schedule health checks on a
# machine without systemd: podman.log, not the console.)
podman_ run --rm "${PODMAN_ULIMITS[@]}" "$IMAGE" --version >"$OUT/version.txt" 2>>"$OUT/podman.log"
podman_ run --rm "${PODMAN_ULIMITS[@]}" --entrypoint /bin/sh "$IMAGE" -c \
  'for t in cc gcc ld cargo rustc make curl wget; do command -v "$t" || true; done' >"$OUT/tools.txt" 2>>"$OUT/podman.log"
"$PY" - "$OUT" "$VERSION" "$REVISION" "$SOURCE_DATE_EPOCH" "$MAX_IMAGE_MB" <<'PYEOF' || fail "image checks"
import datetime, json, sys
out, version, revision, epoch, max_mb = sys.argv[1:]
image = json.load(open(f"{out}/image.json"))[0]
cfg = image["Config"]
labels = cfg.get("Labels") or {}
printed = open(f"{out}/version.txt").read().split()
tools = open(f"{out}/tools.txt").read().split()
created = datetime.datetime.fromisoformat(image["Created"].replace("Z", "+00:00"))
size_mb = image["Size"] / 1e6
problems = []
def check(ok, what):
    print(("  ok   " if ok else "  FAIL ") + what)
    if not ok:
        problems.append(what)
check(cfg.get("User") == "10001:10001", f"runs as 10001:10001 (User={cfg.get('User')!r})")
hc = image.get("Healthcheck") or cfg.get("Healthcheck") or {}
check("healthcheck" in " ".join(hc.get("Test", [])), f"health check {hc.get('Test')}")
check(printed == ["mcapi", version], f"`mcapi --version` prints {' '.join(printed)!r}, Cargo.toml says {version}")
check(labels.get("org.opencontainers.image.version") == version, f"version label {labels.get('org.opencontainers.image.version')!r}")
check(labels.get("org.opencontainers.image.revision") == revision, f"revision label {labels.get('org.opencontainers.image.revision')!r}")
check(int(created.timestamp()) == int(epoch), f"created {image['Created']} = SOURCE_DATE_EPOCH {epoch}")
check(not tools, f"no build tools or curl in the image (found: {tools or 'none'})")
check(size_mb <= float(max_mb), f"image size {size_mb:.1f} MB <= {max_mb} MB")
open(f"{out}/image_size_mb.txt", "w").write(f"{size_mb:.1f}\n")
sys.exit(1 if problems else 0)
PYEOF

# ---------------------------------------------------------------------------
read -r HTTP_PORT GRPC_PORT < <("$PY" -c '
import socket
socks = [socket.socket() for _ in range(2)]
for s in socks: s.bind(("127.0.0.1", 0))
print(*[s.getsockname()[1] for s in socks])')
HTTP=http://127.0.0.1:$HTTP_PORT
GRPC=127.0.0.1:$GRPC_PORT
log "run with a read-only root filesystem, volume $VOL at /data, REST on $HTTP, gRPC on $GRPC"
podman_ run -d --name "$NAME" "${PODMAN_ULIMITS[@]}" \
  --read-only --read-only-tmpfs=false -v "$VOL:/data" \
  -p "127.0.0.1:$HTTP_PORT:8080" -p "127.0.0.1:$GRPC_PORT:50051" \
  "$IMAGE" >/dev/null 2>>"$OUT/podman.log"
ready=$(drive wait-ready --timeout 60) || fail "not ready"
log "ready after ${ready} s"

[ "$(podman_ exec "$NAME" id -u)" = 10001 ] || fail "the server does not run as uid 10001"
if podman_ exec "$NAME" sh -c ': > /probe' 2>/dev/null; then fail "the root filesystem is writable"; fi
podman_ exec "$NAME" sh -c ': > /data/.probe && rm /data/.probe' || fail "/data is not writable"
podman_ healthcheck run "$NAME" || fail "podman healthcheck run"
log "uid 10001, / read-only, /data writable, health check healthy"

drive create --sessions 4
drive drive --steps 25
log "sessions driven over REST and gRPC"

# ---------------------------------------------------------------------------
stop_start=$SECONDS
podman_ stop -t 30 "$NAME" >/dev/null 2>>"$OUT/podman.log"
code=$(podman_ inspect --format '{{.State.ExitCode}}' "$NAME")
[ "$code" = 0 ] || fail "exit code $code after SIGTERM (137 would mean it was killed after the timeout)"
[ $((SECONDS - stop_start)) -lt 20 ] || fail "SIGTERM took $((SECONDS - stop_start)) s"
podman_ logs "$NAME" 2>&1 | grep -q '"mcapi stopped"' || fail "no 'mcapi stopped' in the log after SIGTERM"
log "SIGTERM: clean exit (code 0) in $((SECONDS - stop_start)) s"

podman_ start "$NAME" >/dev/null 2>>"$OUT/podman.log"
drive wait-ready --timeout 60 >/dev/null || fail "not ready after the restart"
drive verify --exact || fail "state lost over a clean stop"

# ---------------------------------------------------------------------------
drive drive --until-error >"$OUT/drive_until_kill.log" 2>&1 &
driver=$!
before=$(acknowledged)
sleep 4
podman_ kill -s KILL "$NAME" >/dev/null 2>>"$OUT/podman.log"
wait "$driver" || { cat "$OUT/drive_until_kill.log"; fail "the driver failed"; }
after=$(acknowledged)
[ "$after" -gt "$before" ] || fail "no observation acknowledged before the kill"
code=$(podman_ inspect --format '{{.State.ExitCode}}' "$NAME")
log "SIGKILL mid-stream after $((after - before)) more acknowledged observations (exit code $code)"

podman_ start "$NAME" >/dev/null 2>>"$OUT/podman.log"
ready=$(drive wait-ready --timeout 60) || fail "not ready after SIGKILL"
log "restarted on the same volume, ready after ${ready} s"
drive verify || fail "acknowledged observations lost to SIGKILL"
drive drive --steps 5
log "sessions go on after recovery"
podman_ stop -t 30 "$NAME" >/dev/null 2>>"$OUT/podman.log"
podman_ rm -f -t 0 "$NAME" >/dev/null 2>>"$OUT/podman.log"

# ---------------------------------------------------------------------------
# compose.yaml as a user runs it (podman-compose, pinned, in .venv-tools/):
# the image it names, keys from the env file, the named volume kept over
# `down` and `up`.
venv=.venv-tools
if ! "$venv/bin/python" -c 'import importlib.metadata as m; assert m.version("podman-compose") == "'"$PODMAN_COMPOSE_VERSION"'"' 2>/dev/null; then
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "podman-compose==$PODMAN_COMPOSE_VERSION"
fi
project=$NAME
compose_dir=$(mktemp -d)
cp compose.yaml "$compose_dir/"
key=ct-$(head -c 12 /dev/urandom | od -An -tx1 | tr -d ' \n')
printf 'MCAPI_API_KEYS=%s\n' "$key" >"$compose_dir/mcapi.env"
podman_ tag "$IMAGE" localhost/mcapi:latest
compose() {
  MCAPI_HTTP_PORT=$HTTP_PORT MCAPI_GRPC_PORT=$GRPC_PORT "$venv/bin/podman-compose" \
    --podman-args "${PODMAN#podman }" --podman-run-args "${PODMAN_ULIMITS[*]}" \
    -p "$project" -f "$compose_dir/compose.yaml" "$@" >>"$OUT/compose.log" 2>&1
}
compose_cleanup() {
  compose down -v || true
  rm -rf "$compose_dir"
}
trap 'compose_cleanup; cleanup' EXIT
compose up -d || fail "podman-compose up (log: $OUT/compose.log)"
drive wait-ready --timeout 60 >/dev/null || fail "compose: not ready"
status=$("$PY" -c 'import httpx,sys; print(httpx.get(sys.argv[1] + "/v1/sessions").status_code)' "$HTTP")
[ "$status" = 401 ] || fail "compose: a request without the env file's key got $status, not 401"
sid=$("$PY" -c '
import sys
from mcapi_client import Client
with Client(sys.argv[1], api_key=sys.argv[2]) as c:
    s = c.create_session("hallway", seed=1)
    c.observe(s.id, 3)
    c.observe(s.id, 4, [0.0, 0.0])
    print(s.id)' "$HTTP" "$key") || fail "compose: create with the key"
compose down || fail "podman-compose down"
compose up -d || fail "podman-compose up again"
drive wait-ready --timeout 60 >/dev/null || fail "compose: not ready after down/up"
"$PY" -c '
import sys
from mcapi_client import Client
with Client(sys.argv[1], api_key=sys.argv[2]) as c:
    info = c.get_session(sys.argv[3])
    assert (info.tick, info.state) == (1, 4), info' "$HTTP" "$key" "$sid" || fail "compose: the session did not survive down/up"
log "compose.yaml: keys from the env file, the session kept in the named volume over down/up"
log "passed (image $(cat "$OUT/image_size_mb.txt") MB)"
