"""The main job on a ROS 2 install: the twin stack as launch-managed nodes plus the episode driver.

    ros2 launch equidiff_ros twin.launch.py episodes:=10
    ros2 launch equidiff_ros twin.launch.py checkpoint:=/path/policy.pt host:=127.0.0.2 out:=runs/twin
    ros2 launch equidiff_ros twin.launch.py clock:=realtime     # wall clock (machines that hold real time)

Starts twin_node (franky-sim + scene on ``host``), one camera_node per camera with backend
twin, voxel_node, policy_node (its chunks remapped to /twin/policy_chunk: the driver's gate),
franka_node (robot_ip = host, no real-time kernel) and recorder_node, then
``equidiff twin run --attach``, which runs the episodes against these nodes, prints the summary
and the JSON line; when it exits, the whole launch shuts down. Use a private ROS_DOMAIN_ID
(export ROS_DOMAIN_ID=...) as ``equidiff twin run`` does by itself.

``clock:=sim`` (default): twin_node publishes /clock and steps in lockstep with the pipeline;
every other node gets use_sim_time and the cameras take the frames the sim requests
(docs/twin.md). ``latency_ms`` is the latency budget L. The policy's chunk execution
(``execute_steps``, ``latency_s``, ``latency_transport_s``, ``rtc``, ``n_action_steps``) and its doubt gate
(``doubt_gate``, ``doubt_quantile``; docs/doubt.md) are launch
arguments with policy_node's defaults; on ``clock:=sim`` ``latency_s:=auto`` is the budget L, which
the twin imposes exactly.
"""

from pathlib import Path

from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    EmitEvent,
    ExecuteProcess,
    RegisterEventHandler,
    SetEnvironmentVariable,
)
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import (
    LaunchConfiguration,
    PathJoinSubstitution,
    PythonExpression,
)
from launch_ros.actions import Node

from equidiff_core.control import load_control_config
from equidiff_ros.launch_arguments import EXECUTION_PARAMETERS, execution_arguments

try:
    from ament_index_python.packages import get_package_share_directory

    SHARE = Path(get_package_share_directory("equidiff_ros"))
except (ImportError, LookupError):  # a source checkout (PackageNotFoundError is a KeyError)
    SHARE = Path(__file__).resolve().parents[1]

CAMERAS = ("cam_front", "cam_left", "cam_right")  # the names in lab.yaml


def generate_launch_description():
    lab = LaunchConfiguration("lab_config")
    # policy_node's rtc_max_gap_m is franka_node's first-step jump limit, from the control.yaml it reads
    jump_limit_m = load_control_config(SHARE / "config" / "control.yaml").safety.max_first_step_jump_m
    twin = LaunchConfiguration("twin_config")
    host = LaunchConfiguration("host")
    out = LaunchConfiguration("out")
    clock = LaunchConfiguration("clock")
    sim = PythonExpression(["'", clock, "' == 'sim'"])
    common = {"lab_config": lab, "use_sim_time": sim}
    clouds = {"reliable_clouds": sim}  # lockstep: no frame owed a chunk may be lost in transport
    latency, budget_ms = LaunchConfiguration("latency_s"), LaunchConfiguration("latency_ms")
    nodes = [
        Node(
            package="equidiff_ros",
            executable="twin_node",
            output="screen",
            parameters=[
                {
                    "lab_config": lab,
                    "twin_config": twin,
                    "host": host,
                    "seed": LaunchConfiguration("seed"),
                    "clock": clock,
                    "latency_s": PythonExpression([LaunchConfiguration("latency_ms"), " / 1000.0"]),
                }
            ],
        ),
        *[
            Node(
                package="equidiff_ros",
                executable="camera_node",
                name=f"camera_{cam}",
                output="screen",
                parameters=[
                    {
                        **common,
                        **clouds,
                        "backend": "twin",
                        "camera": cam,
                        "backend_options": PythonExpression(["'lockstep: true' if ", sim, " else ''"]),
                    }
                ],
            )
            for cam in CAMERAS
        ],
        Node(package="equidiff_ros", executable="voxel_node", output="screen", parameters=[{**common, **clouds}]),
        Node(
            package="equidiff_ros",
            executable="franka_node",
            output="screen",
            # the twin's supervisor is its operator: no start-up acknowledgement (docs/control.md)
            parameters=[{**common, "robot_ip": host, "realtime": False, "require_ack_on_start": False}],
        ),
        Node(
            package="equidiff_ros",
            executable="policy_node",
            output="screen",
            parameters=[
                {
                    **common,
                    "checkpoint": LaunchConfiguration("checkpoint"),
                    "device": LaunchConfiguration("device"),
                    "precision": LaunchConfiguration("precision"),
                    "rtc_max_gap_m": jump_limit_m,
                    **{name: LaunchConfiguration(name) for name in EXECUTION_PARAMETERS},
                    # on simulated time the twin holds each chunk until its stamp + latency_ms exactly
                    # (as `equidiff twin run` does): auto then means that budget, known, not measured
                    "latency_s": PythonExpression(
                        ["'", latency, "' if '", latency, "' != 'auto' or not ", sim, " else ", budget_ms, " / 1000.0"]
                    ),
                }
            ],
            remappings=[("/franka/command_chunk", "/twin/policy_chunk")],
        ),
        Node(
            package="equidiff_ros",
            executable="recorder_node",
            output="screen",
            parameters=[{**common, "output_dir": PathJoinSubstitution([out, "bags"]), "task": "twin_eval"}],
        ),
    ]
    driver = ExecuteProcess(
        cmd=[
            "equidiff",
            "twin",
            "run",
            "--attach",
            "--episodes",
            LaunchConfiguration("episodes"),
            "--seed",
            LaunchConfiguration("seed"),
            "--out",
            out,
            "--checkpoint",
            LaunchConfiguration("checkpoint"),
            "--lab-config",
            lab,
            "--twin-config",
            twin,
            "--clock",
            clock,
            "--latency-ms",
            LaunchConfiguration("latency_ms"),
        ],
        output="screen",
    )
    return LaunchDescription(
        [
            DeclareLaunchArgument("episodes", default_value="5"),
            DeclareLaunchArgument("seed", default_value="100000"),
            DeclareLaunchArgument(
                "host", default_value="127.0.0.1", description="loopback address franky-sim serves on"
            ),
            DeclareLaunchArgument(
                "checkpoint", default_value=str(SHARE / "checkpoints" / "twin_compact" / "policy.pt")
            ),
            DeclareLaunchArgument("device", default_value="cpu"),
            DeclareLaunchArgument(
                "precision",
                default_value="fp32",
                description="policy arithmetic: fp32 on every CPU (auto: bf16 where native)",
            ),
            DeclareLaunchArgument("clock", default_value="sim", description="sim (lockstep, /clock) or realtime"),
            DeclareLaunchArgument("latency_ms", default_value="100", description="latency budget L (clock:=sim)"),
            *execution_arguments(),
            DeclareLaunchArgument("out", default_value="runs/twin_launch"),
            DeclareLaunchArgument("lab_config", default_value=str(SHARE / "config" / "lab.yaml")),
            DeclareLaunchArgument("twin_config", default_value=str(SHARE / "config" / "twin.yaml")),
            SetEnvironmentVariable("MUJOCO_GL", "egl"),
            SetEnvironmentVariable("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST"),
            *nodes,
            driver,
            RegisterEventHandler(
                OnProcessExit(target_action=driver, on_exit=[EmitEvent(event=Shutdown(reason="episodes done"))])
            ),
        ]
    )
