"""Image messages as arrays: sensor_msgs/Image in every encoding a camera driver publishes,
and sensor_msgs/CompressedImage (JPEG and PNG, as image_transport's compressed transport
writes them), through OpenCV. Hostile input is refused with one line, before it can cost
memory: a compressed image's size is read from its header (Pillow, no pixels decoded) and
checked against the largest allowed and, where known, the camera_info's."""

from __future__ import annotations

import array
import io
import warnings
from typing import Any, Sequence

import cv2
import numpy as np
from PIL import Image as PILImage

from ..errors import InputError
from .messages import ROS, message

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)

# encoding -> (dtype, channels as stored)
RAW_LAYOUTS: dict[str, tuple[np.dtype, int]] = {
    **{name: (np.dtype(np.uint8), 1) for name in ("mono8", "8UC1")},
    **{name: (np.dtype(np.uint16), 1) for name in ("mono16", "16UC1")},
    **{name: (np.dtype(np.uint8), 3) for name in ("rgb8", "bgr8", "8UC3")},
    **{name: (np.dtype(np.uint8), 4) for name in ("rgba8", "bgra8", "8UC4")},
    **{name: (np.dtype(np.uint16), 3) for name in ("rgb16", "bgr16", "16UC3")},
    **{name: (np.dtype(np.uint16), 4) for name in ("rgba16", "bgra16", "16UC4")},
    **{f"bayer_{pattern}{bits}": (np.dtype(np.uint8 if bits == 8 else np.uint16), 1)
       for pattern in ("rggb", "bggr", "gbrg", "grbg") for bits in (8, 16)},
    # two bytes a pixel, luma and alternating chroma
    **{name: (np.dtype(np.uint8), 2) for name in ("yuv422", "uyvy", "yuv422_yuy2", "yuyv")},
    "32FC1": (np.dtype(np.float32), 1),
}
_BAYER_TO_RGB = {"rggb": cv2.COLOR_BayerRGGB2RGB, "bggr": cv2.COLOR_BayerBGGR2RGB,
                 "gbrg": cv2.COLOR_BayerGBRG2RGB, "grbg": cv2.COLOR_BayerGRBG2RGB}
_YUV_TO_RGB = {"yuv422": cv2.COLOR_YUV2RGB_UYVY, "uyvy": cv2.COLOR_YUV2RGB_UYVY,
               "yuv422_yuy2": cv2.COLOR_YUV2RGB_YUY2, "yuyv": cv2.COLOR_YUV2RGB_YUY2}
# what a camera may publish (32FC1 is a depth or disparity map's)
INPUT_ENCODINGS = tuple(name for name in RAW_LAYOUTS if name != "32FC1")
# the largest image decoded (pixels): a header claiming more is refused as a decompression bomb
MAX_IMAGE_PIXELS = 64_000_000


def decode(msg: Any, msgtype: str, expected: tuple[int, int] | None = None,
           grey: bool = False) -> np.ndarray:
    """The pixels of an image message of ``msgtype`` (IMAGE_TYPE or COMPRESSED_TYPE): HxW
    (mono, uint8 or uint16) or HxWx3 RGB (uint8 or uint16; alpha dropped); with ``grey``, as
    the matcher takes them: 8-bit colour as grey (a JPEG's own luma, decoded without its
    colour; otherwise OpenCV's RGB to grey, as stages.matching.to_gray8). ``expected``:
    (width, height) the camera_info gives, checked before a compressed image is decoded.
    Raises InputError saying what is wrong."""
    if msgtype == COMPRESSED_TYPE:
        pixels = decode_compressed(msg, expected, grey)
    else:
        pixels = decode_raw(msg)
        if expected is not None and expected != (0, 0) \
                and (pixels.shape[1], pixels.shape[0]) != expected:
            raise InputError(f"image is {pixels.shape[1]}x{pixels.shape[0]} but its "
                             f"camera_info is for {expected[0]}x{expected[1]}; publish "
                             "matching camera_info")
    if grey and pixels.ndim == 3 and pixels.dtype == np.uint8:
        return cv2.cvtColor(pixels, cv2.COLOR_RGB2GRAY)
    return pixels


