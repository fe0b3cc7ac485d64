#!/usr/bin/env bash
# Build msg_schemas/ (pothole_detector_msgs) with CMake and the pip ROS wheels and install it
# into .venv, so rclpy imports pothole_detector_msgs.msg. Skipped when the .msg files and the
# build files are unchanged since the last build.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="$(pwd)/.venv"
stamp="$venv/.pothole_detector_msgs.sha256"
digest="$(cat msg_schemas/CMakeLists.txt msg_schemas/package.xml msg_schemas/msg/*.msg \
    | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$digest" ] \
    && "$venv/bin/python" -c "import pothole_detector_msgs.msg" 2>/dev/null; then
    exit 0
fi
build="$(pwd)/build/msgs"
rm -rf "$build"
mkdir -p "$build"
export AMENT_PREFIX_PATH="$venv"
cmake -S msg_schemas -B "$build" -DCMAKE_PREFIX_PATH="$venv" -DCMAKE_INSTALL_PREFIX="$venv" \
    -DPython3_EXECUTABLE="$venv/bin/python" -DBUILD_TESTING=OFF > "$build.log" 2>&1 \
    || { cat "$build.log"; exit 1; }
cmake --build "$build" -j "$(nproc)" >> "$build.log" 2>&1 || { tail -50 "$build.log"; exit 1; }
cmake --install "$build" >> "$build.log" 2>&1 || { tail -50 "$build.log"; exit 1; }
echo "$digest" > "$stamp"
