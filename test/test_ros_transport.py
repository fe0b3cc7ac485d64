"""The Fast DDS profile for camera-sized messages."""

from __future__ import annotations

import os

from pothole_detector.ros.transport import LARGE_IMAGE_PROFILE, large_image_transport

from conftest import REPO


def test_the_shipped_profile_is_chosen_unless_the_user_chose_one(monkeypatch):
    for name in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"):
        monkeypatch.setenv(name, "")  # restored, or removed again, after the test
        monkeypatch.delenv(name)
    large_image_transport()
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(REPO / "config" /
                                                               LARGE_IMAGE_PROFILE)
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", "/elsewhere/profile.xml")
    large_image_transport()
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/elsewhere/profile.xml"
