#!/usr/bin/env bash
# Set up and run the whole test suite (real-data tests skip when ../shared/data is absent).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
.venv/bin/python -m pytest -q -p no:cacheprovider test "$@"
