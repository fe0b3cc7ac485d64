#!/usr/bin/env bash
# Build msg_schemas/ (pothole_detector_msgs) with CMake and the pip ROS wheels and install it
# into a virtual environment (default .venv), so rclpy imports pothole_detector_msgs.msg.
# Skipped when the .msg files and the build files are unchanged since the last build.
#   scripts/build_msgs.sh [VENV [ARCHIVE]]
# With ARCHIVE, also pack every installed file (paths relative to VENV) into ARCHIVE (.tar.gz),
# which scripts/gpu_machine/env.sh unpacks into a fresh environment of the same Python.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="$(realpath "${1:-.venv}")"
archive="${2:-}"
stamp="$venv/.pothole_detector_msgs.sha256"
digest="$(cat msg_schemas/CMakeLists.txt msg_schemas/package.xml msg_schemas/msg/*.msg \
    | sha256sum | cut -d' ' -f1)"
build="$(pwd)/build/msgs-$(basename "$venv")"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$digest" ] \
    || { [ -n "$archive" ] && [ ! -f "$build/install_manifest.txt" ]; } \
    || ! "$venv/bin/python" -c "import pothole_detector_msgs.msg" 2>/dev/null; then
    rm -rf "$build"
    mkdir -p "$build"
    export AMENT_PREFIX_PATH="$venv"
    cmake -S msg_schemas -B "$build" -DCMAKE_PREFIX_PATH="$venv" -DCMAKE_INSTALL_PREFIX="$venv" \
        -DPython3_EXECUTABLE="$venv/bin/python" -DBUILD_TESTING=OFF > "$build.log" 2>&1 \
        || { cat "$build.log"; exit 1; }
    cmake --build "$build" -j "$(nproc)" >> "$build.log" 2>&1 || { tail -50 "$build.log"; exit 1; }
    cmake --install "$build" >> "$build.log" 2>&1 || { tail -50 "$build.log"; exit 1; }
    echo "$digest" > "$stamp"
fi
if [ -n "$archive" ]; then
    { awk 1 "$build/install_manifest.txt"; echo "$stamp"; } | sed "s|^$venv/||" \
        > "$build/relative_manifest.txt"
    tar -czf "$archive" -C "$venv" -T "$build/relative_manifest.txt"
fi
