"""rerun visualisation offline: bags -> .rrd read back with rerun's own reader, the training callback, the CLI.

The bags are built here with rosbags and the project's wire-format encoders, so every
expected count and time range below comes from what was written, not from the converter.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from equidiff_core import geometry
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.wire.chunk import chunk_from_actions, chunk_to_msg
from equidiff_core.wire.pointcloud import cloud_to_msg, grid_to_voxel_msg
from equidiff_core.wire.rosmsg import NS_PER_S, MsgFactory, RosbagsFactory, rosbags_factory

rr = pytest.importorskip("rerun")

from equidiff_core.viz import VizUnavailable, require_rerun
from equidiff_core.viz.bag_to_rrd import convert_bags
from equidiff_core.viz.logger import RerunLogger
from equidiff_core.viz.recording_setup import VizConfig, open_recording
from equidiff_core.viz.rrd import summarize_rrd

ROOT = Path(__file__).resolve().parents[1]
LAB = load_lab_config(default_config_dir() / "lab.yaml")
T0_NS = 1_700_000_000 * NS_PER_S
DOWN = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
EVERYTHING = VizConfig(ee_hz=1000.0, clouds=True, cloud_hz=1000.0)  # no throttling: counts = messages


# --- message builders shared with test_viz_live.py -------------------------------------------


def voxel_grid(n_occupied: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r = LAB.workspace.resolution
    grid = np.zeros((4, r, r, r), dtype=np.uint8)
    flat = rng.choice(r**3, size=n_occupied, replace=False)
    i, j, k = np.unravel_index(flat, (r, r, r))
    grid[0, i, j, k] = 255
    grid[1:, i, j, k] = rng.integers(0, 256, (3, n_occupied), dtype=np.uint8)
    return grid


def voxel_msg(n_occupied: int, stamp_ns: int, factory: MsgFactory, seed: int = 0):
    ws = LAB.workspace
    return grid_to_voxel_msg(voxel_grid(n_occupied, seed), ws.lower, ws.voxel_size, stamp_ns, LAB.base_frame, factory)


def tcp_pose(t_s: float) -> np.ndarray:
    p = np.array([0.45 + 0.05 * np.cos(t_s), 0.05 * np.sin(t_s), 0.2])
    return geometry.make_pose(geometry.rotz(0.2 * t_s) @ DOWN, p)


def pose_msg(T: np.ndarray, stamp_ns: int, factory: MsgFactory):
    p, q = geometry.pos_quat_from_pose(T)
    mk = factory.make
    return mk(
        "geometry_msgs/msg/PoseStamped",
        header=factory.header(stamp_ns, LAB.base_frame),
        pose=mk(
            "geometry_msgs/msg/Pose",
            position=mk("geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=mk("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        ),
    )


def joint_state_msg(width: float, stamp_ns: int, factory: MsgFactory):
    names = [f"fr3_joint{i}" for i in range(1, 8)] + ["fr3_finger_joint1", "fr3_finger_joint2"]
    return factory.make(
        "sensor_msgs/msg/JointState",
        header=factory.header(stamp_ns, ""),
        name=names,
        position=factory.float64_array([0.0] * 7 + [width / 2, width / 2]),
        velocity=factory.float64_array([]),
        effort=factory.float64_array([]),
    )


def chunk_msg(t_s: float, stamp_ns: int, factory: MsgFactory, steps: int = 8, dt_s: float = 0.2):
    widths = np.linspace(0.08, 0.04, steps)
    actions = np.stack([geometry.pose_to_action(tcp_pose(t_s + i * dt_s), widths[i]) for i in range(steps)])
    return chunk_to_msg(chunk_from_actions(actions, stamp_ns, int(dt_s * NS_PER_S)), factory, LAB.base_frame)


def diagnostics_msg(inference_ms: float, stamp_ns: int, factory: MsgFactory):
    mk = factory.make
    values = [
        mk("diagnostic_msgs/msg/KeyValue", key=k, value=v)
        for k, v in (
            ("inference_ms", f"{inference_ms:.3f}"),
            ("observation_age_ms", "35.5"),
            ("obs_to_cmd_ms", "140"),
            ("skipped_cycles", "2"),
            ("backend", "cpu-bf16"),
        )
    ]
    status = mk(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=0 if isinstance(factory, RosbagsFactory) else b"\x00",
        name="policy_node: inference",
        message="ok",
        hardware_id="",
        values=values,
    )
    return mk("diagnostic_msgs/msg/DiagnosticArray", header=factory.header(stamp_ns, ""), status=[status])


def camera_cloud_msg(n: int, stamp_ns: int, factory: MsgFactory, camera: str = "cam_front"):
    rng = np.random.default_rng(stamp_ns % 1000)
    pts = rng.uniform([-0.3, -0.2, 0.4], [0.3, 0.2, 1.2], (n, 3)).astype(np.float32)
    pts[::50] = np.nan  # realsense-like holes: dropped, not an error
    cols = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    return cloud_to_msg(pts, cols, stamp_ns, LAB.camera(camera).frame_id, factory)


def tf_static_msg(stamp_ns: int, factory: MsgFactory, shift: float = 0.0):
    mk = factory.make
    transforms = []
    for cam in LAB.cameras:
        t, q = cam.extrinsics.translation, cam.extrinsics.quaternion_xyzw
        transforms.append(
            mk(
                "geometry_msgs/msg/TransformStamped",
                header=factory.header(stamp_ns, LAB.base_frame),
                child_frame_id=cam.frame_id,
                transform=mk(
                    "geometry_msgs/msg/Transform",
                    translation=mk("geometry_msgs/msg/Vector3", x=t[0] + shift, y=t[1], z=t[2]),
                    rotation=mk("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )
        )
    return mk("tf2_msgs/msg/TFMessage", transforms=transforms)


# --- a small episode bag ---------------------------------------------------------------------

N_OBS = 10  # voxel frames at 5 Hz: 2 s
STATE_HZ = 50
VOXELS_AT = [100 + 10 * i for i in range(N_OBS)]


def write_episode_bag(path: Path, t0_ns: int = T0_NS, task: str = "pick_cube", with_bad_chunk: bool = True) -> dict:
    """An episode with every topic the viz shows; returns what was written (counts, stamps)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    f = rosbags_factory()
    ts = f.typestore
    messages: list[tuple[str, str, int, object]] = [
        ("/tf_static", "tf2_msgs/msg/TFMessage", t0_ns, tf_static_msg(t0_ns, f, shift=0.01))
    ]
    for i in range(N_OBS):
        t = t0_ns + i * 200_000_000
        messages.append(
            ("/voxels", "sensor_msgs/msg/PointCloud2", t + 30_000_000, voxel_msg(VOXELS_AT[i], t, f, seed=i))
        )
        messages.append(
            (
                "/franka/command_chunk",
                "trajectory_msgs/msg/MultiDOFJointTrajectory",
                t + 150_000_000,
                chunk_msg(i * 0.2, t, f),
            )
        )
        messages.append(
            (
                "/diagnostics",
                "diagnostic_msgs/msg/DiagnosticArray",
                t + 160_000_000,
                diagnostics_msg(120.0 + i, t + 160_000_000, f),
            )
        )
        messages.append(
            ("/cameras/cam_front/points", "sensor_msgs/msg/PointCloud2", t + 10_000_000, camera_cloud_msg(2000, t, f))
        )
    for i in range(N_OBS * 200_000_000 // (NS_PER_S // STATE_HZ)):
        t = t0_ns + i * (NS_PER_S // STATE_HZ)
        T = tcp_pose(i / STATE_HZ)
        messages.append(("/franka/ee_pose", "geometry_msgs/msg/PoseStamped", t + 1_000_000, pose_msg(T, t, f)))
        messages.append(
            (
                "/franka/joint_states",
                "sensor_msgs/msg/JointState",
                t + 1_000_000,
                joint_state_msg(0.08 - 0.0001 * i, t, f),
            )
        )
        messages.append(
            (
                "/franka/executed_target",
                "geometry_msgs/msg/PoseStamped",
                t + 2_000_000,
                pose_msg(tcp_pose(i / STATE_HZ + 0.1), t, f),
            )
        )
    if with_bad_chunk:  # a NaN chunk must be dropped and counted, not stop the conversion
        bad = chunk_msg(0.0, t0_ns + 1_000_000_000, f)
        bad.points[3].transforms[0].translation.x = float("nan")
        messages.append(
            ("/franka/command_chunk", "trajectory_msgs/msg/MultiDOFJointTrajectory", t0_ns + 1_050_000_000, bad)
        )
    messages.sort(key=lambda m: m[2])
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.set_custom_data("task", task)
        writer.set_custom_data("operator", "viz-test")
        writer.set_custom_data("success", "true")
        conns = {}
        for topic, msgtype, _, _ in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for topic, msgtype, t, msg in messages:
            writer.write(conns[topic], t, ts.serialize_cdr(msg, msgtype))
    n_state = N_OBS * 200_000_000 // (NS_PER_S // STATE_HZ)
    return {
        "t0": t0_ns,
        "voxel_stamps": [t0_ns + i * 200_000_000 for i in range(N_OBS)],
        "n_state": n_state,
        "state_last": t0_ns + (n_state - 1) * (NS_PER_S // STATE_HZ),
    }


@pytest.fixture(scope="module")
def episode_bags(tmp_path_factory) -> tuple[list[Path], list[dict]]:
    root = tmp_path_factory.mktemp("bags")
    bags, written = [], []
    for i in range(2):
        bag = root / f"episode_{i:04d}"
        written.append(write_episode_bag(bag, t0_ns=T0_NS + i * 60 * NS_PER_S, task=f"task_{i}"))
        bags.append(bag)
    return bags, written


# --- bag -> .rrd ---------------------------------------------------------------------------


def test_converted_bag_has_expected_entities_counts_and_time_range(episode_bags, tmp_path):
    bags, written = episode_bags
    out = tmp_path / "one.rrd"
    report = convert_bags(bags[:1], out, LAB, EVERYTHING)
    assert report.ok, [e.error for e in report.episodes]
    ep = report.episodes[0]
    assert ep.dropped == {"chunk": 1}  # the NaN chunk
    w = written[0]
    s = summarize_rrd(out, count_instances=("Boxes3D:centers", "Points3D:positions", "LineStrips3D:strips"))
    assert s.has_blueprint and s.recording_ids == ["one"]

    voxels = s["world/voxels"]
    assert voxels.rows == N_OBS and voxels.static_rows == 1  # half-sizes once, static
    assert voxels.instances["Boxes3D:centers"] == VOXELS_AT
    assert voxels.time_range_ns("ros_time") == (w["voxel_stamps"][0], w["voxel_stamps"][-1])
    assert voxels.time_range_ns("episode") == (0, 0)

    assert s["world/ee"].rows == w["n_state"]
    assert s["world/ee"].time_range_ns() == (w["t0"], w["state_last"])
    assert s["world/ee_trail"].rows == w["n_state"] + 1  # + the Clear at the episode start
    assert s["world/executed_target"].rows == w["n_state"]
    assert s["metrics/gripper_width/measured"].rows == w["n_state"]

    assert s["world/chunk/path"].rows == N_OBS
    assert s["world/chunk/steps"].instances["Points3D:positions"] == [8] * N_OBS
    assert s["world/chunk/gripper"].instances["LineStrips3D:strips"][-1] == 8
    assert s["metrics/gripper_width/commanded"].rows == N_OBS

    assert s["metrics/latency/inference"].rows == N_OBS
    assert s["metrics/latency/obs_to_cmd"].rows == N_OBS
    assert s["metrics/observation_age/policy"].rows == N_OBS
    assert s["metrics/observation_age/voxels_on_arrival"].rows == N_OBS
    assert s["diagnostics/policy_node_inference/skipped_cycles"].rows == N_OBS
    assert "diagnostics/policy_node_inference/backend" not in s  # text values have no time series

    clouds = s["world/cameras/cam_front/points"]
    assert clouds.rows == N_OBS
    assert clouds.instances["Points3D:positions"] == [2000 - 40] * N_OBS  # NaN holes dropped
    for cam in LAB.cameras:  # lab.yaml at the episode start, then the bag's /tf_static (same t0)
        entity = s[f"world/cameras/{cam.name}"]
        assert entity.rows == 2 and entity.time_range_ns() == (w["t0"], w["t0"])
        assert "TransformAxes3D:axis_length" in entity.static_components
        assert "Transform3D:translation" not in entity.static_components  # static would shadow /tf_static
    assert s["episode/info"].rows == 1


def test_converted_transforms_and_values_match_the_bag(episode_bags, tmp_path):
    """Values, not just counts: read component columns back and compare with what was written."""
    from rerun.chunk import RrdReader

    bags, _ = episode_bags
    out = tmp_path / "values.rrd"
    assert convert_bags(bags[:1], out, LAB, EVERYTHING).ok
    by_entity: dict[str, list] = {}
    for chunk in RrdReader(out).stream():
        if not chunk.is_static:
            by_entity.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    front = [
        np.array(t, dtype=float).reshape(-1)
        for b in by_entity["/world/cameras/cam_front"]
        for t in b.column("Transform3D:translation").to_pylist()
    ]
    configured = np.array(LAB.camera("cam_front").extrinsics.translation)
    np.testing.assert_allclose(sorted(front, key=lambda t: t[0]), [configured, configured + [0.01, 0, 0]], atol=1e-6)
    widths = np.concatenate(
        [
            np.array(b.column("Scalars:scalars").to_pylist(), dtype=float).reshape(-1)
            for b in by_entity["/metrics/gripper_width/commanded"]
        ]
    )
    np.testing.assert_allclose(widths, 0.08)  # step 0 of every chunk
    inference = np.sort(
        np.concatenate(
            [
                np.array(b.column("Scalars:scalars").to_pylist(), dtype=float).reshape(-1)
                for b in by_entity["/metrics/latency/inference"]
            ]
        )
    )
    np.testing.assert_allclose(inference, 120.0 + np.arange(N_OBS), atol=1e-3)


def test_all_in_one_has_episode_timeline_and_per_episode_writes_one_file_each(episode_bags, tmp_path):
    bags, written = episode_bags
    both = tmp_path / "both.rrd"
    report = convert_bags(bags, both, LAB, VizConfig())
    assert report.ok and [e.logged["voxels"] for e in report.episodes] == [N_OBS, N_OBS]
    s = summarize_rrd(both)
    voxels = s["world/voxels"]
    assert voxels.rows == 2 * N_OBS
    assert voxels.time_range_ns("episode") == (0, 1)
    assert voxels.time_range_ns("ros_time") == (written[0]["voxel_stamps"][0], written[1]["voxel_stamps"][-1])
    # episode_time overlays episodes: both start at their first message
    lo, hi = voxels.time_range_ns("episode_time")
    assert 0 <= lo < 0.1 * NS_PER_S and hi < 2 * NS_PER_S
    assert s["episode/info"].rows == 2
    # default VizConfig throttles 50 Hz state to 20 Hz and does not show raw clouds
    assert s["world/ee"].rows < 0.5 * sum(w["n_state"] for w in written)
    assert "world/cameras/cam_front/points" not in s

    out_dir = tmp_path / "per_episode"
    report = convert_bags(bags, out_dir, LAB, VizConfig(), per_episode=True)
    assert report.ok and sorted(p.name for p in report.outputs) == ["episode_0000.rrd", "episode_0001.rrd"]
    for bag, w in zip(bags, written):
        s = summarize_rrd(out_dir / f"{bag.name}.rrd")
        assert s.recording_ids == [bag.name] and s.has_blueprint
        assert s["world/voxels"].time_range_ns("ros_time") == (w["voxel_stamps"][0], w["voxel_stamps"][-1])


def test_unreadable_bag_is_reported_and_the_others_still_convert(episode_bags, tmp_path):
    bags, _ = episode_bags
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}\n")
    missing = tmp_path / "does_not_exist"
    out = tmp_path / "mixed.rrd"
    report = convert_bags([corrupt, bags[0], missing], out, LAB, VizConfig())
    assert not report.ok
    errors = [e.error for e in report.episodes]
    assert "unreadable bag" in errors[0] and errors[1] is None and "no such bag" in errors[2]
    assert summarize_rrd(out)["world/voxels"].rows == N_OBS
    per = tmp_path / "per"
    report = convert_bags([corrupt, bags[0]], per, LAB, VizConfig(), per_episode=True)
    assert [p.name for p in report.outputs] == ["episode_0000.rrd"]
    assert not (per / "corrupt.rrd").exists()  # no empty file that looks like a converted episode


def test_malformed_live_messages_are_dropped_and_counted(tmp_path):
    f = rosbags_factory()
    rec = open_recording("bad", save=tmp_path / "bad.rrd")
    logger = RerunLogger(rec, LAB, VizConfig())
    logger.log_static_scene()
    short = voxel_msg(50, T0_NS, f)
    short.data = short.data[:-5]
    assert not logger.log_voxels(short)
    pose = pose_msg(tcp_pose(0.0), T0_NS, f)
    pose.pose.orientation.w = 3.0  # not a unit quaternion
    assert not logger.log_ee_pose(pose)
    assert logger.log_voxels(voxel_msg(50, T0_NS, f))
    empty = voxel_msg(0, T0_NS + 1, f)  # an empty workspace is valid
    assert logger.log_voxels(empty)
    assert dict(logger.errors) == {"voxels": 1, "ee_pose": 1}
    assert "does not" in logger.last_error or "unit" in logger.last_error
    rec.flush()
    rec.disconnect()
    s = summarize_rrd(tmp_path / "bad.rrd", count_instances=("Boxes3D:centers",))
    assert s["world/voxels"].instances["Boxes3D:centers"] == [50, 0]


def test_throttling_uses_message_time():
    from equidiff_core.viz.logger import _Throttle, _Trail

    th = _Throttle(20.0)  # 50 ms
    passed = [t for t in range(0, 1_000_000_000, 10_000_000) if th.ready("ee", t)]
    assert len(passed) == 20 and np.all(np.diff(passed) == 50_000_000)
    assert th.ready("ee", 0)  # time went back (next episode): passes again
    trail = _Trail(1_000_000_000)
    for i in range(300):
        pts = trail.add(i * 10_000_000, np.array([i, 0.0, 0.0]))
    assert len(pts) == 101 and pts[0, 0] == 199


def test_missing_rerun_names_the_install_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(VizUnavailable, match=r"equidiff_ros\[viz\]"):
        require_rerun()
    monkeypatch.delitem(sys.modules, "equidiff_core.viz.training_callback", raising=False)
    with pytest.raises(ImportError, match=r"equidiff_ros\[viz\]"):  # what `equidiff train --rerun` catches
        import equidiff_core.viz.training_callback  # noqa: F401
    from equidiff_ros.commands import viz as viz_command

    parser = __import__("argparse").ArgumentParser()
    viz_command.add_arguments(parser)
    assert viz_command.run(parser.parse_args(["some_bag", "-o", "x.rrd"])) == 2


def test_nodes_and_core_import_without_rerun():
    """rerun is optional at run time: the live node module and core viz import without it."""
    code = (
        "import sys; sys.modules['rerun'] = None; import equidiff_core.viz, equidiff_ros.viz_node; "
        "import equidiff_ros.commands.viz; print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr


def test_cli_converts_bags(episode_bags, tmp_path):
    from equidiff_ros.cli import main

    bags, _ = episode_bags
    out = tmp_path / "cli.rrd"
    assert main(["viz", str(bags[0].parent), "-o", str(out)]) == 0  # a folder of bags
    assert summarize_rrd(out)["world/voxels"].time_range_ns("episode") == (0, 1)
    assert main(["viz", str(bags[0]), "-o", str(tmp_path / "dir"), "--per-episode"]) == 0
    assert (tmp_path / "dir" / "episode_0000.rrd").is_file()
    assert main(["viz", str(tmp_path / "nope"), "-o", str(tmp_path / "x.rrd")]) == 1
    assert not (tmp_path / "x.rrd").exists()


def test_cli_never_clobbers_an_output(episode_bags, tmp_path, capsys):
    """An existing -o is refused (left byte-identical) unless --force; a conversion that fails leaves it
    as it was and no temporary beside it; per-episode names same-named bags apart."""
    from equidiff_ros.cli import main

    bags, _ = episode_bags
    out = tmp_path / "kept.rrd"
    out.write_bytes(b"an earlier recording")
    assert main(["viz", str(bags[0]), "-o", str(out)]) == 2
    assert f"{out} exists; not replacing it" in capsys.readouterr().err
    assert main(["viz", str(tmp_path / "nope"), "-o", str(out), "--force"]) == 1  # nothing converted
    assert out.read_bytes() == b"an earlier recording"
    assert main(["viz", str(bags[0]), "-o", str(out), "--force"]) == 0
    assert summarize_rrd(out)["world/voxels"].rows == N_OBS

    day1, day2 = tmp_path / "day1" / bags[0].name, tmp_path / "day2" / bags[0].name
    shutil.copytree(bags[0], day1)
    shutil.copytree(bags[0], day2)
    per = tmp_path / "per"
    assert main(["viz", str(day1), str(day2), "-o", str(per), "--per-episode"]) == 0
    assert sorted(p.name for p in per.iterdir()) == [f"day1__{bags[0].name}.rrd", f"day2__{bags[0].name}.rrd"]
    before = {p.name: p.read_bytes() for p in per.iterdir()}
    assert main(["viz", str(day1), "-o", str(per), "--per-episode"]) == 2
    assert main(["viz", str(tmp_path / "nope"), "-o", str(per), "--per-episode", "--force"]) == 1
    assert {p.name: p.read_bytes() for p in per.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["day1", "day2", "kept.rrd", "per"]  # no temporaries


def test_voxel_logging_keeps_up_with_a_dense_grid(tmp_path):
    """~10k occupied voxels at 5 Hz must cost the live graph little: time decode + log per frame."""
    f = rosbags_factory()
    msgs = [voxel_msg(10_000, T0_NS + i * 200_000_000, f, seed=i) for i in range(20)]
    rec = open_recording("perf", save=tmp_path / "perf.rrd")
    logger = RerunLogger(rec, LAB, VizConfig())
    logger.log_static_scene()
    t0 = time.perf_counter()
    for m in msgs:
        logger.log_voxels(m)
    per_frame_ms = (time.perf_counter() - t0) / len(msgs) * 1e3
    rec.flush()
    rec.disconnect()
    print(f"voxel frame (10k boxes) decode+log: {per_frame_ms:.2f} ms")
    assert per_frame_ms < 40, per_frame_ms  # 200 ms budget per frame at 5 Hz; typically a few ms
    assert summarize_rrd(tmp_path / "perf.rrd")["world/voxels"].rows == 20


def test_sample_bag_converts_if_present(tmp_path):
    bags = sorted(p for p in (ROOT / "bags").glob("*") if (p / "metadata.yaml").is_file())
    if not bags:
        pytest.skip("no sample bag under bags/ in this checkout")
    out = tmp_path / "sample.rrd"
    report = convert_bags(bags[:1], out, LAB, VizConfig())
    assert report.ok, report.episodes[0].error
    s = summarize_rrd(out)
    assert s["world/voxels"].rows == report.episodes[0].logged["voxels"] > 0
    assert s["world/ee"].rows > 0


# --- training views ------------------------------------------------------------------------


def _fake_sample(rng, horizon: int = 16) -> dict:
    poses = np.stack([tcp_pose(0.1 * i) for i in range(horizon)])
    gt = geometry.pose_to_action(poses, np.linspace(0.08, 0.03, horizon))
    pred = gt + np.concatenate([rng.normal(0, 0.01, (horizon, 3)), np.zeros((horizon, 7))], axis=1)
    return {"pred": pred.astype(np.float32), "gt": gt.astype(np.float32), "ee": gt[0].astype(np.float32)}


def test_training_callback_logs_loss_curves_and_sampled_chunks(tmp_path):
    from equidiff_core.viz.training_callback import RerunTrainingCallback

    rng = np.random.default_rng(0)
    cb = RerunTrainingCallback(tmp_path / "train.rrd", max_samples=2)
    losses = []
    for step in range(1, 31):
        losses.append(1.0 / step)
        cb.on_step(step, {"step": step, "loss": losses[-1], "lr": 1e-4, "note": "text is skipped"})
        if step % 10 == 0:
            samples = [_fake_sample(rng) for _ in range(3)]  # one more than max_samples
            if step == 20:
                samples[1]["pred"][:] = np.nan  # a diverged sample: reported, not fatal
            cb.on_eval(step, {"val_loss": 0.5 / step, "val_pos_err_m": 0.01, "step": step}, samples)
    cb.on_end(None)
    s = summarize_rrd(tmp_path / "train.rrd", count_instances=("Points3D:positions",))
    assert s.has_blueprint
    assert s["train/loss"].rows == 30 and s["train/loss"].time_range_ns("step") == (1, 30)
    assert "train/note" not in s and "train/step" not in s
    assert s["eval/val_loss"].rows == 3
    assert s["samples/0/pred/path"].rows == 3 and s["samples/0/gt/path"].rows == 3
    assert s["samples/0/pred/steps"].instances["Points3D:positions"] == [16] * 3
    assert s["samples/1/pred/path"].rows == 2 and s["samples/1/error"].rows == 1
    assert "samples/2/pred/path" not in s  # max_samples
    assert s["eval/samples/0/pos_err_mm"].rows == 3


@pytest.mark.slow
def test_training_callback_with_the_real_trainer(tmp_path):
    """`training.loop.train` drives the callback through its protocol (tiny preset, a handful of steps)."""
    training = pytest.importorskip("equidiff_core.training.loop")
    import torch

    from equidiff_core.policy.diffusion import make_policy
    from equidiff_core.policy.presets import get_preset
    from equidiff_core.training.config import TrainConfig
    from equidiff_core.viz.training_callback import RerunTrainingCallback

    preset = get_preset("tiny")
    policy = make_policy("baseline", preset, LAB.workspace)
    rng = np.random.default_rng(0)
    samples = []
    for i in range(8):
        s = _fake_sample(rng, preset.horizon)
        vox = torch.from_numpy(voxel_grid(200, seed=i))[None].expand(preset.n_obs_steps, -1, -1, -1, -1)
        samples.append(
            {
                "voxels": vox.contiguous(),
                "ee": torch.from_numpy(s["ee"])[None].repeat(preset.n_obs_steps, 1),
                "action": torch.from_numpy(s["gt"]),
            }
        )
    cfg = TrainConfig(
        steps=4,
        batch_size=4,
        warmup_steps=1,
        eval_every=2,
        eval_samples=2,
        val_batches=1,
        checkpoint_every=0,
        log_every=1,
        device="cpu",
    )
    cb = RerunTrainingCallback(tmp_path / "train.rrd", max_samples=2)
    training.train(policy, samples, samples[:4], cfg, tmp_path / "run", callbacks=[cb])
    assert cb.closed  # on_end closed the recording
    s = summarize_rrd(tmp_path / "train.rrd")
    assert s["train/loss"].rows == 4 and s["eval/val_loss"].rows == 2
    assert s["samples/0/pred/path"].rows == 2 and s["samples/1/gt/path"].rows == 2


def test_throttle_keeps_the_requested_rate_for_uneven_input():
    from equidiff_core.viz.logger import _Throttle

    th = _Throttle(20.0)
    passed = [t for t in range(0, 2_000_000_000, 20_000_000) if th.ready("ee", t)]  # 50 Hz in
    assert len(passed) == 40  # 20 Hz out over 2 s, not every third message (34)
    gap = [t for t in (5_000_000_000, 5_020_000_000, 5_040_000_000, 5_060_000_000) if th.ready("ee", t)]
    assert gap == [5_000_000_000, 5_060_000_000]  # after a gap in the data: restart, no burst


@pytest.mark.slow
def test_equidiff_train_logs_to_rerun(tmp_path):
    """End to end: `equidiff train --rerun FILE.rrd` on the sample bag (tiny preset, 4 steps)."""
    bags = sorted(p for p in (ROOT / "bags").glob("*") if (p / "metadata.yaml").is_file())
    if not bags:
        pytest.skip("no sample bag under bags/ in this checkout")
    out = tmp_path / "train.rrd"
    cmd = [
        sys.executable,
        "-m",
        "equidiff_ros.cli",
        "train",
        str(bags[0]),
        "--out",
        str(tmp_path / "run"),
        "--policy",
        "baseline",
        "--preset",
        "tiny",
        "--steps",
        "4",
        "--batch-size",
        "4",
        "--eval-every",
        "2",
        "--no-progress",
        "--rerun",
        str(out),
    ]
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=300, env={**__import__("os").environ, "OMP_NUM_THREADS": "1"}
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    s = summarize_rrd(out)
    assert s["train/loss"].rows == 4 and s["train/loss"].time_range_ns("step") == (1, 4)
    assert s["eval/val_loss"].rows == 2
    assert s["samples/0/pred/path"].rows == 2 and s["samples/0/gt/path"].rows == 2


def test_bag_conversion_needs_no_ros(episode_bags, tmp_path):
    """`equidiff viz BAG -o out.rrd` with rclpy and every ROS message package made unimportable."""
    bags, _ = episode_bags
    out = tmp_path / "noros.rrd"
    code = (
        "import sys\n"
        "for m in ('rclpy', 'sensor_msgs', 'geometry_msgs', 'std_msgs', 'trajectory_msgs', 'diagnostic_msgs',"
        " 'tf2_msgs', 'builtin_interfaces'):\n    sys.modules[m] = None\n"
        "from equidiff_ros.cli import main\n"
        f"sys.exit(main(['viz', {str(bags[0])!r}, '-o', {str(out)!r}]))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert summarize_rrd(out)["world/voxels"].rows == N_OBS


def test_viewer_address_forms():
    from equidiff_core.viz.recording_setup import grpc_url

    assert grpc_url("10.0.0.5:9877") == "rerun+http://10.0.0.5:9877/proxy"
    assert grpc_url("viewer-host") == "rerun+http://viewer-host:9876/proxy"
    assert grpc_url("rerun+http://h:1/proxy") == "rerun+http://h:1/proxy"
    with pytest.raises(ValueError, match="exactly one"):
        open_recording("x", spawn=True, save="x.rrd")


def test_voxel_box_size_follows_the_message_not_a_mismatched_lab_config(tmp_path):
    f = rosbags_factory()
    rec = open_recording("size", save=tmp_path / "size.rrd")
    logger = RerunLogger(rec, LAB, VizConfig())
    logger.log_static_scene()
    grid = voxel_grid(300, seed=3)
    other_size = LAB.workspace.voxel_size * 1.5  # recorded with a 0.6 m workspace at 64^3
    assert logger.log_voxels(grid_to_voxel_msg(grid, LAB.workspace.lower, other_size, T0_NS, "fr3_link0", f))
    assert logger.log_voxels(voxel_msg(300, T0_NS + 1, f))  # checked once, not per frame
    assert len(logger.warnings) == 1 and "9.38 mm" in logger.warnings[0]
    rec.flush()
    rec.disconnect()
    from rerun.chunk import RrdReader

    half_sizes = [
        np.array(b.column("Boxes3D:half_sizes").to_pylist(), dtype=float).reshape(-1, 3)
        for c in RrdReader(tmp_path / "size.rrd").stream()
        if c.is_static and c.entity_path == "/world/voxels"
        for b in [c.to_record_batch()]
        if "Boxes3D:half_sizes" in b.schema.names
    ]
    sizes = sorted(float(h[0, 0]) for h in half_sizes)
    np.testing.assert_allclose(sizes, [LAB.workspace.voxel_size / 2, other_size / 2], rtol=1e-5)


def test_recorded_camera_images_are_logged_as_the_jpegs_they_are(tmp_path):
    sys.path.insert(0, str(ROOT / "test"))
    from helpers_data import SyntheticEpisode, write_synthetic_episode

    from equidiff_core.data.bags import read_episode
    from equidiff_core.data.recording import RecordingConfig
    from equidiff_core.wire.topics import camera_color_topic

    bag = write_synthetic_episode(
        tmp_path / "ep_0000", SyntheticEpisode(duration_s=2.0), config=RecordingConfig(min_free_gib=0)
    )
    out = tmp_path / "images.rrd"
    report = convert_bags([bag], out, LAB)
    assert report.ok and report.episodes[0].logged["images"] == 3 * 10
    s = summarize_rrd(out)
    topic = camera_color_topic("cam_left")
    recorded = read_episode(bag, topics=[topic])[topic]
    for cam in LAB.cameras:
        images = s[f"images/{cam.name}"]
        assert images.rows == 10
        assert images.time_range_ns("ros_time") == (int(recorded.header_ns()[0]), int(recorded.header_ns()[-1]))
    # the blob is the recorded JPEG itself, not a re-encoding
    from rerun.chunk import RrdReader

    blobs = [
        bytes(row[0])
        for chunk in RrdReader(out).stream()
        if chunk.entity_path == "/images/cam_left" and not chunk.is_static
        for row in chunk.to_record_batch().column("EncodedImage:blob").to_pylist()
    ]
    assert sorted(blobs) == sorted(bytes(m.data) for m in recorded.messages)
    # images off: none logged
    off = convert_bags([bag], tmp_path / "off.rrd", LAB, VizConfig(images=False))
    assert "images" not in off.episodes[0].logged

    # a corrupt or mislabelled image is dropped and counted, never logged
    f = rosbags_factory()
    rec = open_recording("bad", save=tmp_path / "bad.rrd")
    logger = RerunLogger(rec, LAB, VizConfig())
    good = recorded.messages[0]
    assert logger.log_message(topic, good, 1)
    not_jpeg = f.make(
        "sensor_msgs/msg/CompressedImage", header=good.header, format=good.format, data=np.arange(40, dtype=np.uint8)
    )
    assert not logger.log_message(topic, not_jpeg, 2)
    unknown = f.make("sensor_msgs/msg/CompressedImage", header=good.header, format="theora", data=good.data)
    assert not logger.log_message(topic, unknown, 3)
    assert dict(logger.errors) == {"images": 2} and logger.logged["images"] == 1
    rec.flush()
    rec.disconnect()


def test_the_policys_doubt_is_a_time_series_at_each_chunks_stamp(tmp_path):
    from equidiff_core.policy.doubt import ChunkDoubt
    from equidiff_core.wire.rosmsg import doubt_msg
    from equidiff_core.wire.topics import TOPIC_POLICY_DOUBT

    f = rosbags_factory()
    rec = open_recording("doubt", save=tmp_path / "doubt.rrd")
    logger = RerunLogger(rec, LAB, VizConfig())
    stamps = [T0_NS + i * 200_000_000 for i in range(3)]
    doubts = [
        ChunkDoubt(stamps[0], float("nan"), 0.01),
        ChunkDoubt(stamps[1], 0.02, 0.01),
        ChunkDoubt(stamps[2], 0.05, 0.02),
    ]
    assert all(logger.log_message(TOPIC_POLICY_DOUBT, doubt_msg(f, d)) for d in doubts)
    bad = doubt_msg(f, doubts[1])
    bad.vector.y = -1.0
    assert not logger.log_message(TOPIC_POLICY_DOUBT, bad)
    assert logger.errors["doubt"] == 1
    rec.flush()
    rec.disconnect()
    s = summarize_rrd(tmp_path / "doubt.rrd")
    assert s["metrics/doubt/spread"].rows == 3
    assert s["metrics/doubt/disagreement"].rows == 2  # the first chunk has nothing to disagree with
    assert s["metrics/doubt/disagreement"].time_range_ns("ros_time") == (stamps[1], stamps[2])
