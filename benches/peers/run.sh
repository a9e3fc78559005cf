#!/usr/bin/env bash
# Runs the numpy peer baseline of the MCA-PI tick (see README.md).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
venv="$here/.venv"

if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
fi
"$venv/bin/pip" install --quiet --disable-pip-version-check 'numpy==2.3.*' >&2

cd "$root"
exec "$venv/bin/python" benches/peers/tick_numpy.py
