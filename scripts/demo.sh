#!/usr/bin/env bash
# The README's first command: install (if needed), serve models/ on loopback, ask the demo scene a few
# questions with the thin client, write a relevancy PNG and a PLY, then stop the server.
#   bash scripts/demo.sh [OUT_DIR]        (default demo_out/)
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/fmgs ] && [ -x .venv/bin/fmgs-client ] || bash .ci/install
out=${1:-demo_out}
mkdir -p "$out"
port=${FMGS_DEMO_PORT:-50061}
addr="127.0.0.1:$port"
.venv/bin/fmgs serve --models models --port "$port" --preload >"$out/server.log" 2>&1 &
pid=$!
trap 'kill -TERM $pid 2>/dev/null || true; wait $pid 2>/dev/null || true' EXIT
# FMGS_CLIENT: another fmgs-client to use (CI runs one from a venv without torch).
client() { "${FMGS_CLIENT:-.venv/bin/fmgs-client}" --address "$addr" "$@"; }
for _ in $(seq 1 180); do
  if client health >/dev/null 2>&1; then break; fi
  if ! kill -0 "$pid" 2>/dev/null; then cat "$out/server.log"; echo "server exited" >&2; exit 1; fi
  sleep 1
done
client health
client list
client info demo
client query demo "red cube" "blue ball" "something to sit on" --top-k 300 --threshold 0.5 --instances \
  --rows 5 --ply "$out/query.ply"
client render demo "red cube" --out "$out/relevancy_red_cube.png" --rgb "$out/rgb.png"
client segment demo "red cube" "blue ball" "green cylinder" "yellow cone" "floor" --out "$out/segment.png"
client stream demo "blue ball" --frames 12
echo "wrote: $(ls "$out" | tr '\n' ' ')"
