"""twin_node: the digital twin's robot and its clock. franky-sim (MuJoCo FR3) + the block-in-bowl scene.

Wiring:
  ``twin.sim.TwinSim``: franky-sim's libfranka server on ``host`` (franka_node connects to it
      with ``robot_ip:=<host>``, exactly as to a real FR3), stepped in 1 ms ticks; the MuJoCo
      state goes to shared memory for the twin cameras (camera_node with backend ``twin``, same
      ROS_DOMAIN_ID -> same shared-memory name)
  clock ``sim`` (default): the sim owns time and steps in lockstep with the pipeline
      (``twin.lockstep``: camera frames taken at their instants, a policy chunk in place by its
      observation's time + ``latency_s`` while an episode awaits the policy);
      /clock (rosgraph_msgs/Clock) <- sim time every 5 ms of it; every other twin node runs
      with use_sim_time
  clock ``realtime``: 1 kHz to fixed wall-clock deadlines; no /clock
  /twin/reset (std_msgs/Int64: seed)      -> new object poses drawn from that seed
  /twin/await_policy (std_msgs/Int64, latched) -> frames stamped from this sim time (ns) on are owed a
                                             policy chunk; -1: none (between episodes)
  /franka/command_chunk, /voxels, /policy/skipped -> stamps only: what arrived or will not (the
                                             lockstep, stall reports)
  /twin/scene (std_msgs/String, latched)  <- JSON {seed, block_xy, block_yaw, bowl_xy, bowl_yaw, host, shm}
  /twin/state (std_msgs/String, 10 Hz wall) <- JSON {seed, sim_time, success, details, objects, steps_per_s,
                                             overruns, missed_commands, clock, stalls, last_stall, wait_s}

The robot is never teleported: a reset moves the objects only; whoever resets commands the arm
home first (``equidiff twin run`` does), so the franky client's controller is never surprised.

Parameters: ``PARAMETERS`` below (``--help``, ``ros2 param describe``, docs/parameters.md).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Int64, String
from trajectory_msgs.msg import MultiDOFJointTrajectory

from equidiff_core.config import Bounds, ConfigError, default_config_dir
from equidiff_core.twin.config import load_twin_config
from equidiff_core.twin.lockstep import LockstepConfig
from equidiff_core.twin.scene import SceneError
from equidiff_core.twin.sim import TwinSim
from equidiff_core.wire.rosmsg import header_stamp_ns_from_cdr
from equidiff_core.wire.topics import (
    TOPIC_CLOCK,
    TOPIC_COMMAND_CHUNK,
    TOPIC_POLICY_SKIPPED,
    TOPIC_TWIN_AWAIT_POLICY,
    TOPIC_TWIN_RESET,
    TOPIC_TWIN_SCENE,
    TOPIC_TWIN_STATE,
    TOPIC_VOXELS,
)
from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS, VOXEL_QOS, declare_lab_config
from equidiff_ros.parameters import LAB_CONFIG, NodeParameter, NodeParameters, parameters_help
from equidiff_ros.runner import run_node

NODE_NAME = "twin_node"
CLOCKS = ("sim", "realtime")

PARAMETERS = NodeParameters(
    LAB_CONFIG,
    NodeParameter(
        "twin_config",
        "",
        "Path of twin.yaml: scene, success, render, sim",
        default_from="the installed config/twin.yaml",
    ),
    NodeParameter(
        "host",
        "",
        "Loopback address franky-sim serves libfranka on; auto: a free random 127.x.y.z, so parallel twins never "
        "collide on port 1337; empty: twin.yaml's sim.host",
    ),
    NodeParameter("seed", 0, "Seed of the first episode's scene", Bounds("", ge=0)),
    NodeParameter(
        "shm_name",
        "",
        "Shared-memory state the twin cameras read; empty: equidiff_twin_<ROS_DOMAIN_ID>, or $EQUIDIFF_TWIN_SHM",
    ),
    NodeParameter(
        "clock",
        "sim",
        "sim: the sim owns time (/clock) in lockstep with the pipeline; realtime: 1 kHz to wall-clock deadlines",
        choices=CLOCKS,
    ),
    NodeParameter(
        "latency_s",
        0.1,
        "Clock sim: the latency budget L, a policy chunk is in place by its observation's time + L",
        Bounds("s", ge=0, le=10.0),
        number=True,
    ),
    NodeParameter(
        "stall_timeout_s",
        30.0,
        "Clock sim: wall seconds a lockstep wait may last before it counts as a stall",
        Bounds("s", gt=0, le=3600.0),
        number=True,
    ),
    NodeParameter(
        "max_speed",
        1.0,
        "Clock sim: at most this many sim seconds per wall second; 0: unbounded",
        Bounds("", ge=0, le=1000.0),
        number=True,
    ),
)

USAGE = (
    __doc__
    + parameters_help(PARAMETERS)
    + """
