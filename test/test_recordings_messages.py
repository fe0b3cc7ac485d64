"""Messages without ROS: typestore classes with ROS defaults and constants, CDR round trips."""

from __future__ import annotations

import numpy as np

from pothole_detector.recordings.messages import (StoreMessage, deserialize, message, serialize,
                                                  typestore)


def test_store_messages_default_every_field_and_carry_constants():
    marker = StoreMessage("visualization_msgs/msg/Marker")(ns="outline")
    assert marker.ns == "outline" and marker.id == 0 and marker.points == []
    assert marker.pose.orientation.w == 1.0 and marker.header.frame_id == ""
    assert StoreMessage("visualization_msgs/msg/Marker").DELETEALL == 3
    info = StoreMessage("sensor_msgs/msg/CameraInfo")(k=[1.0] * 9)
    assert info.k.dtype == np.float64 and info.p.shape == (12,)
    array = StoreMessage("pothole_detector_msgs/msg/PotholeArray")
    assert {array.PROCESSED, array.NOT_OBSERVED, array.FAILED} == {0, 1, 2}


def test_store_messages_serialize_like_the_typestore_reads():
    image = StoreMessage("sensor_msgs/msg/Image")(height=2, width=3, encoding="mono8", step=3,
                                                  data=np.arange(6, dtype=np.uint8))
    raw = bytes(typestore().serialize_cdr(image, "sensor_msgs/msg/Image"))
    back = typestore().deserialize_cdr(raw, "sensor_msgs/msg/Image")
    assert (back.height, back.width, back.encoding) == (2, 3, "mono8")
    np.testing.assert_array_equal(back.data, np.arange(6))


def test_serialize_and_deserialize_round_trip_with_either_kind():
    header = message("std_msgs/msg/Header")(frame_id="cam")
    header.stamp.sec = 12
    raw = serialize(header, "std_msgs/msg/Header")
    back = deserialize(raw, "std_msgs/msg/Header")
    assert (back.frame_id, back.stamp.sec) == ("cam", 12)


def test_typestore_knows_our_messages():
    store = typestore()
    names = [n for n, *_ in store.fielddefs["pothole_detector_msgs/msg/PotholeArray"][1]]
    assert names == ["header", "status", "reason", "a0", "a1", "roll_deg", "inlier_fraction",
                     "observed_near_m", "observed_far_m", "potholes"]
    assert "bbox_px" in [n for n, *_ in store.fielddefs["pothole_detector_msgs/msg/Pothole"][1]]
