#!/usr/bin/env bash
# Set up and run the whole test suite (real-data tests skip when ../shared/data is absent).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
# headless Chromium checks report.html (test_survey_report.py skips without it): Debian's package
if ! command -v chromium > /dev/null && command -v apt-get > /dev/null && [ "$(id -u)" = 0 ]; then
    apt-get install -y -q chromium > /dev/null 2>&1 \
        || echo "note: could not install chromium; the report's browser check will skip"
fi
.venv/bin/python -m pytest -q -p no:cacheprovider test "$@"