usage: twin_node [--ros-args -p host:=127.0.0.1 -p seed:=0 -p twin_config:=config/twin.yaml]
"""
)


class TwinNode(Node):
    def __init__(self, node_name: str = NODE_NAME):
        super().__init__(node_name)
        self.lab = declare_lab_config(self)
        param = lambda name: PARAMETERS.declare(self, name)
        cfg_path = PARAMETERS.declare(self, "twin_config", str(default_config_dir() / "twin.yaml"))
        host = param("host")
        seed = param("seed")
        shm = param("shm_name") or None
        clock = param("clock")
        latency_s, stall_timeout_s, max_speed = param("latency_s"), param("stall_timeout_s"), param("max_speed")
        self.cfg = load_twin_config(Path(cfg_path))
        lockstep = None
        if clock == "sim":
            periods = {round(1000 / c.publish_hz) for c in self.lab.cameras}
            if len(periods) != 1:
                raise ValueError(
                    f"on simulated time every camera must publish at the same rate; lab.yaml has "
                    f"{sorted(c.publish_hz for c in self.lab.cameras)} Hz"
                )
            lockstep = LockstepConfig(
                frame_period_ticks=periods.pop(),
                latency_ticks=round(1000 * latency_s),
                stall_timeout_s=stall_timeout_s,
                max_speed=max_speed,
            )
            # best effort like rclpy's own /clock subscription; a lost message is repeated while the sim waits
            self.pub_clock = self.create_publisher(
                Clock, TOPIC_CLOCK, QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
            )
        self.twin = TwinSim(
            self.cfg,
            host=host or None,
            shm_name=shm,
            lockstep=lockstep,
            on_clock=self.publish_clock,
            camera_names=tuple(c.name for c in self.lab.cameras),
            log=self.get_logger().info,
        )
        self.pub_scene = self.create_publisher(String, TOPIC_TWIN_SCENE, LATCHED_QOS)
        self.pub_state = self.create_publisher(String, TOPIC_TWIN_STATE, RELIABLE_QOS)
        self.create_subscription(Int64, TOPIC_TWIN_RESET, self.on_reset, RELIABLE_QOS)
        if lockstep is not None:
            ls = self.twin.lockstep
            self.create_subscription(Int64, TOPIC_TWIN_AWAIT_POLICY, self.on_await_policy, LATCHED_QOS)
            # stamps only: read from the serialised messages (a voxel grid is up to 1 MiB)
            self.create_subscription(
                MultiDOFJointTrajectory,
                TOPIC_COMMAND_CHUNK,
                lambda m: ls.on_chunk(header_stamp_ns_from_cdr(m)),
                RELIABLE_QOS,
                raw=True,
            )
            self.create_subscription(
                PointCloud2, TOPIC_VOXELS, lambda m: ls.on_voxels(header_stamp_ns_from_cdr(m)), VOXEL_QOS, raw=True
            )
            self.create_subscription(
                String, TOPIC_POLICY_SKIPPED, lambda m: ls.on_skipped(json.loads(m.data)["stamp_ns"]), RELIABLE_QOS
            )
        self.twin.start(seed)
        self.create_timer(1.0 / self.cfg.sim.status_hz, self.publish_state)
        self.publish_scene()
        self.get_logger().info(
            f"franky-sim serving on {self.twin.host} (robot_ip:={self.twin.host}); state in shared memory "
            f"{self.twin.shm_name!r}; seed {seed}; "
            + (
                "real time"
                if lockstep is None
                else f"simulated time on /clock, latency budget {lockstep.latency_ticks} ms, "
                f"at most {lockstep.max_speed or 'unbounded'}x real time"
            )
        )

    def publish_clock(self, t_ns: int) -> None:
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(t_ns), 1_000_000_000)
        self.pub_clock.publish(msg)

    def on_await_policy(self, msg) -> None:
        if not self.twin.lockstep.await_from(msg.data):
            self.get_logger().warning(
                f"an episode starting at t={msg.data / 1e9:.3f} s was announced after its first camera frame: "
                "frames taken before the announcement are not owed a chunk"
            )

    def on_reset(self, msg) -> None:
        poses = self.twin.reset(int(msg.data))
        self.get_logger().info(f"reset to seed {poses.seed}: block {poses.block_xy}, bowl {poses.bowl_xy}")
        self.publish_scene()

    def publish_scene(self) -> None:
        data = {**self.twin.poses.to_dict(), "host": self.twin.host, "shm": self.twin.shm_name}
        self.pub_scene.publish(String(data=json.dumps(data)))

    def publish_state(self) -> None:
        self.pub_state.publish(String(data=json.dumps(self.twin.status())))

    def shutdown(self) -> None:
        self.twin.stop()


# the errors that end a start-up with a one-line message (exit 1), not a traceback
STARTUP_ERRORS = (ConfigError, SceneError, OSError, RuntimeError, ValueError)  # OSError: the libfranka port is taken


def main(args=None) -> int:
    return run_node(NODE_NAME, USAGE, TwinNode, STARTUP_ERRORS, args)


if __name__ == "__main__":
    sys.exit(main())
