"""Which topics of a bag are the stereo camera: found as a person would, by the names camera
drivers use (left/right, infra1/infra2, cam0/cam1, camera_left/camera_right, left_raw, ...),
rectified pairs first (compressed or not), else raw images with the camera_info that rectifies
them; named ones are checked."""

from __future__ import annotations

import re
from dataclasses import dataclass

from ..errors import InputError
from .images import COMPRESSED_TYPE, IMAGE_TYPE, IMAGE_TYPES

INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TRANSPORT_SUFFIX = "compressed"
# numbered camera names: prefix -> (left's number, right's number)
_NUMBERED = re.compile(r"^(infra|ir|cam|image|camera)([0-9])$")
_NUMBERED_SIDES = {"infra": ("1", "2"), "ir": ("1", "2"), "cam": ("0", "1"),
                   "image": ("0", "1"), "camera": ("0", "1")}
# image topics that are no camera's: outputs of stereo processing and our own
_NOT_CAMERA = ("depth", "disparity", "overlay", "labels", "confidence", "ground_truth", "mask",
               "points", "segmentation")
# how a pair's images were recorded, best first
KINDS = ("rectified", "unknown", "raw")


@dataclass(frozen=True)
class StereoTopics:
    """The topics of one stereo camera: left and right images (``image_type``: Image or
    CompressedImage) and their camera_info."""

    left: str
    right: str
    left_info: str
    right_info: str
    image_type: str = IMAGE_TYPE

    @property
    def compressed(self) -> bool:
        return self.image_type == COMPRESSED_TYPE

    @property
    def namespace(self) -> str:
        """The common parent of the left and right image topics ('' for the root)."""
        left, right = self.left.strip("/").split("/"), self.right.strip("/").split("/")
        common = []
        for a, b in zip(left, right):
            if a != b:
                break
            common.append(a)
        return "/" + "/".join(common) if common else ""

    def describe(self) -> str:
        """One line: the topics used and how the images come."""
        kind = _image_name(self.left)[1]
        how = {"rectified": "rectified", "raw": "raw", "unknown": "rectified or raw"}[kind]
        coding = "compressed" if self.compressed else "uncompressed"
        return (f"stereo topics: {self.left} and {self.right} ({how}, {coding}), camera_info "
                f"{self.left_info} and {self.right_info}")


def _image_name(topic: str) -> tuple[list[str], str]:
    """The topic's segments without image_transport's suffix, and its kind (KINDS) by the
    image's name: rectified ("rect" in it), raw ("raw" without "rect"), else unknown."""
    segments = topic.strip("/").split("/")
    if len(segments) > 1 and segments[-1] == TRANSPORT_SUFFIX:
        segments = segments[:-1]
    name = segments[-1].lower()
    kind = "rectified" if "rect" in name else "raw" if "raw" in name else "unknown"
    return segments, kind


def side_of(topic: str) -> tuple[str, str] | None:
    """(side, key) of an image or camera_info topic: left or right by the nearest segment
    that names one, and the topic with that side written as ``{}`` (the partner's key is the
    same); None where no segment names a side."""
    segments, _ = _image_name(topic)
    for index in range(len(segments) - 1, -1, -1):
        segment = segments[index]
        lowered = segment.lower()
        numbered = _NUMBERED.match(lowered)
        template = None
        if numbered and numbered.group(1) in _NUMBERED_SIDES:
            sides = _NUMBERED_SIDES[numbered.group(1)]
            if numbered.group(2) in sides:
                side = "left" if numbered.group(2) == sides[0] else "right"
                template = numbered.group(1) + "{}"
        elif ("left" in lowered) != ("right" in lowered):
            side = "left" if "left" in lowered else "right"
            template = lowered.replace(side, "{}")
        if template is not None:
            key = "/".join(segments[:index] + [template] + segments[index + 1:])
            return side, key
    return None


def _is_camera_image(topic: str, msgtype: str) -> bool:
    if msgtype not in IMAGE_TYPES:
        return False
    segments = topic.strip("/").split("/")
    if msgtype == COMPRESSED_TYPE and segments[-1] != TRANSPORT_SUFFIX \
            and not segments[-1].startswith("image"):
        return False  # compressedDepth, theora, ... are other transports
    return not any(word in topic.lower() for word in _NOT_CAMERA)