def decode_raw(msg: Any, allowed: Sequence[str] = INPUT_ENCODINGS) -> np.ndarray:
    """A sensor_msgs/Image of an ``allowed`` encoding as an array (see :func:`decode`; 32FC1
    as float32 HxW), honouring ``step`` and ``is_bigendian``; Bayer demosaiced and YUV 4:2:2
    converted to RGB by OpenCV."""
    encoding = str(msg.encoding)
    if encoding not in RAW_LAYOUTS and encoding.lower() in RAW_LAYOUTS:
        encoding = encoding.lower()
    if encoding not in allowed or encoding not in RAW_LAYOUTS:
        raise InputError(f"image encoding {msg.encoding!r} is not supported; publish one of "
                         f"{', '.join(allowed)}, or compress with image_transport")
    layout = RAW_LAYOUTS[encoding]
    dtype, channels = layout
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * dtype.itemsize
    if height == 0 or width == 0:
        raise InputError(f"image is empty ({width}x{height})")
    if height * width > MAX_IMAGE_PIXELS:
        raise InputError(f"image claims {width}x{height} px, more than the "
                         f"{MAX_IMAGE_PIXELS / 1e6:.0f} MP a camera image may have")
    if step < row_bytes:
        raise InputError(f"image step {step} B is shorter than a {encoding} row of {width} px "
                         f"({row_bytes} B); fix the publisher's step")
    if len(msg.data) < step * (height - 1) + row_bytes:
        raise InputError(f"image data holds {len(msg.data)} B but {width}x{height} {encoding} "
                         f"with step {step} needs {step * height} B")
    raw = np.frombuffer(msg.data, dtype=np.uint8, count=min(len(msg.data), step * height))
    if raw.size < step * height:
        raw = np.concatenate([raw, np.zeros(step * height - raw.size, np.uint8)])
    rows = raw.reshape(height, step)[:, :row_bytes]
    order = ">" if msg.is_bigendian else "<"
    pixels = np.ascontiguousarray(rows).view(dtype.newbyteorder(order))
    pixels = pixels.astype(dtype, copy=False).reshape(height, width, channels)
    if encoding.startswith("bayer_"):
        if height < 2 or width < 2 or height % 2 or width % 2:
            raise InputError(f"a {encoding} image needs an even width and height, got "
                             f"{width}x{height}")
        return cv2.cvtColor(np.ascontiguousarray(pixels[..., 0]),
                            _BAYER_TO_RGB[encoding[6:10]])
    if encoding in _YUV_TO_RGB:
        if width % 2:
            raise InputError(f"a {encoding} image needs an even width, got {width}")
        return cv2.cvtColor(pixels, _YUV_TO_RGB[encoding])
    if channels == 1:
        return np.ascontiguousarray(pixels[..., 0])
    if encoding.startswith("bgr") or "UC" in encoding:
        pixels = pixels[..., 2::-1]  # OpenCV's nUCk images are BGR(A), as cv_bridge takes them
    return np.ascontiguousarray(pixels[..., :3])


def compressed_format(msg: Any) -> str:
    """jpeg or png: the codec of a CompressedImage by its ``format`` ("jpeg", "png", or
    image_transport's "rgb8; jpeg compressed bgr8"); raises InputError for others
    (compressedDepth, theora, ...)."""
    text = str(msg.format).lower()
    codec = text.split(";")[-1].strip().split(" ")[0] if ";" in text else text.strip()
    if codec in ("jpg", "jpeg"):
        return "jpeg"
    if codec == "png":
        return "png"
    raise InputError(f"compressed image format {msg.format!r} is not supported; use "
                     "image_transport's compressed transport (jpeg or png)")


