# On the GPU machine (Python 3.12, CUDA, no ROS), from the repository root:
#   source scripts/gpu_machine/env.sh
# Makes a virtual environment in $ROS_VENV (default /tmp/ros_venv) that sees the image's own
# packages (CuPy, NumPy, OpenCV), installs the ROS 2 runtime from .gpu_machine/wheels, puts
# this repository on its path (python -m pothole_detector.ros.node, python -m pothole_detector.cli)
# and unpacks our messages from .gpu_machine/pothole_detector_msgs-cp312.tar.gz.
# When that archive is missing, it builds the messages there with CMake (from
# .gpu_machine/build_wheels) and writes the archive to $OUT (or .gpu_machine/): bring it back
# into .gpu_machine/ once and later runs only unpack it. Then activates the environment.
# Wheels: scripts/gpu_machine/fetch_wheels.sh, here. Exits (returns) non-zero on failure.
_pd_setup() {
    local venv="${ROS_VENV:-/tmp/ros_venv}" archive=.gpu_machine/pothole_detector_msgs-cp312.tar.gz
    local base_python base_site
    base_python="$(command -v python3)"
    [ -d .gpu_machine/wheels ] || {
        echo "no .gpu_machine/wheels: run scripts/gpu_machine/fetch_wheels.sh here first and" \
             "name .gpu_machine in the run's carry" >&2; return 2; }
    base_site="$("$base_python" -c 'import site; print(site.getsitepackages()[0])')"
    if [ ! -x "$venv/bin/python" ]; then
        "$base_python" -m venv --without-pip "$venv" || return 1
        "$venv/bin/python" -c 'import site; print(site.getsitepackages()[0])' \
            | xargs -I{} sh -c "echo '$base_site' > {}/gpu_machine_image.pth" || return 1
    fi
    "$base_python" -m pip --python "$venv/bin/python" install --quiet --no-index --no-deps \
        --no-compile .gpu_machine/wheels/*.whl || return 1
    if [ -f "$archive" ]; then
        tar -xzf "$archive" -C "$venv" || return 1
    else
        "$base_python" -m pip --python "$venv/bin/python" install --quiet --no-index \
            --no-deps --no-compile .gpu_machine/build_wheels/*.whl || return 1
        local built="${OUT:-.gpu_machine}/pothole_detector_msgs-cp312.tar.gz"
        scripts/build_msgs.sh "$venv" "$built" || return 1
        echo "built our messages for $("$venv/bin/python" -V); bring $built back into" \
             ".gpu_machine/ so later runs only unpack it" >&2
    fi
    local venv_site
    venv_site="$("$venv/bin/python" -c 'import site; print(site.getsitepackages()[0])')"
    pwd > "$venv_site/pothole_detector_repo.pth"
    export PATH="$venv/bin:$PATH" VIRTUAL_ENV="$venv" AMENT_PREFIX_PATH="$venv"
    export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
    export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
    python -c "import rclpy, pothole_detector_msgs.msg" || return 1
}
_pd_setup
