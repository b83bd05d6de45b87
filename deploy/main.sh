#!/usr/bin/env bash
# The main job: set up, start a think server on localhost, and run the simulated HyDrA active head
# learning 1-DOF visual servoing through it (right verge-axis joint, right camera x; swinging
# target; 15 Hz real time; act-learn-think-C/S over Zenoh). Extra arguments go to wfnn-client
# (e.g. --episodes 20, --regime static, --joints pan,tilt,left,right --axes left_x,left_y,right_x,right_y).
# Results: runs/main/ (client: weights, journal, metrics.json, learning_curve.png, cameras/;
# server/: store, checkpoint; server.log; report.html). A previous runs/main/ is kept as
# runs/main.<time>/. While it runs, the think server's live dashboard is on the printed address.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/setup.sh
if [ -e runs/main ]; then
  mv runs/main "runs/main.$(date +%Y%m%d-%H%M%S)"
fi
mkdir -p runs/main
read -r port web < <(.venv/bin/python -c 'from wfnn_server.spawn import free_port; print(free_port(), free_port())')
.venv/bin/wfnn-server --id think1 --controller main --listen "tcp/127.0.0.1:$port" \
  --data-dir runs/main/server --dashboard "$web" --quiet --verbose > runs/main/server.log 2>&1 &
server=$!
trap 'kill -TERM "$server" 2>/dev/null && wait "$server" 2>/dev/null; true' EXIT
.venv/bin/python -c "from wfnn_server.spawn import wait_listening; wait_listening($port)"
echo "think server think1 on tcp/127.0.0.1:$port (log: runs/main/server.log)"
echo "live dashboard: http://127.0.0.1:$web/"
.venv/bin/wfnn-client --sim hydra --episodes 8 --camera-every 75 --controller main \
  --server "tcp/127.0.0.1:$port" --out runs/main "$@"
.venv/bin/wfnn report runs/main
