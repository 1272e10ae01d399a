"""Every node parameter describes itself (``equidiff_ros.parameters``): ``ros2 param describe`` (the
DescribeParameters service) gives its description and range, rclpy refuses a value outside the range,
and docs/parameters.md's tables are generated from the same declarations."""

import ast
import math
from pathlib import Path

import pytest
from test_package import NODES

from equidiff_ros.parameters import NodeParameters, node_parameters, with_parameter_tables

REPO = Path(__file__).resolve().parents[1]
RCLPY_OWN = {"use_sim_time", "start_type_description_service"}  # declared by rclpy.Node itself


def test_the_parameter_docs_cover_every_node_executable():
    assert tuple(NODES) == tuple(node_parameters())


def test_no_module_declares_a_parameter_but_through_its_description():
    """``declare_parameter`` is called in one place, which hands rclpy the descriptor: a parameter
    declared elsewhere would have none."""
    callers = []
    for path in (REPO / "src").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("declare_parameter", "declare_parameters"):
                callers.append(str(path.relative_to(REPO)))
    assert callers == ["src/equidiff_ros/parameters.py"]


def test_the_committed_parameter_tables_are_the_generated_ones():
    document = (REPO / "docs" / "parameters.md").read_text()
    assert document == with_parameter_tables(document, node_parameters()), "run python scripts/gen_parameters_doc.py"
    assert "| `slop_s` | `0.1` | s | 0 < x <= 1 |" in document


def test_a_parameter_without_a_description_cannot_be_listed():
    from equidiff_ros.parameters import NodeParameter

    with pytest.raises(ValueError, match="no description"):
        NodeParameters(NodeParameter("slop_s", 0.1, " "))


# --- the nodes themselves, in process ------------------------------------------------------------


NODE_CLASSES = {
    "camera_node": "CameraNode",
    "voxel_node": "VoxelNode",
    "policy_node": "PolicyNode",
    "franka_node": "FrankaNode",
    "teleop_node": "TeleopNode",
    "recorder_node": "RecorderNode",
    "twin_node": "TwinNode",
}
# how each node is started here: fully where that is cheap, else up to the start-up error that follows
# its declarations (no RealSense here, no checkpoint, a twin.yaml that is not a mapping)
NODE_ARGS = {
    "camera_node": [],
    "voxel_node": [],
    "policy_node": [],
    "franka_node": ["-p", "backend:=dryrun"],
    "teleop_node": [],
    "recorder_node": ["-p", "output_dir:={tmp}"],
    "twin_node": ["-p", "twin_config:={tmp}/twin.yaml"],
}


def _started(kind: str):
    """(the node of ``kind`` as far as it got, its listed parameters, whether it stopped at its start-up error)."""
    import importlib

    from equidiff_core.cameras import CameraError
    from equidiff_core.config import ConfigError
    from equidiff_core.policy.file import CheckpointError

    module = importlib.import_module(f"equidiff_ros.{kind}")
    expected_error = {"camera_node": CameraError, "policy_node": CheckpointError, "twin_node": ConfigError}
    holder = {}

    class Probe(getattr(module, NODE_CLASSES[kind])):
        def __init__(self):
            holder["node"] = self
            try:
                super().__init__()
            except expected_error.get(kind, ()) as err:
                holder["stopped_by"] = err

    Probe()
    assert (kind in expected_error) == ("stopped_by" in holder), holder.get("stopped_by")
    return holder["node"], module.PARAMETERS, "stopped_by" in holder


@pytest.mark.ros
@pytest.mark.parametrize("kind", NODES)
def test_each_node_declares_its_listed_parameters_each_with_a_description_and_its_range(kind, ros_domain, tmp_path):
    import rclpy
    from rcl_interfaces.msg import ParameterType

    (tmp_path / "twin.yaml").write_text("- not a mapping\n")
    args = [a.format(tmp=tmp_path) for a in NODE_ARGS[kind]]
    rclpy.init(args=["--ros-args", *args])
    try:
        node, listed, stopped = _started(kind)
        try:
            declared = set(node._parameters) - RCLPY_OWN
            descriptors = {d.name: d for d in node.describe_parameters(sorted(declared))}
        finally:
            if not stopped:
                getattr(node, "shutdown", lambda: None)()  # as runner.run_nodes: not every node has one
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    assert declared == set(listed.names)
    for parameter in listed:
        descriptor = descriptors[parameter.name]
        assert descriptor.description.startswith(parameter.description), parameter.name
        bounds = parameter.bounds
        if bounds is None or bounds.describe() == "any":
            assert not descriptor.floating_point_range and not descriptor.integer_range, parameter.name
            continue
        low = bounds.ge if bounds.ge is not None else bounds.gt
        high = bounds.le if bounds.le is not None else bounds.lt
        if descriptor.type == ParameterType.PARAMETER_INTEGER:
            (rng,) = descriptor.integer_range
            assert low is None or rng.from_value == math.ceil(low) + (bounds.gt is not None), parameter.name
            assert high is None or rng.to_value == math.floor(high) - (bounds.lt is not None), parameter.name
        else:
            (rng,) = descriptor.floating_point_range
            assert rng.from_value == (-math.inf if low is None else low), parameter.name
            assert rng.to_value == (math.inf if high is None else high), parameter.name
            if bounds.gt is not None or bounds.lt is not None:  # ROS ranges are inclusive: said in words
                assert bounds.describe() in descriptor.additional_constraints, parameter.name


