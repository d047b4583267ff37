"""msg_adapters.images and camera_info: raw and compressed images, calibration."""

from __future__ import annotations

import struct
import time
import zlib
from typing import Any

import cv2
import numpy as np
import pytest
from bag_messages import SOURCES, as_source, to_rosbags
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from msg_adapters import (
    AdapterError,
    camera_info_from_msg,
    check_stereo_pair,
    compressed_image_to_numpy,
    fill_image,
    image_msg_to_gray8,
    image_to_numpy,
    stereo_baseline_m,
)
from msg_adapters.images import compressed_image_shape

RNG = np.random.default_rng(0)
GRAY = RNG.integers(0, 256, (4, 5), dtype=np.uint8)
COLOR = RNG.integers(0, 256, (4, 5, 3), dtype=np.uint8)
DEPTH = RNG.integers(0, 65536, (4, 5), dtype=np.uint16)


def raw(pixels: np.ndarray, encoding: str, pad: int = 0, big: bool = False) -> Image:
    """An Image with ``pad`` bytes of padding per row, built by hand (not by fill_image)."""
    h, w = pixels.shape[:2]
    data = pixels.astype(pixels.dtype.newbyteorder(">" if big else "<")).reshape(h, -1)
    rows = data.view(np.uint8).reshape(h, -1)
    rows = np.concatenate([rows, np.full((h, pad), 0xEE, dtype=np.uint8)], axis=1)
    return Image(
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=int(big),
        step=rows.shape[1],
        data=rows.tobytes(),
    )


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize(
    ("pixels", "encoding"),
    [
        (GRAY, "mono8"),
        (GRAY, "8UC1"),
        (DEPTH, "mono16"),
        (DEPTH, "16UC1"),
        (COLOR, "rgb8"),
        (COLOR, "bgr8"),
        (COLOR, "8UC3"),
        (np.dstack([COLOR, GRAY]), "bgra8"),
        (np.dstack([COLOR, GRAY]), "rgba8"),
    ],
)
@pytest.mark.parametrize("pad", [0, 3])
@pytest.mark.parametrize("big", [False, True])
def test_raw_encodings(
    source: str, pixels: np.ndarray, encoding: str, pad: int, big: bool
) -> None:
    msg = as_source(raw(pixels, encoding, pad, big), source)
    out = image_to_numpy(msg, expected_size=(5, 4))
    assert out.dtype == pixels.dtype and out.dtype.isnative
    np.testing.assert_array_equal(out, pixels)
    out[...] = 0  # a copy, never the message's buffer
    np.testing.assert_array_equal(image_to_numpy(msg), pixels)


def test_grayscale_output() -> None:
    np.testing.assert_array_equal(image_to_numpy(raw(GRAY, "mono8"), grayscale=True), GRAY)
    gray16 = image_to_numpy(raw(DEPTH, "mono16"), grayscale=True)
    np.testing.assert_array_equal(gray16, (DEPTH >> 8).astype(np.uint8))
    bgr_gray = cv2.cvtColor(COLOR, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(image_to_numpy(raw(COLOR, "bgr8"), grayscale=True), bgr_gray)
    rgb = COLOR[..., ::-1]
    np.testing.assert_array_equal(image_to_numpy(raw(rgb, "rgb8"), grayscale=True), bgr_gray)
    rgba = np.dstack([rgb, GRAY])
    np.testing.assert_array_equal(image_msg_to_gray8(raw(rgba, "rgba8")), bgr_gray)


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda m: setattr(m, "encoding", "yuv422"), "unsupported 'yuv422'"),
        (lambda m: setattr(m, "encoding", "32FC1"), "Image.encoding: unsupported"),
        (lambda m: setattr(m, "height", 0), r"empty image \(5x0\)"),
        (lambda m: setattr(m, "step", 4), "step: 4 bytes is less than width"),
        (lambda m: setattr(m, "step", 6), r"Image.data: 20 bytes, expected step × height"),
        (lambda m: setattr(m, "height", 5), "expected step × height = 5×5"),
        (lambda m: setattr(m, "data", b""), r"Image.data: 0 bytes"),
    ],
)
def test_raw_rejects(source: str, mutate: Any, match: str) -> None:
    msg = as_source(raw(GRAY, "mono8"), source)
    mutate(msg)
    with pytest.raises(AdapterError, match=match):
        image_to_numpy(msg)


def test_expected_size() -> None:
    with pytest.raises(AdapterError, match="size 5x4 differs from the expected 640x480"):
        image_to_numpy(raw(GRAY, "mono8"), expected_size=(640, 480))


def compressed(pixels: np.ndarray, ext: str, fmt: str) -> CompressedImage:
    ok, buf = cv2.imencode(ext, pixels)
    assert ok
    return CompressedImage(format=fmt, data=buf.tobytes())


