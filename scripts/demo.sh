#!/usr/bin/env bash
# Set up, then run the ROS 2 node live on the sample drive bag (play -> node -> record) and
# process the same bag offline with overlay pictures, survey it (one entry per pothole, report
# page); also detect on the bundled real pair.
# Results: out/demo/live_outputs (bag recorded from the live node), out/demo/processed (mcap
# with every output, opens in Foxglove), out/demo/pictures/*.png, out/demo/survey/, out/sample/.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
bin=.venv/bin
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-77}" ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
rm -rf out/demo out/sample
mkdir -p out/demo

"$bin/pothole_detector_node" --ros-args -r __ns:=/stereo \
    --params-file config/pothole_detector.yaml > out/demo/node.log 2>&1 &
node_pid=$!
"$bin/pothole-detector" record out/demo/live_outputs --topics /stereo/potholes \
    /stereo/disparity /stereo/pothole_points /stereo/pothole_markers /stereo/overlay \
    /diagnostics > out/demo/record.log 2>&1 &
record_pid=$!
trap 'kill -INT $node_pid $record_pid 2>/dev/null || true' EXIT
sleep 3
"$bin/pothole-detector" play bags/sample_drive --rate 0.5 --wait-for-subscribers 10
sleep 3
kill -INT "$record_pid"; wait "$record_pid" || true
kill -INT "$node_pid"; wait "$node_pid" || true
trap - EXIT
cat out/demo/record.log

"$bin/pothole-detector" process bags/sample_drive --out out/demo/processed \
    --pictures out/demo/pictures
"$bin/pothole-detector" survey bags/sample_drive --out out/demo/survey
"$bin/pothole-detector" detect \
    --left bags/sample_pair/left.png --right bags/sample_pair/right.png \
    --camera-info-left bags/sample_pair/left_camera_info.yaml \
    --camera-info-right bags/sample_pair/right_camera_info.yaml \
    --out out/sample
echo "live node outputs: out/demo/live_outputs; offline: out/demo/processed;" \
     "survey: out/demo/survey/report.html and survey.csv;" \
     "pictures: out/demo/pictures/ and out/sample/overlay.png"
