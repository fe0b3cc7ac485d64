from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("pothole_detector_msgs.msg")
pytest.importorskip("rosbags")

from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from pothole_detector.ros import bagtools, conversions  # noqa: E402
from pothole_detector.recordings.images import IMAGE_TYPE, decode_raw  # noqa: E402
from pothole_detector.recordings.messages import stamp_ns, typestore  # noqa: E402
from pothole_detector.recordings.topics import INFO_TYPE  # noqa: E402
from pothole_detector.recordings.bagwriter import BagWriter  # noqa: E402
from pothole_detector.recordings.writing import write_stereo_bag  # noqa: E402
from pothole_detector.recordings import bags  # noqa: E402
from pothole_detector.errors import InputError  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402
from pothole_detector.evaluation.synthetic import drive_scenes, render  # noqa: E402

from conftest import REPO, rewrite_bag  # noqa: E402

START = 1_700_000_000_000_000_000
STEREO = ["/cam/left/image_rect", "/cam/right/image_rect", "/cam/left/camera_info",
          "/cam/right/camera_info"]


@pytest.fixture(scope="module")
def drive_frames():
    """Three frames of the driving sequence at 640x360."""
    return [(START + i * 100_000_000, render(scene))
            for i, scene in enumerate(drive_scenes(frames=3))]


@pytest.fixture(scope="module")
def drive_bag(tmp_path_factory, drive_frames):
    path = tmp_path_factory.mktemp("bags") / "drive"
    assert write_stereo_bag(path, drive_frames, namespace="/cam") == 3
    return path


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_process_writes_every_output_equal_to_the_pipeline(tmp_path, drive_bag, drive_frames,
                                                           storage):
    out = tmp_path / "processed"
    summary = bagtools.process(drive_bag, out, Config({"backend": "cpu"}), storage=storage,
                               pictures=tmp_path / "pictures")
    assert (summary.frames, summary.failed) == (3, 0)
    assert len(list((tmp_path / "pictures").glob("overlay_*.png"))) == 3
    topics = bags.topics_of(out)
    for name, msgtype in bagtools.OUTPUT_TYPES.items():
        if name in bagtools.OFFLINE_OUTPUTS:
            assert topics[f"/cam/{name}"] == msgtype
    assert "/cam/points2" not in topics  # the live road cloud stays out of bags
    assert STEREO[0] in topics
    pipeline = Pipeline(Config(), drive_frames[0][1].calibration)
    expected = {stamp: pipeline.run(s.left, s.right) for stamp, s in drive_frames}
    seen = set()
    for topic, stamp, msg in bags.read_messages(out, ["/cam/disparity", "/cam/potholes"]):
        assert stamp_ns(msg.header) == stamp
        assert msg.header.frame_id == "stereo_left_optical_frame"
        if topic == "/cam/disparity":
            np.testing.assert_array_equal(conversions.disparity_from_message(msg),
                                          expected[stamp].disparity)
        else:
            assert len(msg.potholes) == len(expected[stamp].potholes) > 0
        seen.add((topic, stamp))
    assert len(seen) == 6


def test_mcap_carries_message_definitions_for_foxglove(tmp_path, drive_bag):
    out = tmp_path / "processed"
    bagtools.process(drive_bag, out, Config({"backend": "cpu"}), keep_inputs=False)
    with AnyReader([out]) as reader:  # no default typestore: definitions come from the file
        connection = next(c for c in reader.connections if c.topic == "/cam/potholes")
        assert "Pothole[] potholes" in connection.msgdef.data
        _, _, raw = next(iter(reader.messages(connections=[connection])))
        msg = reader.deserialize(raw, connection.msgtype)
        assert msg.header.frame_id == "stereo_left_optical_frame"


def test_process_reads_a_ros1_bag(tmp_path, drive_bag):
    noetic = get_typestore(Stores.ROS1_NOETIC)
    path = tmp_path / "drive.bag"
    with AnyReader([drive_bag], default_typestore=typestore()) as source, \
            Writer1(path) as writer:
        connections = {}
        for connection, stamp, raw in source.messages():
            if connection.topic not in STEREO:
                continue
            msg = source.deserialize(raw, connection.msgtype)
            fields = {k: getattr(msg, k) for k in msg.__dataclass_fields__}
            header = noetic.types["std_msgs/msg/Header"](
                seq=0, stamp=noetic.types["builtin_interfaces/msg/Time"](
                    sec=msg.header.stamp.sec, nanosec=msg.header.stamp.nanosec),
                frame_id=msg.header.frame_id)
            fields["header"] = header
            if connection.msgtype == INFO_TYPE:
                fields = {(k.upper() if k in "dkrp" else k): v for k, v in fields.items()}
                fields["roi"] = noetic.types["sensor_msgs/msg/RegionOfInterest"](
                    **{k: getattr(msg.roi, k) for k in msg.roi.__dataclass_fields__})
            ros1 = noetic.types[connection.msgtype](**fields)
            if connection.topic not in connections:
                connections[connection.topic] = writer.add_connection(
                    connection.topic, connection.msgtype, typestore=noetic)
            writer.write(connections[connection.topic], stamp,
                         noetic.serialize_ros1(ros1, connection.msgtype))
    summary = bagtools.process(path, tmp_path / "out", Config({"backend": "cpu"}))
    assert (summary.frames, summary.failed) == (3, 0)
    assert summary.potholes > 0


