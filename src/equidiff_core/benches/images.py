"""What recording each camera's colour image costs: bytes per frame, CPU per frame on the camera
node and on the recorder, MB per minute of demonstrations; with the baselines of the same run
(the cloud message camera_node already builds per frame, the /voxels grid the recorder already
writes per observation). ``equidiff bench images`` prints ``measure()``'s result.

The frames are the twin's own renders of a seeded scene (``cameras.twin.TwinCamera``) at the
twin's render size and at lab.yaml's camera size (a real D455's 848x480). A rendered frame has
no sensor noise, which JPEG would spend bytes on, so a third case adds Gaussian noise (sigma 2
levels) to the lab-size render: an estimate for a real camera, labelled as such.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from ..cameras.base import limit_depth
from ..cameras.color import DEFAULT_JPEG_QUALITY, color_image_msg
from ..cameras.twin import TwinCamera
from ..config import LabConfig
from ..data.recording import EpisodeWriter, RecordingConfig
from ..perception.voxels import Voxelizer
from ..twin import scene
from ..wire.pointcloud import cloud_to_msg, grid_to_voxel_msg
from ..wire.rosmsg import rosbags_factory
from ..wire.topics import COMPRESSED_IMAGE_TYPE, TOPIC_VOXELS, camera_color_topic

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"


def _cpu_ms(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """Median CPU time of this thread per call, ms (CPU, not wall: the machine may be busy), and the last result."""
    times, result = [], None
    for _ in range(repeats):
        t0 = time.thread_time()
        result = fn()
        times.append(time.thread_time() - t0)
    return float(np.median(times) * 1e3), result


def _scene_qpos(twin_cfg, seed: int) -> np.ndarray:
    model = scene.build_model(twin_cfg)
    data = mujoco.MjData(model)
    data.qpos[:7] = twin_cfg.sim.initial_q
    scene.apply_scene(model, data, scene.sample_scene(twin_cfg.scene, seed), twin_cfg.scene)
    return data.qpos.copy()


def _frames(lab: LabConfig, twin_cfg, qpos: np.ndarray, width: int, height: int):
    frames = []
    for cam in lab.cameras:
        source = lambda t: (qpos, 0.0, 1)
        with TwinCamera(cam, source, paced=False, twin_config=twin_cfg, width=width, height=height) as c:
            frames.append(limit_depth(c.read(), cam.min_depth, cam.max_depth))
    return frames


def _writer_cpu_ms(directory: Path, topic: str, raw: bytes, msgtype: str, repeats: int) -> float:
    """The recorder's CPU per message: ``EpisodeWriter.write_raw`` (what its subscription callback does)
    into a real bag, with closing the bag (writing its chunk, summary and metadata) shared out."""
    writer = EpisodeWriter(directory, config=RecordingConfig(min_free_gib=0.0)).open()
    writer.add_topic(topic, msgtype)
    t0 = time.thread_time()
    for stamp in range(1, repeats + 1):
        writer.write_raw(topic, stamp, raw)
    writer.close()
    return (time.thread_time() - t0) / repeats * 1e3


def _case(images, lab: LabConfig, quality: int, repeats: int, tmp: Path, baseline: dict) -> dict:
    f = rosbags_factory()
    encoded = [
        _cpu_ms(lambda im=im, c=c: color_image_msg(im, 1, c.frame_id, f, quality), repeats)
        for im, c in zip(images, lab.cameras)
    ]
    raws = [f.typestore.serialize_cdr(msg, COMPRESSED_IMAGE_TYPE) for _, msg in encoded]
    topic = camera_color_topic(lab.cameras[0].name)
    write_ms = _writer_cpu_ms(tmp / "images", topic, raws[0], COMPRESSED_IMAGE_TYPE, repeats)
    kb = float(np.mean([len(r) for r in raws]) / 1e3)
    hz, n_cams = lab.observation_hz, len(lab.cameras)
    return {
        "width": int(images[0].shape[1]),
        "height": int(images[0].shape[0]),
        "jpeg_kb_per_frame": round(kb, 1),
        "raw_rgb_kb_per_frame": round(images[0].nbytes / 1e3, 1),
        "camera_node_jpeg_cpu_ms": round(float(np.mean([ms for ms, _ in encoded])), 2),
        "recorder_write_image_cpu_ms": round(write_ms, 3),
        "images_mb_per_min": round(kb * n_cams * hz * 60 / 1e3, 1),
        **baseline,
    }


def measure(lab: LabConfig, twin_cfg, repeats: int = 20, quality: int = DEFAULT_JPEG_QUALITY, seed: int = 0) -> dict:
    """The cost of colour images per frame and per minute, per image size (see the module docstring)."""
    f = rosbags_factory()
    qpos = _scene_qpos(twin_cfg, seed)
    rng = np.random.default_rng(seed)
    sizes = {
        f"twin_{twin_cfg.render.width}x{twin_cfg.render.height}": (twin_cfg.render.width, twin_cfg.render.height),
        f"lab_{lab.cameras[0].width}x{lab.cameras[0].height}": (lab.cameras[0].width, lab.cameras[0].height),
    }
    voxelizer = Voxelizer(lab.workspace, [c.extrinsics.matrix() for c in lab.cameras])
    ws, cam0 = lab.workspace, lab.cameras[0]
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (w, h) in sizes.items():
            frames = _frames(lab, twin_cfg, qpos, w, h)
            grid_msg = grid_to_voxel_msg(voxelizer(frames), ws.lower, ws.voxel_size, 1, lab.base_frame, f)
            voxel_raw = f.typestore.serialize_cdr(grid_msg, CLOUD_TYPE)
            fr0 = frames[0]
            cloud_ms, _ = _cpu_ms(lambda fr0=fr0: cloud_to_msg(fr0.points, fr0.colors, 1, cam0.frame_id, f), repeats)
            baseline = {
                "camera_node_cloud_msg_cpu_ms_baseline": round(cloud_ms, 2),
                "recorder_write_voxels_cpu_ms_baseline": round(
                    _writer_cpu_ms(Path(tmp) / f"voxels_{name}", TOPIC_VOXELS, voxel_raw, CLOUD_TYPE, repeats), 3
                ),
                "voxels_kb_per_frame_baseline": round(len(voxel_raw) / 1e3, 1),
                "voxels_mb_per_min_baseline": round(len(voxel_raw) / 1e3 * lab.observation_hz * 60 / 1e3, 1),
            }
            images = [fr.image for fr in frames]
            results[name] = _case(images, lab, quality, repeats, Path(tmp) / name, baseline)
            if name.startswith("lab_"):  # sensor noise, as a real camera's: an estimate
                noisy = [np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8) for im in images]
                results[name + "_noise2_estimate"] = _case(
                    noisy, lab, quality, repeats, Path(tmp) / f"{name}_n", baseline
                )
    return {
        "bench": "images",
        "cameras": len(lab.cameras),
        "observation_hz": lab.observation_hz,
        "jpeg_quality": quality,
        "repeats": repeats,
        "cases": results,
    }