def info_for(image_topic: str, topics: dict[str, str]) -> str | None:
    """The camera_info topic of an image topic: ``camera_info`` beside it, or beside one of
    its parents (the nearest)."""
    segments, _ = _image_name(image_topic)
    for end in range(len(segments) - 1, -1, -1):
        candidate = "/" + "/".join(segments[:end] + ["camera_info"])
        if topics.get(candidate) == INFO_TYPE:
            return candidate
    return None


@dataclass(frozen=True)
class _Candidate:
    topics: StereoTopics
    kind: str
    colour: bool

    def rank(self) -> tuple[int, int, int]:
        return (KINDS.index(self.kind), int(self.topics.compressed), int(not self.colour))


def candidates(topics: dict[str, str]) -> list[_Candidate]:
    """Every left/right image pair of the bag (``topics``: name -> type) with camera_info
    for both, best first (rectified, then of unknown kind, then raw; uncompressed before
    compressed; colour before grey)."""
    by_key: dict[tuple[str, str], dict[str, str]] = {}
    for topic, msgtype in topics.items():
        if not _is_camera_image(topic, msgtype):
            continue
        found = side_of(topic)
        if found is None:
            continue
        side, key = found
        by_key.setdefault((key, msgtype), {})[side] = topic
    pairs = []
    for (_, msgtype), sides in by_key.items():
        if set(sides) != {"left", "right"}:
            continue
        left_info, right_info = info_for(sides["left"], topics), info_for(sides["right"], topics)
        if left_info is None or right_info is None or left_info == right_info:
            continue
        name = _image_name(sides["left"])[0][-1].lower()
        pairs.append(_Candidate(StereoTopics(sides["left"], sides["right"], left_info,
                                             right_info, msgtype), _image_name(sides["left"])[1],
                                not any(word in name for word in ("gray", "grey", "mono"))))
    return sorted(pairs, key=lambda c: (c.rank(), c.topics.left))


def find_stereo_topics(topics: dict[str, str], left: str | None = None,
                       right: str | None = None, left_info: str | None = None,
                       right_info: str | None = None) -> StereoTopics:
    """The stereo topics of a bag (``topics``: name -> type). Named ones are checked and the
    rest found for them; with none named, the best pair (:func:`candidates`). Raises
    InputError listing the candidates and the flags that choose where it is truly ambiguous,
    or saying what the bag lacks."""
    for given, kinds, what in ((left, IMAGE_TYPES, "image"), (right, IMAGE_TYPES, "image"),
                               (left_info, (INFO_TYPE,), "camera_info"),
                               (right_info, (INFO_TYPE,), "camera_info")):
        if given is not None and topics.get(given) not in kinds:
            kind = "Image or CompressedImage" if what == "image" else "CameraInfo"
            raise InputError(f"the bag has no {kind} topic named {given}; it has "
                             f"{', '.join(sorted(topics))}")
    if left is not None and right is not None:
        if topics[left] != topics[right]:
            raise InputError(f"{left} is {topics[left]} but {right} is {topics[right]}; name "
                             "two image topics of one kind")
        infos = (left_info or info_for(left, topics), right_info or info_for(right, topics))
        if infos[0] is None or infos[1] is None:
            raise InputError(f"cannot tell the camera_info of {left} and {right}; name them "
                             "with --left-info-topic and --right-info-topic")
        return StereoTopics(left, right, infos[0], infos[1], topics[left])
    found = [c for c in candidates(topics)
             if (left is None or c.topics.left == left)
             and (right is None or c.topics.right == right)
             and (left_info is None or c.topics.left_info == left_info)
             and (right_info is None or c.topics.right_info == right_info)]
    if not found:
        images = sorted(t for t, k in topics.items() if k in IMAGE_TYPES)
        infos = sorted(t for t, k in topics.items() if k == INFO_TYPE)
        raise InputError(
            f"cannot find a left/right image pair with camera_info among the image topics "
            f"{images or 'none'} and camera_info topics {infos or 'none'}; name them with "
            "--left-topic, --right-topic, --left-info-topic and --right-info-topic")
    best = [c for c in found if c.rank() == found[0].rank()]
    if len(best) > 1:
        listed = "; ".join(f"{c.topics.left} + {c.topics.right}" for c in best)
        raise InputError(f"the bag holds several stereo cameras alike ({listed}); choose one "
                         "with --left-topic and --right-topic")
    return best[0].topics