def test_process_refuses_existing_output_and_missing_bag(tmp_path, drive_bag):
    with pytest.raises(InputError, match="exists already"):
        bagtools.process(drive_bag, drive_bag, Config())
    with pytest.raises(InputError, match="does not exist"):
        bagtools.process(tmp_path / "nope", tmp_path / "out", Config())


def test_committed_sample_bag_is_the_generators_output():
    bag = REPO / "bags" / "sample_drive"
    topics = bags.topics_of(bag)
    assert topics["/stereo/left/image_rect"] == IMAGE_TYPE
    assert topics["/stereo/ground_truth/pothole_labels"] == IMAGE_TYPE
    first = {}
    for topic, stamp, msg in bags.read_messages(bag):
        first.setdefault(topic, (stamp, msg))
    sample = render(drive_scenes(frames=1)[0])
    assert first["/stereo/left/image_rect"][0] == START
    np.testing.assert_array_equal(
        decode_raw(first["/stereo/left/image_rect"][1]), sample.left)
    np.testing.assert_array_equal(
        decode_raw(first["/stereo/ground_truth/pothole_labels"][1]),
        sample.labels)
    counts = {}
    for topic, _, _ in bags.read_messages(bag, ["/stereo/right/image_rect"]):
        counts[topic] = counts.get(topic, 0) + 1
    assert counts == {"/stereo/right/image_rect": 16}


def test_process_counts_unpaired_images(tmp_path, drive_bag):
    cut = tmp_path / "cut"
    writer = BagWriter(cut, "mcap")
    store = typestore()
    connections = {}
    with AnyReader([drive_bag], default_typestore=store) as reader:
        for connection, stamp, raw in reader.messages():
            if connection.topic == STEREO[1] and stamp == START:
                continue  # the first right image is lost
            if connection.topic not in connections:
                connections[connection.topic] = writer.add_connection(
                    connection.topic, connection.msgtype, typestore=store)
            writer.write(connections[connection.topic], stamp, raw)
    writer.close()
    summary = bagtools.process(cut, tmp_path / "out", Config({"backend": "cpu"}))
    assert (summary.frames, summary.unpaired) == (2, 1)
    assert "1 unpaired images" in summary.text()


def test_process_goes_on_after_a_failed_frame_and_a_new_calibration(tmp_path, drive_frames):
    """Frames stream through the pipeline; a frame that fails is counted and the next one is
    processed; a new camera_info starts a pipeline with the new calibration."""
    import dataclasses

    (s0, first), (s1, second), (s2, third) = drive_frames
    blank = dataclasses.replace(second, right=np.full_like(second.right, 128),
                                left=np.full_like(second.left, 128))
    wider = dataclasses.replace(third.calibration, baseline=third.calibration.baseline * 1.5)
    moved = dataclasses.replace(third, calibration=wider)
    bag = tmp_path / "mixed"
    frames = [(s0, first), (s1, blank), (s2, moved), (s2 + 100_000_000, moved)]
    assert write_stereo_bag(bag, frames, namespace="/cam") == 4
    summary = bagtools.process(bag, tmp_path / "out", Config({"backend": "cpu"}))
    assert (summary.frames, summary.failed) == (3, 1)
    [(count, reason, stamp)] = summary.failures.rows()
    assert (count, stamp) == (1, s1) and "texture" in reason
    assert f"1 frame failed: {reason} (first at stamp {s1})" == summary.failures.lines()[0]
    before = Pipeline(Config(), first.calibration).run(first.left, first.right)
    after = Pipeline(Config(), wider)
    expected = {s0: before, s2: after.run(third.left, third.right),
                s2 + 100_000_000: after.run(third.left, third.right)}
    seen, failed = {}, {}
    for _, stamp, msg in bags.read_messages(tmp_path / "out", ["/cam/potholes"]):
        if msg.status == msg.FAILED:
            failed[stamp] = msg.reason
            continue
        assert msg.status == msg.PROCESSED
        seen[stamp] = sorted(p.area_m2 for p in msg.potholes)
    assert set(seen) == set(expected)
    assert set(failed) == {s1} and "texture" in failed[s1]  # every set has its message
    for stamp, result in expected.items():
        np.testing.assert_allclose(seen[stamp], sorted(p.area_m2 for p in result.potholes),
                                   rtol=1e-5)
    assert seen[s2] != seen[s0]


