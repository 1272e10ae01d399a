"""`equidiff export lerobot BAGS... --out DIR`: episodes as a LeRobot dataset (format v2.1).

One frame per observation (the dataset's alignment: /voxels header stamps, nearest ee pose
and finger width, commanded target in effect), so LeRobot, diffusion_policy-style loaders and
our own ``DemoDataset`` see the same samples:

* ``observation.state`` float32 (10,): measured TCP pose + width as an absolute action
  ``[x, y, z, r6(6), width]`` (``geometry.pose_to_action``);
* ``action`` float32 (10,): the commanded absolute target in effect at the frame;
* ``observation.voxels`` uint8 (4, R, R, R): occupancy + RGB grid (``--no-voxels`` to leave out;
  ~1 MiB per frame uncompressed, parquet's compression shrinks sparse scenes a lot);
* ``timestamp``, ``frame_index``, ``episode_index``, ``index``, ``task_index``.

Files: ``meta/info.json``, ``meta/episodes.jsonl``, ``meta/tasks.jsonl``,
``meta/episodes_stats.jsonl``, ``meta/stats.json``,
``data/chunk-XXX/episode_XXXXXX.parquet`` (pyarrow, no LeRobot install needed). LeRobot's
own converter upgrades v2.1 to its newer layouts. Written with pyarrow because LeRobot (and
its torch/ffmpeg stack) is not a dependency here; the layout follows LeRobot's v2.1 datasets.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

CODEBASE_VERSION = "v2.1"
CHUNKS_SIZE = 1000
ACTION_NAMES = ["x", "y", "z", "r00", "r01", "r02", "r10", "r11", "r12", "gripper_width"]


def add_arguments(parser) -> None:
    parser.add_argument("bags", nargs="+", help="bag directories, or folders holding bag directories")
    parser.add_argument("--out", required=True, help="new dataset directory (never overwritten)")
    parser.add_argument("--no-voxels", action="store_true", help="leave the voxel grids out")
    parser.add_argument("--robot-type", default="franka_fr3")
    parser.add_argument("--tolerance", type=float, default=0.05, help="state/voxel stamp tolerance, s")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--only-successful", action="store_true", help="skip episodes not marked success")


def _stats(x) -> dict:
    import numpy as np

    x = np.asarray(x, dtype=np.float64)
    return {
        "min": x.min(0).tolist(),
        "max": x.max(0).tolist(),
        "mean": x.mean(0).tolist(),
        "std": x.std(0).tolist(),
        "count": [len(x)],
    }


def _voxel_stats(grids) -> dict:
    """Per-channel stats in [0, 1], shaped (4, 1, 1, 1) like LeRobot's per-channel image stats."""
    import numpy as np

    g = np.asarray(grids, dtype=np.float64) / 255.0  # (T, 4, R, R, R)
    axes = (0, 2, 3, 4)

    def shaped(v):
        return np.asarray(v).reshape(4, 1, 1, 1).tolist()

    return {
        "min": shaped(g.min(axes)),
        "max": shaped(g.max(axes)),
        "mean": shaped(g.mean(axes)),
        "std": shaped(g.std(axes)),
        "count": [len(g)],
    }


def _merge_stats(all_stats: list[dict]) -> dict:
    """Aggregate per-episode stats (count-weighted mean, pooled variance), as LeRobot does."""
    import numpy as np

    out = {}
    for key in all_stats[0]:
        parts = [s[key] for s in all_stats]
        n = np.array([p["count"][0] for p in parts], dtype=np.float64)
        means = np.stack([np.asarray(p["mean"]) for p in parts])
        stds = np.stack([np.asarray(p["std"]) for p in parts])
        w = (n / n.sum()).reshape(-1, *([1] * (means.ndim - 1)))
        mean = (w * means).sum(0)
        var = (w * (stds**2 + (means - mean) ** 2)).sum(0)
        out[key] = {
            "min": np.min(np.stack([np.asarray(p["min"]) for p in parts]), 0).tolist(),
            "max": np.max(np.stack([np.asarray(p["max"]) for p in parts]), 0).tolist(),
            "mean": mean.tolist(),
            "std": np.sqrt(var).tolist(),
            "count": [int(n.sum())],
        }
    return out