def image_size(data: bytes | np.ndarray) -> tuple[int, int]:
    """(width, height) a JPEG or PNG header claims, read without decoding any pixel."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # our own bound below says what is too large
            header = PILImage.open(io.BytesIO(bytes(data)))
            return int(header.size[0]), int(header.size[1])
    except (OSError, ValueError, SyntaxError, PILImage.DecompressionBombError) as exc:
        raise InputError(f"compressed image has no readable header ({exc}); the message is "
                         "corrupt") from None


def decode_compressed(msg: Any, expected: tuple[int, int] | None = None,
                      grey: bool = False) -> np.ndarray:
    """A sensor_msgs/CompressedImage as an array (see :func:`decode`). Its header's size is
    checked first (at most MAX_IMAGE_PIXELS, equal to ``expected`` where given); a JPEG must
    end with its end-of-image marker and a PNG with IEND (a truncated one is refused rather
    than half decoded). ``grey``: a JPEG decoded to its luma alone."""
    codec = compressed_format(msg)
    data = np.frombuffer(msg.data, dtype=np.uint8) if not isinstance(msg.data, np.ndarray) \
        else msg.data.view(np.uint8)
    if data.size < 8:
        raise InputError(f"compressed {codec} image holds only {data.size} B")
    width, height = image_size(data)
    if width * height > MAX_IMAGE_PIXELS or width <= 0 or height <= 0:
        raise InputError(f"compressed image claims {width}x{height} px, more than the "
                         f"{MAX_IMAGE_PIXELS / 1e6:.0f} MP a camera image may have "
                         "(a decompression bomb?); not decoded")
    if expected is not None and expected != (0, 0) and (width, height) != expected:
        raise InputError(f"compressed image is {width}x{height} but its camera_info is for "
                         f"{expected[0]}x{expected[1]}; publish matching camera_info")
    tail = bytes(data[-32:])
    if codec == "jpeg" and b"\xff\xd9" not in tail:
        raise InputError("JPEG image is truncated (no end-of-image marker); the message was "
                         "cut off")
    if codec == "png" and b"IEND" not in tail:
        raise InputError("PNG image is truncated (no IEND chunk); the message was cut off")
    pixels = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if grey and codec == "jpeg"
                          else cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise InputError(f"compressed {codec} image could not be decoded; the message is "
                         "corrupt")
    if (pixels.shape[1], pixels.shape[0]) != (width, height):
        raise InputError(f"compressed image decoded to {pixels.shape[1]}x{pixels.shape[0]} "
                         f"but its header says {width}x{height}; the message is corrupt")
    if pixels.ndim == 3:
        if pixels.shape[2] == 1:
            return np.ascontiguousarray(pixels[..., 0])
        code = cv2.COLOR_BGRA2RGB if pixels.shape[2] == 4 else cv2.COLOR_BGR2RGB
        return cv2.cvtColor(pixels, code)
    return pixels


def encode_raw(pixels: np.ndarray, encoding: str) -> np.ndarray:
    """HxW grey or HxWx3 RGB uint8 ``pixels`` as a camera stores them in ``encoding`` (the
    array a sensor_msgs/Image of that encoding holds, HxW or HxWxC): mono8, rgb8 and bgr8
    converted, a Bayer pattern sampled from the colours (grey: every site the grey), yuv422
    (UYVY) and yuv422_yuy2 (YUYV) by the BT.601 video-range formulas."""
    rgb = np.repeat(pixels[..., None], 3, axis=2) if pixels.ndim == 2 else pixels[..., :3]
    if encoding == "mono8":
        return pixels if pixels.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if encoding == "rgb8":
        return rgb
    if encoding == "bgr8":
        return np.ascontiguousarray(rgb[..., ::-1])
    if encoding.startswith("bayer_") and encoding.endswith("8"):
        mosaic = np.empty(rgb.shape[:2], np.uint8)
        for index, colour in enumerate(encoding[6:10]):
            row, col = divmod(index, 2)
            mosaic[row::2, col::2] = rgb[row::2, col::2, "rgb".index(colour)]
        return mosaic
    if encoding in _YUV_TO_RGB:
        r, g, b = (rgb[..., k].astype(np.float64) for k in range(3))
        y = 16 + 0.257 * r + 0.504 * g + 0.098 * b
        u = 128 - 0.148 * r - 0.291 * g + 0.439 * b
        v = 128 + 0.439 * r - 0.368 * g - 0.071 * b
        packed = np.empty(rgb.shape[:2] + (2,), np.float64)
        luma, chroma = (1, 0) if encoding in ("yuv422", "uyvy") else (0, 1)
        packed[..., luma] = y
        packed[:, 0::2, chroma] = (u[:, 0::2] + u[:, 1::2]) / 2
        packed[:, 1::2, chroma] = (v[:, 0::2] + v[:, 1::2]) / 2
        return np.clip(np.rint(packed), 0, 255).astype(np.uint8)
    raise InputError(f"cannot store images as {encoding!r}")


def encode_compressed(pixels: np.ndarray, codec: str = "jpeg", quality: int = 90) -> bytes:
    """The bytes of a CompressedImage of HxW or HxWx3 RGB ``pixels`` (as image_transport
    writes them: OpenCV, BGR order for colour)."""
    image = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR) if pixels.ndim == 3 else pixels
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if codec == "jpeg" else []
    ok, encoded = cv2.imencode(".jpg" if codec == "jpeg" else ".png", image, params)
    if not ok:
        raise InputError(f"could not encode a {codec} image")
    return encoded.tobytes()


def compressed_format_string(pixels: np.ndarray, codec: str = "jpeg") -> str:
    """image_transport's format string for ``pixels`` compressed with ``codec``."""
    if pixels.ndim == 2:
        kind = "mono16" if pixels.dtype == np.uint16 else "mono8"
        return f"{kind}; {codec} compressed {kind}"
    return f"rgb8; {codec} compressed bgr8"


