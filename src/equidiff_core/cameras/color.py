"""Colour images on the wire: ``sensor_msgs/CompressedImage`` holding a JPEG, as image_transport writes it.

Each camera's colour image travels beside its cloud on ``wire.topics.camera_color_topic(name)``
(``/cameras/<name>/color/image_raw/compressed``), stamped with the cloud's capture time in the
same ``<name>_color_optical_frame``. The topic and the ``format`` field follow ROS'
``compressed_image_transport`` (what realsense-ros publishes through image_transport): the
base topic ``…/color/image_raw`` plus the transport's ``/compressed`` suffix, and
``format = "rgb8; jpeg compressed bgr8"``. So rqt_image_view, ``image_transport republish``,
Foxglove and rerun read these images as they read a RealSense driver's, and a bag recorded
from realsense-ros itself has the same layout.

Encoding and decoding use OpenCV (libjpeg-turbo), which the calibration already depends on.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..wire.rosmsg import stamp_to_ns, uint8_buffer

# compressed_image_transport's format string for an rgb8 source compressed as JPEG (colour order bgr8)
JPEG_FORMAT = "rgb8; jpeg compressed bgr8"
DEFAULT_JPEG_QUALITY = 90  # libjpeg quality 1-100


class ImageError(ValueError):
    """An image that cannot be encoded or decoded (wrong shape, unknown format, corrupt bytes)."""


def encode_jpeg(rgb: np.ndarray, quality: int = DEFAULT_JPEG_QUALITY) -> np.ndarray:
    """RGB uint8 (H, W, 3) -> JPEG bytes as a uint8 array."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8 or rgb.size == 0:
        raise ImageError(f"expected an RGB uint8 image (H, W, 3), got {rgb.dtype} {rgb.shape}")
    if not 1 <= int(quality) <= 100:
        raise ImageError(f"JPEG quality must be in 1..100, got {quality}")
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ImageError("OpenCV could not encode the image as JPEG")
    return buf.reshape(-1)


def decode_image(data: Any) -> np.ndarray:
    """JPEG (or PNG) bytes -> RGB uint8 (H, W, 3)."""
    buf = uint8_buffer(data)
    if buf.size == 0:
        raise ImageError("empty compressed image")
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if bgr is None:
        raise ImageError(f"undecodable compressed image ({buf.size} bytes)")
    return np.ascontiguousarray(bgr[..., ::-1])


def color_image_msg(rgb: np.ndarray, stamp_ns: int, frame_id: str, factory, quality: int = DEFAULT_JPEG_QUALITY):
    """RGB uint8 (H, W, 3) -> ``sensor_msgs/CompressedImage`` (JPEG, ``JPEG_FORMAT``) stamped ``stamp_ns``."""
    return factory.make(
        "sensor_msgs/msg/CompressedImage",
        header=factory.header(stamp_ns, frame_id),
        format=JPEG_FORMAT,
        data=factory.uint8_array(encode_jpeg(rgb, quality)),
    )


def compressed_format(msg: Any) -> str:
    """'jpeg' or 'png' from a CompressedImage's ``format`` (image_transport's "rgb8; jpeg compressed bgr8",
    or a bare "jpeg" / "png" as Foxglove's tools write it); raises ImageError for anything else."""
    text = str(msg.format).lower()
    for name, words in (("jpeg", ("jpeg", "jpg")), ("png", ("png",))):
        if any(w in text for w in words):
            return name
    raise ImageError(f"unsupported CompressedImage format {msg.format!r} (expected JPEG or PNG)")


def image_from_msg(msg: Any) -> tuple[np.ndarray, int]:
    """``sensor_msgs/CompressedImage`` (JPEG or PNG) -> (RGB uint8 (H, W, 3), header stamp ns)."""
    compressed_format(msg)
    return decode_image(msg.data), stamp_to_ns(msg.header.stamp)
