"""twin_node: the digital twin's robot. franky-sim (MuJoCo FR3) + the block-in-bowl scene, in real time.

Wiring:
  ``twin.sim.TwinSim``: franky-sim's libfranka server on ``host`` (franka_node connects to it
      with ``robot_ip:=<host>``, exactly as to a real FR3), stepped at 1 kHz to fixed deadlines;
      the MuJoCo state goes to shared memory at ``sim.state_hz`` for the twin cameras
      (camera_node with backend ``twin``, same ROS_DOMAIN_ID -> same shared-memory name)
  /twin/reset (std_msgs/Int64: seed)      -> new object poses drawn from that seed
  /twin/scene (std_msgs/String, latched)  <- JSON {seed, block_xy, block_yaw, bowl_xy, bowl_yaw, host, shm}
  /twin/state (std_msgs/String, 10 Hz)    <- JSON {seed, sim_time, success, details, objects, steps_per_s, overruns, missed_commands}

The robot is never teleported: a reset moves the objects only; whoever resets commands the arm
home first (``equidiff twin run`` does), so the franky client's controller is never surprised.

Parameters: ``twin_config`` (twin.yaml), ``lab_config``, ``host`` (loopback address to serve on;
"auto" picks a free one, "" = twin.yaml's), ``seed`` (first episode), ``shm_name`` ("" = from
ROS_DOMAIN_ID).
"""

from __future__ import annotations

import sys

from equidiff_ros.runner import run_node

USAGE = __doc__ + """
usage: twin_node [--ros-args -p host:=127.0.0.1 -p seed:=0 -p twin_config:=config/twin.yaml]
"""

NODE_NAME = "twin_node"
TOPIC_RESET = "/twin/reset"
TOPIC_SCENE = "/twin/scene"
TOPIC_STATE = "/twin/state"


def build_node():
    import json
    from pathlib import Path

    from rclpy.node import Node

    from equidiff_core.config import default_config_dir
    from equidiff_core.twin.config import load_twin_config
    from equidiff_core.twin.sim import TwinSim
    from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS, declare_lab_config
    from std_msgs.msg import Int64, String

    class TwinNode(Node):
        def __init__(self):
            super().__init__(NODE_NAME)
            self.lab = declare_lab_config(self)
            cfg_path = self.declare_parameter("twin_config", str(default_config_dir() / "twin.yaml")).value
            host = self.declare_parameter("host", "").value
            seed = int(self.declare_parameter("seed", 0).value)
            shm = self.declare_parameter("shm_name", "").value or None
            self.cfg = load_twin_config(Path(cfg_path))
            self.twin = TwinSim(self.cfg, host=host or None, shm_name=shm)
            self.twin.start(seed)
            self.pub_scene = self.create_publisher(String, TOPIC_SCENE, LATCHED_QOS)
            self.pub_state = self.create_publisher(String, TOPIC_STATE, RELIABLE_QOS)
            self.create_subscription(Int64, TOPIC_RESET, self.on_reset, RELIABLE_QOS)
            self.create_timer(1.0 / self.cfg.sim.status_hz, self.publish_state)
            self.publish_scene()
            self.get_logger().info(f"franky-sim serving on {self.twin.host} (robot_ip:={self.twin.host}); "
                                   f"state in shared memory {self.twin.shm_name!r}; seed {seed}")

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

    return TwinNode()


def main(args=None) -> int:
    def startup_errors():
        from equidiff_core.config import ConfigError
        from equidiff_core.twin.scene import SceneError

        return (ConfigError, SceneError, OSError, RuntimeError)  # OSError: the libfranka port is taken

    return run_node(NODE_NAME, USAGE, build_node, startup_errors, args)


if __name__ == "__main__":
    sys.exit(main())