def run(args) -> int:
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from equidiff_core.dataset import DatasetConfig, load_episodes
    from equidiff_core.rosmsg import NS_PER_S

    out = Path(args.out)
    if out.exists():
        print(f"equidiff export lerobot: {out} exists; not overwriting", file=sys.stderr)
        return 2
    cfg = DatasetConfig(resolution=args.resolution, state_tolerance_s=args.tolerance)
    episodes, skipped = load_episodes(
        args.bags, cfg, log=lambda m: print(f"equidiff export lerobot: {m}", file=sys.stderr)
    )
    if args.only_successful:
        episodes = [ep for ep in episodes if ep.meta.success]
    if not episodes:
        print("equidiff export lerobot: no usable episodes", file=sys.stderr)
        return 1
    rates = {round(NS_PER_S / ep.obs_period_ns, 3) for ep in episodes}
    fps = round(next(iter(rates)))
    if any(abs(r - fps) > 0.05 * fps for r in rates):
        print(
            f"equidiff export lerobot: episodes have different observation rates {sorted(rates)}; "
            "LeRobot datasets have one fps",
            file=sys.stderr,
        )
        return 1

    R = args.resolution
    features = {
        "observation.state": {"dtype": "float32", "shape": [10], "names": {"axes": ACTION_NAMES}},
        "action": {"dtype": "float32", "shape": [10], "names": {"axes": ACTION_NAMES}},
    }
    if not args.no_voxels:
        features["observation.voxels"] = {"dtype": "uint8", "shape": [4, R, R, R], "names": ["channel", "x", "y", "z"]}
    for name, dtype in (
        ("timestamp", "float32"),
        ("frame_index", "int64"),
        ("episode_index", "int64"),
        ("index", "int64"),
        ("task_index", "int64"),
    ):
        features[name] = {"dtype": dtype, "shape": [1], "names": None}

    tasks: dict[str, int] = {}
    (out / "meta").mkdir(parents=True)
    index = 0
    episode_rows, stats_rows = [], []
    vec = pa.list_(pa.float32(), 10)
    vox_type = pa.list_(pa.list_(pa.list_(pa.list_(pa.uint8(), R), R), R), 4)
    for e, ep in enumerate(episodes):
        task = ep.meta.task or "unknown"
        task_index = tasks.setdefault(task, len(tasks))
        n = len(ep)
        state = ep.ee.astype(np.float32)
        action = ep.actions.astype(np.float32)
        columns = {
            "observation.state": pa.FixedSizeListArray.from_arrays(pa.array(state.reshape(-1)), 10).cast(vec),
            "action": pa.FixedSizeListArray.from_arrays(pa.array(action.reshape(-1)), 10).cast(vec),
        }
        ep_stats = {"observation.state": _stats(state), "action": _stats(action)}
        if not args.no_voxels:
            grids = np.stack([ep.grid(k, R) for k in range(n)])
            flat = pa.array(grids.reshape(-1), type=pa.uint8())
            nested = flat
            for size in (R, R, R, 4):
                nested = pa.FixedSizeListArray.from_arrays(nested, size)
            columns["observation.voxels"] = nested.cast(vox_type)
            ep_stats["observation.voxels"] = _voxel_stats(grids)
        timestamps = ((ep.stamps_ns - ep.stamps_ns[0]) / NS_PER_S).astype(np.float32)
        scalars = {
            "timestamp": timestamps,
            "frame_index": np.arange(n, dtype=np.int64),
            "episode_index": np.full(n, e, np.int64),
            "index": np.arange(index, index + n, dtype=np.int64),
            "task_index": np.full(n, task_index, np.int64),
        }
        for name, values in scalars.items():
            columns[name] = pa.array(values)
            ep_stats[name] = _stats(values.reshape(-1, 1))
        path = out / "data" / f"chunk-{e // CHUNKS_SIZE:03d}" / f"episode_{e:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(columns), path, compression="zstd")
        episode_rows.append(
            {
                "episode_index": e,
                "tasks": [task],
                "length": n,
                "source_bag": str(ep.path),
                "success": ep.meta.success,
                "operator": ep.meta.operator,
            }
        )
        stats_rows.append({"episode_index": e, "stats": ep_stats})
        index += n

    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": args.robot_type,
        "total_episodes": len(episodes),
        "total_frames": index,
        "total_tasks": len(tasks),
        "total_videos": 0,
        "total_chunks": (len(episodes) - 1) // CHUNKS_SIZE + 1,
        "chunks_size": CHUNKS_SIZE,
        "fps": fps,
        "splits": {"train": f"0:{len(episodes)}"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": None,
        "features": features,
    }
    meta = out / "meta"
    (meta / "info.json").write_text(json.dumps(info, indent=4))
    (meta / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in episode_rows))
    (meta / "tasks.jsonl").write_text(
        "".join(json.dumps({"task_index": i, "task": t}) + "\n" for t, i in tasks.items())
    )
    (meta / "episodes_stats.jsonl").write_text("".join(json.dumps(r) + "\n" for r in stats_rows))
    (meta / "stats.json").write_text(json.dumps(_merge_stats([r["stats"] for r in stats_rows]), indent=1))
    print(
        json.dumps(
            {
                "out": str(out),
                "episodes": len(episodes),
                "frames": index,
                "fps": fps,
                "tasks": sorted(tasks),
                "skipped": len(skipped),
            }
        )
    )
    return 1 if skipped else 0
