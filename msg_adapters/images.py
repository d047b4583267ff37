"""``sensor_msgs/Image`` and ``CompressedImage`` ⇄ numpy, without cv_bridge.

Raw encodings: ``mono8``/``8UC1``, ``mono16``/``16UC1``, ``rgb8``, ``bgr8``/``8UC3``,
``rgba8``, ``bgra8``/``8UC4``. Rows may be padded (``step`` > ``width`` × bytes per
pixel); 16-bit data honours ``is_bigendian``. Arrays come back as ``(height, width)`` for
one channel and ``(height, width, channels)`` otherwise, channels in the encoding's order,
always a fresh copy (never a view of the message's buffer).

Compressed images (``format`` naming ``jpeg``/``jpg`` or ``png``, as image_transport's
compressed plugin writes them, e.g. ``"bgr8; jpeg compressed bgr8"``) are decoded with
``cv2.imdecode``: colour comes back in OpenCV's BGR order. ``compressedDepth`` is refused.
OpenCV is imported on first use.

Size is checked before any pixel is touched: a raw image from its header fields, a
compressed one from its PNG ``IHDR`` or JPEG ``SOF`` header (data that carries neither is
refused). Images above :data:`MAX_IMAGE_PIXELS`, or of a size other than the expected one,
are refused there: a 1 MB PNG of 32000² pixels would otherwise cost seconds and gigabytes
of decoding before its size could be compared.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msg_adapters._util import new_message, set_bytes
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import fill_header

#: encoding → (numpy item type, channels).
ENCODINGS: dict[str, tuple[type[np.generic], int]] = {
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1),
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "8UC3": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    "8UC4": (np.uint8, 4),
}

# cv2.cvtColor codes to grayscale by channel order (8UCn is taken as OpenCV's BGR(A)).
_GRAY_CODE = {
    "rgb8": "COLOR_RGB2GRAY",
    "bgr8": "COLOR_BGR2GRAY",
    "8UC3": "COLOR_BGR2GRAY",
    "rgba8": "COLOR_RGBA2GRAY",
    "bgra8": "COLOR_BGRA2GRAY",
    "8UC4": "COLOR_BGRA2GRAY",
}

ImageArray = NDArray[Any]

#: Largest accepted image, pixels (50 MP: above any camera this package serves; an 8K
#: frame is 33 MP).
MAX_IMAGE_PIXELS = 50_000_000

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, progressive, lossless, ...); C4, C8 and CC are not.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
# JPEG markers that stand alone, without a length (TEM, RSTn, SOI).
_JPEG_STANDALONE = {0x01, *range(0xD0, 0xD9)}


def _cv2() -> Any:
    try:
        import cv2
    except ImportError:  # pragma: no cover - opencv is a dependency of the package
        raise AdapterError(
            "image conversion needs OpenCV: pip install opencv-python-headless"
        ) from None
    return cv2


def _check_size(shape: tuple[int, ...], expected_size: tuple[int, int] | None, what: str) -> None:
    if shape[0] * shape[1] > MAX_IMAGE_PIXELS:
        raise AdapterError(
            f"{what}: size {shape[1]}x{shape[0]} exceeds {MAX_IMAGE_PIXELS} pixels"
        )
    if expected_size is None:
        return
    width, height = expected_size
    if shape[0] != height or shape[1] != width:
        raise AdapterError(
            f"{what}: size {shape[1]}x{shape[0]} differs from the expected {width}x{height}"
        )


def image_to_numpy(
    msg: Any, *, grayscale: bool = False, expected_size: tuple[int, int] | None = None
) -> ImageArray:
    """Pixels of a ``sensor_msgs/Image`` (rclpy or rosbags).

    Args:
        msg: the message.
        grayscale: return ``(height, width)`` uint8 luminance whatever the encoding
            (16-bit images keep their top 8 bits) — the odometer's input.
        expected_size: ``(width, height)`` the image must have (e.g. its CameraInfo's).

    Raises:
        AdapterError: unsupported encoding, zero size, ``step`` too small, data length
            not ``step × height``, or a size other than ``expected_size``.
    """
    encoding = str(msg.encoding)
    if encoding not in ENCODINGS:
        raise AdapterError(
            f"Image.encoding: unsupported {encoding!r} (supported: {', '.join(ENCODINGS)})"
        )
    dtype, channels = ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise AdapterError(f"Image: empty image ({width}x{height})")
    _check_size((height, width), expected_size, "Image")
    itemsize = np.dtype(dtype).itemsize
    row_bytes = width * channels * itemsize
    if step < row_bytes:
        raise AdapterError(
            f"Image.step: {step} bytes is less than width × pixel size = {row_bytes}"
        )
    buf = _bytes(msg.data, "Image.data")
    if buf.size != step * height:
        raise AdapterError(
            f"Image.data: {buf.size} bytes, expected step × height = {step}×{height} "
            f"= {step * height}"
        )
    rows = buf.reshape(height, step)[:, :row_bytes]
    wire = np.dtype(dtype).newbyteorder(">" if int(msg.is_bigendian) else "<")
    pixels = np.ascontiguousarray(rows).view(wire)
    shape = (height, width) if channels == 1 else (height, width, channels)
    out = pixels.reshape(shape).astype(dtype)  # native byte order, always a copy
    if grayscale:
        return _to_gray8(out, encoding)
    return out


def _to_gray8(pixels: ImageArray, encoding: str) -> NDArray[np.uint8]:
    if pixels.dtype == np.uint16:
        return (pixels >> 8).astype(np.uint8)
    if pixels.ndim == 2:
        return pixels.astype(np.uint8)
    cv2 = _cv2()
    gray: NDArray[np.uint8] = cv2.cvtColor(pixels, getattr(cv2, _GRAY_CODE[encoding]))
    return gray


def compressed_image_to_numpy(
    msg: Any, *, grayscale: bool = False, expected_size: tuple[int, int] | None = None
) -> ImageArray:
    """Pixels of a ``sensor_msgs/CompressedImage`` (JPEG or PNG), decoded by OpenCV.

    Args:
        msg: the message.
        grayscale: decode to ``(height, width)`` uint8 luminance.
        expected_size: ``(width, height)`` the image must have.

    Returns:
        ``(h, w)`` or ``(h, w, 3|4)`` in BGR(A) order; 16-bit PNGs stay uint16 unless
        ``grayscale``.

    Raises:
        AdapterError: unsupported ``format``, empty data, undecodable data, or a size other
            than ``expected_size``.
    """
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt:
        raise AdapterError(f"CompressedImage.format: {msg.format!r} (compressedDepth) unsupported")
    if not any(name in fmt for name in ("jpeg", "jpg", "png")):
        raise AdapterError(
            f"CompressedImage.format: unsupported {msg.format!r} (expected jpeg or png)"
        )
    buf = _bytes(msg.data, "CompressedImage.data")
    if buf.size == 0:
        raise AdapterError("CompressedImage.data: empty")
    _check_size(compressed_image_shape(buf), expected_size, "CompressedImage")
    cv2 = _cv2()
    flag = cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_UNCHANGED
    try:
        out = cv2.imdecode(buf, flag)
    except cv2.error as exc:
        raise AdapterError(f"CompressedImage.data: OpenCV cannot decode it ({exc})") from None
    if out is None or out.size == 0:
        raise AdapterError(
            f"CompressedImage.data: {buf.size} bytes do not decode as {msg.format!r}"
        )
    _check_size(out.shape, expected_size, "CompressedImage")
    result: ImageArray = out
    return result


def _bytes(data: Any, field: str) -> NDArray[np.uint8]:
    """A ``uint8[]`` field (``bytes``, ``array('B')``, numpy or a list) as a uint8 array."""
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except (TypeError, ValueError):
        pass
    try:
        return np.asarray(data, dtype=np.uint8).ravel()
    except (TypeError, ValueError, OverflowError) as exc:
        raise AdapterError(f"{field}: not bytes ({exc})") from None


def compressed_image_shape(data: Any) -> tuple[int, int]:
    """``(height, width)`` from the header of PNG or JPEG data, without decoding it.

    Raises:
        AdapterError: data that starts as neither, or a header that is cut short.
    """
    buf = bytes(_bytes(data, "CompressedImage.data")[:65536])
    if buf.startswith(_PNG_SIGNATURE):
        if len(buf) < 24 or buf[12:16] != b"IHDR":
            raise AdapterError("CompressedImage.data: PNG without an IHDR header")
        width, height = int.from_bytes(buf[16:20], "big"), int.from_bytes(buf[20:24], "big")
        return height, width
    if buf.startswith(b"\xff\xd8"):
        return _jpeg_shape(buf)
    raise AdapterError("CompressedImage.data: neither PNG nor JPEG (no signature)")


def _jpeg_shape(buf: bytes) -> tuple[int, int]:
    """``(height, width)`` of the first start-of-frame segment of JPEG data."""
    i = 2
    while i + 4 <= len(buf):
        if buf[i] != 0xFF:
            raise AdapterError(f"CompressedImage.data: JPEG marker expected at byte {i}")
        marker = buf[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _JPEG_STANDALONE:
            i += 2
            continue
        length = int.from_bytes(buf[i + 2 : i + 4], "big")
        if marker in _JPEG_SOF:
            if i + 9 > len(buf) or length < 7:
                break
            height = int.from_bytes(buf[i + 5 : i + 7], "big")
            width = int.from_bytes(buf[i + 7 : i + 9], "big")
            return height, width
        if marker == 0xDA or length < 2:  # scan data before any frame header
            break
        i += 2 + length
    raise AdapterError("CompressedImage.data: JPEG without a frame (SOF) header")


def image_msg_to_gray8(msg: Any, *, expected_size: tuple[int, int] | None = None) -> ImageArray:
    """uint8 ``(height, width)`` luminance of an ``Image`` or a ``CompressedImage``
    (told apart by the ``format`` field)."""
    if hasattr(msg, "format") and not hasattr(msg, "encoding"):
        return compressed_image_to_numpy(msg, grayscale=True, expected_size=expected_size)
    return image_to_numpy(msg, grayscale=True, expected_size=expected_size)


def fill_image(
    msg_or_cls: Any,
    pixels: ImageArray,
    *,
    stamp_ns: int,
    frame_id: str,
    encoding: str | None = None,
) -> Any:
    """Fill a ``sensor_msgs/Image`` (an instance, or a new one of the class given).

    Args:
        pixels: ``(h, w)`` uint8 or uint16, ``(h, w, 3)`` or ``(h, w, 4)`` uint8.
        encoding: defaults to ``mono8``, ``mono16``, ``bgr8`` (OpenCV's order) or ``bgra8``
            by dtype and channels; if given, it must agree with them.

    Raises:
        AdapterError: an array that no supported encoding describes, or a mismatching
            ``encoding``.
    """
    arr = np.asarray(pixels)
    channels = 1 if arr.ndim == 2 else (arr.shape[2] if arr.ndim == 3 else 0)
    default = {
        (np.dtype(np.uint8), 1): "mono8",
        (np.dtype(np.uint16), 1): "mono16",
        (np.dtype(np.uint8), 3): "bgr8",
        (np.dtype(np.uint8), 4): "bgra8",
    }.get((arr.dtype, channels))
    if default is None or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise AdapterError(
            f"image array: shape {arr.shape} of {arr.dtype} is not an image this package "
            "encodes (uint8/uint16 (h, w), uint8 (h, w, 3|4))"
        )
    encoding = default if encoding is None else encoding
    if ENCODINGS.get(encoding) != (arr.dtype.type, channels):
        raise AdapterError(
            f"Image.encoding: {encoding!r} does not describe {arr.dtype} with {channels} "
            "channel(s)"
        )
    msg = new_message(msg_or_cls)
    fill_header(msg.header, stamp_ns, frame_id)
    msg.height, msg.width = int(arr.shape[0]), int(arr.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = int(sys.byteorder == "big" and arr.dtype.itemsize > 1)
    msg.step = int(arr.shape[1] * channels * arr.dtype.itemsize)
    set_bytes(msg, "data", np.ascontiguousarray(arr).tobytes())
    return msg
