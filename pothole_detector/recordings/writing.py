"""Writing bags: a new ROS 2 bag, messages copied from another, and stereo drives of our
generator as a camera driver and a recorder would store them (topics, encodings,
compression, raw or rectified views, odometry and GNSS beside them)."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np
from rosbags.highlevel import AnyReader

from ..calibration import StereoCamera
from ..geodesy import latlon_of
from .bags import cdr_bytes
from .bagwriter import BagWriter
from .camera import camera_info_message, camera_info_of
from .images import COMPRESSED_TYPE, IMAGE_TYPE, array_to_image, compressed_image, encode_raw
from .messages import header_at, message, serialize, typestore
from .topics import INFO_TYPE, StereoTopics


def copy_messages(reader: AnyReader, writer: BagWriter, topics: Sequence[str]) -> None:
    """Copy the messages of ``topics`` from a bag into a new one (ROS 2 CDR), up to where
    the bag is damaged, if it is."""
    store = typestore()
    bag_topics = {c.topic: c.msgtype for c in reader.connections}
    connections = {topic: writer.add_connection(topic, bag_topics[topic], typestore=store)
                   for topic in topics}
    messages = reader.messages(connections=[c for c in reader.connections
                                            if c.topic in connections])
    while True:
        try:
            connection, timestamp, rawdata = next(messages)
        except StopIteration:
            return
        except Exception:  # noqa: BLE001 - a damaged bag: reading the sets will say where
            return
        writer.write(connections[connection.topic], timestamp,
                     cdr_bytes(reader, connection, rawdata))



ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
GNSS_TYPE = "sensor_msgs/msg/NavSatFix"


def odometry_message(stamp_ns: int, x: float, y: float, yaw: float,
                     frame_id: str = "odom", child_frame_id: str = "base_link") -> Any:
    """nav_msgs/Odometry of a planar pose (m, rad)."""
    msg = message(ODOMETRY_TYPE)(header=header_at(stamp_ns, frame_id),
                                 child_frame_id=child_frame_id)
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x), float(y)
    msg.pose.pose.orientation.z = math.sin(yaw / 2)
    msg.pose.pose.orientation.w = math.cos(yaw / 2)
    return msg


def gnss_message(stamp_ns: int, lat_deg: float, lon_deg: float,
                 frame_id: str = "gnss") -> Any:
    """sensor_msgs/NavSatFix of a fix (status FIX, GPS)."""
    msg = message(GNSS_TYPE)(header=header_at(stamp_ns, frame_id),
                             latitude=float(lat_deg), longitude=float(lon_deg))
    msg.status.status, msg.status.service = 0, 1
    return msg


@dataclass(frozen=True)
class RecordingForm:
    """How a camera driver records a stereo camera, for :func:`write_stereo_bag`: its topics
    (None: ``<namespace>/left/image_rect`` and so on; CompressedImage topics end in
    ``/compressed``), how its images are stored (``encoding``: one a camera publishes, made
    from the samples' grey or RGB by recordings.images.encode_raw; None: mono8 or rgb8 as the
    samples are) or compressed (``compression``: jpeg or png), the calibrated camera they come
    from (raw images: its camera_info, with distortion and R; None: the rectified camera of
    the samples) and whether the right camera_info leaves the baseline out (Tx = 0)."""

    topics: StereoTopics | None = None
    encoding: str | None = None
    compression: str | None = None
    camera: StereoCamera | None = None
    no_baseline: bool = False


DRIVE_MOTIONS = ("none", "odom", "gnss")


def write_drive_bag(out: str | Path, forward_m: Sequence[float], samples: Sequence[Any],
                    motion: str = "none", origin_latlon: tuple[float, float] = (48.137, 11.575),
                    start_ns: int = 1_700_000_000_000_000_000, rate_hz: float = 10.0,
                    ground_truth: bool = True, form: RecordingForm | None = None) -> int:
    """A stereo bag of a straight drive of our generator: frame i (StereoSample) taken
    ``forward_m[i]`` m along the road from the first, at ``rate_hz``; with ``motion`` "odom"
    also /odom (the road point below the camera, x forward), with "gnss" /gnss/fix (driving
    north from ``origin_latlon``); the label images as write_stereo_bag's ``ground_truth``, the
    camera's topics and images as ``form`` says (write_stereo_bag)."""
    if motion not in DRIVE_MOTIONS:
        raise ValueError(f"motion must be one of {DRIVE_MOTIONS}")

    def extras(index: int, stamp: int, sample: Any) -> dict[str, Any]:
        if motion == "odom":
            return {"/odom": odometry_message(stamp, forward_m[index], 0.0, 0.0)}
        if motion == "gnss":
            lat, lon = latlon_of(np.array([[0.0, forward_m[index]]]), *origin_latlon)[0]
            return {"/gnss/fix": gnss_message(stamp, lat, lon)}
        return {}

    return write_stereo_bag(out, ((start_ns + round(i * 1e9 / rate_hz), sample)
                                  for i, sample in enumerate(samples)),
                            ground_truth=ground_truth, extras=extras,
                            form=form or RecordingForm())


