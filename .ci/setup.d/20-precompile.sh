#!/usr/bin/env bash
# Compile the numba kernels once after the install (semcal_tools/precompile.py): numba caches them
# in __pycache__ beside the sources, so the first calibration, the demo and the test suite start
# from compiled code instead of spending ~1 minute (2 cores) compiling in whichever process comes
# first. Called by .ci/setup-env.sh with $VENV set; a later source change recompiles on first use.
set -euo pipefail
cd "$(dirname "$0")/../.."
VENV=$(cd "${VENV:-.venv}" && pwd)
"$VENV/bin/python" -m semcal_tools.precompile
