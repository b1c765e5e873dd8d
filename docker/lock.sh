#!/usr/bin/env bash
# Regenerate docker/requirements.lock: `pip install '.[fleet]'` in a clean virtualenv of the
# image's Python (3.11), then `pip freeze`, under the lock file's header comment.
#   bash docker/lock.sh            (PYTHON=python3.11 by default)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3.11}"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$PYTHON" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install -q --upgrade pip
"$tmp/venv/bin/python" -m pip install -q '.[fleet]'
{
  sed -n '/^#/p' docker/requirements.lock
  "$tmp/venv/bin/python" -m pip freeze --exclude-editable | grep -v '^recal @'
} > "$tmp/requirements.lock"
mv "$tmp/requirements.lock" docker/requirements.lock
echo "docker/requirements.lock: $(grep -vc '^#' docker/requirements.lock) pinned packages"
