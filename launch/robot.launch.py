"""The real lab: three RealSense D455s, voxels, the FR3 through franky, the policy or teleop, the recorder.

    ros2 launch equidiff_ros robot.launch.py checkpoint:=/path/policy.pt            # policy at 5 Hz
    ros2 launch equidiff_ros robot.launch.py mode:=teleop task:=pick operator:=ana   # record demos
    ros2 launch equidiff_ros robot.launch.py robot_backend:=dryrun checkpoint:=...    # no arm motion

mode:=policy runs policy_node, started paused: ``equidiff lab policy enable`` starts it, and
the SpaceMouse takes over (pausing it) whenever the operator moves it. Both modes run
teleop_node (SpaceMouse via the spacenav driver's /spacenav/joy, or
``teleop_source:=spacemouse`` for direct HID) and the recorder, driven by ``equidiff lab record
start|success|failure|discard`` from any terminal (its keyboard needs a terminal, which nodes
under ros2 launch do not have). With ``teleop_source:=joy`` (the default) the spacenav driver
(``spacenav`` package, ``spacenav_node``; it needs spacenavd running) is started too. Everything
reads config/lab.yaml (cameras, extrinsics, robot IP). The policy's chunk execution
(``execute_steps``, ``latency_s``, ``latency_transport_s``, ``rtc``, ``n_action_steps``) and its doubt gate
(``doubt_gate``, ``doubt_quantile``; docs/doubt.md) are launch
arguments with policy_node's defaults: by default each chunk bridges the measured latency, so the
arm does not stand still between chunks.
"""

from pathlib import Path

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import LaunchConfigurationEquals
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from equidiff_core.control import load_control_config
from equidiff_ros.launch_arguments import EXECUTION_PARAMETERS, execution_arguments

try:
    from ament_index_python.packages import get_package_share_directory

    SHARE = Path(get_package_share_directory("equidiff_ros"))
except (ImportError, LookupError):  # a source checkout (PackageNotFoundError is a KeyError)
    SHARE = Path(__file__).resolve().parents[1]


def generate_launch_description():
    lab = LaunchConfiguration("lab_config")
    # policy_node's rtc_max_gap_m is franka_node's first-step jump limit, from the control.yaml it reads
    jump_limit_m = load_control_config(SHARE / "config" / "control.yaml").safety.max_first_step_jump_m
    common = {"lab_config": lab}
    return LaunchDescription(
        [
            DeclareLaunchArgument("mode", default_value="policy", choices=["policy", "teleop"]),
            DeclareLaunchArgument("checkpoint", default_value=""),
            DeclareLaunchArgument("device", default_value="auto"),
            DeclareLaunchArgument("precision", default_value="fp32"),
            DeclareLaunchArgument("robot_ip", default_value="", description="empty: lab.yaml's robot.ip"),
            DeclareLaunchArgument(
                "robot_backend",
                default_value="franky",
                choices=["franky", "dryrun"],
                description="dryrun: the whole stack with an arm that only pretends to move",
            ),
            DeclareLaunchArgument("teleop_source", default_value="joy", choices=["joy", "spacemouse"]),
            DeclareLaunchArgument("task", default_value="episode"),
            DeclareLaunchArgument("operator", default_value=""),
            DeclareLaunchArgument("output_dir", default_value="bags"),
            DeclareLaunchArgument("lab_config", default_value=str(SHARE / "config" / "lab.yaml")),
            *execution_arguments(),
            Node(
                package="equidiff_ros",
                executable="camera_node",
                output="screen",
                parameters=[{**common, "backend": "realsense"}],
            ),
            Node(package="equidiff_ros", executable="voxel_node", output="screen", parameters=[common]),
            Node(
                package="equidiff_ros",
                executable="franka_node",
                output="screen",
                parameters=[
                    {
                        **common,
                        "robot_ip": LaunchConfiguration("robot_ip"),
                        "realtime": True,
                        "backend": LaunchConfiguration("robot_backend"),
                    }
                ],
            ),
            Node(
                package="equidiff_ros",
                executable="policy_node",
                output="screen",
                condition=LaunchConfigurationEquals("mode", "policy"),
                parameters=[
                    {
                        **common,
                        "checkpoint": LaunchConfiguration("checkpoint"),
                        "device": LaunchConfiguration("device"),
                        "precision": LaunchConfiguration("precision"),
                        "start_paused": True,
                        "rtc_max_gap_m": jump_limit_m,
                        **{name: LaunchConfiguration(name) for name in EXECUTION_PARAMETERS},
                    }
                ],
            ),
            # The SpaceMouse through spacenavd: sensor_msgs/Joy on /spacenav/joy, stamped per device
            # event and zeroed once the device goes quiet (its zero_when_static default).
            Node(
                package="spacenav",
                executable="spacenav_node",
                output="screen",
                condition=LaunchConfigurationEquals("teleop_source", "joy"),
            ),
            # In both modes: in mode:=policy it is the operator's takeover (it publishes nothing while idle).
            Node(
                package="equidiff_ros",
                executable="teleop_node",
                output="screen",
                parameters=[{**common, "source": LaunchConfiguration("teleop_source")}],
            ),
            Node(
                package="equidiff_ros",
                executable="recorder_node",
                output="screen",
                emulate_tty=True,
                parameters=[
                    {
                        **common,
                        "output_dir": LaunchConfiguration("output_dir"),
                        "task": LaunchConfiguration("task"),
                        "operator": LaunchConfiguration("operator"),
                        "keyboard": True,
                    }
                ],
            ),
        ]
    )
