"""`equidiff dataset revoxelize`: a recorded demo's voxels rebuilt from its clouds with new extrinsics."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from equidiff_core.benches.voxelize import synthetic_scene
from equidiff_core.config import Extrinsics, default_config_dir, load_lab_config
from equidiff_core.data.bags import EpisodeMeta, read_episode, read_meta
from equidiff_core.data.mcap_reader import BagError
from equidiff_core.data.recording import EpisodeWriter, RecordingConfig, recorded_topics
from equidiff_core.perception.voxels import voxelize_reference
from equidiff_core.wire.pointcloud import cloud_to_msg, grid_to_voxel_msg, voxel_msg_to_grid
from equidiff_core.wire.rosmsg import tf_message
from equidiff_core.wire.topics import TOPIC_EE_POSE, TOPIC_VOXELS

LAB = load_lab_config(default_config_dir() / "lab.yaml")
NS = 1_000_000_000
T0 = 1_700_000_000 * NS


def _record(path, lab, clouds, n_sets=6, with_clouds=True, with_tf=True):
    """An episode as recorder_node writes it with record_clouds: /tf_static from ``lab`` first,
    three clouds every 0.2 s (a few ms apart, in camera order), a stale /voxels grid after each
    set, and 100 Hz ee poses."""
    from equidiff_core.wire import rosmsg

    ws = lab.workspace
    wrong = np.zeros((4, ws.resolution, ws.resolution, ws.resolution), np.uint8)
    wrong[:, 1, 1, 1] = 255  # what a wrong calibration left: not what the clouds give
    with EpisodeWriter(path, EpisodeMeta(task="pick", success=True), RecordingConfig(min_free_gib=0.0)) as writer:
        for topic, msgtype in recorded_topics(lab, record_clouds=with_clouds).items():
            writer.add_topic(topic, msgtype)
        if with_tf:
            writer.write_tf_static(lab, T0 - NS // 10)
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
                writer.write(TOPIC_EE_POSE, rosmsg.pose_stamped(writer.factory, np.eye(4), t, lab.base_frame), t)
    return path


def _recalibrated(lab):
    """The lab after a recalibration: cam_left turned 3 degrees about z and moved 1 cm."""
    left = lab.cameras[1]
    T = left.extrinsics.matrix()
    T[:3, :3] = Rotation.from_euler("z", 3, degrees=True).as_matrix() @ T[:3, :3]
    T[:3, 3] += [0.01, 0.0, 0.0]
    return dataclasses.replace(
        lab,
        cameras=(lab.cameras[0], dataclasses.replace(left, extrinsics=Extrinsics.from_matrix(T)), *lab.cameras[2:]),
    )


@pytest.fixture(scope="module")
def clouds():
    return synthetic_scene(LAB, 5000, seed=3)


def test_revoxelize_rebuilds_the_voxels_from_the_clouds_with_new_extrinsics(tmp_path, clouds):
    from equidiff_core.perception.fusion import revoxelize_bag

    src = _record(tmp_path / "demo", LAB, clouds)
    new_lab = _recalibrated(LAB)
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


def _mcap_tf_static(bag):
    """Every /tf_static message of the bag as {child frame: (parent frame, stamp ns, 4x4)}, read
    with the mcap library and its own ROS 2 decoder (not rosbags, which wrote the bag)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    (mcap_file,) = bag.glob("*.mcap")
    messages = []
    with mcap_file.open("rb") as f:
        for _, _, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
            topics=["/tf_static"]
        ):
            frames = {}
            for t in msg.transforms:
                tr, q = t.transform.translation, t.transform.rotation
                T = np.eye(4)
                T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
                T[:3, 3] = [tr.x, tr.y, tr.z]
                stamp = t.header.stamp.sec * NS + t.header.stamp.nanosec
                frames[t.child_frame_id] = (t.header.frame_id, stamp, T)
            messages.append(frames)
    return messages


def _metadata_extrinsics(bag):
    """Camera -> 4x4 from metadata.yaml's custom_data, read as plain YAML."""
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    custom = info["custom_data"]
    out = {}
    for key, value in custom.items():
        if key.startswith("extra.extrinsics."):
            e = yaml.safe_load(value)
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(e["quaternion_xyzw"]).as_matrix()
            T[:3, 3] = e["translation"]
            out[key.removeprefix("extra.extrinsics.")] = T
    return custom, out


