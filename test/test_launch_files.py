"""What the launch files start for a given set of launch arguments.

``launch`` / ``launch_ros`` are not in the test venv (rclpy comes from PyPI wheels), so the
launch file is read with ``ast``: every ``Node(...)`` with its package, executable and condition.
Conditions are evaluated for the given arguments; one this reader does not understand fails the
test rather than being guessed at.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

LAUNCH = Path(__file__).resolve().parents[1] / "launch"


def _literal(node: ast.AST):
    return ast.literal_eval(node)


def _kwargs(call: ast.Call) -> dict[str, ast.AST]:
    return {k.arg: k.value for k in call.keywords if k.arg}


def _name(call: ast.Call) -> str:
    return call.func.id if isinstance(call.func, ast.Name) else call.func.attr


def launch_arguments(path: Path) -> dict[str, str]:
    """Each DeclareLaunchArgument's default (a non-literal default is left out)."""
    out = {}
    for call in ast.walk(ast.parse(path.read_text())):
        if isinstance(call, ast.Call) and _name(call) == "DeclareLaunchArgument":
            default = _kwargs(call).get("default_value")
            try:
                out[_literal(call.args[0])] = _literal(default) if default is not None else ""
            except ValueError:
                continue
    return out


def _condition_holds(cond: ast.AST | None, args: dict[str, str]) -> bool:
    if cond is None:
        return True
    if isinstance(cond, ast.Call) and _name(cond) in ("LaunchConfigurationEquals", "LaunchConfigurationNotEquals"):
        key, value = (_literal(a) for a in cond.args)
        equal = args[key] == value
        return equal if _name(cond) == "LaunchConfigurationEquals" else not equal
    raise AssertionError(f"launch condition not understood by this test: {ast.unparse(cond)}")


def started_nodes(name: str, **overrides: str) -> list[tuple[str, str]]:
    """(package, executable) of every Node the launch file starts with these arguments."""
    path = LAUNCH / name
    args = launch_arguments(path) | overrides
    nodes = []
    for call in ast.walk(ast.parse(path.read_text())):
        if isinstance(call, ast.Call) and _name(call) == "Node":
            kw = _kwargs(call)
            if _condition_holds(kw.get("condition"), args):
                nodes.append((_literal(kw["package"]), _literal(kw["executable"])))
    return nodes


SPACENAV = ("spacenav", "spacenav_node")


@pytest.mark.parametrize("mode", ["teleop", "policy"])
def test_robot_launch_starts_the_spacenav_driver_for_joy_only(mode):
    assert launch_arguments(LAUNCH / "robot.launch.py")["teleop_source"] == "joy"
    assert SPACENAV in started_nodes("robot.launch.py", mode=mode)  # the default source
    assert SPACENAV in started_nodes("robot.launch.py", mode=mode, teleop_source="joy")
    assert SPACENAV not in started_nodes("robot.launch.py", mode=mode, teleop_source="spacemouse")


@pytest.mark.parametrize("mode", ["teleop", "policy"])
def test_robot_launch_starts_teleop_in_both_modes_for_the_takeover(mode):
    assert ("equidiff_ros", "teleop_node") in started_nodes("robot.launch.py", mode=mode)
    assert ("equidiff_ros", "recorder_node") in started_nodes("robot.launch.py", mode=mode)


def test_robot_launch_policy_mode_starts_paused():
    source = (LAUNCH / "robot.launch.py").read_text()
    assert '"start_paused": True' in source


def test_robot_launch_policy_only_in_policy_mode():
    assert ("equidiff_ros", "policy_node") not in started_nodes("robot.launch.py", mode="teleop")
    assert ("equidiff_ros", "policy_node") in started_nodes("robot.launch.py", mode="policy")
