#!/usr/bin/env bash
# Create .venv (Python 3.11), install pothole_detector with ROS 2 Jazzy from pip wheels, Ray and
# its test tools, and build our messages (pothole_detector_msgs) into the same prefix.
set -euo pipefail
cd "$(dirname "$0")/.."
python="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    "$python" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[test,ros,msgs,fleet,gis]"
scripts/build_msgs.sh
# the CPU kernels (Numba) compiled into their cache now: no first run waits for the compiler
.venv/bin/python -m pothole_detector.stages
.venv/bin/python -c "from pothole_detector.survey.roadmap import compile_map_kernels as c; c()"
