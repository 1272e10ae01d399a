"""The camera videos of a LeRobot export: each camera's recorded images matched to the frames, decoded,
and encoded to AV1 mp4 files with LeRobot's default encoder settings."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np

from ...cameras.color import ImageError, image_from_msg
from ...runtime.machine import keep_thread_scheduler
from ...wire.topics import camera_color_topic, camera_of_color_topic
from ..bags import read_episode
from ..episode_arrays import EpisodeArrays
from .layout import VIDEO_PATH, ExportError, MiB, next_chunk_file

# SVT-AV1 prints its whole configuration to stderr for each encoder it opens; errors only
os.environ.setdefault("SVT_LOG", "1")


@dataclass(frozen=True)
class VideoEncoding:
    """LeRobot 0.6.1's RGB encoder defaults (``lerobot.configs.video.VideoEncoderConfig``)."""

    vcodec: str = "libsvtav1"
    pix_fmt: str = "yuv420p"
    g: int = 2  # a key frame every 2 frames: random access for training
    crf: int = 30
    preset: int = 12
    fast_decode: int = 0

    def codec_options(self) -> dict[str, str]:
        """What LeRobot's ``get_codec_options(as_strings=True)`` passes to PyAV for this codec."""
        opts = {"g": str(self.g), "crf": str(self.crf), "preset": str(self.preset)}
        if self.vcodec == "libsvtav1":
            opts["svtav1-params"] = f"fast-decode={max(0, min(2, self.fast_decode))}"
        elif self.fast_decode:
            opts["tune"] = "fastdecode"
        return opts

    def info(self, stream) -> dict[str, Any]:
        """The feature's ``info`` block in info.json, as ``lerobot.datasets.video_utils.get_video_info``."""
        return {
            "video.height": stream.height,
            "video.width": stream.width,
            "video.codec": stream.codec_context.codec.canonical_name,
            "video.pix_fmt": self.pix_fmt,
            "video.fps": int(stream.base_rate or stream.average_rate),
            "video.channels": 3,
            "has_audio": False,
            "video.g": self.g,
            "video.crf": self.crf,
            "video.preset": self.preset,
            "video.fast_decode": self.fast_decode,
            "video.video_backend": "pyav",
            "video.extra_options": {},
            "is_depth_map": False,
        }


