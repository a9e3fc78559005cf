#!/usr/bin/env bash
# The REST contract, fuzzed: schemathesis against a live server.
#
# Installs a pinned schemathesis into .venv-tools/ (like tools/hadolint.sh),
# starts the debug binary (`make build`) with an in-memory store and an API
# key on free loopback ports, waits for /readyz, runs every phase (examples,
# coverage, fuzzing, stateful) with every check against /v1/openapi.json,
# then checks that the server is still up and answering quickly, and stops
# it. Exits non-zero on any schemathesis failure or if the server died.
#
#   bash tools/contract.sh                   # the bounded run of `make test`
#   CONTRACT_MAX_EXAMPLES=500 bash tools/contract.sh   # longer
#   MCAPI_BIN=target/release/mcapi bash tools/contract.sh
#
# Reports (JUnit XML, NDJSON events) go to target/contract/.
set -euo pipefail

SCHEMATHESIS_VERSION=4.32.5

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv-tools"
st="$venv/bin/schemathesis"
bin="${MCAPI_BIN:-$root/target/debug/mcapi}"
max_examples="${CONTRACT_MAX_EXAMPLES:-200}"

reports="$root/target/contract"

# shellcheck source=tools/venv-tools.sh
source "$root/tools/venv-tools.sh"
venv_tools_install contract.sh schemathesis "$SCHEMATHESIS_VERSION" "$st"

if [[ ! -x "$bin" ]]; then
    echo "contract.sh: $bin is missing; run \`make build\` first" >&2
    exit 2
fi

free_port() {
    python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1]); s.close()'
}
http_port="$(free_port)"
grpc_port="$(free_port)"
base="http://127.0.0.1:$http_port"
key="contract-$(python3 -c 'import secrets; print(secrets.token_hex(16))')"
mkdir -p "$reports"
log="$reports/server.log"

# Groups of at most 16 members: a generated `n` builds that many sessions in
# the debug build within the response-time check (the bound is the
# document's, so schemathesis generates within it).
"$bin" serve --store memory --http "127.0.0.1:$http_port" --grpc "127.0.0.1:$grpc_port" \
    --api-key "$key" --max-group-members 16 --log-format text >"$log" 2>&1 &
server=$!
stop_server() {
    if kill -0 "$server" 2>/dev/null; then
        kill -TERM "$server"
        wait "$server" 2>/dev/null || true
    fi
}
trap stop_server EXIT

for _ in $(seq 1 300); do
    if curl -fsS "$base/readyz" >/dev/null 2>&1; then
        break
    fi
    if ! kill -0 "$server" 2>/dev/null; then
        echo "contract.sh: the server exited at start; its log:" >&2
        cat "$log" >&2
        exit 1
    fi
    sleep 0.1
done
curl -fsS "$base/readyz" >/dev/null

echo "contract.sh: schemathesis $SCHEMATHESIS_VERSION against $base (max-examples $max_examples)"
status=0
(
    # Its cache goes to the working directory: keep it under target/.
    cd "$reports"
    PYTHONPATH="$root/tools" SCHEMATHESIS_HOOKS=schemathesis_hooks "$st" --config-file "$root/tools/schemathesis.toml" run \
        "$base/v1/openapi.json" \
        --header "Authorization: Bearer $key" \
        --phases examples,coverage,fuzzing,stateful \
        --checks all \
        --max-examples "$max_examples" \
        --seed "${CONTRACT_SEED:-1}" \
        --workers 2 \
        --generation-database none \
        --report junit,ndjson --report-dir "$reports" \
        --no-color
) || status=$?

# The server must have survived, and still answer at once.
if ! kill -0 "$server" 2>/dev/null; then
    echo "contract.sh: the server died during the run; the end of its log:" >&2
    tail -n 50 "$log" >&2
    exit 1
fi
took=$(curl -fsS -o /dev/null -w '%{time_total}' "$base/healthz")
rss_kib=$(awk '/^VmRSS:/ {print $2}' "/proc/$server/status")
echo "contract.sh: server alive after the run; /healthz took ${took}s; RSS $((rss_kib / 1024)) MiB"
if python3 -c "import sys; sys.exit(0 if float('$took') < 1.0 else 1)"; then :; else
    echo "contract.sh: the server answers /healthz slowly after the run (${took}s)" >&2
    exit 1
fi
if grep -q "panicked" "$log"; then
    echo "contract.sh: the server log shows a panic:" >&2
    grep -n -A5 "panicked" "$log" >&2
    exit 1
fi
exit "$status"
