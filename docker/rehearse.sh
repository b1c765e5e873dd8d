#!/usr/bin/env bash
# The image's build and start, rehearsed without a Docker engine (the development machines have
# none): the same steps as docker/Dockerfile in a clean virtualenv of the image's Python, as an
# unprivileged user where this runs as root, then the image's HEALTHCHECK command against the
# started service. It proves the lock installs on its own (nothing resolved outside it: --no-deps)
# and that the service starts and answers with exactly those packages. It does not prove the base
# image or the Docker engine's behaviour (a `docker build` does).
#   bash docker/rehearse.sh            (PYTHON=python3.11 by default; PORT=18000)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3.11}"
PORT="${PORT:-18000}"
tmp="$(mktemp -d)"
chmod 755 "$tmp"
cleanup() { [ -n "${pid:-}" ] && kill "$pid" 2>/dev/null; rm -rf "$tmp"; }
trap cleanup EXIT
"$PYTHON" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install -q --upgrade pip
# RUN pip install --no-cache-dir -r docker/requirements.lock
"$tmp/venv/bin/python" -m pip install -q --no-cache-dir -r docker/requirements.lock
# COPY ... ; RUN pip install --no-cache-dir --no-deps '.[fleet]'
mkdir "$tmp/src" && cp -r pyproject.toml README.md calibration drivers fakes service "$tmp/src/"
"$tmp/venv/bin/python" -m pip install -q --no-cache-dir --no-deps "$tmp/src[fleet]"
"$tmp/venv/bin/python" -m pip check
# USER recal; ENV RECAL_HOME=/var/lib/recal; CMD ["recal", "serve", ...]
mkdir -p "$tmp/home"
as_user=()
if [ "$(id -u)" = 0 ] && id nobody >/dev/null 2>&1; then
  chown nobody "$tmp/home"
  as_user=(setpriv --reuid=nobody --regid=nogroup --clear-groups)
fi
( cd "$tmp" && RECAL_HOME="$tmp/home" "${as_user[@]}" "$tmp/venv/bin/recal" serve --host 127.0.0.1 --port "$PORT" \
    >"$tmp/serve.log" 2>&1 ) &
pid=$!
# HEALTHCHECK --start-period=20s ... CMD python -c "... urlopen('http://127.0.0.1:8000/api/v1/health') ..."
for _ in $(seq 1 40); do
  if "$tmp/venv/bin/python" -c "import sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:$PORT/api/v1/health', timeout=2).status != 200)" 2>/dev/null; then
    echo "rehearsal: the lock installed ($(grep -vc '^#' docker/requirements.lock) pins, pip check clean), the service started as $(stat -c %U "$tmp/home") and its healthcheck passed"
    exit 0
  fi
  sleep 0.5
done
echo "rehearsal: the healthcheck did not pass within 20 s; the service's log:" >&2
cat "$tmp/serve.log" >&2
exit 1
