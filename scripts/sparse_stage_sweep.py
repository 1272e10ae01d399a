"""The encoder's first stage, dense against computed from the occupied voxels, by how many voxels and how spread.

    PYTHONPATH=src python scripts/sparse_stage_sweep.py [--demos DIR ...]

One JSON line per grid set: batch 8 of 4-channel 58³ crops, either the twin's table, block and bowl voxelised
(``models.equivariance.twin_scenes``, centre crop), random voxels scattered at a share of the grid, or with
``--demos`` eight frames of recorded episodes (evenly spaced over their training samples, centre crop); each with
the occupied voxels per sample, the share of the 28³ pooled cells some voxel reaches, how many of the 28 vertical
layers hold a reached cell, and the CPU milliseconds
(one thread) of a forward and backward of ``max_pool3d(conv3d(x, w, b), 2)`` densely and of the sparse
computation (``models.sparse_stage``, forced whatever the share), the median of 3 after a warm-up. The shipped
threshold, ``sparse_stage.DENSE_ABOVE_REACHED``, sits where the sparse computation stops paying
(docs/results/model.md, "What a CPU training step costs").
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
import torch.nn.functional as F

from equidiff_core.benches import BenchError
from equidiff_core.benches.throughput import recorded_training_set
from equidiff_core.config import Workspace
from equidiff_core.models import sparse_stage
from equidiff_core.models.equivariance import twin_scenes
from equidiff_core.policy.augment import center_crop
from equidiff_core.policy.presets import get_preset
from equidiff_core.twin.config import load_twin_config


def cpu_ms(run, weight, bias, repeats: int = 3) -> float:
    run().sum().backward()  # warm-up
    times = []
    for _ in range(repeats):
        start = time.process_time()
        run().sum().backward()
        times.append((time.process_time() - start) * 1000)
    weight.grad = bias.grad = None
    return round(statistics.median(times), 1)


def recorded_frames(paths, preset, count: int = 8) -> torch.Tensor:
    """``count`` frames of the recorded episodes at ``paths``, evenly spaced over their training samples."""
    try:
        data = recorded_training_set(paths, preset, Workspace(), count)
    except BenchError as err:
        raise SystemExit(str(err)) from err
    picks = torch.linspace(0, len(data) - 1, count).long().tolist()
    return torch.stack([torch.as_tensor(data[i]["voxels"][-1]) for i in picks])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demos", nargs="+", default=(), metavar="DIR", help="recorded episodes: a grid set of theirs")
    args = parser.parse_args()
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(0)
    weight = torch.randn(8, 4, 3, 3, 3, generator=gen, requires_grad=True)
    bias = torch.randn(8, generator=gen, requires_grad=True)
    preset = get_preset("compact")
    voxels, _ = twin_scenes(preset, Workspace(), 8, seed=0, scene=load_twin_config().scene)
    grids = {"twin": center_crop(voxels[:, 0], preset.crop).float().div(255)}
    if args.demos:
        grids["recorded"] = center_crop(recorded_frames(args.demos, preset), preset.crop).float().div(255)
    for share in (0.001, 0.003, 0.006, 0.01, 0.02, 0.03, 0.04, 0.06, 0.1):
        occupied = torch.rand(8, 1, 58, 58, 58, generator=gen) < share
        grids[f"scattered {share}"] = torch.rand(8, 4, 58, 58, 58, generator=gen) * occupied
    for name, x in grids.items():
        feats, _, reached, pooled, cells = sparse_stage._plan(x)
        layers = torch.unique(reached % pooled[-1])  # the last axis is the vertical one, z
        dense = cpu_ms(lambda x=x: F.max_pool3d(F.conv3d(x, weight, bias), 2), weight, bias)
        sparse = cpu_ms(
            lambda x=x: sparse_stage._ConvPoolOccupied.apply(*sparse_stage._plan(x), weight, bias), weight, bias
        )
        line = {
            "grids": name,
            "voxels_per_sample": len(feats) // 8,
            "reached_share": round(len(reached) / cells, 3),
            "layers_reached": f"{len(layers)} of {pooled[-1]}",
            "dense_ms": dense,
            "sparse_ms": sparse,
            "threshold_picks": "dense" if len(reached) > sparse_stage.DENSE_ABOVE_REACHED * cells else "sparse",
        }
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
