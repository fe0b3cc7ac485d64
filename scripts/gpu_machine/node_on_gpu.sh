#!/usr/bin/env bash
# On the GPU machine, from the repository root (with .gpu_machine carried): set up ROS there
# (env.sh), run the node's tests with the GPU backend, then the node benchmark at the issue's
# sizes and rates. Writes node_tests.txt and bench_node.md to $OUT (or out/gpu_machine/).
set -uo pipefail
cd "$(dirname "$0")/../.."
out="${OUT:-out/gpu_machine}"
mkdir -p "$out"
export PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
# shellcheck source=env.sh
source scripts/gpu_machine/env.sh || exit 1
nvidia-smi --query-gpu=name --format=csv,noheader > "$out/device.txt"
timeout 230 python -m pytest -q -p no:cacheprovider test/test_ros_node.py test/test_ros_conversions.py \
    > "$out/node_tests.txt" 2>&1
echo "tests rc $?" >> "$out/node_tests.txt"
timeout 300 python benchmarks/bench_node.py --backend gpu --sizes 1280x720 2079x1040 \
    --rates 30 60 --seconds 10 "$@" > "$out/bench_node.md" 2>&1
echo "bench rc $?" >> "$out/bench_node.md"
