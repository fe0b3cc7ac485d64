"""The Fast DDS transport profile for camera-sized messages between processes."""

from __future__ import annotations

import os
from pathlib import Path

from ..params import NODE_NAME

LARGE_IMAGE_PROFILE = "fastdds_large_images.xml"


def large_image_transport() -> None:
    """Point Fast DDS at config/fastdds_large_images.xml (32 MiB shared memory, 4 MiB socket
    buffers) unless the user chose a profile; call before rclpy.init. Without it, camera
    images between processes on this host arrive in bursts seconds late."""
    if os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE") or \
            os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE"):
        return
    profile = Path(__file__).resolve().parents[2] / "config" / LARGE_IMAGE_PROFILE
    if not profile.is_file():
        try:
            from ament_index_python.packages import get_package_share_directory
            profile = Path(get_package_share_directory(NODE_NAME)) / "config" / \
                LARGE_IMAGE_PROFILE
        except (ImportError, LookupError, OSError):
            return
    if profile.is_file():
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