@pytest.mark.parametrize("source", SOURCES)
def test_compressed(source: str) -> None:
    png = as_source(compressed(COLOR, ".png", "bgr8; png compressed bgr8"), source)
    np.testing.assert_array_equal(compressed_image_to_numpy(png, expected_size=(5, 4)), COLOR)
    # The decoder's own luminance (libpng) may round differently from cvtColor.
    gray = image_msg_to_gray8(png).astype(int)
    assert np.abs(gray - cv2.cvtColor(COLOR, cv2.COLOR_BGR2GRAY)).max() <= 1
    png16 = as_source(compressed(DEPTH, ".png", "png"), source)
    np.testing.assert_array_equal(compressed_image_to_numpy(png16), DEPTH)
    smooth = np.tile(np.arange(0, 256, 4, dtype=np.uint8), (64, 1))
    jpeg = as_source(compressed(smooth, ".jpg", "jpeg"), source)
    out = compressed_image_to_numpy(jpeg, grayscale=True)
    assert out.shape == smooth.shape
    assert np.abs(out.astype(int) - smooth).max() < 8


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize(
    ("fmt", "data", "match"),
    [
        ("tiff", b"\x01", "unsupported 'tiff'"),
        ("16UC1; compressedDepth png", b"\x01", "compressedDepth"),
        ("jpeg", b"", "CompressedImage.data: empty"),
        ("jpeg", b"not a jpeg", "neither PNG nor JPEG"),
        ("png", b"\x89PNG\r\n\x1a\n", "PNG without an IHDR header"),
        ("jpeg", b"\xff\xd8\xff\xe0\x00\x04ab", "JPEG without a frame"),
        # A valid header over garbage: the size passes, the decoder refuses the rest.
        ("png", b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR\x00\x00\x00\x04\x00\x00\x00\x04"
         b"junk", "28 bytes do not decode as 'png'"),
    ],
)
def test_compressed_rejects(source: str, fmt: str, data: bytes, match: str) -> None:
    msg = as_source(CompressedImage(format=fmt, data=data), source)
    with pytest.raises(AdapterError, match=match):
        compressed_image_to_numpy(msg)


