"""`equidiff dataset revoxelize`: a recorded demo's voxels rebuilt from its clouds with new extrinsics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from equidiff_core.bags import BagError, EpisodeMeta, read_episode, read_meta
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.pointcloud import cloud_to_msg, grid_to_voxel_msg, voxel_msg_to_grid
from equidiff_core.recording import EpisodeWriter, RecordingConfig, recorded_topics
from equidiff_core.topics import TOPIC_EE_POSE, TOPIC_VOXELS
from equidiff_core.voxels import voxelize_reference
from equidiff_ros.commands.bench_voxelize import synthetic_scene

LAB = load_lab_config(default_config_dir() / "lab.yaml")
NS = 1_000_000_000
T0 = 1_700_000_000 * NS


def _record(path, lab, clouds, n_sets=6, with_clouds=True):
    """An episode as recorder_node writes it with record_clouds: three clouds every 0.2 s (a few
    ms apart, in camera order), a stale /voxels grid after each set, and 100 Hz ee poses."""
    from equidiff_core.control import messages as cm

    ws = lab.workspace
    wrong = np.zeros((4, ws.resolution, ws.resolution, ws.resolution), np.uint8)
    wrong[:, 1, 1, 1] = 255  # what a wrong calibration left: not what the clouds give
    with EpisodeWriter(path, EpisodeMeta(task="pick", success=True), RecordingConfig(min_free_gib=0.0)) as writer:
        for topic, msgtype in recorded_topics(lab, record_clouds=with_clouds).items():
            writer.add_topic(topic, msgtype)
        for i in range(n_sets):
            stamp = T0 + i * NS // 5
            if with_clouds:
                for k, (cam, (pts, cols)) in enumerate(zip(lab.cameras, clouds)):
                    writer.write(
                        cam.topic,
                        cloud_to_msg(pts, cols, stamp + k * 1_000_000, cam.frame_id, writer.factory),
                        stamp + k * 1_000_000 + 30_000_000,
                    )
            writer.write(
                TOPIC_VOXELS,
                grid_to_voxel_msg(wrong, ws.lower, ws.voxel_size, stamp, lab.base_frame, writer.factory),
                stamp + 60_000_000,
            )
            for j in range(20):
                t = stamp + j * NS // 100
                writer.write(TOPIC_EE_POSE, cm.pose_stamped(writer.factory, np.eye(4), t, lab.base_frame), t)
    return path


@pytest.fixture(scope="module")
def clouds():
    return synthetic_scene(LAB, 5000, seed=3)


def test_revoxelize_rebuilds_the_voxels_from_the_clouds_with_new_extrinsics(tmp_path, clouds):
    from equidiff_core.fusion import revoxelize_bag

    src = _record(tmp_path / "demo", LAB, clouds)
    # the lab after recalibration: cam_left turns 3 degrees about z and moves 1 cm
    from scipy.spatial.transform import Rotation

    left = LAB.cameras[1]
    T = left.extrinsics.matrix()
    T[:3, :3] = Rotation.from_euler("z", 3, degrees=True).as_matrix() @ T[:3, :3]
    T[:3, 3] += [0.01, 0.0, 0.0]
    new_ext = dataclasses.replace(
        left.extrinsics, translation=tuple(T[:3, 3]), quaternion_xyzw=tuple(Rotation.from_matrix(T[:3, :3]).as_quat())
    )
    new_lab = dataclasses.replace(
        LAB, cameras=(LAB.cameras[0], dataclasses.replace(left, extrinsics=new_ext), *LAB.cameras[2:])
    )
    report = revoxelize_bag(src, tmp_path / "out" / "demo", new_lab)

    assert report.grids == 6 and report.replaced == 6 and set(report.clouds.values()) == {6}
    ep = read_episode(report.path)
    expected = voxelize_reference(clouds, [c.extrinsics.matrix() for c in new_lab.cameras], new_lab.workspace)
    old = voxelize_reference(clouds, [c.extrinsics.matrix() for c in LAB.cameras], LAB.workspace)
    assert not np.array_equal(expected, old)  # the recalibration changes the grid
    grids = [voxel_msg_to_grid(m, LAB.workspace.resolution) for m in ep.topics[TOPIC_VOXELS].messages]
    assert len(grids) == 6 and all(np.array_equal(g, expected) for g in grids)
    # each grid stamped with its set's newest cloud, as voxel_node stamps it
    stamps = [m.header.stamp.sec * NS + m.header.stamp.nanosec for m in ep.topics[TOPIC_VOXELS].messages]
    assert stamps == [T0 + i * NS // 5 + 2_000_000 for i in range(6)]
    # everything else is copied, and the episode's metadata says what happened
    assert len(ep.topics[TOPIC_EE_POSE].messages) == 120
    for cam in LAB.cameras:
        assert len(ep.topics[cam.topic].messages) == 6
    meta = read_meta(report.path)
    assert meta.task == "pick" and meta.success and "re-voxelised" in meta.notes


def test_revoxelize_refuses_a_bag_without_clouds_and_an_existing_output(tmp_path, clouds):
    from equidiff_core.fusion import revoxelize_bag

    src = _record(tmp_path / "demo", LAB, clouds, n_sets=2, with_clouds=False)
    with pytest.raises(BagError, match="no recorded clouds on /cameras/cam_front/points"):
        revoxelize_bag(src, tmp_path / "out", LAB)
    assert not (tmp_path / "out").exists()  # nothing half-written
    with pytest.raises(BagError, match="already exists"):
        revoxelize_bag(src, src, LAB)


def test_revoxelize_command_writes_one_bag_per_input(tmp_path, clouds, capsys):
    from equidiff_ros.cli import main

    _record(tmp_path / "bags" / "a", LAB, clouds, n_sets=2)
    _record(tmp_path / "bags" / "b", LAB, clouds, n_sets=3)
    lab_yaml = default_config_dir() / "lab.yaml"
    assert (
        main(["dataset", "revoxelize", str(tmp_path / "bags"), "--lab", str(lab_yaml), "--out", str(tmp_path / "new")])
        == 0
    )
    assert sorted(p.name for p in (tmp_path / "new").iterdir()) == ["a", "b"]
    out = capsys.readouterr().out
    assert "a: 2 grids" in out and "b: 3 grids" in out
    assert (
        main(["dataset", "revoxelize", str(tmp_path / "bags"), "--lab", str(lab_yaml), "--out", str(tmp_path / "new")])
        == 1
    )  # never overwrites
    assert "already exists" in capsys.readouterr().err
