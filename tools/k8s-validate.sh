#!/usr/bin/env bash
# Validates every Kubernetes manifest in deploy/k8s/ offline and strictly:
# kubernetes-validate (PyPI, pinned; its JSON schemas are bundled, so no
# cluster and no network are needed) against the schemas of one named
# Kubernetes version, failing on unknown fields (`--strict`), wrong types
# and missing required fields. Installed into .venv-tools/ at the
# repository root on first use, like tools/hadolint.sh.
#
#   bash tools/k8s-validate.sh                      # deploy/k8s/*.yaml
#   bash tools/k8s-validate.sh some.yaml            # the given files
#   K8S_VERSION=1.33.0 bash tools/k8s-validate.sh   # another Kubernetes
set -euo pipefail

KUBERNETES_VALIDATE_VERSION=1.37.0
# The oldest Kubernetes still supported upstream when these manifests were
# written; every field used (persistentVolumeClaimRetentionPolicy,
# appProtocol kubernetes.io/h2c, policy/v1) is older than it.
K8S_VERSION="${K8S_VERSION:-1.32.0}"

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv-tools"
kv="$venv/bin/kubernetes-validate"

# shellcheck source=tools/venv-tools.sh
source "$root/tools/venv-tools.sh"
venv_tools_install k8s-validate.sh kubernetes-validate "$KUBERNETES_VALIDATE_VERSION" "$kv"

cd "$root"
if [[ $# -eq 0 ]]; then
    shopt -s nullglob
    set -- deploy/k8s/*.yaml
    if [[ $# -eq 0 ]]; then
        echo "k8s-validate.sh: no manifests in deploy/k8s/" >&2
        exit 1
    fi
fi

# A canary first: a manifest with an unknown field must be refused, or a
# validator that passes everything (a schema missing, --strict ignored)
# would pass the real manifests too.
canary="$(mktemp --suffix=.yaml)"
trap 'rm -f "$canary"' EXIT
cat >"$canary" <<'YAML'
apiVersion: v1
kind: Service
metadata:
  name: canary
spec:
  selector:
    app: canary
  ports:
    - port: 8080
      targetPort: 8080
  sessionAfinity: None
YAML
if "$kv" --strict --kubernetes-version "$K8S_VERSION" "$canary" >/dev/null 2>&1; then
    echo "k8s-validate.sh: kubernetes-validate accepted an unknown field (sessionAfinity): it checks nothing" >&2
    exit 1
fi

"$kv" --strict --kubernetes-version "$K8S_VERSION" "$@"
echo "kubernetes-validate $KUBERNETES_VALIDATE_VERSION (Kubernetes $K8S_VERSION, strict): $# files valid"
