"""The node as its own process, driven over DDS: bag play, parameters, QoS, sync, bad input."""

from __future__ import annotations

import copy
import math
import signal
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("pothole_detector_msgs.msg")

import rclpy  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import ReliabilityPolicy  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from pothole_detector.ros import conversions  # noqa: E402
from pothole_detector.recordings.camera import (camera_info_message, camera_info_of,
                                                pipeline_inputs, stereo_camera)  # noqa: E402
from pothole_detector.recordings.images import (array_to_image, compressed_image,
                                                decode_raw)  # noqa: E402
from pothole_detector.backend import gpu_available  # noqa: E402
from pothole_detector.params import Config  # noqa: E402
from pothole_detector.pipeline import Pipeline  # noqa: E402
from pothole_detector.evaluation.synthetic import (drive_scenes, raw_camera, render,
                                                   render_raw)  # noqa
from rosgraph import (SAMPLE_DRIVE, NodeProcess, Probe, header_at,  # noqa: E402
                      isolate_ros_graph, labels_of, sample_frames, stamp_ns)

T0 = 1_800_000_000_000_000_000


@pytest.fixture(scope="module", autouse=True)
def ros():
    isolate_ros_graph()
    rclpy.init()
    yield
    rclpy.shutdown()


@pytest.fixture(scope="module")
def frames():
    return sample_frames(3)


@pytest.fixture
def node_factory(tmp_path):
    started = []

    def start(**params):
        node = NodeProcess(tmp_path / f"node{len(started)}.log", **params)
        started.append(node)
        return node

    yield start
    for node in started:
        assert node.alive(), f"the node died:\n{node.text()}"
        assert node.stop() == 0, node.text()


@pytest.fixture
def probe():
    made = []

    def make(**kwargs):
        made.append(Probe(**kwargs))
        return made[-1]

    yield make
    for p in made:
        p.close()


def offline_results(frames):
    left = decode_raw(frames[0]["left"])
    calibration = stereo_camera(frames[0]["left_info"], frames[0]["right_info"], left.shape[1],
                                left.shape[0]).calibration()
    pipeline = Pipeline(Config({"backend": "cpu"}), calibration)
    return [pipeline.run(decode_raw(f["left"]),
                         decode_raw(f["right"])) for f in frames]


