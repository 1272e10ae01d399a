"""`equidiff export lerobot`: the LeRobot v3.0 layout, read back with pyarrow and PyAV, and loaded by LeRobot itself.

The last test builds (once per machine, cached: helpers_lerobot.py) a Python 3.12 venv with
lerobot 0.6.1 and loads the export with ``LeRobotDataset(repo_id, root=...)``.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq
import pytest
from helpers_data import LAB, SyntheticEpisode, write_synthetic_episode
from helpers_lerobot import LeRobotUnavailable, lerobot_python
from rosbags.rosbag2 import Reader

from equidiff_core.cameras.color import image_from_msg
from equidiff_core.data.bags import read_episode
from equidiff_core.data.dataset import load_episode_arrays
from equidiff_core.data.episode_arrays import DatasetConfig
from equidiff_core.data.recording import EpisodeWriter, RecordingConfig
from equidiff_core.wire.rosmsg import rosbags_factory
from equidiff_core.wire.topics import camera_color_topic
from equidiff_ros.cli import main as cli

CFG = RecordingConfig(min_free_gib=0.0)
CAMERAS = sorted(c.name for c in LAB.cameras)
LENGTHS = [30, 15]  # 6 s and 3 s at 5 Hz
HERE = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("bags")
    return [
        write_synthetic_episode(root / "ep_0000", SyntheticEpisode(duration_s=6.0), config=CFG),
        write_synthetic_episode(root / "ep_0001", SyntheticEpisode(duration_s=3.0, yaw=-0.2), config=CFG),
    ]


@pytest.fixture(scope="module")
def exported(bags, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("lerobot") / "pick"
    assert cli(["export", "lerobot", *map(str, bags), "--out", str(out)]) == 0
    return out


def bag_image(bag: Path, camera: str, k: int) -> np.ndarray:
    """The k-th recorded colour image of a camera, decoded by OpenCV (what the export had to match)."""
    return image_from_msg(
        read_episode(bag, topics=[camera_color_topic(camera)])[camera_color_topic(camera)].messages[k]
    )[0]


def test_export_writes_the_v3_layout(exported, bags):
    info = json.loads((exported / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 5
    assert info["total_episodes"] == 2 and info["total_frames"] == sum(LENGTHS) and info["total_tasks"] == 1
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    video = info["features"]["observation.images.cam_front"]
    assert video["dtype"] == "video" and video["shape"] == [120, 212, 3]
    assert video["info"]["video.codec"] == "av1" and video["info"]["video.pix_fmt"] == "yuv420p"
    assert info["features"]["observation.voxels"]["shape"] == [4, 64, 64, 64]

    # many episodes per file: both episodes in one data file and one video per camera
    table = pq.read_table(exported / "data" / "chunk-000" / "file-000.parquet")
    assert table.num_rows == sum(LENGTHS)
    assert table["episode_index"].to_pylist() == [0] * 30 + [1] * 15
    assert table["index"].to_pylist() == list(range(45))
    np.testing.assert_allclose(table["timestamp"].to_numpy()[30:], np.arange(15) / 5, atol=1e-6)
    ep = load_episode_arrays(bags[1], DatasetConfig())
    np.testing.assert_allclose(np.array(table["observation.state"].to_pylist())[30:], ep.ee, atol=1e-6)
    np.testing.assert_allclose(np.array(table["action"].to_pylist())[30:], ep.actions, atol=1e-6)
    np.testing.assert_array_equal(np.array(table["observation.voxels"][37].as_py(), np.uint8), ep.grid(7, 64))

    episodes = pq.read_table(exported / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    assert [(e["dataset_from_index"], e["dataset_to_index"], e["length"]) for e in episodes] == [
        (0, 30, 30),
        (30, 45, 15),
    ]
    assert episodes[1]["videos/observation.images.cam_left/from_timestamp"] == pytest.approx(6.0)
    assert episodes[1]["videos/observation.images.cam_left/to_timestamp"] == pytest.approx(9.0)
    assert episodes[0]["tasks"] == ["pick_cube"] and episodes[1]["source_bag"] == str(bags[1])
    tasks = pq.read_table(exported / "meta" / "tasks.parquet")
    assert tasks.to_pylist() == [{"task_index": 0, "task": "pick_cube"}]
    stats = json.loads((exported / "meta" / "stats.json").read_text())
    assert stats["action"]["count"] == [45] and set(stats["action"]) >= {"min", "max", "mean", "std", "q01", "q99"}
    assert np.array(stats["observation.images.cam_right"]["mean"]).shape == (3, 1, 1)

    for cam in CAMERAS:
        files = list((exported / "videos" / f"observation.images.{cam}").rglob("*.mp4"))
        assert [f.relative_to(exported).as_posix() for f in files] == [
            f"videos/observation.images.{cam}/chunk-000/file-000.mp4"
        ]
        with av.open(str(files[0])) as container:
            decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
        assert len(decoded) == sum(LENGTHS)  # one video frame per dataset frame, episodes back to back


def test_exporting_videos_leaves_the_threads_scheduling_policy_alone(bags, tmp_path):
    """SVT-AV1 moves the thread that runs it to SCHED_FIFO when it may (root): an export must not leave
    the calling thread real-time, nor every thread it starts afterwards (a policy's inference thread in
    the same process ran 10x slower beside busy ROS executor threads)."""
    before = os.sched_getscheduler(0)
    assert cli(["export", "lerobot", str(bags[1]), "--out", str(tmp_path / "videos"), "--no-voxels"]) == 0
    assert (tmp_path / "videos" / "videos").is_dir()
    assert os.sched_getscheduler(0) == before


def test_export_options_and_refusals(bags, tmp_path, capsys):
    out = tmp_path / "lean"
    capsys.readouterr()
    assert cli(["export", "lerobot", str(bags[1]), "--out", str(out), "--no-voxels", "--no-images"]) == 0
    info = json.loads((out / "meta" / "info.json").read_text())
    assert "observation.voxels" not in info["features"] and info["video_path"] is None
    assert not (out / "videos").exists()
    before = _tree(out)
    assert cli(["export", "lerobot", str(bags[1]), "--out", str(out)]) == 2  # never overwrites
    assert f"{out} exists; not replacing it" in capsys.readouterr().err
    assert _tree(out) == before

    # a bag recorded without images beside one with them: refused, naming the bag and the way out
    plain = write_synthetic_episode(
        tmp_path / "plain_0000", SyntheticEpisode(duration_s=3.0, image_size=None), config=CFG
    )
    assert cli(["export", "lerobot", str(bags[1]), str(plain), "--out", str(tmp_path / "mixed")]) == 2
    assert not (tmp_path / "mixed").exists()
    # a camera that stopped sending images mid-episode: that episode is skipped and named, the others exported
    gap = tmp_path / "gap_0000"
    with Reader(bags[1]) as reader, EpisodeWriter(gap, config=CFG) as writer:
        cut = reader.start_time + 2 * 10**9
        for conn, t, raw in reader.messages():
            if not (conn.topic == camera_color_topic("cam_right") and t > cut):
                writer.write_raw(conn.topic, t, raw, conn.msgtype)
    assert cli(["export", "lerobot", str(gap), str(bags[1]), "--out", str(tmp_path / "gap"), "--no-voxels"]) == 1
    info = json.loads((tmp_path / "gap" / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 1 and info["total_frames"] == 15  # bags[1] only
    err = capsys.readouterr().err
    assert "gap_0000" in err and "camera 'cam_right' has no image within 100 ms" in err, err
    # bags without images at all: exported without image features
    assert cli(["export", "lerobot", str(plain), "--out", str(tmp_path / "old"), "--no-voxels"]) == 0
    assert json.loads((tmp_path / "old" / "meta" / "info.json").read_text())["video_path"] is None


def _tree(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_corrupt_jpeg_half_way_leaves_nothing_and_deletes_nothing(bags, tmp_path, capsys):
    """The second bag's 6th cam_right image is not a JPEG: the first episode is already encoded when the
    export fails. Nothing is left behind (no dataset, no temporary), an existing dataset stays as it was
    even with --force, and the rerun without the bad bag is not blocked."""
    bad = tmp_path / "bad_0000"
    typestore = rosbags_factory().typestore
    images = 0
    with Reader(bags[1]) as reader, EpisodeWriter(bad, config=CFG) as writer:
        for conn, t, raw in reader.messages():
            data = raw
            if conn.topic == camera_color_topic("cam_right"):
                images += 1
                if images == 6:
                    msg = typestore.deserialize_cdr(raw, conn.msgtype)
                    msg.data = np.frombuffer(b"not a jpeg at all", np.uint8)
                    data = typestore.serialize_cdr(msg, conn.msgtype)
            writer.write_raw(conn.topic, t, data, conn.msgtype)
    out = tmp_path / "dataset"
    args = ["export", "lerobot", str(bags[1]), str(bad), "--no-voxels", "--out", str(out)]
    capsys.readouterr()
    assert cli(args) == 2
    err = capsys.readouterr().err
    assert "bad_0000: cam_right: frame 5" in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad_0000"]  # no half-written dataset, no temporary

    assert cli(["export", "lerobot", str(bags[1]), "--no-voxels", "--no-images", "--out", str(out)]) == 0
    before = _tree(out)
    assert cli([*args, "--force"]) == 2
    assert _tree(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad_0000", "dataset"]
    assert cli(["export", "lerobot", str(bags[1]), "--no-voxels", "--out", str(out), "--force"]) == 0
    assert json.loads((out / "meta" / "info.json").read_text())["video_path"] is not None  # replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad_0000", "dataset"]


@pytest.mark.slow
@pytest.mark.timeout(2400)  # the first run on a machine builds LeRobot's venv (~3 min quiet, far longer under load)
def test_lerobot_itself_loads_the_export(exported, bags, tmp_path):
    try:
        python = lerobot_python()
    except LeRobotUnavailable as err:
        pytest.skip(str(err))
    frame = 30 + 7  # episode 1, frame 7: the video lookup must add the episode's from_timestamp
    run = subprocess.run(
        [str(python), str(HERE / "lerobot_check.py"), str(exported), str(tmp_path), str(frame)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    seen = json.loads((tmp_path / "summary.json").read_text())
    assert seen["lerobot_version"] == "0.6.1"
    assert seen["num_frames"] == sum(LENGTHS) and seen["num_episodes"] == 2
    assert seen["episodes"] == [{"from": 0, "to": 30, "length": 30}, {"from": 30, "to": 45, "length": 15}]
    assert seen["episode_index"] == [0] * 30 + [1] * 15
    assert sorted(seen["video_keys"]) == [f"observation.images.{c}" for c in CAMERAS]
    arrays = [load_episode_arrays(b, DatasetConfig()) for b in bags]
    np.testing.assert_allclose(seen["state"], np.concatenate([a.ee for a in arrays]), atol=1e-6)
    np.testing.assert_allclose(seen["action"], np.concatenate([a.actions for a in arrays]), atol=1e-6)
    assert seen["item_task"] == "pick_cube"
    np.testing.assert_allclose(seen["item_state"], arrays[1].ee[7], atol=1e-6)
    np.testing.assert_array_equal(np.load(tmp_path / "voxels.npy"), arrays[1].grid(7, 64))

    for cam in CAMERAS:
        got = np.load(tmp_path / f"frame_{cam}.npy").astype(np.float64)
        want = bag_image(bags[1], cam, 7).astype(np.float64)
        other = bag_image(bags[1], cam, 14).astype(np.float64)  # the gripper has moved by then
        assert got.shape == want.shape
        # AV1 at LeRobot's CRF 30 with 4:2:0 chroma blurs colour edges: a few levels on average,
        # far less than the difference to another instant of the same scene
        mae = np.abs(got - want).mean()
        psnr = 10 * np.log10(255**2 / np.mean((got - want) ** 2))
        assert mae < 4.0 and psnr > 30.0, (cam, mae, psnr)
        # and it is this frame, not a neighbour: where the scene moved between the two instants, the
        # decoded frame matches this instant's JPEG
        moved = np.abs(want - other).max(axis=-1) > 40
        assert moved.sum() > 20, cam
        assert np.abs(got - want)[moved].mean() < np.abs(got - other)[moved].mean() / 3, cam
