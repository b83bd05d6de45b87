#!/usr/bin/env bash
# The main job: set up, start a think server on localhost, and run a simulated robot that learns
# through it (act-learn-think-C/S over Zenoh). Until the HyDrA simulation exists the robot is the
# boat; extra arguments go to wfnn-client (e.g. --sim positioning --episodes 20).
# Results: runs/main/ (client: weights, journal, metrics.json, learning_curve.png;
# server/: store, checkpoint; server.log). A previous runs/main/ is kept as runs/main.<time>/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/setup.sh
if [ -e runs/main ]; then
  mv runs/main "runs/main.$(date +%Y%m%d-%H%M%S)"
fi
mkdir -p runs/main
port=$(.venv/bin/python -c 'from wfnn_server.spawn import free_port; print(free_port())')
.venv/bin/wfnn-server --id local --controller main --listen "tcp/127.0.0.1:$port" \
  --data-dir runs/main/server --quiet --verbose > runs/main/server.log 2>&1 &
server=$!
trap 'kill -TERM "$server" 2>/dev/null && wait "$server" 2>/dev/null; true' EXIT
.venv/bin/python -c "from wfnn_server.spawn import wait_listening; wait_listening($port)"
echo "think server 'local' on tcp/127.0.0.1:$port (log: runs/main/server.log)"
.venv/bin/wfnn-client --sim boat --controller main --server "tcp/127.0.0.1:$port" --out runs/main "$@"
