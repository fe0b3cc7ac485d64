"""Message classes and CDR (de)serialization for reading and writing bags and for the node's
messages: rclpy's where ROS 2 and our messages are installed, else classes of the rosbags
typestore, so that ``process``, ``survey``, ``detect`` and ``evaluate`` run without ROS. Both
kinds take keyword fields, default the rest as ROS does and carry the message constants."""

from __future__ import annotations

import functools
import importlib
import sys
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from ..errors import InputError

MSG_PACKAGE = "pothole_detector_msgs"
MSG_NAMES = ("Pothole", "PotholeArray")
_NUMPY_TYPES = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
    "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
    "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64,
}
# defaults that .msg files of the messages we write declare (rosbags' typestore drops them)
_DECLARED_DEFAULTS = {"geometry_msgs/msg/Quaternion": {"w": 1.0}}
# rosbags' field node kinds
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4


def _ros_available() -> bool:
    try:
        importlib.import_module("rclpy.serialization")
        importlib.import_module(f"{MSG_PACKAGE}.msg")
    except ImportError:
        return False
    return True


ROS = _ros_available()


def msg_directory() -> Path:
    """Where the .msg files of pothole_detector_msgs are: the source tree's msg_schemas/msg,
    else where pip installed them (share/pothole_detector/msg), else the ROS package's share
    directory."""
    source = Path(__file__).resolve().parents[2] / "msg_schemas" / "msg"
    if source.is_dir():
        return source
    installed = Path(sys.prefix) / "share" / "pothole_detector" / "msg"
    if installed.is_dir():
        return installed
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory(MSG_PACKAGE)) / "msg"
    except (ImportError, LookupError) as exc:
        raise InputError(f"cannot find the pothole_detector_msgs definitions ({exc}); "
                         "reinstall pothole_detector") from None


@functools.cache
def typestore() -> Typestore:
    """The Jazzy typestore with our own message types registered from their .msg text."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict[str, Any] = {}
    for name in MSG_NAMES:
        text = (msg_directory() / f"{name}.msg").read_text()
        types.update(get_types_from_msg(text, f"{MSG_PACKAGE}/msg/{name}"))
    store.register(types)
    return store


class StoreMessage:
    """A typestore message type that takes keyword fields and defaults the others (zeros,
    empty strings and sequences, default nested messages); its constants are attributes."""

    def __init__(self, msgtype: str) -> None:
        store = typestore()
        if msgtype not in store.types:
            raise InputError(f"message type {msgtype} is unknown to the rosbags typestore")
        self.msgtype = msgtype
        self.cls = store.types[msgtype]
        constants, self._fields = store.fielddefs[msgtype]
        for name, _, value in constants:
            setattr(self, name, value)

    def __call__(self, **fields: Any) -> Any:
        declared = _DECLARED_DEFAULTS.get(self.msgtype, {})
        values = {name: fields[name] if name in fields else declared.get(name, _default(kind))
                  for name, kind in self._fields}
        for name, kind in self._fields:
            values[name] = _as_field(values[name], kind)
        return self.cls(**values)


def _default(kind: tuple) -> Any:
    node, detail = kind
    if node == _BASE:
        name = detail[0]
        return "" if name == "string" else _NUMPY_TYPES[name](0).item()
    if node == _NAME:
        return store_message(detail)()
    inner, size = detail
    if node == _ARRAY:
        if inner[0] == _BASE and inner[1][0] in _NUMPY_TYPES:
            return np.zeros(size, _NUMPY_TYPES[inner[1][0]])
        return [_default(inner) for _ in range(size)]
    if inner[0] == _BASE and inner[1][0] in _NUMPY_TYPES:
        return np.zeros(0, _NUMPY_TYPES[inner[1][0]])
    return []


def _as_field(value: Any, kind: tuple) -> Any:
    """Numeric arrays and sequences as NumPy arrays of the field's type (rosbags needs them)."""
    node, detail = kind
    if node in (_ARRAY, _SEQUENCE):
        inner = detail[0]
        if inner[0] == _BASE and inner[1][0] in _NUMPY_TYPES:
            return np.asarray(value, dtype=_NUMPY_TYPES[inner[1][0]])
        return list(value)
    return value


@functools.cache
def store_message(msgtype: str) -> StoreMessage:
    """The :class:`StoreMessage` of ``msgtype`` (made once)."""
    return StoreMessage(msgtype)


@functools.cache
def message(msgtype: str) -> Any:
    """The class of ``msgtype`` (e.g. ``sensor_msgs/msg/Image``): rclpy's where ROS is
    installed, else a :class:`StoreMessage`."""
    if not ROS:
        return store_message(msgtype)
    package, _, name = msgtype.rpartition("/")
    try:
        return getattr(importlib.import_module(package.replace("/", ".")), name)
    except (ImportError, AttributeError):
        raise InputError(f"message type {msgtype} is not installed for rclpy; install its "
                         "package or leave the topic out") from None


def serialize(msg: Any, msgtype: str) -> bytes:
    """CDR bytes of ``msg``, a message of type ``msgtype``."""
    if ROS:
        from rclpy.serialization import serialize_message
        return serialize_message(msg)
    return bytes(typestore().serialize_cdr(msg, msgtype))


def deserialize(raw: bytes, msgtype: str) -> Any:
    """The message of type ``msgtype`` in CDR bytes ``raw``."""
    if ROS:
        from rclpy.serialization import deserialize_message
        return deserialize_message(raw, message(msgtype))
    return typestore().deserialize_cdr(raw, msgtype)


def stamp_ns(header: Any) -> int:
    """The stamp of a std_msgs/Header in integer nanoseconds."""
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def header_at(nanoseconds: int, frame_id: str = "") -> Any:
    """A std_msgs/Header stamped ``nanoseconds`` (ns) in ``frame_id``."""
    sec, nanosec = divmod(int(nanoseconds), 1_000_000_000)
    return message("std_msgs/msg/Header")(
        stamp=message("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec),
        frame_id=frame_id)
