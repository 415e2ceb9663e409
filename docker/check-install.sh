#!/usr/bin/env bash
# CI's stand-in for building the image (no Docker engine here): run the Dockerfile's install steps
# (docker/install.sh) in a fresh virtual environment, start the server from it outside the source tree,
# check /healthz and /readyz, then stop it with SIGTERM and expect a clean exit.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
work="$(mktemp -d)"
trap 'kill "${pid:-}" 2>/dev/null || true; rm -rf "$work"' EXIT
python3 -m venv "$work/venv"
PATH="$work/venv/bin:$PATH"
export PATH
(cd "$work" && sh "$root/docker/install.sh" "$root")
cd "$work"
egoposevr serve --host 127.0.0.1 --port 0 2>"$work/log" &
pid=$!
for _ in $(seq 1 120); do
    grep -q "on ws://" "$work/log" && break
    sleep 0.5
done
port="$(grep -o 'ws://127.0.0.1:[0-9]*' "$work/log" | head -1 | cut -d: -f3)"
[ -n "$port" ] || { cat "$work/log"; echo "check-install: the server did not start" >&2; exit 1; }
python - "$port" <<'PY'
import sys, urllib.request
# The viewer's files are package data: the page, a nested vendored module and the avatar must be installed.
for path in ("/healthz", "/readyz", "/viewer/", "/viewer/vendor/three/addons/loaders/GLTFLoader.js",
             "/viewer/vendor/three-vrm/three-vrm.module.min.js", "/viewer/avatar/mannequin.vrm"):
    with urllib.request.urlopen(f"http://127.0.0.1:{sys.argv[1]}{path}", timeout=5) as reply:
        assert reply.status == 200, (path, reply.status)
print("check-install: /healthz, /readyz and the viewer's files answer 200 from the image's install steps")
PY
kill -TERM "$pid"
wait "$pid"
echo "check-install: server stopped cleanly"
