#!/usr/bin/env bash
# The main job: set up, then a simulated robot learning with thinking in a background thread.
# Until the HyDrA simulation exists this is the boat task; extra arguments go to wfnn-client.
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/setup.sh
exec .venv/bin/wfnn-client --sim boat --out runs/main "$@"
