"""The operator flow: `equidiff lab` against live nodes, teleop takeover
marked in the episode, and the policy's enable/pause gate."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers_data import RosHarness, decoded
from helpers_model import export_tiny_baseline
from helpers_ros import spawn_node, stop_node

from equidiff_core import geometry
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.data.recording import InterventionLog

LAB = load_lab_config(default_config_dir() / "lab.yaml")
S = 1_000_000_000


def lab_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "equidiff_ros.cli", "lab", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
    )


def test_intervention_log_lists_each_takeover_from_the_episode_start():
    log = InterventionLog(start_ns=10 * S)
    log.update(False, 10 * S)  # not driving at the start: nothing
    log.update(True, 11 * S)
    log.update(True, 12 * S)  # still the same takeover
    log.update(False, 13 * S + S // 2)
    log.update(True, 20 * S)  # ongoing when the episode ends
    assert log.metadata(end_ns=21 * S) == {"interventions": "1.00-3.50 10.00-11.00", "intervention_count": "2"}
    already = InterventionLog(start_ns=5 * S)
    already.update(True, 4 * S)  # driving before the episode began: counts from its start
    assert already.metadata(end_ns=6 * S)["interventions"] == "0.00-1.00"


@pytest.mark.ros
@pytest.mark.slow
def test_lab_cli_records_an_episode_with_a_teleop_takeover(ros_domain, tmp_path):
    from rosbags.rosbag2 import Reader

    from equidiff_core.data.bags import read_episode
    from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS

    out = tmp_path / "episodes"
    ros = RosHarness()
    recorder = spawn_node("recorder_node", f"output_dir:={out}", "task:=lab", "min_free_gib:=0.0")
    teleop = spawn_node("teleop_node", "source:=joy", "rate_hz:=100.0", "resync_after_s:=0.5")
    try:
        f = ros.f
        pose_pub = ros.node.create_publisher(f.cls("geometry_msgs/msg/PoseStamped"), "/franka/ee_pose", RELIABLE_QOS)
        joy_pub = ros.node.create_publisher(f.cls("sensor_msgs/msg/Joy"), "/spacenav/joy", SENSOR_QOS)
        active: list[bool] = []
        ros.node.create_subscription(
            f.cls("std_msgs/msg/Bool"), "/teleop/active", lambda m: active.append(m.data), LATCHED_QOS
        )
        assert ros.spin_until(lambda: active == [False] and joy_pub.get_subscription_count() > 0, 30.0), stop_node(
            teleop
        )
        p, q = geometry.pos_quat_from_pose(geometry.make_pose(np.diag([1.0, -1, -1]), [0.45, 0.0, 0.2]))
        pose = f.make(
            "geometry_msgs/msg/PoseStamped",
            header=f.header(0, LAB.base_frame),
            pose=f.make(
                "geometry_msgs/msg/Pose",
                position=f.make("geometry_msgs/msg/Point", x=p[0], y=p[1], z=p[2]),
                orientation=f.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )

        started = lab_cli("record", "start")
        assert started.returncode == 0, started.stderr
        episode = Path(started.stdout.strip())
        assert episode.parent == out

        def drive(axes, seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                pose_pub.publish(pose)
                joy_pub.publish(
                    f.make(
                        "sensor_msgs/msg/Joy",
                        header=f.header(ros.node.get_clock().now().nanoseconds, ""),
                        axes=[float(a) for a in axes],
                        buttons=[0, 0],
                    )
                )
                ros.spin_for(0.02)

        drive([0.0] * 6, 0.5)  # input inside the deadzone is no takeover
        assert active == [False]
        drive([0.6, 0, 0, 0, 0, 0], 0.6)
        assert ros.spin_until(lambda: active[-1] is True, 10.0), active
        drive([0.0] * 6, 0.2)
        assert ros.spin_until(lambda: active[-1] is False, 10.0), active  # let go: resync_after_s later
        ros.spin_for(0.5)  # the recorder has the edge before the episode is closed

        status = lab_cli("status", "--json")
        assert status.returncode == 0 and f'"recording {episode}"' in status.stdout, status.stdout
        kept = lab_cli("record", "failure")
        assert kept.returncode == 0, kept.stderr
        again = lab_cli("record", "discard")  # nothing to discard now: a clear refusal, exit 1
        assert again.returncode == 1 and "not recording" in again.stderr
    finally:
        logs = stop_node(teleop) + stop_node(recorder)
        ros.close()
    ep = read_episode(episode)
    assert ep.meta.success is False and ep.meta.task == "lab"
    assert ep.meta.extra["intervention_count"] == "1", logs
    start_s, end_s = (float(v) for v in ep.meta.extra["interventions"].split("-"))
    assert 0.4 < start_s < end_s
    with Reader(episode) as reader:
        marks = [
            decoded(raw, conn.msgtype).data for conn, _t, raw in reader.messages() if conn.topic == "/teleop/active"
        ]
    assert marks[-2:] == [True, False]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return export_tiny_baseline(tmp_path_factory.mktemp("policy") / "policy.pt")


@pytest.mark.ros
@pytest.mark.slow
def test_policy_publishes_nothing_until_enabled_and_a_takeover_pauses_it(ros_domain, checkpoint, tmp_path):
    import signal
    import threading

    from std_msgs.msg import Bool, String

    from equidiff_core.twin.processes import start_node, stop_process
    from equidiff_core.wire.pointcloud import grid_to_voxel_msg
    from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS
    from equidiff_ros.control_client import ControlClient

    lab_path = str(default_config_dir() / "lab.yaml")
    ws = LAB.workspace
    grid = np.zeros((4, ws.resolution, ws.resolution, ws.resolution), np.uint8)
    grid[:, 20:26, 30:36, 2:8] = 200
    stop = threading.Event()
    franka = policy = client = None
    skipped: list[str] = []
    state: list[str] = []
    try:
        franka = start_node("franka_node", {"backend": "dryrun", "lab_config": lab_path}, tmp_path / "franka.log")
        policy = start_node(
            "policy_node",
            {
                "checkpoint": str(checkpoint),
                "lab_config": lab_path,
                "seed": 0,
                "execute_steps": 1,
                "start_paused": True,
            },
            tmp_path / "policy.log",
        )
        client = ControlClient(LAB, lab_path)
        client.node.create_subscription(
            String, "/policy/skipped", lambda m: skipped.append(json.loads(m.data)["reason"]), RELIABLE_QOS
        )
        client.node.create_subscription(String, "/policy/state", lambda m: state.append(m.data), LATCHED_QOS)
        takeover = client.node.create_publisher(Bool, "/teleop/active", LATCHED_QOS)
        client.wait_for(lambda: len(client.data.poses) > 10, 60.0, "/franka/ee_pose from the dry-run arm", franka)

        def feed():
            while not stop.is_set():
                client.pub_voxels.publish(
                    grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, time.time_ns(), LAB.base_frame, client.factory)
                )
                stop.wait(0.2)

        threading.Thread(target=feed, daemon=True).start()
        client.wait_for(lambda: skipped.count("paused") >= 5, 90.0, "'paused' skips while start_paused", policy)
        assert state and state[-1].startswith("paused") and client.data.last_chunk is None
        client.wait_for(lambda: "policy_node" in client.data.diagnostics, 5.0, "policy diagnostics", policy)
        assert client.data.diagnostics["policy_node"]["state"].startswith("paused")

        enabled = lab_cli("policy", "enable")
        assert enabled.returncode == 0 and "running" in enabled.stdout, enabled.stderr
        client.wait_for(lambda: len(client.data.chunks) >= 3, 60.0, "chunks once enabled", policy)
        assert state[-1] == "running"

        takeover.publish(Bool(data=True))  # the operator moves the SpaceMouse
        client.wait_for(lambda: state[-1] == "paused teleop takeover", 10.0, "the takeover pause", policy)
        n = len(client.data.chunks)
        paused_before = skipped.count("paused")
        client.wait_for(lambda: skipped.count("paused") >= paused_before + 5, 30.0, "'paused' skips", policy)
        assert len(client.data.chunks) <= n + 1  # at most one already on the wire
        takeover.publish(Bool(data=False))  # letting go does not resume it
        time.sleep(1.0)
        assert state[-1] == "paused teleop takeover"
        ack = lab_cli("ack")  # franka_node's acknowledgement service answers (nothing was stopped here)
        assert ack.returncode == 0 and "nothing to acknowledge" in ack.stdout, ack.stderr
        home = lab_cli("home")  # the dry-run arm glides home between episodes
        assert home.returncode == 0 and "homing to" in home.stdout, home.stderr
    finally:
        stop.set()
        if client is not None:
            client.close()
        # 30 s: a hang guard only; an inference in flight on a loaded machine finishes first
        codes = [
            stop_process(policy, timeout=30.0, sig=signal.SIGINT),
            stop_process(franka, timeout=30.0, sig=signal.SIGTERM),
        ]
    assert codes == [0, 0], (tmp_path / "policy.log").read_text()[-3000:]


def spacemouse(stack, lab_path):
    """teleop_node in ``stack`` (a running ``TwinStack``) reading a simulated SpaceMouse on /spacenav/joy:
    ``drive(axes, sim_seconds)`` deflects it for that much sim time, reports stamped on the node clock at ~50 Hz."""
    from equidiff_core.twin.processes import node_command
    from equidiff_ros.common import SENSOR_QOS

    sup = stack.sup
    params = {"lab_config": str(lab_path), "use_sim_time": True, "source": "joy", "resync_after_s": 0.5}
    stack.group.start("teleop_node", node_command("teleop_node", params))
    f = sup.factory
    joy_pub = sup.node.create_publisher(f.cls("sensor_msgs/msg/Joy"), "/spacenav/joy", SENSOR_QOS)
    sup.wait_for(lambda: joy_pub.get_subscription_count() > 0, 60.0, "teleop_node", stack.check)

    def drive(axes, sim_seconds: float) -> None:
        end = sup.now_ns() + int(sim_seconds * S)
        while sup.now_ns() < end:
            header = f.header(sup.now_ns(), "")
            joy_pub.publish(f.make("sensor_msgs/msg/Joy", header=header, axes=[float(a) for a in axes], buttons=[0, 0]))
            stack.check()
            time.sleep(0.02)

    return drive


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.sim
def test_the_operator_flow_drives_the_twin_the_same_way(ros_domain, tmp_path):
    """The operator flow in the twin, on simulated time: `equidiff lab` homes the arm, records an
    episode, pauses and resumes the policy; a SpaceMouse takeover pauses it and is marked in the
    bag; the episode is kept as a success. The same commands and nodes as in the lab."""
    from equidiff_core.control import load_control_config
    from equidiff_core.data.bags import read_episode
    from equidiff_core.twin.config import TwinConfig
    from equidiff_core.twin.standin import make_standin_policy
    from equidiff_ros.twin import TwinStack

    cfg_dir = default_config_dir()
    policy = make_standin_policy(tmp_path / "standin.pt", LAB.workspace, preset="tiny", cfg=TwinConfig())
    home = np.array(load_control_config(cfg_dir / "control.yaml").home_position)
    with TwinStack(
        tmp_path / "run",
        cfg_dir / "lab.yaml",
        cfg_dir / "twin.yaml",
        policy=str(policy),
        task="lab",
        domain_id=221 + (ros_domain + 7) % 12,
        log=lambda s: None,
    ) as stack:
        sup = stack.sup
        drive = spacemouse(stack, cfg_dir / "lab.yaml")

        homed = lab_cli("home")
        assert homed.returncode == 0 and "homing" in homed.stdout, homed.stdout + homed.stderr
        sup.wait_for(
            lambda: np.linalg.norm(sup.current()[0][:3, 3] - home) < 0.01, 120.0, "the arm at home", stack.check
        )
        started = lab_cli("record", "start")
        assert started.returncode == 0, started.stderr
        episode = Path(started.stdout.strip())
        sup.open_gate()  # the twin passes the policy's chunks to the arm, as in an episode

        def state() -> dict:
            status = lab_cli("status", "--json")
            assert status.returncode == 0, status.stderr
            return json.loads(status.stdout)

        sup.wait_for(lambda: sup.chunk_arrivals, 60.0, "a policy chunk", stack.check)
        assert lab_cli("policy", "pause").returncode == 0 and state()["policy"].startswith("paused")
        sup.sim_sleep(0.5, stack.check)  # a chunk in flight may still land
        paused_at = len(sup.chunk_arrivals)
        sup.sim_sleep(2.0, stack.check)
        assert len(sup.chunk_arrivals) == paused_at  # paused: no chunk for 2 s of sim time
        assert lab_cli("policy", "resume").returncode == 0
        sup.wait_for(lambda: len(sup.chunk_arrivals) > paused_at, 60.0, "chunks after resuming", stack.check)

        drive([0.5, 0, 0, 0, 0, 0], 1.0)
        policy_state = state()["policy"]
        assert policy_state.startswith("paused") and "teleop" in policy_state
        drive([0.0] * 6, 1.0)  # let go: the takeover ends, and the policy stays paused until resumed
        sup.sim_sleep(1.0, stack.check)
        assert state()["policy"].startswith("paused")
        kept = lab_cli("record", "success")
        assert kept.returncode == 0, kept.stderr
        sup.close_gate()
    ep = read_episode(episode)
    assert ep.meta.success is True and ep.meta.task == "lab"
    assert ep.meta.extra["intervention_count"] == "1", ep.meta.extra
    assert ep.message_counts.get("/franka/command_chunk", 0) > 0  # the arm's commands were recorded
    assert ep.message_counts.get("/teleop/active", 0) >= 2  # the takeover's start and end


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.sim
def test_in_the_twin_the_gate_asks_for_help_and_the_correction_is_recorded_as_such(ros_domain, tmp_path):
    """The corrections loop live, on simulated time: policy_node's doubt gate (threshold 0, so the second
    chunk already doubts) holds the policy, franka_node holds the arm, a SpaceMouse takes over through
    teleop_node, and the episode's bag holds the policy's, the held and the operator's stretches, which
    ``dataset stats`` counts (docs/corrections.md)."""
    from equidiff_core.data.dataset import dataset_stats
    from equidiff_core.data.episode_arrays import DatasetConfig
    from equidiff_core.data.segments import FrameSource
    from equidiff_core.policy.file import with_doubt_calibration
    from equidiff_core.twin.config import TwinConfig
    from equidiff_core.twin.standin import make_standin_policy
    from equidiff_ros.twin import TwinStack

    cfg_dir = default_config_dir()
    standin = make_standin_policy(tmp_path / "standin.pt", LAB.workspace, preset="tiny", cfg=TwinConfig())
    calibration = {"signal": "disagreement", "samples": 1, "episodes": 1, "values_m": [0.0]}
    policy = with_doubt_calibration(standin, calibration, tmp_path / "gated.pt")
    with TwinStack(
        tmp_path / "run",
        cfg_dir / "lab.yaml",
        cfg_dir / "twin.yaml",
        policy=str(policy),
        task="corrections",
        domain_id=221 + (ros_domain + 3) % 12,
        policy_parameters={"doubt_gate": True, "doubt_quantile": 1.0},
        log=lambda s: None,
    ) as stack:
        sup = stack.sup
        drive = spacemouse(stack, cfg_dir / "lab.yaml")
        started = lab_cli("record", "start")
        assert started.returncode == 0, started.stderr
        episode = Path(started.stdout.strip())
        sup.open_gate()

        def status() -> dict:
            got = lab_cli("status", "--json")
            assert got.returncode == 0, got.stderr
            return json.loads(got.stdout)

        def until(predicate, what: str, timeout_s: float = 120.0) -> None:
            deadline = time.monotonic() + timeout_s
            while not predicate():
                assert time.monotonic() < deadline, f"never {what}: {status()}"
                sup.sim_sleep(0.5, stack.check)

        asking = lambda: status()["policy"].startswith("paused asks for help")
        # its first chunks (the twin's start-up, before the gate opened) already disagree: it asks at once
        until(asking, "asked for help")
        enabled = lab_cli("policy", "enable")  # the operator lets it go on: its next chunk reaches the arm
        assert enabled.returncode == 0, enabled.stderr
        until(lambda: sup.chunk_arrivals, "a chunk reached the arm after the enable")
        until(asking, "asked for help again")
        until(lambda: status()["robot"]["state"] == "holding", "franka_node held")
        asked = len(sup.chunk_arrivals)
        sup.sim_sleep(1.0, stack.check)
        assert len(sup.chunk_arrivals) == asked  # the policy sends nothing while it asks for help

        drive([0.5, 0, 0, 0, 0, 0], 2.0)  # the operator drives 2 s of sim time, then lets go
        sup.sim_sleep(1.5, stack.check)
        kept = lab_cli("record", "success")
        assert kept.returncode == 0, kept.stderr
        sup.close_gate()
    arrays_config = DatasetConfig.for_lab(LAB, horizon=4, n_obs_steps=1, n_action_steps=2)
    stats = dataset_stats([episode], arrays_config)
    assert not stats["skipped"], stats["skipped"]
    row = stats["episodes"][0]
    seconds = row["seconds_by_source"]
    assert seconds["policy"] > 0 and seconds["hold"] > 0 and seconds["operator"] > 0, seconds
    assert row["corrected"] and row["gate_alarms"] >= 1
    assert stats["total"]["episodes_with_corrections"] == 1
    from equidiff_core.data.dataset import load_episode_arrays

    sources = load_episode_arrays(episode, arrays_config).sources.tolist()
    # who drove, in order (stretches, not frames): the policy, then the held arm, then the operator
    stretches = [source for k, source in enumerate(sources) if k == 0 or source != sources[k - 1]]
    order = [FrameSource.POLICY, FrameSource.HOLD, FrameSource.OPERATOR]
    assert stretches[stretches.index(FrameSource.POLICY) :][:3] == order, stretches


class Tmux:
    """A terminal the test types into and reads back: a tmux server of its own (private socket),
    so the program runs on a real tty exactly as an operator's terminal runs it."""

    def __init__(self, socket: Path, command: list[str], stderr: Path, width: int = 200, height: int = 50):
        self.base = ["tmux", "-S", str(socket)]
        self.stderr = stderr
        # the server starts with this process's environment (ROS_DOMAIN_ID, PYTHONPATH): the UI gets it
        shell = f"exec {shlex.join(command)} 2>{shlex.quote(str(stderr))}"
        subprocess.run(
            [*self.base, "new-session", "-d", "-s", "lab", "-x", str(width), "-y", str(height), "sh", "-c", shell],
            check=True,
            env=dict(os.environ, OMP_NUM_THREADS="1"),
        )

    def screen(self) -> str:
        got = subprocess.run([*self.base, "capture-pane", "-p", "-t", "lab"], capture_output=True, text=True)
        return got.stdout

    def press(self, key: str) -> None:
        subprocess.run([*self.base, "send-keys", "-t", "lab", "-l", key], check=True)

    def alive(self) -> bool:
        return subprocess.run([*self.base, "has-session", "-t", "lab"], capture_output=True).returncode == 0

    def wait(self, predicate, what: str, timeout: float = 30.0, check=lambda: None) -> str:
        """The screen once ``predicate(screen)`` holds (``check()`` raises if waiting is pointless);
        AssertionError with the screen and the UI's stderr."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            check()
            screen = self.screen()
            if predicate(screen):
                return screen
            if not self.alive():
                break
            time.sleep(0.2)
        err = self.stderr.read_text(errors="replace")[-3000:] if self.stderr.exists() else ""
        raise AssertionError(f"the screen never showed {what}:\n{self.screen()}\nstderr:\n{err}")

    def close(self) -> None:
        subprocess.run([*self.base, "kill-server"], capture_output=True)


def row(screen: str, label: str) -> str:
    """The screen line of one state row (ROBOT, RECORDER, EPISODES, POLICY, TELEOP, RESET)."""
    return next((line for line in screen.splitlines() if line.startswith(f"{label} ")), "")


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.sim
def test_the_operator_screen_drives_the_nodes(ros_domain, checkpoint, tmp_path):
    """`equidiff lab` in a real terminal (tmux) beside real nodes (franky-sim's arm
    under franka_node, recorder, policy, teleop): keys sent, the screen read back, the effects checked
    on the nodes. franka_node starts after an "unclean exit" (a stale marker), so it holds for an
    acknowledgement where franky-sim put the arm: the acknowledge and the homing are real ones."""
    import shutil
    import signal

    import yaml
    from std_msgs.msg import String

    from equidiff_core.control import load_control_config
    from equidiff_core.data.bags import read_episode
    from equidiff_core.robots.franky.sim import SimServer
    from equidiff_core.twin.processes import start_node, stop_process
    from equidiff_core.wire.topics import TOPIC_FRANKA_STATUS, TOPIC_POLICY_STATE
    from equidiff_ros.common import LATCHED_QOS, SENSOR_QOS
    from equidiff_ros.control_client import ControlClient

    if shutil.which("tmux") is None:
        pytest.skip("tmux is not installed")
    # The lab's config, with a safety box tall enough for franky-sim's start pose (TCP at z 0.52 m):
    # franka_node refuses to stream from outside its box, and this one must start without homing.
    lab_yaml = yaml.safe_load((default_config_dir() / "lab.yaml").read_text())
    lab_yaml["safety_box"]["upper"][2] = 0.6
    lab_path = str(tmp_path / "lab.yaml")
    Path(lab_path).write_text(yaml.safe_dump(lab_yaml))
    home = np.array(load_control_config(default_config_dir() / "control.yaml").home_position)
    out, run_dir = tmp_path / "bags", tmp_path / "run"
    run_dir.mkdir()
    gone = subprocess.Popen(["true"])
    gone.wait()  # its pid: the "previous franka_node", which died without cleaning up
    nodes: dict[str, subprocess.Popen] = {}
    client = ui = None
    with SimServer() as sim:
        # its marker: this franka_node holds where the arm is until acknowledged
        (run_dir / f"franka_node_{sim.host}.pid").write_text(str(gone.pid))
        try:
            ui = Tmux(  # the operator opens the screen while the nodes come up
                tmp_path / "tmux.sock",
                [sys.executable, "-m", "equidiff_ros.cli", "lab", "--reset-s", "600", "--output-dir", str(out)],
                tmp_path / "ui.stderr",
            )
            for name, params in {
                "franka_node": {
                    "robot_ip": sim.host,
                    "realtime": False,
                    "lab_config": lab_path,
                    "run_dir": str(run_dir),
                },
                "recorder_node": {"output_dir": str(out), "task": "lab", "min_free_gib": 0.0, "lab_config": lab_path},
                "policy_node": {  # no jit trace: its warm-up is the slowest start-up here, and it never infers
                    "checkpoint": str(checkpoint),
                    "lab_config": lab_path,
                    "start_paused": True,
                    "jit": False,
                    "precision": "fp32",
                },
                # 2 s without input is letting go: this runner's 50 Hz Joy stream stalled for over 0.5 s
                # beside a running twin, and one takeover was recorded as two
                "teleop_node": {"lab_config": lab_path, "source": "joy", "resync_after_s": 2.0},
            }.items():
                nodes[name] = start_node(name, params, tmp_path / f"{name}.log", priority=name == "franka_node")
            client = ControlClient(LAB, lab_path)

            def at_home() -> bool:
                return bool(client.data.poses) and np.linalg.norm(client.latest_position() - home) < 0.01

            policy_state: list[str] = []
            client.node.create_subscription(
                String, TOPIC_POLICY_STATE, lambda m: policy_state.append(m.data), LATCHED_QOS
            )
            joy_pub = client.node.create_publisher(
                client.factory.cls("sensor_msgs/msg/Joy"), "/spacenav/joy", SENSOR_QOS
            )

            def nodes_alive() -> None:
                for name, proc in nodes.items():
                    assert proc.poll() is None, f"{name} exited: {(tmp_path / f'{name}.log').read_text()[-2000:]}"

            def screen_when(predicate, what, timeout=30.0) -> str:
                return ui.wait(predicate, what, timeout, check=nodes_alive)

            # Every node up: the arm holds for an acknowledgement, nothing records, the policy waits
            screen = screen_when(
                lambda s: (
                    "AWAITING ACK" in row(s, "ROBOT")
                    and "IDLE" in row(s, "RECORDER")
                    and "PAUSED" in row(s, "POLICY")
                    and "idle" in row(s, "TELEOP")
                ),
                "every node's state",
                timeout=120.0,
            )
            if client.node.count_publishers(TOPIC_FRANKA_STATUS) == 0:  # franka_node without the topic
                assert "(no status)" in row(screen, "ROBOT") and "/diagnostics" in row(screen, "ROBOT")
            ui.press("s")
            screen_when(lambda s: "not started: the arm holds until acknowledged" in s, "start refused before the ack")
            ui.press("a")
            screen_when(lambda s: "HOLDING" in row(s, "ROBOT"), "the arm holding after the ack")
            client.wait_for(  # franka_node's own word, on its 1 Hz /diagnostics
                lambda: client.diag_value("franka_node", "awaiting_ack") == "", 10.0, "the ack", nodes["franka_node"]
            )

            assert not at_home()
            ui.press("h")
            screen_when(lambda s: "home the arm: homing to" in s, "the home request answered")
            client.wait_for(at_home, 90.0, "the arm at home", nodes["franka_node"])
            screen_when(lambda s: "HOLDING" in row(s, "ROBOT"), "the arm holding at home")

            ui.press("p")
            screen_when(lambda s: "ON" in row(s, "POLICY"), "the policy on")
            # the screen and this client are two subscribers of the same latched topic: either may hear it first
            client.wait_for(lambda: policy_state[-1:] == ["running"], 10.0, "policy_node's own word: running")
            ui.press("s")
            screen = screen_when(lambda s: "RECORDING" in row(s, "RECORDER"), "an episode recording")
            episode = out / "lab_0000"
            assert str(episode) in row(screen, "RECORDER")

            ui.press("t")  # the SpaceMouse takes over: the policy pauses first
            screen_when(lambda s: "PAUSED" in row(s, "POLICY") and "SpaceMouse has the arm" in s, "the takeover")
            client.wait_for(
                lambda: policy_state[-1:] == ["paused by the operator"], 10.0, "policy_node's own word: paused"
            )

            def drive(axes, seconds):
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    header = client.factory.header(time.time_ns(), "")
                    axes_ = [float(a) for a in axes]
                    joy_pub.publish(
                        client.factory.make("sensor_msgs/msg/Joy", header=header, axes=axes_, buttons=[0, 0])
                    )
                    time.sleep(0.02)

            drive([0.5, 0, 0, 0, 0, 0], 1.0)
            screen_when(lambda s: "SPACEMOUSE DRIVING" in row(s, "TELEOP"), "the SpaceMouse driving")
            drive([0.0] * 6, 0.2)
            client.wait_for(lambda: not at_home(), 30.0, "the SpaceMouse moving the arm away from home")
            screen_when(lambda s: "idle" in row(s, "TELEOP"), "the SpaceMouse let go")

            ui.press("k")
            screen = screen_when(
                lambda s: (
                    "1 kept (1 success" in row(s, "EPISODES")
                    and f"in {out}: 1" in row(s, "EPISODES")  # the folder's count
                    and "reset the scene" in row(s, "RESET")
                    and "IDLE" in row(s, "RECORDER")
                ),
                "the episode kept and the reset countdown",
            )
            client.wait_for(at_home, 90.0, "the arm home again after the episode", nodes["franka_node"])
            screen_when(lambda s: "HOLDING" in row(s, "ROBOT"), "the arm holding after the episode")

            ui.press("s")  # ready before the countdown ends: start now
            screen = screen_when(lambda s: str(out / "lab_0001") in row(s, "RECORDER"), "the second episode")
            assert "-" in row(screen, "RESET") and "reset the scene" not in screen
            ui.press("x")
            screen_when(lambda s: f"delete {out / 'lab_0001'}?" in s, "the discard question")
            ui.press("n")
            screen_when(lambda s: "discard: cancelled" in s, "the discard cancelled")
            assert (out / "lab_0001").is_dir()
            ui.press("x")
            screen_when(lambda s: "delete " in s and "y: yes" in s, "the discard question again")
            ui.press("y")
            screen_when(
                lambda s: "1 discarded" in row(s, "EPISODES") and "reset the scene" in row(s, "RESET"), "discarded"
            )
            assert not (out / "lab_0001").exists()
            ui.press("c")
            screen_when(lambda s: "countdown cancelled" in s and "reset the scene" not in row(s, "RESET"), "cancelled")
            screen_when(lambda s: "HOLDING" in row(s, "ROBOT"), "the arm holding at the end")
            status = subprocess.Popen(  # the scripts' view, from a second client, while the screen quits
                [sys.executable, "-m", "equidiff_ros.cli", "lab", "status", "--json"],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                env=dict(os.environ, OMP_NUM_THREADS="1"),
            )
            ui.press("q")
            deadline = time.monotonic() + 30.0
            while ui.alive() and time.monotonic() < deadline:
                time.sleep(0.2)
            assert not ui.alive(), ui.screen()
            assert "Traceback" not in (tmp_path / "ui.stderr").read_text()
            stdout, stderr = status.communicate(timeout=120)
            assert status.returncode == 0 and json.loads(stdout)["robot"]["state"] == "holding", stdout + stderr
        finally:
            if ui is not None:
                ui.close()
            if client is not None:
                client.close()
            for proc in nodes.values():  # all at once, so they shut down in parallel (once: a second SIGINT kills)
                if proc.poll() is None:
                    proc.send_signal(signal.SIGINT)
            for proc in nodes.values():
                stop_process(proc, timeout=30.0, sig=0)  # 0: wait (and kill after the timeout) only
    ep = read_episode(episode)  # the kept episode, read back
    assert ep.meta.success is True and ep.meta.task == "lab"
    assert ep.message_counts.get("/franka/ee_pose", 0) > 10  # the real arm's state was recorded
    assert ep.meta.extra["intervention_count"] == "1", ep.meta.extra  # the SpaceMouse takeover
    assert "paused by the operator" in [m.data for m in ep["/policy/state"].messages]  # the pause, in the bag
