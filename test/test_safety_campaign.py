"""`equidiff bench safety`'s campaign without the CLI and without the graph: the core package imports without
ROS, an unknown fault is refused (exit 2, nothing started) and ``--box-margin-mm`` makes a copy of
control.yaml with the margin set. The campaign itself against franky-sim: test_bench_safety.py."""

from __future__ import annotations

import subprocess
import sys

from equidiff_core.benches.fault_campaign import FAULTS, run_bench
from equidiff_core.benches.fault_campaign.driver import control_config_with_margin
from equidiff_core.config import default_config_dir, to_dict


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


def test_an_unknown_fault_is_refused_before_anything_starts(monkeypatch, capsys, tmp_path):
    monkeypatch.setenv("ROS_DOMAIN_ID", "117")
    # no probe: refusing the list needs nothing of the ROS side, and nothing is started
    code = run_bench("nan, out_of_bounds", None, keep=tmp_path)
    out = capsys.readouterr()
    assert code == 2 and out.out == ""
    assert out.err == f"equidiff bench safety: unknown fault(s) ['out_of_bounds']; choose from {list(FAULTS)}\n"
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
