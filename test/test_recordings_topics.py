"""Topic discovery: the stereo topics of driver layouts found with no flags, rectified before
raw, uncompressed before compressed, colour before grey; ambiguity and absence said with the
flags that choose."""

from __future__ import annotations

import pytest

from pothole_detector.errors import InputError
from pothole_detector.recordings.topics import find_stereo_topics, side_of

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
INFO = "sensor_msgs/msg/CameraInfo"


def _layout(image_type, images, infos, extra=None):
    topics = {topic: image_type for topic in images}
    topics.update({topic: INFO for topic in infos})
    topics.update(extra or {})
    return topics


ZED = {
    **{f"/zed/zed_node/{side}/{name}": IMAGE for side in ("left", "right")
       for name in ("image_rect_color", "image_rect_gray")},
    **{f"/zed/zed_node/{side}_raw/image_raw_color": IMAGE for side in ("left", "right")},
    **{f"/zed/zed_node/{side}/camera_info": INFO
       for side in ("left", "right", "left_raw", "right_raw")},
    **{f"/zed/zed_node/{side}/image_rect_color/compressed": COMPRESSED
       for side in ("left", "right")},
    "/zed/zed_node/rgb/image_rect_color": IMAGE, "/zed/zed_node/rgb/camera_info": INFO,
    "/zed/zed_node/depth/depth_registered": IMAGE,
    "/zed/zed_node/disparity/disparity_image": "stereo_msgs/msg/DisparityImage",
}
REALSENSE = {
    "/camera/infra1/image_rect_raw": IMAGE, "/camera/infra2/image_rect_raw": IMAGE,
    "/camera/infra1/camera_info": INFO, "/camera/infra2/camera_info": INFO,
    "/camera/color/image_raw": IMAGE, "/camera/color/camera_info": INFO,
    "/camera/depth/image_rect_raw": IMAGE, "/camera/depth/camera_info": INFO,
}
OAK = {
    "/oak/left/image_raw": IMAGE, "/oak/right/image_raw": IMAGE,
    "/oak/left/image_rect": IMAGE, "/oak/right/image_rect": IMAGE,
    "/oak/left/camera_info": INFO, "/oak/right/camera_info": INFO,
    "/oak/rgb/image_raw": IMAGE, "/oak/rgb/camera_info": INFO,
}
KALIBR = {"/cam0/image_raw": IMAGE, "/cam1/image_raw": IMAGE, "/cam0/camera_info": INFO,
          "/cam1/camera_info": INFO, "/imu0": "sensor_msgs/msg/Imu"}
CAMERA_LEFT = {"/camera_left/image_raw/compressed": COMPRESSED,
               "/camera_right/image_raw/compressed": COMPRESSED,
               "/camera_left/camera_info": INFO, "/camera_right/camera_info": INFO}


@pytest.mark.parametrize("topics, left, right, left_info, image_type", [
    (ZED, "/zed/zed_node/left/image_rect_color", "/zed/zed_node/right/image_rect_color",
     "/zed/zed_node/left/camera_info", IMAGE),
    (REALSENSE, "/camera/infra1/image_rect_raw", "/camera/infra2/image_rect_raw",
     "/camera/infra1/camera_info", IMAGE),
    (OAK, "/oak/left/image_rect", "/oak/right/image_rect", "/oak/left/camera_info", IMAGE),
    (KALIBR, "/cam0/image_raw", "/cam1/image_raw", "/cam0/camera_info", IMAGE),
    (CAMERA_LEFT, "/camera_left/image_raw/compressed", "/camera_right/image_raw/compressed",
     "/camera_left/camera_info", COMPRESSED),
], ids=["zed", "realsense", "oak", "kalibr", "camera_left"])
def test_driver_layouts_need_no_flags(topics, left, right, left_info, image_type):
    found = find_stereo_topics(topics)
    assert (found.left, found.right, found.left_info, found.image_type) == \
        (left, right, left_info, image_type)
    assert left in found.describe() and right in found.describe()


def test_rectified_before_raw_uncompressed_before_compressed():
    topics = {topic: kind for topic, kind in ZED.items() if "rect_color" not in topic
              or topic.endswith("compressed")}
    # left: rect_gray (uncompressed) beats rect_color/compressed and the raw pair
    assert find_stereo_topics(topics).left == "/zed/zed_node/left/image_rect_gray"
    only_compressed = {t: k for t, k in topics.items() if "rect_gray" not in t}
    found = find_stereo_topics(only_compressed)
    assert found.left == "/zed/zed_node/left/image_rect_color/compressed" and found.compressed
    raw_only = {t: k for t, k in only_compressed.items() if "rect" not in t}
    found = find_stereo_topics(raw_only)
    assert (found.left, found.left_info) == ("/zed/zed_node/left_raw/image_raw_color",
                                            "/zed/zed_node/left_raw/camera_info")
    assert "(raw, uncompressed)" in found.describe()


def test_two_cameras_alike_are_ambiguous_and_named_topics_choose():
    front = {"/front/left/image_rect": IMAGE, "/front/right/image_rect": IMAGE,
             "/front/left/camera_info": INFO, "/front/right/camera_info": INFO}
    both = {**front, **{t.replace("front", "rear"): k for t, k in front.items()}}
    with pytest.raises(InputError, match="several stereo cameras.*--left-topic and "
                                         "--right-topic"):
        find_stereo_topics(both)
    found = find_stereo_topics(both, left="/rear/left/image_rect",
                               right="/rear/right/image_rect")
    assert found.left_info == "/rear/left/camera_info" and found.namespace == "/rear"
    assert find_stereo_topics(both, left="/rear/left/image_rect").right == \
        "/rear/right/image_rect"


def test_missing_pairs_and_wrong_names_say_what_the_bag_has():
    with pytest.raises(InputError, match="cannot find a left/right image pair.*--left-topic"):
        find_stereo_topics({"/camera/color/image_raw": IMAGE, "/camera/color/camera_info": INFO})
    with pytest.raises(InputError, match="no Image or CompressedImage topic named /nope"):
        find_stereo_topics(OAK, left="/nope", right="/oak/right/image_rect")
    no_infos = {t: k for t, k in KALIBR.items() if "camera_info" not in t}
    with pytest.raises(InputError, match="camera_info topics none"):
        find_stereo_topics(no_infos)


def test_our_own_outputs_are_not_cameras():
    topics = {"/stereo/left/image_rect": IMAGE, "/stereo/right/image_rect": IMAGE,
              "/stereo/left/camera_info": INFO, "/stereo/right/camera_info": INFO,
              "/stereo/overlay": IMAGE, "/stereo/pothole_labels": IMAGE,
              "/stereo/ground_truth/pothole_labels": IMAGE,
              "/stereo/disparity_transformed": IMAGE}
    assert find_stereo_topics(topics).left == "/stereo/left/image_rect"


@pytest.mark.parametrize("topic, side, key", [
    ("/a/left/image_raw", "left", "a/{}/image_raw"),
    ("/a/right_raw/image_raw_color", "right", "a/{}_raw/image_raw_color"),
    ("/camera/infra2/image_rect_raw", "right", "camera/infra{}/image_rect_raw"),
    ("/cam0/image_raw/compressed", "left", "cam{}/image_raw"),
    ("/camera_left/image_raw", "left", "camera_{}/image_raw"),
    ("/camera/color/image_raw", None, None),
])
def test_side_of_a_topic(topic, side, key):
    found = side_of(topic)
    assert (found or (None, None)) == (side, key)
