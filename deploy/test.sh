#!/usr/bin/env bash
# Set up, then lint, type-check and run every test (unit, slow and multi-process).
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/setup.sh
.venv/bin/ruff check .
.venv/bin/mypy wfnn_common wfnn_client wfnn_server sims wfnn_bench
.venv/bin/python -m pytest "$@"
