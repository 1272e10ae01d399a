"""Run by LeRobot's own interpreter (Python >= 3.12, lerobot 0.6.1; see helpers_lerobot.py), not by pytest:
loads an exported dataset with ``LeRobotDataset(repo_id, root=...)`` and writes what LeRobot read.

usage: python lerobot_check.py DATASET_ROOT OUT_DIR FRAME_INDEX

OUT_DIR/summary.json: frame and episode counts, fps, video and camera keys, each episode's
[from, to) frame range and length, every frame's state, action, timestamp, episode index and
task; OUT_DIR/frame_<camera>.npy: camera images of frame FRAME_INDEX as LeRobot decodes them,
uint8 (H, W, 3); OUT_DIR/voxels.npy: that frame's voxel grid when the dataset has one.
"""

import json
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

root, out, frame_index = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
out.mkdir(parents=True, exist_ok=True)
ds = LeRobotDataset("local/equidiff_export", root=root)
episodes = [
    {"from": int(e["dataset_from_index"]), "to": int(e["dataset_to_index"]), "length": int(e["length"])}
    for e in ds.meta.episodes
]
frames = ds.hf_dataset.with_format("numpy")[:]  # the non-video columns, as LeRobot's reader holds them
summary = {
    "lerobot_version": __import__("lerobot").__version__,
    "num_frames": ds.num_frames,
    "num_episodes": ds.num_episodes,
    "fps": ds.fps,
    "video_keys": ds.meta.video_keys,
    "camera_keys": ds.meta.camera_keys,
    "video_backend": ds._video_backend,
    "episodes": episodes,
    "state": np.asarray(frames["observation.state"]).tolist(),
    "action": np.asarray(frames["action"]).tolist(),
    "timestamp": np.asarray(frames["timestamp"]).tolist(),
    "episode_index": np.asarray(frames["episode_index"]).tolist(),
}
item = ds[frame_index]  # the full item: decodes each camera's video at the frame's timestamp
summary["item_task"] = item["task"]
summary["item_state"] = item["observation.state"].tolist()
for key in ds.meta.video_keys:
    chw = item[key].numpy()  # float32 in [0, 1], (C, H, W)
    np.save(out / f"frame_{key.split('.')[-1]}.npy", np.round(chw * 255).astype(np.uint8).transpose(1, 2, 0))
if "observation.voxels" in item:
    np.save(out / "voxels.npy", item["observation.voxels"].numpy().astype(np.uint8))
(out / "summary.json").write_text(json.dumps(summary))
print(json.dumps({k: summary[k] for k in ("lerobot_version", "num_frames", "num_episodes", "video_backend")}))
