#!/usr/bin/env bash
# One command, fresh machine: install everything, then run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# One BLAS thread: the solver's matrices are small, and on 2 cores a second BLAS thread per
# process only competes with the other (measured: a 6000x24 J^T J took 254 ms instead of 0.26 ms
# on a loaded machine).
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
exec .venv/bin/python -m pytest "$@"
