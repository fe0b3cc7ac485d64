"""Launch the pothole detector for a stereo camera (ROS 2 Jazzy: ros2 launch pothole_detector
pothole_detector.launch.py).

    ros2 launch pothole_detector pothole_detector.launch.py namespace:=/stereo \
        left_image:=/zed/zed_node/left_raw/image_raw_color \
        right_image:=/zed/zed_node/right_raw/image_raw_color \
        left_camera_info:=/zed/zed_node/left_raw/camera_info \
        right_camera_info:=/zed/zed_node/right_raw/camera_info \
        image_transport:=compressed backend:=gpu

The node takes rectified or raw images (raw ones are rectified from their camera_info: the
rectify parameter, auto by default), as sensor_msgs/Image or, with image_transport:=compressed,
as the CompressedImage topics ``<image>/compressed``; the arguments remap its inputs to the
camera driver's topics. Its outputs are under ``namespace``; config/foxglove_layout.json shows
them in Foxglove."""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = "pothole_detector"
ARGUMENTS = {
    "namespace": ("/stereo", "namespace of the node and its outputs"),
    "left_image": ("left/image_rect", "the left camera's image topic (raw or rectified; "
                   "without /compressed)"),
    "right_image": ("right/image_rect", "the right camera's image topic"),
    "left_camera_info": ("left/camera_info", "the left camera's camera_info topic"),
    "right_camera_info": ("right/camera_info", "the right camera's camera_info topic"),
    "image_transport": ("raw", "raw (sensor_msgs/Image) or compressed (CompressedImage)"),
    "rectify": ("auto", "auto, on or off: rectify the images from camera_info"),
    "backend": ("auto", "auto, cpu or gpu"),
    "baseline_m": ("0.0", "baseline (m) where the right camera_info has none (P[0,3] = 0)"),
    "params_file": ("", "a parameter file (default: the package's "
                    "config/pothole_detector.yaml)"),
}


def generate_launch_description() -> LaunchDescription:
    """The node with the package's parameter file (or params_file), the arguments'
    parameters, and its four inputs remapped to the camera's topics (image topics with the
    transport's suffix)."""
    config = LaunchConfiguration
    default_params = PathJoinSubstitution([FindPackageShare(PACKAGE), "config",
                                           "pothole_detector.yaml"])
    params_file = PythonExpression(["'", config("params_file"), "' or '", default_params, "'"])
    suffix = PythonExpression(["'/compressed' if '", config("image_transport"),
                               "' == 'compressed' else ''"])
    node = Node(
        package=PACKAGE, executable="pothole_detector_node", name="pothole_detector",
        namespace=config("namespace"), output="screen", emulate_tty=True,
        parameters=[params_file, {
            "image_transport": config("image_transport"), "rectify": config("rectify"),
            "backend": config("backend"),
            "baseline_m": PythonExpression(["float(", config("baseline_m"), ")"])}],
        remappings=[
            (["left/image_rect", suffix], [config("left_image"), suffix]),
            (["right/image_rect", suffix], [config("right_image"), suffix]),
            ("left/camera_info", config("left_camera_info")),
            ("right/camera_info", config("right_camera_info")),
        ])
    return LaunchDescription([DeclareLaunchArgument(name, default_value=default,
                                                    description=description)
                              for name, (default, description) in ARGUMENTS.items()] + [node])