def with_bytes(message_type: Any, values: np.ndarray, **fields: Any) -> Any:
    """A message of ``message_type`` with ``fields`` and, as its uint8[] ``data``, the bytes of
    ``values``, copied once (rclpy's messages: into an array.array that the message, its
    fields checked as they are set, keeps as it is)."""
    flat = np.ascontiguousarray(values).view(np.uint8).reshape(-1)
    if not ROS:
        return message_type(data=flat.copy(), **fields)
    data = array.array("B")
    data.frombytes(flat)
    made = message_type(check_fields=True, **fields)
    made.data = data
    return made


def array_to_image(pixels: np.ndarray, encoding: str, header: Any) -> Any:
    """A sensor_msgs/Image of a host array (HxW or HxWxC, as ``encoding`` stores its pixels:
    RAW_LAYOUTS) in ``encoding`` (little endian, tightly packed)."""
    dtype, channels = RAW_LAYOUTS[encoding]
    pixels = np.ascontiguousarray(pixels, dtype=dtype.newbyteorder("<"))
    if pixels.ndim != (2 if channels == 1 else 3):
        raise InputError(f"{encoding} needs {'HxW' if channels == 1 else 'HxWxC'} pixels")
    height, width = pixels.shape[:2]
    return with_bytes(message(IMAGE_TYPE), pixels, header=header, height=height, width=width,
                      encoding=encoding, is_bigendian=0, step=width * channels * dtype.itemsize)


def compressed_image(pixels: np.ndarray, codec: str, header: Any) -> Any:
    """A sensor_msgs/CompressedImage of HxW grey or HxWx3 RGB ``pixels`` compressed with
    ``codec`` (jpeg or png) as image_transport's compressed transport writes it."""
    compressed = np.frombuffer(encode_compressed(pixels, codec), np.uint8)
    return with_bytes(message(COMPRESSED_TYPE), compressed, header=header,
                      format=compressed_format_string(pixels, codec))
