"""Does a live twin episode start from what the in-process evaluation sees? (docs/twin.md)

    PYTHONPATH=src python scripts/first_observation_check.py runs/twin_run_x/bags [--checkpoint P]

For each live episode bag: the scene is set up in-process from the bag's seed (``DirectWorld``)
and its first observation compared with the live one that the first policy chunk answered:

* grids: occupancy IoU of the live grid against the in-process render of the same scene, beside
  the IoU of two consecutive live grids and two in-process renders (the cameras draw depth noise
  and dropout anew for every frame, so identical scenes never give identical grids);
* chunks: the largest TCP distance over the chunk's steps between the live first chunk and the
  in-process prediction for that scene with the live run's sampling seed (``SamplingSeeds``:
  episode seed x 1000), beside the same prediction from another camera draw and from another
  sampling seed. Only meaningful for runs whose policy_node took its seeds from /policy/episode.

One JSON line per bag.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.data.bags import find_bags, read_episode
from equidiff_core.perception.observation import ee_input
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.twin.config import load_twin_config
from equidiff_core.twin.demos import DirectRecorder, DirectWorld
from equidiff_core.wire.chunk import SamplingSeeds, chunk_from_actions, chunk_from_msg
from equidiff_core.wire.pointcloud import voxel_msg_to_grid
from equidiff_core.wire.rosmsg import stamp_to_ns
from equidiff_core.wire.topics import TOPIC_COMMAND_CHUNK, TOPIC_VOXELS


def iou(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a[0] > 0, b[0] > 0
    return round(float((a & b).sum() / (a | b).sum()), 3)


def farthest_mm(a, b) -> float:
    return round(1000 * float(np.linalg.norm(a.poses[:, :3, 3] - b.poses[:, :3, 3], axis=1).max()), 1)


def predicted_chunk(policy, grid, ee, sampling_seed: int, like, dt_ns: int):
    """The policy's chunk for (grid, ee) with that sampling seed, stamped and sized like ``like``."""
    actions = policy.predict(grid, ee, seed=sampling_seed)[: len(like)]
    return chunk_from_actions(actions, like.stamp_ns, dt_ns)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bags", nargs="+", type=Path)
    parser.add_argument("--checkpoint", type=Path, default=Path("checkpoints/twin_compact/policy.pt"))
    args = parser.parse_args()
    lab, cfg = load_lab_config(default_config_dir() / "lab.yaml"), load_twin_config(None)
    policy = load_inference_policy(args.checkpoint, precision="fp32")  # the twin's precision
    rec = DirectRecorder(cfg, lab)
    world, resolution, dt_ns = DirectWorld(rec), lab.workspace.resolution, round(policy.preset.dt * 1e9)
    try:
        for bag in find_bags(args.bags):
            episode = read_episode(bag, [TOPIC_VOXELS, TOPIC_COMMAND_CHUNK])
            live_chunk = next(c for c in map(chunk_from_msg, episode[TOPIC_COMMAND_CHUNK].messages) if len(c) > 1)
            grids = {stamp_to_ns(m.header.stamp): m for m in episode[TOPIC_VOXELS].messages}
            stamps = sorted(grids)
            if live_chunk.stamp_ns not in grids:  # e.g. a bag recorded without /voxels
                print(json.dumps({"bag": str(bag), "error": "no /voxels grid with the first chunk's stamp"}))
                continue
            first = stamps.index(live_chunk.stamp_ns)
            live = [voxel_msg_to_grid(grids[s], resolution) for s in stamps[first : first + 2]]
            world.reset_scene(episode.meta.seed)
            renders = [rec.voxel_grid(k * dt_ns) for k in range(2)]
            ee = ee_input(rec.sim.tcp_pose(), rec.sim.gripper_width())
            seeds = SamplingSeeds()
            seeds.start_episode(episode.meta.seed)
            seed = seeds.next()
            same = predicted_chunk(policy, renders[0], ee, seed, live_chunk, dt_ns)
            row = {
                "bag": str(bag),
                "seed": episode.meta.seed,
                "grid_iou_live_vs_in_process": iou(live[0], renders[0]),
                "grid_iou_live_vs_live": iou(live[0], live[1]) if len(live) > 1 else None,
                "grid_iou_in_process_vs_in_process": iou(renders[0], renders[1]),
                "chunk_mm_live_vs_in_process": farthest_mm(live_chunk, same),
                "chunk_mm_other_camera_draw": farthest_mm(
                    same, predicted_chunk(policy, renders[1], ee, seed, live_chunk, dt_ns)
                ),
                "chunk_mm_other_sampling_seed": farthest_mm(
                    same, predicted_chunk(policy, renders[0], ee, seed + 1, live_chunk, dt_ns)
                ),
            }
            print(json.dumps(row), flush=True)
    finally:
        rec.close()


if __name__ == "__main__":
    main()
