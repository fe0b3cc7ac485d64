#!/usr/bin/env bash
# Set up and run detection on the bundled real sample pair; results land in out/sample/.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
.venv/bin/pothole-detector detect \
    --left bags/sample_pair/left.png --right bags/sample_pair/right.png \
    --camera-info-left bags/sample_pair/left_camera_info.yaml \
    --camera-info-right bags/sample_pair/right_camera_info.yaml \
    --out out/sample
echo "open out/sample/overlay.png; numbers in out/sample/potholes.json"