def test_play_sample_bag_every_output(node_factory, probe):
    node = node_factory(backend="cpu")
    p = probe()
    p.wait_connected()
    p.node.create_subscription(type(sample_frames(1)[0]["truth"]),
                               "/stereo/ground_truth/pothole_labels",
                               lambda m: p.received["truth"].append(m), 50)
    play = subprocess.Popen(
        [sys.executable, "-m", "pothole_detector.cli", "play", str(SAMPLE_DRIVE), "--rate",
         "0.2", "--wait-for-subscribers", "10"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    assert p.spin(60, lambda: play.poll() is not None)
    out, err = play.communicate()
    assert play.returncode == 0, err
    assert "published 80 messages" in out
    p.spin(30, lambda: p.diagnostics().get("frames_processed") == "16")
    p.spin(1.5)
    diagnostics = p.diagnostics()
    processed = int(diagnostics["frames_processed"])
    assert (processed, diagnostics["dropped_sets"]) == (16, "0"), diagnostics
    by_stamp = {stamp_ns(f["left"].header): f for f in sample_frames(16)}
    stamps = p.stamps()
    assert len(stamps) == processed and stamps == sorted(stamps)
    assert set(stamps) <= set(by_stamp)
    for output in ("disparity", "disparity_transformed", "pothole_labels",
                   "pothole_points", "points2", "pothole_markers", "overlay"):
        assert p.stamps(output) == stamps, output
    for msg in p.received["potholes"] + p.received["disparity"] + p.received["overlay"]:
        assert msg.header.frame_id == "stereo_left_optical_frame"

    expected = offline_results([by_stamp[s] for s in stamps])  # same sequence, same seeds
    for msg, result in zip(p.received["disparity"], expected):
        np.testing.assert_array_equal(conversions.disparity_from_message(msg), result.disparity)
        assert msg.min_disparity <= np.nanmin(result.disparity)
        assert msg.max_disparity >= np.nanmax(result.disparity)
    for msg, result in zip(p.received["disparity_transformed"], expected):
        np.testing.assert_array_equal(decode_raw(msg, ("32FC1",)),
                                      result.transformed)
    for msg, result in zip(p.received["potholes"], expected):
        assert [q.area_m2 for q in msg.potholes] == [q.area_m2 for q in result.potholes]

    hits = detected = truth_pixels = 0
    truths = {stamp_ns(m.header): labels_of(m) for m in p.received["truth"]}
    for msg in p.received["pothole_labels"]:
        labels, truth = labels_of(msg) > 0, truths[stamp_ns(msg.header)] > 0
        hits += int((labels & truth).sum())
        detected += int(labels.sum())
        truth_pixels += int(truth.sum())
    assert hits / detected > 0.85, "potholes reported where the generator put none"
    assert hits / truth_pixels > 0.4, "most of the generator's potholes were missed"

    for msg, array in zip(p.received["pothole_markers"], p.received["potholes"]):
        assert msg.markers[0].action == Marker.DELETEALL
        assert len(msg.markers) == 1 + 2 * len(array.potholes)
    for cloud, result in zip(p.received["points2"], expected):
        road = conversions.organized_cloud_to_array(cloud)
        assert road.shape == result.disparity.shape and cloud.is_dense is False
        np.testing.assert_array_equal(np.isnan(road["z"]), np.isnan(result.disparity))
        np.testing.assert_array_equal(road["label"] > 0, result.labels > 0)
    # ids stay with a pothole while it is in view: the drive passes five
    ids = [q.label for msg in p.received["potholes"] for q in msg.potholes]
    assert len(ids) > 2 * len(set(ids)) and len(set(ids)) <= 8, ids
    for msg, array in zip(p.received["pothole_labels"], p.received["potholes"]):
        assert set(np.unique(labels_of(msg))) - {0} == {q.label for q in array.potholes}
    for cloud, array in zip(p.received["pothole_points"], p.received["potholes"]):
        points = conversions.pointcloud_to_array(cloud)
        assert set(np.unique(points["label"])) == {q.label for q in array.potholes}
        for pothole in array.potholes:
            u0, v0, u1, v1 = pothole.bbox_px
            if min(u0, v0) == 0 or u1 == 639 or v1 == 359:
                continue  # entering the view: its rim only
            assert 0.03 < pothole.max_depth_m < 0.08  # the drive's potholes are 5-6 cm deep
            assert np.nanmedian(points["depth_below_road"][points["label"] == pothole.label]) > 0
    overlay = p.received["overlay"][0]
    assert (overlay.encoding, overlay.width, overlay.height) == ("rgb8", 640, 360)
    assert diagnostics["backend"] == "cpu"
    assert "Traceback" not in node.text()


def test_parameters_change_at_run_time_and_bad_values_are_refused(node_factory, probe, frames):
    node_factory(backend="cpu")
    p = probe(outputs=("potholes",))
    p.wait_connected()
    client = AsyncParameterClient(p.node, "/stereo/pothole_detector")
    assert client.wait_for_services(timeout_sec=10)

    def set_parameters(**values):
        return p.answer(lambda: client.set_parameters(
            [Parameter(k, value=v) for k, v in values.items()])).results

    refused = set_parameters(delta_pd_px=-1.0)
    assert not refused[0].successful and "out of range" in refused[0].reason
    refused = set_parameters(sgm_p2=4)
    assert not refused[0].successful and "sgm_p2 must be larger" in refused[0].reason
    refused = set_parameters(backend="tpu")
    assert not refused[0].successful and "one of auto, cpu, gpu" in refused[0].reason

    p.publish(frames[0], T0)
    assert p.spin(15, lambda: len(p.received["potholes"]) == 1)
    assert len(p.received["potholes"][0].potholes) >= 2
    assert set_parameters(min_pothole_area_m2=50.0)[0].successful
    p.publish(frames[0], T0 + 100_000_000)
    assert p.spin(15, lambda: len(p.received["potholes"]) == 2)
    assert p.received["potholes"][1].potholes == []
    assert set_parameters(min_pothole_area_m2=0.0005, qos_depth=3)[0].successful
    p.wait_connected()
    p.publish(frames[0], T0 + 200_000_000)
    assert p.spin(15, lambda: len(p.received["potholes"]) == 3)
    assert len(p.received["potholes"][2].potholes) >= 2


@pytest.mark.parametrize("camera", ["best_effort", "reliable"])
def test_default_qos_takes_either_camera_and_serves_either_subscriber(node_factory, probe,
                                                                      frames, camera):
    """Inputs are sensor data (best effort takes a best-effort camera driver and a reliable
    one), outputs reliable (a reliable and a best-effort subscriber both get them)."""
    node_factory(backend="cpu")
    p = probe(input_reliability=camera, outputs=("potholes",))
    listener = probe(reliability="best_effort", outputs=("potholes",))
    p.wait_connected()
    for index in range(3):  # each set once the last is answered: none is dropped as stale
        p.publish(frames[index % len(frames)], T0 + index * 300_000_000)
        assert p.spin(10, lambda: len(p.received["potholes"]) > index)
        listener.spin(0.05)
    listener.spin(3, lambda: len(listener.received["potholes"]) >= 3)
    assert len(listener.received["potholes"]) >= 3
    info = p.node.get_publishers_info_by_topic("/stereo/potholes")[0].qos_profile
    assert info.reliability == ReliabilityPolicy.RELIABLE
    info = p.node.get_subscriptions_info_by_topic("/stereo/left/image_rect")[0].qos_profile
    assert info.reliability == ReliabilityPolicy.BEST_EFFORT


def test_qos_overrides_per_topic_and_a_transient_local_subscriber_is_told(node_factory, probe,
                                                                        frames):
    node = node_factory(backend="cpu", **{
        "qos_overrides./stereo/potholes.publisher.reliability": "best_effort",
        "qos_overrides./stereo/left/image_rect.subscription.reliability": "reliable"})
    p = probe(outputs=("overlay",), durability="transient_local")
    p.wait_connected()
    assert p.spin(10, lambda: "subscriber of /stereo/overlay asks for QoS" in node.text())
    assert "it offers reliable, volatile durability (no history for late joiners)" \
        in node.text()  # the override of one topic leaves the others as they were
    info = p.node.get_publishers_info_by_topic("/stereo/potholes")[0].qos_profile
    assert info.reliability == ReliabilityPolicy.BEST_EFFORT
    info = p.node.get_subscriptions_info_by_topic("/stereo/left/image_rect")[0].qos_profile
    assert info.reliability == ReliabilityPolicy.RELIABLE


def test_approximate_sync_pairs_jittered_stamps(node_factory, probe, frames):
    node_factory(backend="cpu", approximate_sync=True,
                 approximate_sync_tolerance_seconds=0.01)
    p = probe(outputs=("potholes",))
    p.wait_connected()
    for index, jitter_ms in enumerate((3, -4, 7)):
        stamp = T0 + index * 500_000_000
        p.publish(frames[index], stamp, right_stamp=stamp + jitter_ms * 1_000_000)
        p.spin(0.5)
    p.publish(frames[0], T0 + 2_000_000_000, right_stamp=T0 + 2_030_000_000)  # 30 ms: too far
    assert p.spin(15, lambda: len(p.received["potholes"]) >= 3)
    p.spin(1.5)
    assert p.stamps() == [T0, T0 + 500_000_000, T0 + 1_000_000_000]


def test_exact_sync_refuses_jitter_and_says_so(node_factory, probe, frames):
    node_factory(backend="cpu", diagnostics_period_seconds=0.2)
    p = probe(outputs=("potholes",))
    p.wait_connected()
    for index in range(3):
        stamp = T0 + index * 500_000_000
        p.publish(frames[index], stamp, right_stamp=stamp + 3_000_000)
        p.spin(0.3)
    p.spin(2)
    assert p.received["potholes"] == []
    assert "set approximate_sync:=true" in p.diagnostics()["message"]


def test_bad_input_is_reported_and_the_node_keeps_running(node_factory, probe, frames):
    node = node_factory(backend="cpu", log_throttle_seconds=0.0,
                        diagnostics_period_seconds=0.2)
    p = probe(outputs=("potholes",))
    p.wait_connected()
    good = frames[0]

    p.publish(good, T0, infos=False)
    assert p.spin(10, lambda: "no camera_info" in p.diagnostics().get("message", ""))
    assert p.received["potholes"] == []
    p.publish(good, T0 + 1, infos=True)  # the held pair goes through once infos exist
    assert p.spin(15, lambda: T0 + 1 in p.stamps())

    def smaller(msg, width):
        pixels = decode_raw(msg)[:, :width]
        return array_to_image(pixels, "mono8", msg.header)

    lying_step = copy.deepcopy(good["left"])
    lying_step.step = lying_step.width - 10
    short_data = copy.deepcopy(good["left"])
    short_data.data = bytes(short_data.data)[:1000]
    unknown = copy.deepcopy(good["left"])
    unknown.encoding = "nv24"
    flat_right = copy.deepcopy(good["right_info"])
    flat_right.p[3] = 0.0
    nan_info = copy.deepcopy(good["left_info"])
    nan_info.p[0] = math.nan
    cases = [
        ({"right": smaller(good["right"], 600)},
         "image is 600x360 but its camera_info is for 640x360"),
        ({"left": unknown}, "encoding 'nv24' is not supported"),
        ({"left": lying_step}, "step"),
        ({"left": short_data}, "needs"),
        ({"right_info": flat_right}, "Tx"),
        ({"left_info": nan_info}, "NaN"),
    ]
    stamp = T0 + 1_000_000_000
    for changes, words in cases:
        stamp += 1_000_000_000
        p.publish(good, stamp, **changes)
        assert p.spin(10, lambda: words in p.diagnostics().get("message", "")), words
        p.publish(good, stamp + 500_000_000)
        assert p.spin(15, lambda: stamp + 500_000_000 in p.stamps()), node.text()
        # the refused set has its PotholeArray too: status FAILED and why
        (refused,) = [m for m in p.received["potholes"]
                      if stamp_ns(m.header) == stamp]
        assert refused.status == refused.FAILED and words in refused.reason
        assert not refused.potholes
    p.publish(good, T0 + 2)
    assert p.spin(10, lambda: "backwards" in p.diagnostics().get("message", ""))
    assert p.spin(15, lambda: T0 + 2 in p.stamps())
    log = node.text()
    for _, words in cases:
        assert words in log
    assert "backwards" in log and "Traceback" not in log


def test_record_writes_live_topics_as_raw_cdr(tmp_path, probe, frames):
    from pothole_detector.recordings import bags

    p = probe(outputs=())
    out = tmp_path / "recorded"
    p.spin(0.5)
    record = subprocess.Popen(
        [sys.executable, "-m", "pothole_detector.cli", "record", str(out), "--topics",
         "/stereo/left/image_rect", "--duration", "8"], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    assert p.spin(15, lambda: p.inputs["left"].get_subscription_count() > 0)
    p.spin(1.0)
    for index in range(3):
        p.publish(frames[index], T0 + index, infos=False)
        p.spin(0.2)
    assert p.spin(20, lambda: record.poll() is not None)
    stdout, stderr = record.communicate()
    assert record.returncode == 0, stderr
    assert "/stereo/left/image_rect: 3" in stdout
    recorded = [msg for _, _, msg in bags.read_messages(out)]
    assert [stamp_ns(m.header) for m in recorded] == [T0, T0 + 1, T0 + 2]
    np.testing.assert_array_equal(decode_raw(recorded[1]),
                                  decode_raw(frames[1]["left"]))


@pytest.mark.parametrize("params_file", ["shipped", "written"])
def test_the_parameter_file_applies_under_any_namespace_and_node_name(tmp_path, node_factory,
                                                                     probe, params_file):
    """The README's command (`-r __ns:=... --params-file config/pothole_detector.yaml`): the
    file's `/**` key reaches a node in another namespace under another name."""
    from rcl_interfaces.srv import GetParameters

    from pothole_detector.params import default_yaml
    text = default_yaml().replace("delta_dt_px: 32.0", "delta_dt_px: 41.5")
    path = tmp_path / "params.yaml"
    path.write_text(text if params_file == "written" else default_yaml())
    node_factory(namespace="/robot/front", node_name="holes", params_file=path)
    p = probe(namespace="/robot/front")
    client = p.node.create_client(GetParameters, "/robot/front/holes/get_parameters")
    assert client.wait_for_service(timeout_sec=20.0), "the renamed node did not come up"
    request = GetParameters.Request(names=["delta_dt_px", "queue_size"])
    values = [value.double_value or value.integer_value
              for value in p.answer(lambda: client.call_async(request)).values]
    assert values == [41.5 if params_file == "written" else 32.0, 10]


def test_diagnostics_tell_no_input_and_failures_in_a_row(node_factory, probe, frames):
    """/diagnostics: named after the node's full name with the camera's frame as hardware id;
    WARN while no image comes, ERROR once error_after_failed_frames frames fail in a row, and
    no longer ERROR after a good frame."""
    node_factory(backend="cpu", input_timeout_seconds=0.5, error_after_failed_frames=2,
                 diagnostics_period_seconds=0.2, log_throttle_seconds=0.0)
    p = probe(outputs=("potholes",))
    p.wait_connected()
    assert p.spin(10, lambda: "no stereo image" in p.diagnostics().get("message", ""))
    assert p.diagnostics()["level"] == 1
    status = p.received["diagnostics"][-1].status[0]
    assert status.name == "/stereo/pothole_detector: pipeline"
    good = frames[0]
    right = decode_raw(good["right"])[:, :600]
    narrow = array_to_image(right, "mono8", good["right"].header)
    for index in range(2):  # one at a time: a set arriving while the node is busy is dropped
        p.publish(good, T0 + index, right=narrow)
        assert p.spin(15, lambda: T0 + index in p.stamps())
    assert p.spin(15, lambda: p.diagnostics().get("level") == 2), p.diagnostics()
    assert "2 frames in a row failed" in p.diagnostics()["message"]
    assert p.received["diagnostics"][-1].status[0].hardware_id == good["left"].header.frame_id
    p.publish(good, T0 + 5)
    assert p.spin(15, lambda: T0 + 5 in p.stamps())
    assert p.spin(5, lambda: p.diagnostics().get("failures_in_a_row") == "0")
    assert p.diagnostics()["level"] != 2


def test_shutdown_under_load_is_clean(tmp_path, probe, frames):
    """Ctrl-C while frames keep coming: the worker's frame is published before the context
    goes (no 'context is invalid'), and the node exits 0 within a few seconds."""
    node = NodeProcess(tmp_path / "node.log", backend="cpu")
    p = probe(outputs=("potholes",))
    p.wait_connected()
    for index in range(30):
        p.publish(frames[index % len(frames)], T0 + index * 33_000_000)
        p.spin(0.02)
    started = time.monotonic()
    assert node.stop() == 0
    assert time.monotonic() - started < 6.0
    text = node.text()
    assert "context is invalid" not in text and "Traceback" not in text, text


def test_a_node_started_with_sigint_ignored_still_stops_on_it(tmp_path):
    """A script's background job inherits SIGINT ignored (scripts/demo.sh starts the node so
    and stops it with kill -INT): the node sets its own handler and exits 0."""
    import signal
    import subprocess

    log = open(tmp_path / "node.log", "w")
    process = subprocess.Popen(
        [sys.executable, "-m", "pothole_detector.ros.node", "--ros-args", "-r", "__ns:=/ignored",
         "-p", "backend:=cpu"], stdout=log, stderr=subprocess.STDOUT,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    time.sleep(3.0)
    process.send_signal(signal.SIGINT)
    try:
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
        log.close()


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device")
def test_the_gpu_node_gives_what_the_cpu_pipeline_gives(node_factory, probe):
    """backend:=gpu inside the node: every set of the sample drive processed (one at a time:
    the first compiles the kernels), the same potholes as the census pipeline on the CPU, and
    the conversion/pipeline CPU split in /diagnostics."""
    node_factory(backend="gpu", matcher="census")
    p = probe(outputs=("potholes", "pothole_labels", "disparity"))
    p.wait_connected(timeout=60.0)
    drive = sample_frames(16)
    for index, frame in enumerate(drive):
        p.publish(frame, stamp_ns(frame["left"].header))
        assert p.spin(90 if index == 0 else 10,
                      lambda: len(p.received["potholes"]) == index + 1), index
    p.spin(1.5)
    diagnostics = p.diagnostics()
    assert diagnostics["backend"] == "gpu" and diagnostics["dropped_sets"] == "0", diagnostics
    assert float(diagnostics["pipeline_cpu_ms_per_frame"]) > 0
    assert float(diagnostics["conversion_cpu_ms_per_frame"]) > 0

    left = decode_raw(drive[0]["left"])
    calibration = stereo_camera(drive[0]["left_info"], drive[0]["right_info"], left.shape[1],
                                left.shape[0]).calibration()
    pipeline = Pipeline(Config({"backend": "cpu", "matcher": "census"}), calibration)
    by_stamp = {stamp_ns(m.header): m for m in p.received["pothole_labels"]}
    agreement = []
    for frame, array in zip(drive, p.received["potholes"]):
        expected = pipeline.run(decode_raw(frame["left"]),
                                decode_raw(frame["right"]))
        assert stamp_ns(array.header) == stamp_ns(frame["left"].header)
        assert len(array.potholes) == len(expected.potholes)
        labels = labels_of(by_stamp[stamp_ns(array.header)]) > 0
        agreement.append((labels == (expected.labels > 0)).mean())
    assert min(agreement) > 0.998, agreement


@pytest.mark.parametrize("waiting", [1, 4])
def test_a_burst_of_sets_waits_up_to_max_waiting_sets(node_factory, probe, frames, waiting):
    """Four sets at once (reliable inputs, so that DDS loses none): with max_waiting_sets 4
    all are processed; with 1 the oldest waiting ones are dropped and counted, and the newest
    is processed."""
    node_factory(backend="cpu", max_waiting_sets=waiting, **{
        f"qos_overrides./stereo/{topic}.subscription.reliability": "reliable"
        for topic in ("left/image_rect", "right/image_rect", "left/camera_info",
                      "right/camera_info")})
    p = probe(outputs=("potholes",))
    p.wait_connected()
    p.publish(frames[0], T0)
    assert p.spin(30, lambda: len(p.received["potholes"]) == 1)
    burst = [T0 + (index + 1) * 100_000_000 for index in range(4)]
    for index, stamp in enumerate(burst):
        p.publish(frames[index % len(frames)], stamp)
    p.spin(20, lambda: p.stamps()[-1] == burst[-1])
    p.spin(2.5)
    processed = p.stamps()[1:]
    dropped = int(p.diagnostics()["dropped_sets"])
    assert processed[-1] == burst[-1] and len(processed) + dropped == len(burst)
    assert (processed, dropped) == (burst, 0) if waiting == 4 else dropped >= 1


def test_statistics_tell_whether_the_worker_keeps_up():
    from pothole_detector.ros.node import Statistics

    stats = Statistics(window_seconds=1.0)
    assert stats.keeping_up()
    for _ in range(30):  # 30 sets a second, 20 ms each: keeps up
        stats.input_set()
        stats.done(25.0, 20.0, 1.0, 0, 1.0, 10.0, 2.0)
    assert stats.keeping_up()
    for _ in range(30):  # 60 sets a second at 20 ms: 1.2 s of work a second
        stats.input_set()
    assert not stats.keeping_up()


@pytest.mark.parametrize("odometry", [False, True])
def test_pothole_ids_follow_the_odometry(node_factory, probe, odometry):
    """Every sixth frame of the sample drive (0.3 m apart, more than the match distance and
    about the potholes' spacing): with use_odometry an id that carries over names the same
    generated pothole; without it, ids jump to the next pothole."""
    from nav_msgs.msg import Odometry

    from pothole_detector.recordings.writing import odometry_message

    node_factory(backend="cpu", use_odometry=odometry)
    p = probe(outputs=("potholes", "pothole_labels"))
    odom = p.node.create_publisher(Odometry, "/stereo/odom", 10)
    p.wait_connected()
    drive = sample_frames(16)
    picked = (0, 6, 12)
    for count, index in enumerate(picked, start=1):
        stamp = stamp_ns(drive[index]["left"].header)
        odom.publish(odometry_message(stamp, 0.05 * index, 0.0, 0.0))
        p.spin(0.2)
        p.publish(drive[index], stamp)
        assert p.spin(30, lambda: len(p.received["pothole_labels"]) == count)
    truth_of = []  # per frame: id -> the generated pothole under most of its pixels
    for index, msg in zip(picked, p.received["pothole_labels"]):
        labels, truth = labels_of(msg), labels_of(drive[index]["truth"])
        truth_of.append({int(i): int(np.bincount(truth[labels == i]).argmax())
                         for i in np.unique(labels) if i})
    carried = [(i, a[i], b[i]) for a, b in zip(truth_of, truth_of[1:]) for i in a if i in b]
    assert carried, truth_of
    same = [before == after for _, before, after in carried]
    assert all(same) if odometry else not all(same), truth_of


def test_the_road_map_is_published_around_the_camera_for_rviz_and_planners(node_factory, probe):
    """With odometry and somebody subscribed, the node fuses the sample drive into its road map
    and publishes it around the camera: a cloud of the seen cells and an occupancy grid whose
    pothole cells are the cloud's pothole points, centimetres below the road, in the odometry's
    frame."""
    from nav_msgs.msg import Odometry

    from pothole_detector.recordings.writing import odometry_message

    node_factory(backend="cpu", use_odometry=True, map_publish_rate_hz=30.0)
    p = probe(outputs=("potholes", "map_cloud", "map_potholes"))
    odom = p.node.create_publisher(Odometry, "/stereo/odom", 10)
    p.wait_connected()
    drive = sample_frames(8)
    for count, frame in enumerate(drive, start=1):
        stamp = stamp_ns(frame["left"].header)
        odom.publish(odometry_message(stamp, 0.05 * (count - 1), 0.0, 0.0))
        p.spin(0.2)
        p.publish(frame, stamp)
        assert p.spin(30, lambda: len(p.received["potholes"]) == count)
    assert p.spin(10, lambda: len(p.received["map_potholes"]) == len(drive))
    grid, cloud = p.received["map_potholes"][-1], p.received["map_cloud"][-1]
    assert grid.header.frame_id == cloud.header.frame_id == "odom"
    assert grid.info.resolution == pytest.approx(0.02)
    cells = np.array(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width)
    assert set(np.unique(cells)) == {-1, 0, 100} and (cells == 100).sum() > 20
    points = np.frombuffer(bytes(cloud.data), dtype=conversions.MAP_DTYPE)
    assert [f.name for f in cloud.fields] == list(conversions.MAP_DTYPE.names)
    assert len(points) == (cells >= 0).sum()
    deep = points[points["pothole_id"] > 0]
    assert len(deep) == (cells == 100).sum() and np.median(deep["depth_below_road"]) > 0.01
    assert abs(np.median(points[points["pothole_id"] == 0]["depth_below_road"])) < 0.002
    column = ((deep["x"] - grid.info.origin.position.x) / 0.02).astype(int)
    row = ((deep["y"] - grid.info.origin.position.y) / 0.02).astype(int)
    assert np.all(cells[row, column] == 100)


def test_the_shipped_parameters_take_every_frame_of_a_640x480_vehicle_drive(node_factory,
                                                                            probe):
    """A vehicle rig (1 m up, pitched 15 deg, 0.12 m baseline) at 640x480, half a metre a frame,
    into the node with the shipped parameter file: every frame processed, none failed."""
    from pothole_detector.evaluation.synthetic import render, vehicle_scene
    node_factory()
    p = probe(outputs=("potholes",))
    p.wait_connected()
    for index in range(6):
        sample = render(vehicle_scene(640, 480, camera_y_m=0.5 * index))
        header = header_at(T0, "stereo_left_optical_frame")
        frame = {"left": array_to_image(sample.left, "mono8", header),
                 "right": array_to_image(sample.right, "mono8", header),
                 "left_info": camera_info_message(sample.calibration, 640, 480,
                                                              header),
                 "right_info": camera_info_message(sample.calibration, 640, 480,
                                                               header, right=True)}
        p.publish(frame, T0 + index)  # one at a time: a set arriving while busy is dropped
        assert p.spin(30, lambda: T0 + index in p.stamps()), p.diagnostics()
    assert all(msg.status != msg.FAILED for msg in p.received["potholes"])
    assert p.spin(5, lambda: p.diagnostics().get("frames_processed") == "6"), p.diagnostics()
    assert p.diagnostics()["failures_in_a_row"] == "0"


def test_the_node_takes_compressed_and_raw_distorted_input(node_factory, probe, frames):
    """image_transport:=compressed: the sample drive as PNG CompressedImage on
    .../image_rect/compressed gives the labels of the uncompressed pairs; raw images of a
    distorted, rotated camera with its camera_info (rectify auto): rectified in the node,
    the labels of the same pipeline offline, close to the ground truth."""
    compressed = [{**frame, **{side: compressed_image(
        decode_raw(frame[side]), "png", frame[side].header) for side in ("left", "right")}}
        for frame in frames]
    node_factory(backend="cpu", image_transport="compressed")
    p = probe(outputs=("potholes", "pothole_labels"), compressed=True)
    p.wait_connected()
    for index, frame in enumerate(compressed):
        p.publish(frame, T0 + index)
        assert p.spin(30, lambda: len(p.received["pothole_labels"]) == index + 1), index
    expected = offline_results(frames)
    for msg, result in zip(p.received["pothole_labels"], expected):
        np.testing.assert_array_equal(labels_of(msg) > 0, result.labels > 0)

    scenes = [replace(scene, supersample=1) for scene in drive_scenes(frames=2)]
    samples = [render(scene) for scene in scenes]
    camera = raw_camera(samples[0].calibration, 640, 360, "plumb_bob", seed=2)
    raw = [render_raw(scene, camera) for scene in scenes]
    infos = [camera_info_of(model, header_at(0))
             for model in (camera.left, camera.right)]
    node_factory(backend="cpu", namespace="/raw")
    q = probe(outputs=("potholes", "pothole_labels"), namespace="/raw")
    q.wait_connected()
    calibration, rectification = pipeline_inputs(camera, "auto")
    pipeline = Pipeline(Config({"backend": "cpu"}), calibration, rectification=rectification)
    for index, ((left, right), sample) in enumerate(zip(raw, samples)):
        q.publish({"left": array_to_image(left, "mono8", header_at(0)),
                   "right": array_to_image(right, "mono8", header_at(0)),
                   "left_info": infos[0], "right_info": infos[1]}, T0 + 10 + index)
        assert q.spin(30, lambda: len(q.received["pothole_labels"]) == index + 1), index
        labels = labels_of(q.received["pothole_labels"][-1])
        np.testing.assert_array_equal(labels > 0, pipeline.run(left, right).labels > 0)
        truth = sample.labels > 0
        found = labels > 0
        assert 2 * (found & truth).sum() / (found.sum() + truth.sum()) > 0.85


def test_ctrl_c_while_the_node_starts_exits_quietly(tmp_path):
    """The console script interrupted at once, while Python still loads ROS: status 0 and no
    traceback."""
    for delay in (0.2, 1.5):
        process = subprocess.Popen([sys.executable, "-m", "pothole_detector.ros.node_main",
                                    "--ros-args", "-p", "backend:=cpu"],
                                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        time.sleep(delay)
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=30)
        assert process.returncode == 0 and "Traceback" not in output, output
