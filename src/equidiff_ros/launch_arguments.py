"""The launch arguments both launch files share: how policy_node executes chunks (docs/chunking.md) and its
doubt gate (docs/doubt.md), with the node's own defaults.

The table is plain data, so tests read it without ROS's ``launch`` package; ``execution_arguments``
builds the ``DeclareLaunchArgument`` actions inside a launch file.
"""

from __future__ import annotations

import yaml

from equidiff_core.policy import doubt
from equidiff_core.wire import chunk


def _launch_text(value) -> str:
    # launch_ros reads a substituted parameter as YAML: write each default the way it reads back
    return yaml.safe_dump(value, default_flow_style=True).removesuffix("\n...\n").strip()


# name -> (default, description); the defaults are policy_node's (equidiff_core.wire.chunk.DEFAULT_*)
EXECUTION_ARGUMENTS = {
    "execute_steps": (chunk.DEFAULT_EXECUTE_STEPS, "steps of a chunk run before the next answer (0: all 8)"),
    "latency_s": (
        chunk.DEFAULT_LATENCY_S,
        "observation-to-arrival latency each chunk bridges: auto (measured), seconds, or -1 (off)",
    ),
    "latency_transport_s": (chunk.DEFAULT_TRANSPORT_S, "added to the measured latency (auto)"),
    "rtc": (chunk.DEFAULT_RTC, "real-time chunking"),
    "n_action_steps": (chunk.DEFAULT_N_ACTION_STEPS, "steps published per chunk (0: enough to bridge L)"),
    "doubt_gate": (doubt.DEFAULT_GATE, "hold the arm and ask for help when a chunk's doubt exceeds doubt_quantile"),
    "doubt_quantile": (doubt.DEFAULT_GATE_QUANTILE, "the doubt gate's threshold: this quantile over the demos"),
}
EXECUTION_PARAMETERS = tuple(EXECUTION_ARGUMENTS)


def execution_defaults() -> dict[str, str]:
    """Each execution argument's default as the launch text a launch file declares."""
    return {name: _launch_text(default) for name, (default, _) in EXECUTION_ARGUMENTS.items()}


def execution_arguments() -> list:
    """One ``DeclareLaunchArgument`` per execution parameter (pass them on with ``LaunchConfiguration``)."""
    from launch.actions import DeclareLaunchArgument

    defaults = execution_defaults()
    return [
        DeclareLaunchArgument(name, default_value=defaults[name], description=description)
        for name, (_, description) in EXECUTION_ARGUMENTS.items()
    ]
