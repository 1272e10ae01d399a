"""The package installs two ways: colcon (ament index, lib/equidiff_ros executables, share/) and pip -e."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from equidiff_ros.cli import COMMANDS, GROUPS, build_parser

ROOT = Path(__file__).resolve().parents[1]
NODES = ["camera_node", "voxel_node", "policy_node", "franka_node", "teleop_node", "recorder_node", "twin_node"]
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory) -> Path:
    colcon = shutil.which("colcon", path=str(BIN)) or shutil.which("colcon")
    if colcon is None:
        pytest.fail("colcon is not installed (scripts/setup.sh installs colcon-core + colcon-ros)")
    base = tmp_path_factory.mktemp("colcon")
    # Build from a copy so colcon's build artefacts never touch the checkout.
    src = base / "src" / "equidiff_ros"
    shutil.copytree(
        ROOT,
        src,
        ignore=shutil.ignore_patterns(
            ".venv", ".git", "*.egg-info", "__pycache__", "bags", "build", "install", "log", "runs", "out"
        ),
    )
    result = subprocess.run(
        [
            colcon,
            "--log-base",
            str(base / "log"),
            "build",
            "--base-paths",
            str(base / "src"),
            "--build-base",
            str(base / "build"),
            "--install-base",
            str(base / "install"),
        ],
        cwd=base,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return base / "install"


def test_colcon_registers_the_package_and_installs_share_files(colcon_install):
    prefix = colcon_install / "equidiff_ros"
    assert (prefix / "share/ament_index/resource_index/packages/equidiff_ros").is_file()
    assert (prefix / "share/equidiff_ros/package.xml").is_file()
    assert (prefix / "share/equidiff_ros/config/lab.yaml").is_file()
    launch_files = sorted(p.name for p in (prefix / "share/equidiff_ros/launch").glob("*.py"))
    assert {"twin.launch.py", "robot.launch.py"} <= set(launch_files)
    shipped = prefix / "share/equidiff_ros/checkpoints/twin_compact"
    assert (shipped / "policy.pt").is_file() and (shipped / "README.md").is_file()
    assert (shipped / "policy_ddim4.pt").is_file()  # the four-step policy, selected by its path
    assert not list(shipped.glob("*.ckpt"))  # the resumable training state is not installed


@pytest.mark.parametrize("node", NODES)
def test_colcon_node_executables_start(colcon_install, node):
    exe = colcon_install / "equidiff_ros/lib/equidiff_ros" / node
    assert exe.is_file() and os.access(exe, os.X_OK)
    site = next((colcon_install / "equidiff_ros/lib").glob("python3*/site-packages"))
    env = dict(os.environ, PYTHONPATH=f"{site}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    result = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=120, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "usage" in (result.stdout + result.stderr).lower()


def test_installed_config_is_found_by_the_installed_package(colcon_install):
    site = next((colcon_install / "equidiff_ros/lib").glob("python3*/site-packages"))
    code = "from equidiff_core.config import default_config_dir; print(default_config_dir())"
    env = dict(os.environ, PYTHONPATH=str(site))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd="/", timeout=60)
    assert out.returncode == 0, out.stderr
    assert Path(out.stdout.strip()) == colcon_install / "equidiff_ros/share/equidiff_ros/config"


def test_pip_editable_install_exposes_nodes_and_cli():
    for node in NODES + ["equidiff"]:
        assert (BIN / node).is_file(), f"{node} missing from {BIN}"
    result = subprocess.run([str(BIN / "equidiff"), "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0
    for command in ["train", "dataset", "bags", "replay", "viz", "check", "bench", "twin"]:
        assert command in result.stdout
    bench = subprocess.run([str(BIN / "equidiff"), "bench", "--help"], capture_output=True, text=True, timeout=60)
    for sub in ["voxelize", "policy", "train", "control", "generalization"]:
        assert sub in bench.stdout


@pytest.mark.parametrize("path", [list(p) for p in COMMANDS], ids=" ".join)
def test_every_command_parses_its_own_arguments(path, capsys):
    """Each command's --help is its own parser: a leaf takes its options, not a group's SUBCOMMAND."""
    argv = [*path, "--help"]
    with pytest.raises(SystemExit) as done:
        build_parser(argv).parse_args(argv)
    assert done.value.code == 0
    usage = capsys.readouterr().out
    assert usage.startswith(f"usage: equidiff {' '.join(path)} ")
    has_subcommands = any(len(p) > len(path) and list(p[: len(path)]) == path for p in COMMANDS)
    assert ("SUBCOMMAND" in usage) == has_subcommands, usage


def test_every_command_group_says_what_it_is_for(capsys):
    """`equidiff --help` describes each group by its purpose, not as "<group> commands"."""
    with pytest.raises(SystemExit):
        build_parser(["--help"]).parse_args(["--help"])
    usage = " ".join(capsys.readouterr().out.split())  # argparse wraps the help column
    groups = {path[0] for path in COMMANDS if len(path) > 1}
    assert set(GROUPS) == groups - {path[0] for path in COMMANDS if len(path) == 1}  # lab says its own command's
    for group, purpose in GROUPS.items():
        assert f"{group} {purpose}" in usage
    assert not [group for group in groups if f"{group} commands" in usage], usage


def test_a_leaf_command_takes_a_positional_bag():
    argv = ["viz", "-o", "out.rrd", "bags/sample_pick_0000"]
    args = build_parser(argv).parse_args(argv)
    assert args._module == "viz" and [str(b) for b in args.bags] == ["bags/sample_pick_0000"]


def test_package_xml_declares_runtime_dependencies():
    import xml.etree.ElementTree as ET

    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.get("format") == "3"
    deps = {e.text for e in root.iter("exec_depend")}
    assert {
        "rclpy",
        "sensor_msgs",
        "geometry_msgs",
        "trajectory_msgs",
        "std_msgs",
        "std_srvs",
        "diagnostic_msgs",
        "tf2_msgs",
    } <= deps
    assert root.find("export/build_type").text == "ament_python"


def test_setup_script_is_idempotent_and_fast_the_second_time():
    result = subprocess.run(["bash", str(ROOT / "scripts/setup.sh")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "[setup] python packages" not in result.stdout  # nothing reinstalled


def test_escnn_imports_under_numpy2_and_pip_check_is_clean():
    code = "import numpy, escnn, lie_learn.representations.SO3.wigner_d; assert numpy.__version__ >= '2'"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120).returncode == 0
    check = subprocess.run([sys.executable, "-m", "pip", "check"], capture_output=True, text=True, timeout=120)
    assert check.returncode == 0, check.stdout


@pytest.mark.parametrize("command", [["check"], ["format", "--check"]], ids=["lint", "format"])
def test_ruff_finds_nothing_in_the_sources_and_tests(command):
    """The README's test command is also the lint and format gate (ruff.toml holds the rules)."""
    ruff = shutil.which("ruff", path=str(BIN))
    assert ruff is not None, "ruff is not installed (scripts/setup.sh installs the dev extras)"
    result = subprocess.run(
        [ruff, *command, "src", "test", "launch", "scripts"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stdout + result.stderr


# The twin is the test bed: the jobs (``<package>/job.py``, e.g. calibration.job, lab or twin), benches and
# commands that run it may import it; the libraries a lab runs on its real robot (cameras, robots, calibration,
# control, models, training, viz, ...) may not.
TWIN_USERS = ("twin/", "benches/", "commands/", "/job.py", "_job.py", "twin_node.py")


def _imported_modules(path: Path, module: str) -> set[str]:
    """Absolute names of what ``path``, the module ``module`` (e.g. equidiff_core.viz.logger, or
    equidiff_core.viz.__init__ for a package), imports."""
    import ast

    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = module.split(".")
            base = base[: len(base) - node.level] if node.level else []  # level 1: the module's package
            imported = ".".join([*base, *(node.module.split(".") if node.module else [])])
            names.add(imported)
            names.update(f"{imported}.{alias.name}" for alias in node.names)
    return names


def test_no_general_module_imports_the_twin():
    offenders = []
    for path in sorted((ROOT / "src").rglob("*.py")):
        relative = path.relative_to(ROOT / "src").as_posix()
        if any(part in relative for part in TWIN_USERS):
            continue
        module = relative.removesuffix(".py").replace("/", ".")
        twin = {m for m in _imported_modules(path, module) if m.startswith(("equidiff_core.twin", "equidiff_ros.twin"))}
        if twin:
            offenders.append(f"{relative}: {sorted(twin)}")
    assert not offenders, offenders


# A figure in a comment goes stale with the machine and the code it was measured on; the docs keep
# each with its command, machine and date (docs/model.md, docs/control.md, ...), and the code says why
# and points there. Names of processors and ISO dates are the sure sign of a figure in code.
DATED_FIGURE = re.compile(
    r"\b20\d\d-[01]\d-[0-3]\d\b"
    r"|\b(?:Xeon|EPYC|Epyc|Ryzen|Threadripper|Opteron|Core i[3579]|Zen ?\d|Sapphire Rapids|Ice Lake)\b"
    r"|\b(?:[ABH]100|H200|B200|GB200|L40S?|RTX ?\d{4})\b"
    r"|\bAVX-?512 (?:machine|box|CPU|host)\b"
)


def test_no_source_line_names_a_processor_or_a_date():
    offending = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in sorted((ROOT / "src").rglob("*.py"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if DATED_FIGURE.search(line)
    ]
    assert not offending, "figures belong in docs/*.md with their command, machine and date:\n" + "\n".join(offending)


def test_the_dated_figure_check_catches_what_it_is_for():
    for line in ("# 2.2 ms on the 2-core EPYC", "(2026-11-27, the Xeon)", "on one H100", "an AVX-512 machine"):
        assert DATED_FIGURE.search(line), line
    for line in ("cpu_model()", "bf16 with AVX512-BF16/AMX", "YYYY-MM-DD", "100 Hz"):
        assert not DATED_FIGURE.search(line), line


def test_the_core_prints_only_in_its_process_entry_points():
    """The core logs (``logging``) or reports through a callback; only a ``python -m equidiff_core...`` process,
    whose output its parent reads, writes to stdout or stderr itself."""
    import ast

    offenders = []
    for path in sorted((ROOT / "src" / "equidiff_core").rglob("*.py")):
        text = path.read_text()
        if 'if __name__ == "__main__":' in text:
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, offenders


# A command's usage lines and help say what it does; how long it took on some machine goes stale with the
# machine and lives in docs/results/ with its command, machine and date.
TIMING_FIGURE = re.compile(r"~ ?\d+(?:\.\d+)? ?(?:ms|s|min|h)\b|\bon \d+ cores\b")


def test_no_command_help_quotes_a_timing():
    offending = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in sorted((ROOT / "src" / "equidiff_ros" / "commands").glob("*.py"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if TIMING_FIGURE.search(line)
    ]
    assert not offending, "timings belong in docs/results/ with their command, machine and date:\n" + "\n".join(
        offending
    )


def test_the_timing_check_catches_what_it_is_for():
    for line in ("# 1200 steps (~2 min on 2 cores)", 'help="compile (~45 s the first time)"', "demos ~14 s each"):
        assert TIMING_FIGURE.search(line), line
    for line in ("--timeout 10 s", "0.5 s after the last chunk", "at 5 Hz", "min_width_m", "~2 mm off"):
        assert not TIMING_FIGURE.search(line), line
