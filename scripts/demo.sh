#!/usr/bin/env bash
# One command, fresh machine: install everything, then calibrate the shipped sample.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/calib3r-graph solve datasets/sample --out results/sample "$@"
