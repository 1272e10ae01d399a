"""One observation builder (equidiff_core.perception.observation) for training, the live node and the twin's evaluation."""

from pathlib import Path

import numpy as np
import pytest

from equidiff_core.data.bags import read_episode
from equidiff_core.data.dataset import load_episode_arrays
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.perception.observation import STATE_TOLERANCE_S, StateHistory, ee_input, nearest
from equidiff_core.wire.pointcloud import voxel_msg_to_grid
from equidiff_core.wire.rosmsg import gripper_width_from_joint_state, pose_from_msg, stamp_to_ns

BAG = Path(__file__).resolve().parents[1] / "bags" / "sample_pick_0000"


def test_training_and_the_live_node_build_identical_inputs_from_the_same_bag(tmp_path):
    """The dataset (vectorised over a whole bag) and policy_node's path (messages arriving one by
    one into StateHistory, matched at each voxel stamp, ``ee_input``; the twin's evaluation calls
    the same ``ee_input`` on the sim's state) give bit-identical grids and robot-state inputs."""
    arrays = load_episode_arrays(BAG, DatasetConfig(cache_dir=None))
    episode = read_episode(BAG, topics=("/voxels", "/franka/ee_pose", "/franka/joint_states"))
    arrival = sorted(
        [(t, "pose", m) for t, m in zip(episode["/franka/ee_pose"].header_ns(), episode["/franka/ee_pose"].messages)]
        + [
            (t, "joints", m)
            for t, m in zip(episode["/franka/joint_states"].header_ns(), episode["/franka/joint_states"].messages)
        ],
        key=lambda item: item[0],
    )
    poses, widths = StateHistory(maxlen=100_000), StateHistory(maxlen=100_000)
    for _t, kind, msg in arrival:  # as policy_node's callbacks receive them
        if kind == "pose":
            poses.add(stamp_to_ns(msg.header.stamp), pose_from_msg(msg))
        elif (width := gripper_width_from_joint_state(msg)) is not None:
            widths.add(stamp_to_ns(msg.header.stamp), width)
    live = {}
    for msg in episode["/voxels"].messages:
        stamp = stamp_to_ns(msg.header.stamp)
        pose, width = poses.nearest(stamp), widths.nearest(stamp)
        if pose is not None and width is not None:
            live[stamp] = (voxel_msg_to_grid(msg, 64), ee_input(pose, width))
    assert len(arrays) > 10 and sorted(live) == arrays.stamps_ns.tolist()  # the same steps kept
    for i, stamp in enumerate(arrays.stamps_ns.tolist()):
        grid, ee = live[stamp]
        assert np.array_equal(arrays.grid(i, 64), grid)
        assert arrays.ee[i].dtype == ee.dtype and np.array_equal(arrays.ee[i], ee)


def test_a_state_outside_the_tolerance_is_no_state():
    history = StateHistory()
    assert history.nearest(0) is None
    tol = round(STATE_TOLERANCE_S * 1e9)
    history.add(2 * tol, "late")  # arrival order need not be stamp order
    history.add(0, "on time")
    assert history.nearest(tol // 2) == "on time"
    assert history.nearest(3 * tol + 1) is None and history.nearest(3 * tol) == "late"
    assert history.nearest(5 * tol, tolerance_ns=3 * tol) == "late"


def test_nearest_prefers_the_earlier_state_on_a_tie_and_rejects_an_empty_stream():
    idx, dist = nearest(np.array([0, 10, 20]), np.array([-5, 5, 14, 16, 99]))
    assert idx.tolist() == [0, 0, 1, 2, 2] and dist.tolist() == [5, 5, 4, 4, 79]
    with pytest.raises(ValueError, match="no stamps"):
        nearest(np.array([]), np.array([1]))