@pytest.mark.ros
def test_ros2_param_describe_reads_the_description_and_range_and_a_set_out_of_range_is_refused(ros_domain):
    """Through the real services (what ``ros2 param describe`` / ``set`` call), on a running voxel_node."""
    import rclpy
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import DescribeParameters, SetParameters
    from rclpy.executors import SingleThreadedExecutor

    from equidiff_ros.voxel_node import VoxelNode

    rclpy.init(args=["--ros-args", "-p", "observation_hz:=5"])  # an integer for a float parameter is taken
    try:
        node = VoxelNode()
        client_node = rclpy.create_node("param_client")
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.add_node(client_node)
        try:
            assert node.get_parameter("observation_hz").value == 5.0

            def call(srv_type, name, request):
                client = client_node.create_client(srv_type, f"/voxel_node/{name}")
                assert client.wait_for_service(timeout_sec=10.0)
                future = client.call_async(request)
                executor.spin_until_future_complete(future, timeout_sec=10.0)
                return future.result()

            (slop,) = call(
                DescribeParameters, "describe_parameters", DescribeParameters.Request(names=["slop_s"])
            ).descriptors
            assert slop.description.startswith("Largest capture-stamp spread") and "[s]" in slop.description
            assert (slop.floating_point_range[0].from_value, slop.floating_point_range[0].to_value) == (0.0, 1.0)
            assert slop.additional_constraints == "0 < x <= 1 s"

            too_large = Parameter(
                name="slop_s", value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=5.0)
            )
            (result,) = call(SetParameters, "set_parameters", SetParameters.Request(parameters=[too_large])).results
            assert not result.successful and "out of range" in result.reason
            assert node.get_parameter("slop_s").value == 0.1
        finally:
            executor.shutdown()
            client_node.destroy_node()
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.mark.ros
@pytest.mark.parametrize(
    "override, expected",
    [
        ("slop_s:=5.0", "slop_s: Parameter slop_s out of range Min: 0.0, Max: 1.0, value: 5.0, unit s (voxel_node)"),
        (
            "slop_s:=0.0",
            "slop_s: 0.0 s is out of range; allowed: 0 < x <= 1 s (voxel_node)",
        ),  # the exclusive end, checked by the node
        (
            "observation_hz:=500",
            "observation_hz: 500.0 Hz is out of range; allowed: 0 < x <= 100 Hz (voxel_node)",
        ),  # an integer for a float
        ("queue_size:=0", "Parameter queue_size out of range. Min: 1, Max: 100, value: 0 (voxel_node)"),
        ("queue_size:=many", "expecting type 'INTEGER'"),
    ],
)
def test_an_out_of_range_override_stops_the_node_at_start_naming_the_parameter(ros_domain, capsys, override, expected):
    """In-process ``main`` (the console script is ``sys.exit(main())``): exit status 1, one line."""
    from equidiff_ros import voxel_node

    assert voxel_node.main(["--ros-args", "-p", override]) == 1
    err = capsys.readouterr().err.strip()
    name = override.split(":=")[0]
    assert err.startswith(f"voxel_node: parameter {name}: ") and expected in err
    assert voxel_node.PARAMETERS.by_name[name].description in err and "\n" not in err


@pytest.mark.ros
def test_an_array_parameter_is_checked_item_by_item(ros_domain, capsys):
    """rclpy applies a range to scalars only; the node checks each item of an array parameter."""
    from equidiff_ros import teleop_node

    assert teleop_node.main(["--ros-args", "-p", "linear_scale:=[0.1, -0.2, 0.1]"]) == 1
    err = capsys.readouterr().err
    assert "parameter linear_scale[1]: -0.2 m/s is out of range; allowed: 0 <= x m/s (teleop_node)" in err
