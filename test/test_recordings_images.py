"""Image decoding: every encoding a camera driver publishes and image_transport's compressed
images as the arrays they hold; bad, hostile and truncated messages refused with one line
before they cost memory; a fuzz of random bytes and mutated real messages never raises
anything but InputError and never hangs."""

from __future__ import annotations

import time
import zlib

import numpy as np
import pytest

from pothole_detector.recordings.messages import header_at, message
from pothole_detector.errors import InputError
from pothole_detector.recordings import images

Image = message("sensor_msgs/msg/Image")
CompressedImage = message("sensor_msgs/msg/CompressedImage")
HEADER = header_at(1_700_000_000_000_000_000, "cam")
RNG = np.random.default_rng(3)


def _image(pixels: np.ndarray, encoding: str, step_padding: int = 0, big_endian: bool = False):
    """An Image of raw ``pixels`` bytes (HxW or HxWxC as stored) in ``encoding``."""
    height, width = pixels.shape[:2]
    row = pixels[0].nbytes
    data = np.zeros((height, row + step_padding), np.uint8)
    stored = pixels.astype(pixels.dtype.newbyteorder(">" if big_endian else "<"))
    data[:, :row] = stored.view(np.uint8).reshape(height, row)
    return Image(header=HEADER, height=height, width=width, encoding=encoding,
                 is_bigendian=int(big_endian), step=row + step_padding, data=data.tobytes())


def _smooth_rgb(height: int = 48, width: int = 64) -> np.ndarray:
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([(u * 3) % 256, (v * 4) % 256, (u + 2 * v) % 256], -1).astype(np.uint8)


@pytest.mark.parametrize("encoding", ["mono8", "8UC1", "mono16", "16UC1", "rgb8", "bgr8",
                                      "rgba8", "bgra8", "8UC3", "rgb16", "bgr16", "rgba16"])
def test_direct_encodings_with_padded_step(encoding):
    dtype, channels = images.RAW_LAYOUTS[encoding]
    shape = (5, 7) if channels == 1 else (5, 7, channels)
    pixels = RNG.integers(0, np.iinfo(dtype).max, size=shape).astype(dtype)
    out = images.decode_raw(_image(pixels.reshape(5, 7, channels), encoding, step_padding=6))
    expected = pixels
    if channels > 1:
        expected = pixels[..., 2::-1] if encoding.startswith("bgr") or "UC" in encoding \
            else pixels[..., :3]
    np.testing.assert_array_equal(out, expected)


def test_a_message_holds_its_own_copy_of_the_pixels():
    """array_to_image copies the pixels' bytes into the message: later writes to the array
    leave it alone, and it decodes to the pixels (a float image from a strided view too)."""
    for source in (RNG.random((6, 10)).astype(np.float32),
                   RNG.random((6, 20)).astype(np.float32)[:, ::2]):
        kept = source.copy()
        msg = images.array_to_image(source, "32FC1", HEADER)
        source[...] = -1.0
        assert (msg.height, msg.width, msg.step) == (6, 10, 40)
        np.testing.assert_array_equal(images.decode_raw(msg, allowed=("32FC1",)), kept)


def test_big_endian_mono16():
    pixels = np.array([[1, 258], [65535, 4096]], dtype=np.uint16)
    out = images.decode_raw(_image(pixels[..., None], "mono16", big_endian=True))
    np.testing.assert_array_equal(out, pixels)


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
@pytest.mark.parametrize("bits", [8, 16])
def test_bayer_patterns_demosaic_to_the_colours_they_sampled(pattern, bits):
    """A smooth colour image sampled through each Bayer pattern comes back as that image (away
    from the border, where the interpolation has no neighbours)."""
    rgb = _smooth_rgb().astype(np.uint16 if bits == 16 else np.uint8)
    if bits == 16:
        rgb = rgb * 256
    channel = {"r": 0, "g": 1, "b": 2}
    mosaic = np.zeros(rgb.shape[:2], rgb.dtype)
    for index, colour in enumerate(pattern):
        row, col = divmod(index, 2)
        mosaic[row::2, col::2] = rgb[row::2, col::2, channel[colour]]
    out = images.decode_raw(_image(mosaic[..., None], f"bayer_{pattern}{bits}"))
    assert out.shape == rgb.shape and out.dtype == rgb.dtype
    error = np.abs(out[4:-4, 4:-4].astype(float) - rgb[4:-4, 4:-4]) / (256 if bits == 16 else 1)
    assert error.mean() < 0.5