def test_process_pairs_camera_info_written_after_the_images(tmp_path, drive_frames):
    """A bag that writes each camera_info after its images (bag time 5 ms later, header stamp
    the images'): every pair still gets the camera_info of its own stamp."""
    source, late = tmp_path / "ordered", tmp_path / "late"
    assert write_stereo_bag(source, drive_frames[:2], namespace="/cam") == 2
    rewrite_bag(source, late, lambda topic, timestamp: timestamp + (
        5_000_000 if topic.endswith("camera_info") else 0))
    summary = bagtools.process(late, tmp_path / "out", Config({"backend": "cpu"}))
    assert (summary.frames, summary.failed) == (2, 0), summary.failures.lines()


def test_process_with_the_shipped_config_takes_every_frame_of_a_640x480_vehicle_drive(tmp_path):
    """A vehicle rig (1 m up, pitched 15 deg, 0.12 m baseline) at 640x480, half a metre a frame:
    the shipped parameter file processes every frame, none refused."""
    from pothole_detector.params import load_yaml
    from pothole_detector.evaluation.synthetic import vehicle_scene
    frames = [(START + i * 100_000_000, render(vehicle_scene(640, 480, camera_y_m=0.5 * i)))
              for i in range(6)]
    assert write_stereo_bag(tmp_path / "vehicle", frames, namespace="/cam") == 6
    config = Config(load_yaml(REPO / "config" / "pothole_detector.yaml"))
    summary = bagtools.process(tmp_path / "vehicle", tmp_path / "out", config)
    assert (summary.frames, summary.failed) == (6, 0)
    messages = [msg for _, _, msg in bags.read_messages(tmp_path / "out", ["/cam/potholes"])]
    assert len(messages) == 6 and all(msg.status != msg.FAILED for msg in messages)


def test_a_span_reads_its_own_sets_and_finds_a_camera_info_latched_before_it(tmp_path,
                                                                           drive_frames):
    """Nine sets 0.2 s apart, camera_info only with the first: sets read by spans of log time
    (each with a lead of one frame) are the bag's sets, each once, each with the camera_info
    (for the last span, logged more than a second before it); no set after a span is
    read."""
    source, latched = tmp_path / "every", tmp_path / "latched"
    frames = [(START + i * 200_000_000, drive_frames[i % 3][1]) for i in range(9)]
    assert write_stereo_bag(source, frames, namespace="/cam") == 9
    rewrite_bag(source, latched, lambda topic, timestamp: timestamp if (
        not topic.endswith("camera_info") or timestamp == START) else None)
    config = Config()
    topics = bags.StereoTopics(*STEREO)
    reader = bags.open_bag(latched)
    try:
        whole = [s[0] for s in bags.stereo_sets(reader, topics, config,
                                                    bags.SetCounts())]
        assert whole == [stamp for stamp, _ in frames]
        kept = []
        for first, stop in ((START, START + 700_000_000), (START + 700_000_000,
                                                           START + 1_400_000_000),
                            (START + 1_400_000_000, START + 1_800_000_000)):
            span = bags.LogSpan(first, stop, 200_000_000)
            sets = list(bags.stereo_sets(reader, topics, config,
                                             bags.SetCounts(), span))
            assert all(s[4] is not None and s[5] is not None for s in sets)
            assert all(first - 200_000_000 <= s[1] < stop for s in sets)
            kept += [s[0] for s in sets if s[1] >= first]
        assert kept == whole
    finally:
        reader.close()


def test_sets_read_ahead_in_threads_are_the_sets_read_in_one(tmp_path, drive_frames,
                                                           monkeypatch):
    """Twenty sets 0.1 s apart, the right image and both camera_infos logged 30 ms after the
    left (partners across the blocks' edges): read in blocks of three sets by three threads,
    of the whole bag and of a span with its lead, they are the sets one reader finds, in
    order, each with its camera_info."""
    source, late = tmp_path / "source", tmp_path / "late"
    frames = [(START + i * 100_000_000, drive_frames[i % 3][1]) for i in range(20)]
    assert write_stereo_bag(source, frames, namespace="/cam") == 20
    rewrite_bag(source, late, lambda topic, timestamp: timestamp + (
        0 if topic == STEREO[0] else 30_000_000))
    monkeypatch.setattr(bags, "READ_BLOCK_FRAMES", 3)
    config = Config()
    topics = bags.StereoTopics(*STEREO)
    reader = bags.open_bag(late)
    try:
        for span in (None, bags.LogSpan(START + 450_000_000, START + 1_650_000_000,
                                            250_000_000)):
            alone = list(bags.stereo_sets(reader, topics, config,
                                              bags.SetCounts(), span))
            ahead = list(bags.read_sets_ahead(reader, topics, config, span, 3))
            assert [s[:2] for s in ahead] == [s[:2] for s in alone]
            assert len(alone) == (20 if span is None else 15)
            assert all(s[4] is not None and s[5] is not None for s in ahead)
            assert [s[2].header.stamp.sec * 10**9 + s[2].header.stamp.nanosec
                    for s in ahead] == [s[0] for s in alone]
    finally:
        reader.close()
