"""`equidiff bench safety`'s campaign without the CLI and without the graph: the core package imports without
ROS, an unknown fault is refused (JobError, exit status 2, nothing started) and ``--box-margin-mm`` makes a copy of
control.yaml with the margin set. The campaign itself against franky-sim: test_bench_safety.py."""

from __future__ import annotations

import subprocess
import sys

import pytest

from equidiff_core.benches.fault_campaign import FAULTS, run_bench
from equidiff_core.benches.fault_campaign.driver import control_config_with_margin
from equidiff_core.config import default_config_dir, to_dict
from equidiff_core.runtime.jobs import JobError


def test_the_campaign_imports_without_ros():
    code = (
        "import sys\n"
        "for m in ('rclpy', 'std_msgs', 'geometry_msgs'):\n"
        "    sys.modules[m] = None\n"
        "import equidiff_core.benches.fault_campaign as safety\n"
        "print(sorted(m for m in sys.modules if m.startswith('equidiff_ros')))\n"
        "print(len(safety.FAULTS))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["[]", "14"]


def test_an_unknown_fault_is_refused_before_anything_starts(monkeypatch, tmp_path):
    monkeypatch.setenv("ROS_DOMAIN_ID", "117")
    # no probe: refusing the list needs nothing of the ROS side, and nothing is started
    with pytest.raises(JobError) as refused:
        run_bench("nan, out_of_bounds", None, keep=tmp_path / "keep")
    assert refused.value.exit_status == 2
    assert str(refused.value) == f"unknown fault(s) ['out_of_bounds']; choose from {list(FAULTS)}"
    assert list(tmp_path.iterdir()) == []


def test_box_margin_mm_writes_a_control_config_with_that_margin(tmp_path):
    path, control = control_config_with_margin(tmp_path, 0.0)
    assert path == tmp_path / "control.yaml" and control.safety.box_margin_m == 0.0
    default_path, default = control_config_with_margin(tmp_path, None)
    assert default_path == default_config_dir() / "control.yaml"
    assert default.safety.box_margin_m > 0.0  # control.yaml's own margin, the file left alone
    expected = to_dict(default)
    expected["safety"]["box_margin_m"] = 0.0
    assert to_dict(control) == expected  # only the margin changed