@pytest.mark.parametrize("encoding", ["yuv422", "uyvy", "yuv422_yuy2", "yuyv"])
def test_yuv422_comes_back_as_the_colours_it_was_made_of(encoding):
    """Packed 4:2:2 made by the BT.601 video-range formulas that cameras use."""
    rgb = _smooth_rgb()
    r, g, b = (rgb[..., k].astype(np.float64) for k in range(3))
    y = np.rint(16 + 0.257 * r + 0.504 * g + 0.098 * b).astype(np.int32)
    u = np.rint(128 - 0.148 * r - 0.291 * g + 0.439 * b).astype(np.int32)
    v = np.rint(128 + 0.439 * r - 0.368 * g - 0.071 * b).astype(np.int32)
    u2 = ((u[:, 0::2] + u[:, 1::2] + 1) // 2).astype(np.uint8)
    v2 = ((v[:, 0::2] + v[:, 1::2] + 1) // 2).astype(np.uint8)
    packed = np.zeros((rgb.shape[0], rgb.shape[1], 2), np.uint8)
    luma, chroma = (1, 0) if encoding in ("yuv422", "uyvy") else (0, 1)
    packed[..., luma] = y
    packed[:, 0::2, chroma] = u2
    packed[:, 1::2, chroma] = v2
    out = images.decode_raw(_image(packed, encoding))
    assert np.abs(out.astype(int) - rgb).mean() < 6


@pytest.mark.parametrize("change, words", [
    ({"encoding": "nv24"}, "not supported"),
    ({"encoding": "32FC1"}, "not supported"),
    ({"step": 6}, "step"),
    ({"data": bytes(10)}, "needs"),
    ({"width": 0}, "empty"),
    ({"width": 100_000, "height": 100_000, "step": 100_000}, "more than"),
    ({"encoding": "bayer_rggb8", "width": 7, "step": 7}, "even"),
])
def test_bad_images_say_what_is_wrong(change, words):
    msg = _image(np.zeros((4, 8, 1), np.uint8), "mono8")
    for key, value in change.items():
        setattr(msg, key, value)
    with pytest.raises(InputError, match=words):
        images.decode_raw(msg)


def _compressed(pixels: np.ndarray, codec: str):
    return CompressedImage(header=HEADER,
                           format=images.compressed_format_string(pixels, codec),
                           data=np.frombuffer(images.encode_compressed(pixels, codec),
                                              np.uint8).copy())


@pytest.mark.parametrize("codec", ["jpeg", "png"])
@pytest.mark.parametrize("colour", [False, True], ids=["mono", "rgb"])
def test_compressed_images_decode_to_what_was_compressed(codec, colour):
    pixels = _smooth_rgb() if colour else _smooth_rgb()[..., 1]
    msg = _compressed(pixels, codec)
    out = images.decode(msg, images.COMPRESSED_TYPE, expected=(64, 48))
    assert out.shape == pixels.shape and out.dtype == np.uint8
    if codec == "png":
        np.testing.assert_array_equal(out, pixels)
    else:
        assert np.abs(out.astype(int) - pixels).mean() < 3


def test_png_mono16_keeps_its_bits():
    pixels = (np.arange(48 * 64, dtype=np.uint16).reshape(48, 64) * 17)
    out = images.decode(_compressed(pixels, "png"), images.COMPRESSED_TYPE)
    np.testing.assert_array_equal(out, pixels)


@pytest.mark.parametrize("text, codec", [("jpeg", "jpeg"), ("png", "png"),
                                         ("rgb8; jpeg compressed bgr8", "jpeg"),
                                         ("mono16; png compressed mono16", "png"),
                                         ("JPG", "jpeg")])
def test_format_strings_as_image_transport_writes_them(text, codec):
    assert images.compressed_format(CompressedImage(format=text)) == codec


def test_other_transports_and_a_wrong_size_are_refused():
    with pytest.raises(InputError, match="not supported"):
        images.compressed_format(CompressedImage(format="16UC1; compressedDepth png"))
    with pytest.raises(InputError, match="camera_info is for 640x480"):
        images.decode(_compressed(_smooth_rgb(), "png"), images.COMPRESSED_TYPE, (640, 480))


def _bomb_png(width: int, height: int) -> bytes:
    """A valid PNG header claiming ``width`` x ``height`` with almost no data."""
    small = images.encode_compressed(np.zeros((2, 2), np.uint8), "png")
    header = bytearray(small)
    header[16:20] = width.to_bytes(4, "big")
    header[20:24] = height.to_bytes(4, "big")
    header[29:33] = zlib.crc32(bytes(header[12:29])).to_bytes(4, "big")
    return bytes(header)


def test_a_decompression_bomb_is_refused_before_decoding():
    msg = CompressedImage(format="png", data=np.frombuffer(_bomb_png(60_000, 60_000),
                                                           np.uint8).copy())
    started = time.perf_counter()
    with pytest.raises(InputError, match="decompression bomb"):
        images.decode(msg, images.COMPRESSED_TYPE)
    assert time.perf_counter() - started < 1.0


@pytest.mark.parametrize("codec", ["jpeg", "png"])
def test_a_truncated_image_is_refused_not_half_decoded(codec):
    data = images.encode_compressed(_smooth_rgb(), codec)
    msg = CompressedImage(format=codec, data=np.frombuffer(data[:len(data) * 2 // 3],
                                                           np.uint8).copy())
    with pytest.raises(InputError, match="truncated|corrupt"):
        images.decode(msg, images.COMPRESSED_TYPE)


def test_fuzz_random_bytes_and_mutated_messages_only_raise_input_errors():
    """Random bytes, and real JPEG and PNG messages with bytes flipped, cut or repeated, through
    the decoders: each comes back as pixels of the header's size or an InputError, within a
    second; the same for raw images whose fields lie."""
    rng = np.random.default_rng(11)
    originals = [images.encode_compressed(_smooth_rgb(), codec) for codec in ("jpeg", "png")]
    cases = [rng.integers(0, 256, int(rng.integers(0, 4000)), dtype=np.uint8).tobytes()
             for _ in range(40)]
    for original in originals:
        for _ in range(60):
            data = bytearray(original)
            kind = rng.integers(0, 3)
            if kind == 0:
                for index in rng.integers(0, len(data), int(rng.integers(1, 20))):
                    data[index] = int(rng.integers(0, 256))
            elif kind == 1:
                data = data[:int(rng.integers(0, len(data)))]
            else:
                start = int(rng.integers(0, len(data)))
                data = data[:start] + data[start:start + 200] * 3 + data[start:]
            cases.append(bytes(data))
    outcomes = {"decoded": 0, "refused": 0}
    for data in cases:
        for text in ("jpeg", "png"):
            msg = CompressedImage(format=text, data=np.frombuffer(data, np.uint8).copy())
            started = time.perf_counter()
            try:
                pixels = images.decode(msg, images.COMPRESSED_TYPE, expected=(64, 48))
                assert pixels.shape[:2] == (48, 64)
                outcomes["decoded"] += 1
            except InputError:
                outcomes["refused"] += 1
            assert time.perf_counter() - started < 1.0
    for _ in range(200):
        msg = _image(rng.integers(0, 256, (6, 8, 3), dtype=np.uint8), "rgb8")
        msg.width, msg.height = (int(v) for v in rng.integers(0, 20, 2))
        msg.step = int(rng.integers(0, 40))
        msg.encoding = str(rng.choice(list(images.RAW_LAYOUTS) + ["junk", ""]))
        try:
            images.decode_raw(msg)
        except InputError:
            outcomes["refused"] += 1
    assert outcomes["decoded"] > 0 and outcomes["refused"] > 0
