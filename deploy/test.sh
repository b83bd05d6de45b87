#!/usr/bin/env bash
# Set up, then lint, type-check and run every test (unit, slow and multi-process).
set -euo pipefail
cd "$(dirname "$0")/.."
bash deploy/setup.sh
# The dashboard's end-to-end test drives Debian's headless Chromium; where it is missing and this
# script may install Debian packages, it does (otherwise that test is skipped, saying why).
if [ ! -x /usr/bin/chromium ] || [ ! -x /usr/bin/chromedriver ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get > /dev/null; then
    echo "installing Debian's chromium and chromium-driver for the dashboard's browser test"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      chromium chromium-driver > /dev/null || echo "could not install chromium: its test will be skipped"
  fi
fi
# The tests across hosts (network namespaces, marked netns) need iptables beside iproute2; where it
# is missing and this script may install Debian packages, it does (otherwise they are skipped).
if ! command -v iptables > /dev/null && [ "$(id -u)" = 0 ] && command -v apt-get > /dev/null; then
  echo "installing Debian's iptables for the tests across hosts"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    iptables > /dev/null || echo "could not install iptables: the tests across hosts will be skipped"
fi
.venv/bin/ruff check .
.venv/bin/mypy wfnn_common wfnn_io wfnn_client wfnn_server sims wfnn_bench
.venv/bin/python -m pytest "$@"
