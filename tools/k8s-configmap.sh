#!/usr/bin/env bash
# Writes deploy/k8s/10-mcapi-cluster.yaml: the ConfigMap mcapi-cluster with
# the shard map (for the replicas) and HAProxy's configuration and map file
# (for the router), from `mcapi cluster plan` and
# `mcapi cluster haproxy-config --configmap`. The manifests thus cannot
# drift from the code: tests/integration/cluster/kubernetes.rs runs this script and compares.
#
#   bash tools/k8s-configmap.sh               # rewrites deploy/k8s/10-mcapi-cluster.yaml
#   bash tools/k8s-configmap.sh OUT.yaml      # writes elsewhere
#   REPLICAS=5 bash tools/k8s-configmap.sh    # a fresh map of 5 replicas (also set
#                                             # the StatefulSet's replicas to 5)
#   MAP=shards.map bash tools/k8s-configmap.sh   # from a given shard map
#   MCAPI_BIN=target/release/mcapi bash tools/k8s-configmap.sh
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bin="${MCAPI_BIN:-$root/target/debug/mcapi}"
out="${1:-$root/deploy/k8s/10-mcapi-cluster.yaml}"
replicas="${REPLICAS:-3}"
namespace=mcapi
# Fully qualified: HAProxy's resolvers do not use resolv.conf's search list.
host="{replica}.mcapi-headless.$namespace.svc.cluster.local"

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
map="${MAP:-}"
if [[ -z "$map" ]]; then
    map="$tmp/shards.map"
    "$bin" cluster plan --replicas "$replicas" --out "$map"
fi
"$bin" cluster haproxy-config --map "$map" --out-dir "$tmp/router" \
    --backend-template "$host:8080,$host:50051" --resolvers \
    --rest-bind :8080 --grpc-bind :50051 \
    --map-path /usr/local/etc/haproxy/shards.map \
    --stats-socket /var/run/haproxy/admin.sock --admin-bind 127.0.0.1:9999 \
    --configmap mcapi-cluster --namespace "$namespace"
cp "$tmp/router/mcapi-cluster.yaml" "$out"
echo "k8s-configmap.sh: wrote $out" >&2