def oversize_png(side: int) -> bytes:
    """A valid PNG of ``side``² black pixels that compresses to about a megabyte."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body) & 0xFFFFFFFF
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    rows = zlib.compress(b"".join(b"\x00" + bytes(side) for _ in range(side // 32)), 9)
    header = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", rows) + chunk(
        b"IEND", b"")


@pytest.mark.parametrize("source", SOURCES)
def test_oversize_refused_from_the_header(source: str) -> None:
    """A 32000² PNG is refused from its IHDR in well under a millisecond's work, and a raw
    image from its header fields, before anything is decoded or allocated."""
    msg = as_source(CompressedImage(format="png", data=oversize_png(32000)), source)
    start = time.perf_counter()
    with pytest.raises(AdapterError, match="32000x32000 exceeds 50000000 pixels"):
        compressed_image_to_numpy(msg, grayscale=True)
    assert time.perf_counter() - start < 0.05
    # Smaller than the limit but not what the calibration says: also refused undecoded.
    small = as_source(CompressedImage(format="png", data=oversize_png(4000)), source)
    start = time.perf_counter()
    with pytest.raises(AdapterError, match="4000x4000 differs from the expected 640x480"):
        image_msg_to_gray8(small, expected_size=(640, 480))
    assert time.perf_counter() - start < 0.05
    huge = Image(height=40000, width=40000, encoding="mono8", step=40000, data=b"\x00")
    with pytest.raises(AdapterError, match="40000x40000 exceeds"):
        image_to_numpy(as_source(huge, source))


@pytest.mark.parametrize("progressive", [False, True])
def test_compressed_shape_from_header(progressive: bool) -> None:
    flags = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else []
    ok, jpeg = cv2.imencode(".jpg", COLOR, flags)
    assert ok
    assert compressed_image_shape(jpeg.tobytes()) == COLOR.shape[:2]
    assert compressed_image_shape(compressed(GRAY, ".png", "png").data) == GRAY.shape


def test_compressed_expected_size() -> None:
    with pytest.raises(AdapterError, match="CompressedImage: size 5x4 differs"):
        compressed_image_to_numpy(compressed(GRAY, ".png", "png"), expected_size=(4, 5))


@pytest.mark.parametrize(
    ("pixels", "encoding"),
    [(GRAY, "mono8"), (DEPTH, "mono16"), (COLOR, "bgr8"), (np.dstack([COLOR, GRAY]), "bgra8")],
)
def test_fill_image_round_trip(pixels: np.ndarray, encoding: str) -> None:
    msg = fill_image(Image, pixels, stamp_ns=5, frame_id="debug")
    assert (msg.encoding, msg.header.frame_id, msg.header.stamp.nanosec) == (encoding, "debug", 5)
    np.testing.assert_array_equal(image_to_numpy(msg), pixels)
    np.testing.assert_array_equal(image_to_numpy(to_rosbags(msg)), pixels)
    # A rosbags instance is filled with a numpy data field.
    bag_msg = to_rosbags(Image())
    fill_image(bag_msg, pixels, stamp_ns=5, frame_id="debug")
    assert isinstance(bag_msg.data, np.ndarray)
    np.testing.assert_array_equal(image_to_numpy(bag_msg), pixels)


def test_fill_image_explicit_encoding_and_errors() -> None:
    msg = fill_image(Image(), COLOR, stamp_ns=0, frame_id="x", encoding="rgb8")
    assert msg.encoding == "rgb8"
    with pytest.raises(AdapterError, match="'mono8' does not describe uint8 with 3 channel"):
        fill_image(Image, COLOR, stamp_ns=0, frame_id="x", encoding="mono8")
    with pytest.raises(AdapterError, match="not an image this package encodes"):
        fill_image(Image, np.zeros((2, 2), np.float32), stamp_ns=0, frame_id="x")
    with pytest.raises(AdapterError, match="not an image"):
        fill_image(Image, np.zeros((0, 2), np.uint8), stamp_ns=0, frame_id="x")


# --------------------------------------------------------------------------- CameraInfo

FX, CX, CY, BASELINE = 718.856, 607.19, 185.21, 0.537


def camera_info(right: bool = False) -> CameraInfo:
    msg = CameraInfo(width=1226, height=370, distortion_model="plumb_bob")
    msg.header.frame_id = "right_optical" if right else "left_optical"
    msg.header.stamp.sec = 7
    msg.k = np.array([FX, 0, CX, 0, FX, CY, 0, 0, 1.0])
    msg.r = np.eye(3).ravel()
    msg.p = np.array([FX, 0, CX, -FX * BASELINE if right else 0.0, 0, FX, CY, 0, 0, 0, 1, 0])
    msg.d = [0.0] * 5
    return msg


@pytest.mark.parametrize("source", SOURCES)
def test_camera_info(source: str) -> None:
    left = camera_info_from_msg(as_source(camera_info(), source))
    right = camera_info_from_msg(as_source(camera_info(right=True), source))
    assert (left.width, left.height, left.stamp_ns, left.frame_id) == (
        1226,
        370,
        7 * 10**9,
        "left_optical",
    )
    assert (left.fx, left.fy, left.cx, left.cy) == (FX, FX, CX, CY)
    assert left.K.shape == (3, 3) and left.P.shape == (3, 4) and left.D.shape == (5,)
    assert stereo_baseline_m(right) == pytest.approx(BASELINE)
    assert check_stereo_pair(left, right) == pytest.approx(BASELINE)


def test_camera_info_zero_r_is_identity_and_empty_d() -> None:
    msg = camera_info()
    msg.r = np.zeros(9)
    msg.d = []
    model = camera_info_from_msg(msg)
    np.testing.assert_array_equal(model.R, np.eye(3))
    assert model.D.shape == (0,)


def _set(field: str, index: int, value: float) -> Any:
    def mutate(msg: Any) -> None:
        arr = np.array(getattr(msg, field), dtype=float)
        arr[index] = value
        setattr(msg, field, arr)

    return mutate


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda m: setattr(m, "width", 0), "empty image size 0x370"),
        (_set("k", 0, float("nan")), r"CameraInfo.k: contains NaN"),
        (lambda m: setattr(m, "k", np.zeros(9)), "k: all zero .camera not calibrated"),
        (lambda m: setattr(m, "p", np.zeros(12)), "p: all zero"),
        (_set("k", 4, -1.0), "k: focal lengths"),
        (_set("p", 0, 0.0), "p: focal lengths"),
        (_set("k", 8, 2.0), r"k: last row .* is not \[0, 0, 1\]"),
        (_set("p", 10, 0.5), r"p: last row"),
        (_set("r", 0, 2.0), "r: not a rotation"),
        (lambda m: setattr(m, "distortion_model", "fisheye9"), "unknown 'fisheye9'"),
        (lambda m: setattr(m, "d", [0.0] * 4), "d: 4 coefficients, plumb_bob has 5"),
        (lambda m: setattr(m.header.stamp, "nanosec", 2 * 10**9), "nanosec"),
    ],
)
def test_camera_info_rejects(source: str, mutate: Any, match: str) -> None:
    msg = camera_info()
    mutate(msg)
    msg = as_source(msg, source)
    with pytest.raises(AdapterError, match=match):
        camera_info_from_msg(msg)


def test_stereo_rejects() -> None:
    left = camera_info_from_msg(camera_info())
    with pytest.raises(AdapterError, match="baseline 0 m is not positive .*left camera"):
        stereo_baseline_m(left)
    right = camera_info_from_msg(camera_info(right=True))
    with pytest.raises(AdapterError, match="left CameraInfo.p: P.0, 3. = "):
        check_stereo_pair(right, right)
    small = camera_info(right=True)
    small.width = 100
    with pytest.raises(AdapterError, match="sizes differ"):
        check_stereo_pair(left, camera_info_from_msg(small))
    other = camera_info(right=True)
    other.p = np.array(other.p) * np.r_[1.1, np.ones(11)]
    with pytest.raises(AdapterError, match="rectified intrinsics differ"):
        check_stereo_pair(left, camera_info_from_msg(other))
