"""What the launch files start for a given set of launch arguments.

``launch`` / ``launch_ros`` are not in the test venv (rclpy comes from PyPI wheels), so the
launch file is read with ``ast``: every ``Node(...)`` with its package, executable and condition.
The execution arguments both launchers share come from ``equidiff_ros.launch_arguments``, plain data
this test imports. Conditions are evaluated for the given arguments; one this reader does not understand fails the
test rather than being guessed at.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from equidiff_ros import launch_arguments as shared

LAUNCH = Path(__file__).resolve().parents[1] / "launch"


def _literal(node: ast.AST):
    return ast.literal_eval(node)


def _kwargs(call: ast.Call) -> dict[str, ast.AST]:
    return {k.arg: k.value for k in call.keywords if k.arg}


def _name(call: ast.Call) -> str:
    return call.func.id if isinstance(call.func, ast.Name) else call.func.attr


def launch_arguments(path: Path) -> dict[str, str]:
    """Each DeclareLaunchArgument's default (a non-literal default is left out), with the shared
    execution arguments where the file declares them (``*execution_arguments()``)."""
    out = {}
    for call in ast.walk(ast.parse(path.read_text())):
        if isinstance(call, ast.Call) and _name(call) == shared.execution_arguments.__name__:
            out |= shared.execution_defaults()
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


def node_parameter_keys(name: str, executable: str) -> set[str]:
    """The parameter names the launch file gives ``executable`` (keys of the dicts in its
    ``parameters``, with ``**{name: ... for name in TUPLE}`` expanded from the tuple the file defines or
    imports from ``equidiff_ros.launch_arguments``)."""
    tree = ast.parse((LAUNCH / name).read_text())
    tuples = {
        t.id: _literal(node.value)
        for node in tree.body
        if isinstance(node, ast.Assign)
        for t in node.targets
        if isinstance(t, ast.Name) and isinstance(node.value, ast.Tuple)
    }
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module == shared.__name__:
            tuples |= {
                a.name: getattr(shared, a.name) for a in node.names if isinstance(getattr(shared, a.name), tuple)
            }
    keys: set[str] = set()
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and _name(call) == "Node" and _literal(_kwargs(call)["executable"]) == executable:
            for d in ast.walk(_kwargs(call)["parameters"]):
                if not isinstance(d, ast.Dict):
                    continue
                for key, value in zip(d.keys, d.values, strict=True):
                    if key is not None:
                        keys.add(_literal(key))
                    elif isinstance(value, ast.DictComp):  # **{name: ... for name in EXECUTION_PARAMETERS}
                        keys.update(tuples[value.generators[0].iter.id])
    return keys


@pytest.mark.parametrize("launch_file", ["robot.launch.py", "twin.launch.py"])
def test_launchers_expose_chunk_execution_with_the_nodes_defaults(launch_file):
    """Each launcher declares policy_node's execution parameters as launch arguments whose defaults are
    the node's own (launch_ros reads a substituted parameter as YAML, as this test does), and passes
    every one of them to policy_node. (test_policy_node.py checks that a started policy_node's
    parameters are these constants.)"""
    import yaml

    from equidiff_core.wire import chunk

    node_defaults = {
        "execute_steps": chunk.DEFAULT_EXECUTE_STEPS,
        "latency_s": chunk.DEFAULT_LATENCY_S,
        "latency_transport_s": chunk.DEFAULT_TRANSPORT_S,
        "rtc": chunk.DEFAULT_RTC,
        "n_action_steps": chunk.DEFAULT_N_ACTION_STEPS,
    }
    declared = launch_arguments(LAUNCH / launch_file)
    launch_defaults = {name: yaml.safe_load(declared[name]) for name in node_defaults if name in declared}
    assert launch_defaults == node_defaults
    assert set(node_defaults) <= node_parameter_keys(launch_file, "policy_node")