class VideoFiles:
    """One camera's frames as mp4 files, episodes back to back at exactly 1/fps per frame, so the
    k-th frame of an episode that starts at ``from_timestamp`` plays at ``from_timestamp + k/fps``."""

    def __init__(self, root: Path, key: str, fps: int, encoding: VideoEncoding, limit_mb: float, chunks_size: int):
        self.root, self.key, self.fps, self.encoding = root, key, fps, encoding
        self.limit_mb, self.chunks_size = limit_mb, chunks_size
        self.chunk = self.file = 0
        self.container = self.stream = self.path = None
        self.frames_in_file = 0
        self.info: dict[str, Any] | None = None
        self.shape: tuple[int, int, int] | None = None

    def _open(self, width: int, height: int) -> None:
        self.path = self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=self.chunk, file_index=self.file)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.container = av.open(str(self.path), "w")
        self.stream = self.container.add_stream(
            self.encoding.vcodec, rate=self.fps, options=self.encoding.codec_options()
        )
        self.stream.pix_fmt = self.encoding.pix_fmt
        self.stream.width, self.stream.height = width, height
        self.stream.time_base = Fraction(1, self.fps)
        self.frames_in_file = 0
        if self.info is None:
            self.info = self.encoding.info(self.stream)
            self.shape = (height, width, 3)

    def add_episode(self, frames: Iterable[np.ndarray]) -> dict[str, Any]:
        """Append one episode's RGB frames (H, W, 3); returns its LeRobot episode-metadata columns."""
        # the muxer creates the file with its first packet: the encoder may still hold every frame so far
        if self.container is not None and self.path.is_file() and self.path.stat().st_size / MiB >= self.limit_mb:
            self.close()
            self.chunk, self.file = next_chunk_file(self.chunk, self.file, self.chunks_size)
        start = None
        for rgb in frames:
            if self.container is None:
                self._open(rgb.shape[1], rgb.shape[0])
            if start is None:
                start = self.frames_in_file
            if (rgb.shape[1], rgb.shape[0]) != (self.stream.width, self.stream.height):
                raise ExportError(
                    f"{self.key}: a {rgb.shape[1]}x{rgb.shape[0]} image in a {self.stream.width}x"
                    f"{self.stream.height} video (one resolution per camera)"
                )
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
            frame.pts = self.frames_in_file
            self.frames_in_file += 1
            self._encode(frame)
        start = self.frames_in_file if start is None else start
        prefix = f"videos/{self.key}/"
        return {
            prefix + "chunk_index": self.chunk,
            prefix + "file_index": self.file,
            prefix + "from_timestamp": start / self.fps,
            prefix + "to_timestamp": self.frames_in_file / self.fps,
        }

    def _encode(self, frame: av.VideoFrame | None) -> None:
        """One frame into the file (None: flush the encoder)."""
        # SVT-AV1 moves the thread that opens or runs it to SCHED_FIFO when it may (root)
        with keep_thread_scheduler(self.encoding.vcodec):
            for packet in self.stream.encode(frame):
                self.container.mux(packet)

    def close(self) -> None:
        if self.container is not None:
            self._encode(None)
            with keep_thread_scheduler(self.encoding.vcodec):
                self.container.close()
            self.container = None


# --- the frames of one episode ----------------------------------------------------------------


def bag_cameras(ep: EpisodeArrays) -> list[str]:
    """Cameras with a recorded colour-image topic in the episode's bag (sorted)."""
    from rosbags.rosbag2 import Reader

    if not (Path(ep.path) / "metadata.yaml").is_file():
        return []  # a packed episode: no images kept
    with Reader(ep.path) as reader:
        return sorted({cam for t, info in reader.topics.items() if info.msgcount and (cam := camera_of_color_topic(t))})


def matched_images(ep: EpisodeArrays, cameras: Sequence[str], tolerance_ns: int) -> dict[str, list]:
    """Per camera, the CompressedImage message nearest each observation's stamp (header stamps).

    Raises ExportError naming the frame when a camera has no image within the tolerance."""
    episode = read_episode(ep.path, topics=[camera_color_topic(c) for c in cameras])
    out = {}
    for cam in cameras:
        topic = camera_color_topic(cam)
        if topic not in episode:
            raise ExportError(f"{ep.path}: no colour images of camera {cam!r} ({topic})")
        msgs = episode[topic]
        stamps = msgs.header_ns()
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        after = np.minimum(np.searchsorted(stamps, ep.stamps_ns), len(stamps) - 1)
        before = np.maximum(after - 1, 0)
        closer_before = np.abs(stamps[before] - ep.stamps_ns) <= np.abs(stamps[after] - ep.stamps_ns)
        nearest = np.where(closer_before, before, after)
        gap = np.abs(stamps[nearest] - ep.stamps_ns)
        if np.any(gap > tolerance_ns):
            i = int(np.argmax(gap > tolerance_ns))
            raise ExportError(
                f"{ep.path}: camera {cam!r} has no image within {tolerance_ns / 1e6:.0f} ms of observation {i} "
                f"(nearest {gap[i] / 1e6:.0f} ms away)"
            )
        out[cam] = [msgs.messages[order[j]] for j in nearest]
    return out


def decoded_images(messages: list, where: str) -> Iterable[np.ndarray]:
    for i, msg in enumerate(messages):
        try:
            yield image_from_msg(msg)[0]
        except ImageError as err:
            raise ExportError(f"{where}: frame {i}: {err}") from err