@pytest.mark.parametrize("with_tf", [True, False], ids=["recorded-tf_static", "no-tf_static"])
def test_revoxelized_bag_carries_the_new_extrinsics_in_tf_static_and_metadata(tmp_path, clouds, with_tf):
    from equidiff_core.perception.fusion import revoxelize_bag

    src = _record(tmp_path / "demo", LAB, clouds, n_sets=2, with_tf=with_tf)
    new_lab = _recalibrated(LAB)
    report = revoxelize_bag(src, tmp_path / "out" / "demo", new_lab)

    if with_tf:  # the source says the old calibration, as the recorder wrote it
        (old_tf,) = _mcap_tf_static(src)
        np.testing.assert_allclose(
            old_tf["cam_left_color_optical_frame"][2], LAB.cameras[1].extrinsics.matrix(), atol=1e-9
        )
    (new_tf,) = _mcap_tf_static(report.path)
    assert set(new_tf) == {cam.frame_id for cam in new_lab.cameras}
    for cam in new_lab.cameras:
        parent, stamp, T = new_tf[cam.frame_id]
        assert parent == new_lab.base_frame
        np.testing.assert_allclose(T, cam.extrinsics.matrix(), atol=1e-9)
        # the recorder's stamp is kept; a bag without /tf_static gets one at its first message
        assert stamp == (T0 - NS // 10 if with_tf else T0)  # T0: the first ee pose
    assert not np.allclose(new_tf["cam_left_color_optical_frame"][2], LAB.cameras[1].extrinsics.matrix(), atol=1e-3)

    custom, extrinsics = _metadata_extrinsics(report.path)
    assert custom["task"] == "pick" and custom["success"] == "true"  # the episode's own metadata kept
    assert custom["extra.extrinsics_base_frame"] == new_lab.base_frame
    assert set(extrinsics) == {cam.name for cam in new_lab.cameras}
    for cam in new_lab.cameras:
        np.testing.assert_allclose(extrinsics[cam.name], cam.extrinsics.matrix(), atol=1e-12)
    assert read_meta(report.path).extra["extrinsics.cam_left"] == custom["extra.extrinsics.cam_left"]  # sidecar too
    sidecar = yaml.safe_load((report.path / "episode.yaml").read_text())
    assert sidecar["extra"]["extrinsics.cam_left"] == custom["extra.extrinsics.cam_left"]


def test_revoxelize_keeps_transforms_to_other_frames():
    from equidiff_core.perception.fusion import replace_camera_transforms
    from equidiff_core.wire.rosmsg import rosbags_factory

    factory = rosbags_factory()
    tool = np.eye(4)
    tool[:3, 3] = [0.0, 0.0, 0.1034]
    old = tf_message(
        factory,
        [("fr3_hand", "fr3_hand_tcp", tool), (LAB.base_frame, "cam_front_color_optical_frame", np.eye(4))],
        T0,
    )
    new = replace_camera_transforms(old, _recalibrated(LAB), factory)
    frames = [t.child_frame_id for t in new.transforms]
    assert frames == ["fr3_hand_tcp", "cam_front_color_optical_frame", *[c.frame_id for c in LAB.cameras[1:]]]
    assert new.transforms[0] is old.transforms[0]
    assert all(t.header.stamp.sec * NS + t.header.stamp.nanosec == T0 for t in new.transforms)


def test_revoxelize_refuses_a_bag_without_clouds_and_an_existing_output(tmp_path, clouds):
    from equidiff_core.perception.fusion import revoxelize_bag

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
    new = tmp_path / "new"
    before = _tree(new)
    assert main(["dataset", "revoxelize", str(tmp_path / "bags"), "--lab", str(lab_yaml), "--out", str(new)]) == 2
    assert f"{new} exists; not replacing it" in capsys.readouterr().err  # never overwrites
    assert _tree(new) == before
    # every bag fails (no clouds): even with --force the old folder stays, and no temporary is left
    _record(tmp_path / "plain" / "a", LAB, clouds, n_sets=2, with_clouds=False)
    assert (
        main(["dataset", "revoxelize", str(tmp_path / "plain"), "--lab", str(lab_yaml), "--out", str(new), "--force"])
        == 1
    )
    assert "no recorded clouds" in capsys.readouterr().err
    assert _tree(new) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bags", "new", "plain"]
    # two days' same-named bags land apart; --force replaces the folder whole
    shutil.copytree(tmp_path / "bags" / "a", tmp_path / "day1" / "a")
    shutil.copytree(tmp_path / "bags" / "a", tmp_path / "day2" / "a")
    days = [str(tmp_path / "day1"), str(tmp_path / "day2")]
    assert main(["dataset", "revoxelize", *days, "--lab", str(lab_yaml), "--out", str(new), "--force"]) == 0
    assert sorted(p.name for p in new.iterdir()) == ["day1__a", "day2__a"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bags", "day1", "day2", "new", "plain"]


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
