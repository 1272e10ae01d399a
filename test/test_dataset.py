"""Dataset from bags: sample indices, padding, header-stamp alignment, command schedule, cache, bad bags."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers_bad_messages import robot_state
from helpers_data import (
    LAB,
    SyntheticEpisode,
    command_at,
    measured_at,
    voxel_grid,
    write_synthetic_episode,
)

import equidiff_core.data.dataset as dataset_mod
from equidiff_core import geometry
from equidiff_core.config import Workspace
from equidiff_core.data.dataset import (
    DemoDataset,
    command_schedule,
    dataset_stats,
    load_episode_arrays,
    sample_starts,
    split_episodes,
)
from equidiff_core.data.episode_arrays import PACKED_SUFFIX, DatasetConfig
from equidiff_core.data.mcap_reader import BagError
from equidiff_core.data.recording import RecordingConfig
from equidiff_core.wire.chunk import PoseChunk
from equidiff_core.wire.rosmsg import NS_PER_S, joint_state, pose_stamped, rosbags_factory, stamp_to_ns
from equidiff_core.wire.topics import TOPIC_EE_POSE, TOPIC_JOINT_STATES

CFG = RecordingConfig(min_free_gib=0.0)
EP = SyntheticEpisode(duration_s=6.0)  # 30 observations at 5 Hz


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    return write_synthetic_episode(tmp_path_factory.mktemp("bags") / "ep_0000", EP, config=CFG)


def t_of(ns: int) -> float:
    return (ns - EP.t0_ns) / NS_PER_S


def action(pose_width) -> np.ndarray:
    pose, width = pose_width
    return geometry.pose_to_action(pose, np.float64(width))


def test_sample_starts_follow_the_official_sequence_sampler():
    # n_obs 1, horizon 16, n_action 8: pad_before 0, pad_after 7
    np.testing.assert_array_equal(sample_starts(30, 16, 1, 8), np.arange(0, 30 - 16 + 7 + 1))
    np.testing.assert_array_equal(sample_starts(30, 16, 2, 8), np.arange(-1, 30 - 16 + 7 + 1))
    assert len(sample_starts(8, 16, 1, 8)) == 0  # too short for one window
    assert len(sample_starts(9, 16, 1, 8)) == 1


def test_command_schedule_newer_chunk_replaces_the_remaining_steps():
    eye = np.repeat(np.eye(4)[None], 3, axis=0)

    def chunk(stamp, times, widths):
        return PoseChunk(stamp, np.asarray(times, dtype=np.int64), eye[: len(times)].copy(), np.asarray(widths, float))

    a = chunk(0, [10, 20, 30], [1, 2, 3])
    b = chunk(15, [25, 35], [4, 5])  # arrives before a's step at 30: replaces it
    times, targets = command_schedule([b, a])  # arrival order is by stamp
    np.testing.assert_array_equal(times, [10, 20, 25, 35])
    np.testing.assert_array_equal(targets[:, 9], [1, 2, 4, 5])


def test_samples_match_the_recorded_episode(bag):
    ds = DemoDataset.from_bags([bag], DatasetConfig())
    ep = ds.episodes[0]
    n = len(ep)
    assert n == 30 and ep.dropped_steps == 0
    assert len(ds) == n - 16 + 7 + 1
    for i in (0, 5, len(ds) - 1):
        s = ds[i]
        assert s["voxels"].dtype.is_floating_point is False and tuple(s["voxels"].shape) == (1, 4, 64, 64, 64)
        assert tuple(s["ee"].shape) == (1, 10) and tuple(s["action"].shape) == (16, 10)
        k = int(ds.index[i][1])
        t = t_of(ep.stamps_ns[k])
        assert t == pytest.approx(0.2 * k)
        np.testing.assert_array_equal(s["voxels"][0].numpy(), voxel_grid(EP, LAB.workspace, t))
        np.testing.assert_allclose(s["ee"][0].numpy(), action(measured_at(EP, t)), atol=1e-6)
        for j in range(16):
            tj = 0.2 * min(k + j, n - 1)  # padded with the last step past the end
            np.testing.assert_allclose(
                s["action"][j].numpy(), action(command_at(EP, tj)), atol=1e-6, err_msg=f"sample {i} step {j}"
            )


def test_end_padding_repeats_the_last_step(bag):
    ds = DemoDataset.from_bags([bag], DatasetConfig())
    last = ds[len(ds) - 1]["action"].numpy()
    # the final window starts at n - 9: steps 0..8 are real, 9..15 repeat step 8 (the last observation)
    np.testing.assert_array_equal(last[9:], np.repeat(last[8:9], 7, axis=0))
    assert not np.allclose(last[7], last[8])  # the arm is still lifting: padding is not a no-op


def test_start_padding_with_two_observation_steps(bag):
    ds = DemoDataset.from_bags([bag], DatasetConfig(n_obs_steps=2))
    first = ds[0]
    assert int(ds.index[0][1]) == -1
    np.testing.assert_array_equal(first["voxels"][0].numpy(), first["voxels"][1].numpy())
    np.testing.assert_array_equal(first["ee"][0].numpy(), first["ee"][1].numpy())
    np.testing.assert_array_equal(first["action"][0].numpy(), first["action"][1].numpy())


def test_alignment_uses_header_stamps_not_receive_times(bag):
    # /voxels were logged 40 ms after their header stamp; ee poses 0.3 ms after theirs.
    ep = load_episode_arrays(bag, DatasetConfig())
    k = 10
    np.testing.assert_allclose(ep.ee[k], action(measured_at(EP, 0.2 * k)), atol=1e-6)
    np.testing.assert_allclose(ep.actions[k], action(command_at(EP, 0.2 * k)), atol=1e-6)


def test_states_outside_the_tolerance_drop_the_step(tmp_path):
    sparse = SyntheticEpisode(duration_s=6.0, state_hz=2.0)  # one ee pose every 0.5 s
    path = write_synthetic_episode(tmp_path / "ep", sparse, config=CFG)
    ep = load_episode_arrays(path, DatasetConfig(state_tolerance_s=0.05))
    # observations at 0.2 k; states at 0.5 m: only t = 0, 1, 2, ... (every 5th observation) align
    assert len(ep) == 6 and ep.dropped_steps == 24
    np.testing.assert_allclose((ep.stamps_ns - sparse.t0_ns) / NS_PER_S, np.arange(6.0))
    wide = load_episode_arrays(path, DatasetConfig(state_tolerance_s=0.3))
    assert len(wide) == 30 and wide.dropped_steps == 0


def test_before_the_first_command_the_target_is_the_measured_pose(tmp_path):
    ep = load_episode_arrays(write_synthetic_episode(tmp_path / "ep", EP, config=CFG), DatasetConfig())
    before = ep.targets_at(np.array([ep.stamps_ns[0] - 1]))
    np.testing.assert_allclose(before[0], ep.ee[0])


def test_cache_means_bags_are_decoded_once(bag, tmp_path, monkeypatch):
    cfg = DatasetConfig(cache_dir=str(tmp_path / "cache"))
    first = DemoDataset.from_bags([bag], cfg)
    assert list((tmp_path / "cache").glob("*.npz"))

    def no_decoding(*a, **k):
        raise AssertionError("bag decoded again")

    monkeypatch.setattr(dataset_mod, "read_episode", no_decoding)
    second = DemoDataset.from_bags([bag], cfg)
    assert len(second) == len(first) and second.skipped == []
    for i in (0, len(first) - 1):
        for key in ("voxels", "ee", "action"):
            np.testing.assert_array_equal(first[i][key].numpy(), second[i][key].numpy())
    # in memory: epochs never touch the bag (read_episode is still patched out)
    for i in range(len(second)):
        second[i]


def test_bad_bags_are_reported_and_skipped(bag, tmp_path):
    truncated = write_synthetic_episode(tmp_path / "trunc", SyntheticEpisode(duration_s=2.0), config=CFG)
    mcap = truncated / "trunc.mcap"
    mcap.write_bytes(mcap.read_bytes()[:-3000])
    (tmp_path / "killed").mkdir()
    (tmp_path / "killed" / "killed.mcap").write_bytes(b"\x89MCAP0\r\n")
    ds = DemoDataset.from_bags([bag, truncated, tmp_path / "killed", tmp_path / "missing"], DatasetConfig())
    assert len(ds.episodes) == 1 and ds.episodes[0].path == bag
    reasons = {p.name: r for p, r in ds.skipped}
    assert set(reasons) == {"trunc", "killed", "missing"}
    assert "bags repair" in reasons["trunc"] and "bags repair" in reasons["killed"]
    assert "no such bag" in reasons["missing"]


def test_packed_episodes_hold_exactly_what_the_bag_decodes_to(bag, tmp_path):
    """`equidiff dataset pack`: a compressed file per bag that training reads instead of the bag."""
    out = subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "dataset", "pack", str(bag), "--out", str(tmp_path / "packed")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.splitlines()[-1])["packed"] == 1
    packed = tmp_path / "packed" / f"ep_0000{PACKED_SUFFIX}"
    assert packed.stat().st_size < sum(f.stat().st_size for f in bag.glob("*.mcap")) / 4
    decoded, restored = load_episode_arrays(bag), load_episode_arrays(packed)
    for field in ("stamps_ns", "voxel_offsets", "voxel_idx", "voxel_rgb", "ee", "schedule_ns", "schedule"):
        np.testing.assert_array_equal(getattr(restored, field), getattr(decoded, field))
    assert restored.meta == decoded.meta and restored.obs_period_ns == decoded.obs_period_ns
    # a folder of packed episodes trains like a folder of bags: the same samples
    from_bag, from_packed = DemoDataset.from_bags([bag]), DemoDataset.from_bags([tmp_path / "packed"])
    assert len(from_packed) == len(from_bag) > 0 and from_packed.skipped == []
    for key in ("voxels", "ee", "action"):
        np.testing.assert_array_equal(from_packed[3][key].numpy(), from_bag[3][key].numpy())


def test_packed_episode_decoded_differently_or_damaged_is_refused(bag, tmp_path):
    packed = dataset_mod.pack_episodes([bag], tmp_path)[0][0]
    with pytest.raises(BagError, match="pack the bags again"):
        load_episode_arrays(packed, DatasetConfig(resolution=32))
    broken = tmp_path / f"broken{PACKED_SUFFIX}"
    broken.write_bytes(packed.read_bytes()[:200])
    episodes, skipped = dataset_mod.load_episodes([tmp_path])
    assert len(episodes) == 1 and [p.name for p, _ in skipped] == [broken.name]
    assert "not a readable packed episode" in skipped[0][1]


def _pack(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "dataset", "pack", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_pack_names_same_named_bags_apart_and_never_clobbers(bag, tmp_path):
    """Two days' ``ep_0000`` give two files; an existing folder is refused unless --force, and a pack that
    produces nothing leaves the old folder as it was and no temporary behind."""
    day1, day2 = tmp_path / "day1" / bag.name, tmp_path / "day2" / bag.name
    shutil.copytree(bag, day1)
    shutil.copytree(bag, day2)
    out = tmp_path / "packed"
    first = _pack(str(tmp_path / "day1"), str(tmp_path / "day2"), str(day1), "--out", str(out))
    assert first.returncode == 0, first.stderr
    names = sorted(p.name for p in out.iterdir())
    assert names == [f"day1__ep_0000{PACKED_SUFFIX}", f"day2__ep_0000{PACKED_SUFFIX}"]
    assert json.loads(first.stdout.splitlines()[-1])["packed"] == 2  # day1 named twice is packed once
    before = _tree(out)

    again = _pack(str(day1), "--out", str(out))
    assert again.returncode == 2 and f"{out} exists; not replacing it" in again.stderr and "--force" in again.stderr
    assert "Traceback" not in again.stderr
    assert _tree(out) == before

    nothing = _pack(str(tmp_path / "missing"), "--out", str(out), "--force")
    assert nothing.returncode == 1 and json.loads(nothing.stdout.splitlines()[-1])["packed"] == 0
    assert _tree(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["day1", "day2", "packed"]  # no temporary left

    forced = _pack(str(day2), "--out", str(out), "--force")
    assert forced.returncode == 0, forced.stderr
    assert [p.name for p in out.iterdir()] == [f"ep_0000{PACKED_SUFFIX}"]  # replaced, not merged
    assert sorted(p.name for p in tmp_path.iterdir()) == ["day1", "day2", "packed"]


def test_split_holds_out_whole_episodes_deterministically():
    eps = list(range(10))
    train, val = split_episodes(eps, 0.2, seed=3)
    assert sorted(train + val) == eps and len(val) == 2
    assert split_episodes(eps, 0.2, seed=3) == (train, val)
    assert split_episodes([0, 1], 0.1, seed=0)[1] != []  # at least one held out when asked
    assert split_episodes(eps, 0.0, seed=0) == (eps, [])


def test_stats(bag, tmp_path):
    stats = dataset_stats([bag, tmp_path / "missing"])
    (row,) = stats["episodes"]
    assert row["steps"] == 30 and row["samples"] == 22 and row["obs_hz"] == pytest.approx(5.0)
    assert row["duration_s"] == pytest.approx(5.8)
    assert row["task"] == "pick_cube" and row["success"] is True
    lo, hi = np.array(row["action_min"]), np.array(row["action_max"])
    assert hi[2] == pytest.approx(0.30) and lo[9] == pytest.approx(0.038) and hi[9] == pytest.approx(0.08)
    assert stats["total"]["skipped"] == 1 and stats["skipped"][0]["path"].endswith("missing")


def test_dataset_stats_cli(bag, tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "dataset", "stats", str(bag), str(tmp_path / "missing"), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 1, out.stderr  # a skipped bag makes it fail loudly (exit 1)
    data = json.loads(out.stdout)
    assert data["total"]["episodes"] == 1 and data["total"]["steps"] == 30
    table = subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "dataset", "stats", str(bag)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert table.returncode == 0, table.stderr
    assert "ep_0000" in table.stdout and "30" in table.stdout and "total" in table.stdout


# --- offline decoding checks: the lab's grid, and robot state rosmsg refuses ------------------------


def test_grids_are_checked_against_the_labs_workspace_where_the_lab_is_known(tmp_path):
    moved = Workspace(tuple(np.asarray(LAB.workspace.center) + 0.05), LAB.workspace.edge, LAB.workspace.resolution)
    elsewhere = write_synthetic_episode(tmp_path / "ep_moved", SyntheticEpisode(duration_s=2.0), ws=moved, config=CFG)
    with pytest.raises(BagError, match="origin or voxel size"):
        load_episode_arrays(elsewhere, DatasetConfig.for_lab(LAB))
    # without the lab only the resolution can be checked: the same bag decodes
    assert len(load_episode_arrays(elsewhere, DatasetConfig(resolution=moved.resolution)).stamps_ns) > 0
    with pytest.raises(ValueError, match="resolution"):
        DatasetConfig(resolution=32, grid=DatasetConfig.for_lab(LAB).grid)


class _Episode(dict):
    path = Path("in_memory_bag")


class _Topic:
    def __init__(self, messages):
        self.messages = messages

    def header_ns(self) -> np.ndarray:
        return np.array([stamp_to_ns(m.header.stamp) for m in self.messages], dtype=np.int64)


def test_refused_poses_and_joint_states_are_left_out_and_the_next_nearest_is_used():
    f = rosbags_factory()
    t, ms = 10 * NS_PER_S, 1_000_000
    down = (1.0, 0.0, 0.0, 0.0)

    def pose(x, stamp, frame=LAB.base_frame):
        return pose_stamped(f, geometry.pose_from_pos_quat((x, 0.0, 0.3), down), stamp, frame)

    def joints(width, stamp):
        return joint_state(f, robot_state((0.4, 0.0, 0.3), width), stamp)

    nan_pose = pose(0.4, t)
    nan_pose.pose.position.x = float("nan")
    poses = [pose(0.41, t - 20 * ms), nan_pose, pose(0.42, t + 1 * ms, frame="elsewhere"), pose(0.43, t + 10 * ms)]
    too_wide = joints(0.04, t)
    too_wide.position = f.float64_array([*list(too_wide.position)[:-2], 0.06, 0.06])
    states = [joints(0.02, t - 30 * ms), too_wide, joints(0.03, t + 5 * ms)]
    episode = _Episode({TOPIC_EE_POSE: _Topic(poses), TOPIC_JOINT_STATES: _Topic(states)})
    stamps = np.array([t], dtype=np.int64)
    ee, ok = dataset_mod._ee_actions(episode, stamps, 50 * ms, LAB.base_frame)
    assert ok.tolist() == [True]
    assert ee[0, 0] == pytest.approx(0.43) and ee[0, 9] == pytest.approx(0.03)  # not the NaN, foreign or 0.12 m
    ee, ok = dataset_mod._ee_actions(episode, stamps, 50 * ms, None)  # no frame known: the foreign pose is nearest
    assert ee[0, 0] == pytest.approx(0.42)
    # every pose refused: the episode has no robot state, said so
    with pytest.raises(BagError, match="no usable /franka/ee_pose"):
        dataset_mod._ee_actions(
            _Episode({**episode, TOPIC_EE_POSE: _Topic([nan_pose])}), stamps, 50 * ms, LAB.base_frame
        )