def write_stereo_bag(out: str | Path, frames: Iterable[tuple[int, Any]],
                     namespace: str = "/stereo",
                     frame_id: str = "stereo_left_optical_frame", storage: str = "mcap",
                     ground_truth: bool = True,
                     extras: Callable[[int, int, Any], dict[str, Any]] | None = None,
                     form: RecordingForm = RecordingForm()) -> int:
    """Write (stamp ns, StereoSample) frames as a stereo bag: ``left/image_rect``,
    ``right/image_rect`` (mono8, or rgb8 for colour samples), both camera_info and, with
    ``ground_truth``, ``ground_truth/pothole_labels`` (mono16) under ``namespace``; or in the
    topics, encoding or compression and calibration of ``form`` (raw images: the samples'
    images must be the camera's raw ones, synthetic.render_raw). ``extras(index, stamp,
    sample)`` gives more messages per frame by topic (``/odom``: nav_msgs/Odometry,
    ``/gnss/fix``: sensor_msgs/NavSatFix). Returns the number of frames written."""
    store = typestore()
    writer = BagWriter(out, storage)
    image_type = COMPRESSED_TYPE if form.compression else IMAGE_TYPE
    names = form.topics or StereoTopics(
        *(f"{namespace}/{side}/image_rect" + ("/compressed" if form.compression else "")
          for side in ("left", "right")),
        f"{namespace}/left/camera_info", f"{namespace}/right/camera_info")
    topics = {"left": (names.left, image_type), "right": (names.right, image_type),
              "left_info": (names.left_info, INFO_TYPE),
              "right_info": (names.right_info, INFO_TYPE)}
    if ground_truth:
        topics["truth"] = (f"{names.namespace or namespace}/ground_truth/pothole_labels",
                           IMAGE_TYPE)
    connections = {key: writer.add_connection(topic, msgtype, typestore=store)
                   for key, (topic, msgtype) in topics.items()}
    extra_types = {"/odom": ODOMETRY_TYPE, "/gnss/fix": GNSS_TYPE}
    count = 0

    stored: dict[int, tuple[np.ndarray, Any]] = {}

    def image(pixels: np.ndarray, header: Any) -> Any:
        """The image message of ``pixels``, encoded once per array (a drive may cycle a few
        samples) and stamped ``header``."""
        if id(pixels) not in stored:
            if form.compression:
                made = compressed_image(pixels, form.compression, header)
            else:
                encoding = form.encoding or ("mono8" if pixels.ndim == 2 else "rgb8")
                made = array_to_image(encode_raw(pixels, encoding), encoding, header)
            stored[id(pixels)] = (pixels, made)
        made = copy.copy(stored[id(pixels)][1])
        made.header = header
        return made

    try:
        for index, (stamp_ns, sample) in enumerate(frames):
            for topic, extra in (extras(index, stamp_ns, sample) if extras else {}).items():
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, extra_types[topic],
                                                               typestore=store)
                writer.write(connections[topic], int(stamp_ns),
                             serialize(extra, extra_types[topic]))
            header = header_at(stamp_ns, frame_id)
            height, width = sample.left.shape[:2]
            if form.camera is not None:
                infos = [camera_info_of(model, header)
                         for model in (form.camera.left, form.camera.right)]
            else:
                infos = [camera_info_message(sample.calibration, width, height,
                                                         header, right=right)
                         for right in (False, True)]
            if form.no_baseline:
                infos[1].p[3] = 0.0
            messages = {"left": image(sample.left, header),
                        "right": image(sample.right, header),
                        "left_info": infos[0], "right_info": infos[1]}
            if ground_truth:
                messages["truth"] = array_to_image(
                    sample.labels.astype(np.uint16), "mono16", header)
            for key in ("left_info", "right_info", "left", "right", "truth"):
                if key in messages:
                    writer.write(connections[key], int(stamp_ns),
                                 serialize(messages[key], topics[key][1]))
            count += 1
    finally:
        writer.close()
    return count
