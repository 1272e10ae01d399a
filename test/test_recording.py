"""EpisodeWriter (rosbag2 MCAP episodes), read_episode, and repair of killed recordings (no ROS needed)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers_data import SyntheticEpisode, write_synthetic_episode

from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.data.bags import EpisodeMeta, find_bags, read_episode, repair_bag, scan_mcap
from equidiff_core.data.mcap_reader import BagError
from equidiff_core.data.recording import (
    EpisodeWriter,
    RecordingConfig,
    RecordingError,
    next_episode_path,
)
from equidiff_core.wire.pointcloud import grid_to_voxel_msg, voxel_msg_to_grid
from equidiff_core.wire.rosmsg import rosbags_factory
from equidiff_core.wire.topics import camera_color_topic

ROOT = Path(__file__).resolve().parents[1]
LAB = load_lab_config(default_config_dir() / "lab.yaml")
CFG = RecordingConfig(min_free_gib=0.0)
F = rosbags_factory()


def dense_grid(seed: int, fill: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    grid = np.zeros((4, 64, 64, 64), np.uint8)
    occ = rng.random((64, 64, 64)) < fill
    grid[0][occ] = 255
    grid[1:, occ] = rng.integers(0, 256, size=(3, int(occ.sum())), dtype=np.uint8)
    return grid


def voxel_msg(grid, stamp):
    ws = LAB.workspace
    return grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, stamp, LAB.base_frame, F)


def test_episode_round_trip_with_metadata_and_tf_static(tmp_path):
    meta = EpisodeMeta(task="pick", operator="ana", notes="first try", seed=7, extra={"scene": "A"})
    grids = [dense_grid(i, 0.01) for i in range(3)]
    with EpisodeWriter(tmp_path / "ep", meta, CFG) as w:
        w.write_tf_static(LAB, 5)
        for i, g in enumerate(grids):
            w.write("/voxels", voxel_msg(g, 1000 + i), 2000 + i)
    ep = read_episode(tmp_path / "ep")
    assert ep.meta == meta
    assert ep.message_counts == {"/tf_static": 1, "/voxels": 3}
    for g, m in zip(grids, ep["/voxels"].messages):
        np.testing.assert_array_equal(voxel_msg_to_grid(m, 64), g)
    np.testing.assert_array_equal(ep["/voxels"].log_ns, [2000, 2001, 2002])
    np.testing.assert_array_equal(ep["/voxels"].header_ns(), [1000, 1001, 1002])
    tf = ep["/tf_static"].messages[0].transforms
    assert [t.child_frame_id for t in tf] == [c.frame_id for c in LAB.cameras]
    np.testing.assert_allclose(
        [tf[0].transform.translation.x, tf[0].transform.rotation.w],
        [LAB.cameras[0].extrinsics.translation[0], LAB.cameras[0].extrinsics.quaternion_xyzw[3]],
    )
    info = yaml.safe_load((tmp_path / "ep" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap" and info["custom_data"]["task"] == "pick"
    qos = {
        t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
        for t in info["topics_with_message_count"]
    }
    assert "durability: transient_local" in qos["/tf_static"] or qos["/tf_static"][0]["durability"] in (
        1,
        "transient_local",
    )


def test_close_records_success_and_notes(tmp_path):
    w = EpisodeWriter(tmp_path / "ep", EpisodeMeta(task="t"), CFG).open()
    w.write("/voxels", voxel_msg(dense_grid(0, 0.001), 1), 1)
    w.close(success=False, notes="dropped it")
    meta = read_episode(tmp_path / "ep").meta
    assert meta.success is False and meta.notes == "dropped it" and meta.task == "t"
    with pytest.raises(RecordingError, match="not open"):
        w.write("/voxels", voxel_msg(dense_grid(0, 0.001), 2), 2)


def test_never_overwrites_and_numbers_episodes(tmp_path):
    assert next_episode_path(tmp_path, "pick cube!").name == "pick_cube_0000"
    (tmp_path / "pick_cube_0000").mkdir()
    (tmp_path / "pick_cube_0007").mkdir()
    (tmp_path / "other_0042").mkdir()
    assert next_episode_path(tmp_path, "pick cube!").name == "pick_cube_0008"
    with pytest.raises(RecordingError, match="never overwritten"):
        EpisodeWriter(tmp_path / "pick_cube_0007", config=CFG).open()


def test_refuses_to_start_without_free_disk(tmp_path):
    with pytest.raises(RecordingError, match="free"):
        EpisodeWriter(tmp_path / "ep", config=RecordingConfig(min_free_gib=1e9)).open()
    assert not (tmp_path / "ep").exists()


def test_discard_removes_the_episode(tmp_path):
    w = EpisodeWriter(tmp_path / "ep", config=CFG).open()
    w.write("/voxels", voxel_msg(dense_grid(0, 0.001), 1), 1)
    w.discard()
    assert not (tmp_path / "ep").exists()


def test_chunks_are_larger_than_the_largest_message(tmp_path):
    # a dense grid (~60% occupied) is ~3.8 MiB as an occupied-voxel cloud: bigger than rosbags' 1 MiB default
    big = dense_grid(1, 0.6)
    with EpisodeWriter(tmp_path / "ep", config=RecordingConfig(min_free_gib=0.0, chunk_size_mib=8)) as w:
        for i in range(4):
            w.write("/voxels", voxel_msg(big, i), i)
    mcap = tmp_path / "ep" / "ep.mcap"
    scan = scan_mcap(mcap)
    assert scan.chunks == 2  # 4 x 3.8 MiB in 8 MiB chunks
    assert len(scan.messages) == 4
    assert max(len(d) for _, _, d in scan.messages) > 3 * (1 << 20)


def test_config_rejects_chunks_smaller_than_messages():
    with pytest.raises(ValueError, match="chunk_size_mib"):
        RecordingConfig(chunk_size_mib=1.0)


def test_repair_recovers_every_complete_chunk(tmp_path):
    path = write_synthetic_episode(
        tmp_path / "ep", SyntheticEpisode(duration_s=8.0), config=RecordingConfig(min_free_gib=0.0, chunk_size_mib=2.0)
    )
    full = read_episode(path)
    # simulate SIGKILL: no metadata.yaml, file cut inside the last chunk
    mcap = path / "ep.mcap"
    data = mcap.read_bytes()
    scan_full = scan_mcap(mcap)
    assert scan_full.chunks >= 2
    (path / "metadata.yaml").unlink()
    cut = int(len(data) * 0.75)
    mcap.write_bytes(data[:cut])
    with pytest.raises(BagError, match="bags repair"):
        read_episode(path)
    report = repair_bag(path)
    assert report is not None and report.dropped_bytes > 0 and "cut off" in report.reason
    assert report.original == tmp_path / "ep.unrepaired" and report.original.exists()
    got = read_episode(path)
    # every recovered message equals the original's message at the same position, and the
    # recovered set is exactly the complete chunks: more than half, not all
    for topic, msgs in got.topics.items():
        orig = full[topic].log_ns
        np.testing.assert_array_equal(msgs.log_ns, orig[: len(msgs)])
    vox_full, vox_got = full["/voxels"], got["/voxels"]
    assert len(vox_full) // 3 < len(vox_got) < len(vox_full)
    for a, b in zip(vox_got.messages, vox_full.messages):
        np.testing.assert_array_equal(voxel_msg_to_grid(a, 64), voxel_msg_to_grid(b, 64))
    assert got.meta.task == "pick_cube" and "recovered by equidiff bags repair" in got.meta.notes
    assert got.meta.success is True  # from the sidecar written at start (synthetic episodes mark success)
    # the repaired bag is healthy: a second repair has nothing to do
    assert repair_bag(path) is None
    # find_bags skips the kept original
    assert find_bags([tmp_path]) == [path]


def test_repair_of_a_bag_cut_before_the_first_chunk_says_so(tmp_path):
    path = write_synthetic_episode(tmp_path / "ep", SyntheticEpisode(duration_s=2.0), config=CFG)
    (path / "metadata.yaml").unlink()
    mcap = path / "ep.mcap"
    mcap.write_bytes(mcap.read_bytes()[:5000])
    with pytest.raises(BagError, match="nothing recoverable"):
        repair_bag(path)
    assert mcap.exists()  # nothing deleted


def test_repair_to_a_separate_output_keeps_the_original_untouched(tmp_path):
    path = write_synthetic_episode(
        tmp_path / "ep", SyntheticEpisode(duration_s=4.0), config=RecordingConfig(min_free_gib=0.0, chunk_size_mib=2.0)
    )
    (path / "metadata.yaml").unlink()
    before = sorted(p.name for p in path.iterdir())
    report = repair_bag(path, output=tmp_path / "fixed")
    assert report.original is None and sorted(p.name for p in path.iterdir()) == before
    assert read_episode(tmp_path / "fixed").message_counts["/voxels"] > 0


def test_unreadable_inputs_give_clear_errors(tmp_path):
    with pytest.raises(BagError, match="no such bag"):
        read_episode(tmp_path / "missing")
    (tmp_path / "file.mcap").write_bytes(b"not a bag")
    with pytest.raises(BagError, match="not a rosbag2 directory"):
        read_episode(tmp_path / "file.mcap")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "bad.mcap").write_bytes(b"garbage" * 10)
    with pytest.raises(BagError, match="not an MCAP"):
        repair_bag(bad)
    # a truncated file *with* metadata.yaml (copied around half-way) is reported, not half-read
    path = write_synthetic_episode(tmp_path / "ep", SyntheticEpisode(duration_s=2.0), config=CFG)
    mcap = path / "ep.mcap"
    mcap.write_bytes(mcap.read_bytes()[:-2000])
    with pytest.raises(BagError, match="unreadable bag"):
        read_episode(path)


def test_sample_bag_ships_and_reads():
    bags = find_bags([ROOT / "bags"])
    assert bags, "bags/ must hold a sample episode"
    total = sum(f.stat().st_size for b in bags for f in b.iterdir())
    assert total < 5 * (1 << 20)
    ep = read_episode(bags[0])
    for topic in ("/voxels", "/franka/ee_pose", "/franka/joint_states", "/franka/command_chunk", "/tf_static"):
        assert topic in ep, topic
    assert ep.meta.task
    images = read_episode(bags[0], topics=[camera_color_topic(c.name) for c in LAB.cameras])
    for cam in LAB.cameras:  # every camera's colour image, one per voxel grid, stamped like it
        stamps = images[camera_color_topic(cam.name)].header_ns()
        np.testing.assert_array_equal(stamps, ep["/voxels"].header_ns())


def test_copied_bag_dir_is_still_readable(tmp_path):
    # rosbag2 directories are relocatable: metadata.yaml names the .mcap relative to itself
    src = write_synthetic_episode(tmp_path / "a", SyntheticEpisode(duration_s=1.0), config=CFG)
    shutil.copytree(src, tmp_path / "b")
    assert read_episode(tmp_path / "b").message_counts == read_episode(src).message_counts


def test_recorder_command_parsing():
    from equidiff_ros.recorder_node import parse_command

    assert parse_command("start") == ("start", {})
    assert parse_command("start pick_cube") == ("start", {"task": "pick_cube"})
    assert parse_command("stop") == ("stop", {"success": True})
    assert parse_command("STOP failure seed=7 operator=ana slipped off") == (
        "stop",
        {"success": False, "seed": 7, "operator": "ana", "notes": "slipped off"},
    )
    assert parse_command("stop success fine") == ("stop", {"success": True, "notes": "fine"})
    assert parse_command("stop seed=2 extra.block_yaw_deg=-12.5 extra.range=-15,15 extra.=x") == (
        "stop",
        {"success": True, "seed": 2, "extra": {"block_yaw_deg": "-12.5", "range": "-15,15"}, "notes": "extra.=x"},
    )
    assert parse_command(" discard ") == ("discard", {})
    with pytest.raises(ValueError, match="unknown recorder command"):
        parse_command("halt")
    with pytest.raises(ValueError, match="empty"):
        parse_command("  ")


def test_bags_repair_cli(tmp_path, capsys):
    from equidiff_ros.cli import main as cli

    healthy = write_synthetic_episode(tmp_path / "ok", SyntheticEpisode(duration_s=1.0), config=CFG)
    killed = write_synthetic_episode(
        tmp_path / "killed",
        SyntheticEpisode(duration_s=4.0),
        config=RecordingConfig(min_free_gib=0.0, chunk_size_mib=2.0),
    )
    (killed / "metadata.yaml").unlink()
    mcap = killed / "killed.mcap"
    mcap.write_bytes(mcap.read_bytes()[:-1000])
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli(["bags", "repair", str(healthy), str(killed), str(empty)]) == 1  # one failure -> exit 1
    out, err = capsys.readouterr()
    assert f"ok {healthy}" in out and f"repaired {killed}" in out and "original kept at" in out
    assert f"FAILED {empty}" in err and "expected one .mcap" in err
    assert read_episode(killed).message_counts["/voxels"] > 0


def test_episode_is_valid_mcap_for_other_readers(tmp_path):
    """The official mcap reader + mcap-ros2 decoder (what Foxglove builds on) read our episodes."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = write_synthetic_episode(tmp_path / "ep", SyntheticEpisode(duration_s=2.0), config=CFG)
    ours = read_episode(path)
    with open(path / "ep.mcap", "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary.statistics.message_count == sum(ours.message_counts.values())
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
        assert schemas["sensor_msgs/msg/PointCloud2"] == "ros2msg"
        voxels = [m for _s, ch, _m, m in reader.iter_decoded_messages(topics=["/voxels"])]
    assert len(voxels) == len(ours["/voxels"])
    assert voxels[3].width == ours["/voxels"].messages[3].width and voxels[3].header.frame_id == LAB.base_frame
    assert bytes(voxels[3].data) == ours["/voxels"].messages[3].data.tobytes()


def test_low_disk_while_recording_is_flagged(tmp_path, monkeypatch):
    from equidiff_core.data import recording

    w = EpisodeWriter(tmp_path / "ep", config=RecordingConfig(min_free_gib=1.0, chunk_size_mib=2.0)).open()
    big = dense_grid(2, 0.4)  # ~2.5 MiB: closes a chunk, which checks the disk
    w.write("/voxels", voxel_msg(big, 0), 0)
    assert not w.low_disk
    monkeypatch.setattr(recording, "free_bytes", lambda path: 100 << 20)  # 100 MiB left
    w.write("/voxels", voxel_msg(big, 1), 1)
    assert w.low_disk  # recorder_node stops and keeps the episode on its next tick
    w.close()
    assert read_episode(tmp_path / "ep").message_counts["/voxels"] == 2


def test_recorded_topics_hold_each_cameras_colour_image_by_default():
    from equidiff_core.data.recording import recorded_topics

    images = {camera_color_topic(c.name) for c in LAB.cameras}
    assert images == {f"/cameras/{c.name}/color/image_raw/compressed" for c in LAB.cameras}
    default = recorded_topics(LAB, record_clouds=False)
    assert {t: default[t] for t in images} == dict.fromkeys(images, "sensor_msgs/msg/CompressedImage")
    assert not images & set(recorded_topics(LAB, record_clouds=False, record_images=False))
    assert RecordingConfig().record_images is True and RecordingConfig().record_clouds is False
