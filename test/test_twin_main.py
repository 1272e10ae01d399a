"""The main job: twin_node, process supervision, metrics, and a smoke run of `equidiff twin run`."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers_ros import run_job

from equidiff_core.twin.episode import SuccessHold
from equidiff_core.twin.processes import (
    NodeProcessError,
    ProcessGroup,
    node_command,
    private_ros_env,
)
from equidiff_core.twin.run_summary import EpisodeRecord, RunSummary

REQUIRED_KEYS = {"episodes", "success_rate", "inference_p95_ms", "end_to_end_p95_ms", "dropped_cycles"}


def test_summary_json_line_has_the_issue_keys_and_pools_episodes():
    eps = [
        EpisodeRecord(1, True, 10.0, 50, 2, end_to_end_ms=[100, 200], inference_ms=[80]),
        EpisodeRecord(2, False, 40.0, 190, 10, end_to_end_ms=[300], inference_ms=[90, 100]),
    ]
    s = RunSummary(eps, sim_rate=0.97, policy="p")
    d = json.loads(s.json_line())
    assert REQUIRED_KEYS <= set(d)
    assert d["episodes"] == 2 and d["success_rate"] == 0.5 and d["dropped_cycles"] == 12
    assert d["end_to_end_p95_ms"] == pytest.approx(290.0) and d["inference_p95_ms"] == pytest.approx(99.0)
    assert "success rate:      50 % of 2 (95 % interval 10%-90%)" in s.human()
    assert d["success_ci95"] == [0.095, 0.905]  # Wilson's interval of 1 of 2
    assert d["clock"] == "sim" and d["representative"] is True


def test_success_counts_only_once_it_has_held_without_a_break():
    hold = SuccessHold(0.5)
    assert [hold.update(ok, t) for ok, t in [(True, 0.0), (True, 0.3), (False, 0.4), (True, 0.6), (True, 1.0)]] == [
        False,
        False,
        False,
        False,
        False,
    ]  # the lapse at 0.4 s restarted the hold
    assert hold.update(True, 1.1) and hold.since == 0.6


def test_a_real_time_run_whose_sim_fell_behind_is_flagged_as_not_representative():
    eps = [EpisodeRecord(1, True, 10.0, 50, 2)]
    slow = RunSummary(eps, sim_rate=0.52, clock="realtime", wall_s=80.0)
    assert json.loads(slow.json_line())["representative"] is False
    assert "NOT REPRESENTATIVE" in slow.human()
    assert json.loads(RunSummary(eps, sim_rate=0.95, clock="realtime").json_line())["representative"] is True
    stalled = RunSummary([EpisodeRecord(2, stalled="policy_node: no chunk")], clock="sim", latency_budget_ms=100.0)
    d = json.loads(stalled.json_line())
    assert d["stalled_episodes"] == 1 and d["latency_budget_ms"] == 100.0 and "stalled" in stalled.human()


def test_node_command_and_private_env():
    cmd = node_command("no_such_node_xyz", {"a": True, "b": 1.5}, {"/x": "/y"})
    assert cmd[:3] == [sys.executable, "-m", "equidiff_ros.no_such_node_xyz"]
    assert cmd[3:] == ["--ros-args", "-p", "a:=true", "-p", "b:=1.5", "-r", "/x:=/y"]
    env = private_ros_env(None)
    assert 101 <= int(env["ROS_DOMAIN_ID"]) <= 215 and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"


def test_node_command_quotes_mappings_and_empty_strings_but_not_numbers():
    cmd = node_command("x", {"backend_options": "{lockstep: true}", "camera": "", "rate_hz": "100.0", "name": "cam"})
    assert cmd[-8:] == [
        "-p",
        "backend_options:='{lockstep: true}'",
        "-p",
        "camera:=''",
        "-p",
        "rate_hz:=100.0",
        "-p",
        "name:=cam",
    ]


def test_composed_command_writes_each_nodes_parameters_under_its_name(tmp_path):
    import yaml

    from equidiff_core.twin.processes import composed_command
    from equidiff_ros.composed import parse_nodes

    cmd = composed_command(
        {"voxel_node": {"slop_s": 0.15, "use_sim_time": True}, "policy_node": {"seed": 3}, "cam_a": {"camera": "a"}},
        tmp_path / "p.yaml",
        {"policy_node": {"/franka/command_chunk": "/twin/policy_chunk"}},
        kinds={"voxel_node": "voxel_node", "cam_a": "camera_node"},
    )
    i = cmd.index("--nodes")
    assert cmd[i + 1] == "voxel_node,policy_node,cam_a=camera_node"
    assert cmd[i + 2 :] == [
        "--ros-args",
        "--params-file",
        str(tmp_path / "p.yaml"),
        "-r",
        "policy_node:/franka/command_chunk:=/twin/policy_chunk",
    ]
    assert yaml.safe_load((tmp_path / "p.yaml").read_text()) == {
        "voxel_node": {"ros__parameters": {"slop_s": 0.15, "use_sim_time": True}},
        "policy_node": {"ros__parameters": {"seed": 3}},
        "cam_a": {"ros__parameters": {"camera": "a"}},
    }
    nodes, rest = parse_nodes(cmd[i:])
    assert nodes == [("voxel_node", "voxel_node"), ("policy_node", "policy_node"), ("cam_a", "camera_node")]
    assert rest[0] == "--ros-args"
    for bad in (
        ["--nodes", "voxel_node,twin_node"],
        ["--nodes", "voxel_node,voxel_node"],
        ["--nodes", "a=camera_node,a=voxel_node"],
        ["--nodes", "=camera_node"],
        ["--nodes", "a=twin_node"],
        ["--ros-args"],
    ):
        with pytest.raises(ValueError):
            parse_nodes(bad)


def test_process_group_detects_deaths_and_stops_whole_process_trees(tmp_path):
    env = dict(os.environ)
    with ProcessGroup(env, tmp_path, grace_s=2.0) as group:
        # a "node" that ignores SIGINT and has a child: both must still be gone afterwards
        tree = group.start(
            "stubborn",
            [
                sys.executable,
                "-c",
                (
                    "import signal, subprocess, sys, time; signal.signal(signal.SIGINT, signal.SIG_IGN);"
                    "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)']);"
                    "print(p.pid, flush=True); time.sleep(60)"
                ),
            ],
        )
        group.start("dies", [sys.executable, "-c", "print('bad config'); raise SystemExit(3)"])
        time.sleep(1.0)
        with pytest.raises(NodeProcessError, match="(?s)dies exited with code 3.*bad config"):
            group.check()
        group.stop("dies")
        group.check()
        child = int((tmp_path / "stubborn.log").read_text().split()[0])
    assert tree.popen.poll() is not None
    time.sleep(0.2)
    try:  # gone, or a zombie waiting for init to reap it
        assert Path(f"/proc/{child}/stat").read_text().split()[2] == "Z"
    except FileNotFoundError:
        pass


def test_a_process_group_stops_its_clients_together_and_then_their_server(tmp_path):
    """twin_node serves franky-sim and the cameras' shared memory: every other node must be gone before
    it is stopped; those others are stopped together, not one after another."""
    node = (
        "import signal, sys, time\n"
        "def leave(*_):\n"
        "    print('got', time.monotonic(), flush=True); time.sleep(2.0)\n"
        "    print('bye', time.monotonic(), flush=True); sys.exit(0)\n"
        "signal.signal(signal.SIGINT, leave); print('up', flush=True); time.sleep(60)\n"
    )
    names = ("server", "client_a", "client_b")
    with ProcessGroup(dict(os.environ), tmp_path, grace_s=10.0, servers=("server",)) as group:
        for name in names:
            group.start(name, [sys.executable, "-c", node])
        deadline = time.monotonic() + 60
        while not all("up" in (tmp_path / f"{n}.log").read_text() for n in names) and time.monotonic() < deadline:
            time.sleep(0.05)

    def stamps(name: str) -> dict[str, float]:
        return {
            k: float(v)
            for k, v in (line.split() for line in (tmp_path / f"{name}.log").read_text().split("\n")[1:] if line)
        }

    server, a, b = (stamps(n) for n in names)
    assert server["got"] > max(a["bye"], b["bye"])  # the server outlived its clients
    assert max(a["got"], b["got"]) < min(a["bye"], b["bye"])  # both clients were told before either left


@pytest.mark.ros
def test_nodes_shut_down_when_their_job_is_killed(ros_domain, tmp_path):
    """A job killed with SIGKILL cannot stop its nodes (their own sessions): they notice and exit."""
    job_script = (
        "import sys, time; from pathlib import Path;"
        "from equidiff_core.twin.processes import ProcessGroup, node_command, private_ros_env;"
        "g = ProcessGroup(private_ros_env(), Path(sys.argv[1])).__enter__();"
        "print(g.start('voxel_node', node_command('voxel_node')).popen.pid, flush=True); time.sleep(600)"
    )
    job = subprocess.Popen([sys.executable, "-c", job_script, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    node_pid = int(job.stdout.readline())
    log = tmp_path / "voxel_node.log"
    deadline = time.monotonic() + 60
    while "fusing" not in log.read_text() and time.monotonic() < deadline:  # the node is up and spinning
        time.sleep(0.2)
    job.kill()
    job.wait()
    deadline = time.monotonic() + 20
    while _alive(node_pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    alive = _alive(node_pid)
    if alive:
        os.kill(node_pid, signal.SIGKILL)
    assert not alive, log.read_text()
    assert "the job that started this node is gone" in log.read_text()


def _alive(pid: int) -> bool:
    try:  # a zombie waiting for init to reap it counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except FileNotFoundError:
        return False


def test_twin_node_help():
    out = subprocess.run(
        [sys.executable, "-m", "equidiff_ros.twin_node", "--help"], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0 and "/twin/reset" in out.stdout


@pytest.mark.ros
@pytest.mark.sim
def test_twin_node_resets_from_a_seed_and_reports_state(ros_domain, tmp_path):
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import Int64, String

    from equidiff_core.twin import TwinConfig, sample_scene
    from equidiff_ros.common import LATCHED_QOS, RELIABLE_QOS

    shm = f"equidiff_twin_nodetest_{os.getpid()}"
    with open(tmp_path / "twin.log", "w") as log:  # the child keeps its own copy of the descriptor
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "equidiff_ros.twin_node",
                "--ros-args",
                "-p",
                "host:=auto",
                "-p",
                "seed:=3",
                "-p",
                f"shm_name:={shm}",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    rclpy.init()
    node = Node("twin_probe")
    got = {"scene": [], "state": []}
    node.create_subscription(String, "/twin/scene", lambda m: got["scene"].append(json.loads(m.data)), LATCHED_QOS)
    node.create_subscription(String, "/twin/state", lambda m: got["state"].append(json.loads(m.data)), RELIABLE_QOS)
    reset = node.create_publisher(Int64, "/twin/reset", RELIABLE_QOS)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and not (got["state"] and got["scene"]):
            rclpy.spin_once(node, timeout_sec=0.1)
        assert got["scene"] and got["scene"][-1]["seed"] == 3, (tmp_path / "twin.log").read_text()
        assert os.path.exists(f"/dev/shm/{shm}")
        reset.publish(Int64(data=42))
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and got["scene"][-1]["seed"] != 42:
            rclpy.spin_once(node, timeout_sec=0.1)
        scene = got["scene"][-1]
        expected = sample_scene(TwinConfig().scene, 42)
        assert scene["seed"] == 42 and scene["block_xy"] == pytest.approx(expected.block_xy)
        got["state"].clear()
        while not got["state"]:
            rclpy.spin_once(node, timeout_sec=0.1)
        state = got["state"][-1]
        assert state["seed"] == 42 and state["success"] is False
        assert state["objects"]["block"]["xyz"][:2] == pytest.approx(expected.block_xy, abs=0.01)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=20)
    assert code == 0, (tmp_path / "twin.log").read_text()
    assert not os.path.exists(f"/dev/shm/{shm}")  # shared memory released on shutdown


def _pids_mentioning(text: str) -> list[int]:
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                if text in (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"):
                    pids.append(int(proc.name))
            except OSError:
                pass
    return pids


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.sim
def test_main_job_smoke_run_end_to_end(ros_domain, tmp_path):
    out = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # a domain from the top of the range (221-232), away from other tests' 1-100 and the twin's default
    # 101-215: a stray policy or teleop in the same domain would command this robot
    domain = 221 + ros_domain % 12
    proc = run_job(
        [
            sys.executable,
            "-m",
            "equidiff_ros.cli",
            "twin",
            "run",
            "--smoke",
            "--out",
            str(out),
            "--domain",
            str(domain),
        ],
        timeout_s=420,
        env=env,
        log_dir=tmp_path,
    )
    logs = "\n".join(f"== {p.name}\n{p.read_text()[-1500:]}" for p in sorted((out / "logs").glob("*.log")))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:] + logs
    last = json.loads(proc.stdout.strip().splitlines()[-1])
    assert REQUIRED_KEYS <= set(last) and last["episodes"] == 1
    # simulated time: the policy answers every observation, each chunk takes effect at its
    # observation + L, however slow this (shared, busy) machine is
    assert last["clock"] == "sim" and last["latency_budget_ms"] == 100.0 and last["wall_s"] > 0
    assert last["stalled_episodes"] == 0 and last["representative"] is True
    assert last["dropped_cycles"] == 0, proc.stdout[-2000:]  # no observation due an answer went without
    assert last["chunks"] >= 4  # 8 s of episode, a chunk of 8 steps (1.6 s) executed per answer
    assert last["end_to_end_p95_ms"] <= 100.0 + 200.0
    assert "untrained stand-in" in proc.stdout  # the smoke run says what it ran
    # the policy's chunks reached the robot through the gate, and the episode was recorded
    summary = proc.stdout
    assert "success rate" in summary and "end to end" in summary
    bags = list((out / "bags").glob("twin_eval_*"))
    assert len(bags) == 1 and (bags[0] / "metadata.yaml").is_file()
    from equidiff_core.data.bags import read_episode

    episode = read_episode(bags[0])
    assert episode.meta.success is not None
    franka_log = (out / "logs" / "franka_node.log").read_text()
    assert "stale" not in franka_log, franka_log[-2000:]  # no chunk rejected as stale
    assert (out / "twin_run.rrd").is_file() or "rerun" in proc.stderr
    # every node process is gone
    assert _pids_mentioning(str(out)) == []


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.sim
def test_twin_collect_over_ros_records_the_experts_demo_with_its_seed(ros_domain, tmp_path):
    """`equidiff twin collect` through the live graph (teleop-style chunks, recorder_node): the
    same episode sequence as the main job, and a kept demo the dataset reads."""
    from equidiff_core.data.bags import read_meta

    out = tmp_path / "demos"
    proc = run_job(
        [
            sys.executable,
            "-m",
            "equidiff_ros.cli",
            "twin",
            "collect",
            "--episodes",
            "1",
            "--seed",
            "4",
            "--yaw-range",
            "-10",
            "10",
            "--out",
            str(out),
            "--domain",
            str(221 + (ros_domain + 3) % 12),
        ],
        timeout_s=420,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        log_dir=tmp_path,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    last = json.loads(proc.stdout.strip().splitlines()[-1])
    assert last["episodes"] == 1 and last["successes"] == 1 and last["kept"] == 1 and last["mode"] == "ros"
    bags = list((out / "bags").glob("twin_block_in_bowl_*"))
    assert len(bags) == 1
    meta = read_meta(bags[0])
    assert meta.success is True and meta.seed == 4 and "scripted expert" in (meta.notes or "")
    assert meta.extra["block_yaw_range_deg"] == "-10,10" and abs(float(meta.extra["block_yaw_deg"])) <= 10.0


def test_generalisation_eval_scenes_have_unseen_block_yaw_modulo_its_half_turn_symmetry():
    import math

    import pytest

    from equidiff_core.twin import TwinConfig, sample_scene
    from equidiff_core.twin.yaw_range import in_range_yaw_seeds, unseen_yaw_seeds

    cfg = TwinConfig()
    seeds = unseen_yaw_seeds(cfg, (-15.0, 15.0), 12)
    assert len(set(seeds)) == 12
    in_range = in_range_yaw_seeds(cfg, (-15.0, 15.0), 12)  # the bench's control scenes
    assert len(set(in_range)) == 12 and not set(in_range) & set(seeds)
    for s in in_range:
        yaw = math.degrees(sample_scene(cfg.scene, s).block_yaw)
        assert min(abs(yaw - k * 180.0) for k in (-1, 0, 1)) <= 15.0
    for s in seeds:
        yaw = math.degrees(sample_scene(cfg.scene, s).block_yaw)
        # >= 15 deg outside [-15, 15] both ways round and after a half turn (the box looks the same)
        assert min(abs(yaw - k * 180.0) for k in (-1, 0, 1)) > 30.0
    # a scene whose block is a half turn from the training range is not among them
    seeds = unseen_yaw_seeds(cfg, (-15.0, 15.0), 60)
    near_half_turn = [
        s
        for s in range(10_000_000, seeds[-1])
        if abs(abs(math.degrees(sample_scene(cfg.scene, s).block_yaw)) - 180.0) < 15.0
    ]
    assert near_half_turn and not set(near_half_turn) & set(seeds)
    # and the training-range config never draws such yaws
    narrow = cfg.with_yaw_range((-15.0, 15.0))
    assert all(abs(math.degrees(sample_scene(narrow.scene, s).block_yaw)) <= 15.0 for s in seeds)
    with pytest.raises(ValueError, match="no unseen"):
        unseen_yaw_seeds(cfg, (-80.0, 80.0), 1)
    with pytest.raises(ValueError, match="yaw range empty"):  # not an endless search
        in_range_yaw_seeds(cfg, (5.0, 5.0), 1)


def test_bench_and_collect_commands_parse():
    from equidiff_ros.cli import build_parser

    for argv in (
        ["bench", "generalization", "--quick"],
        ["twin", "collect", "--episodes", "2", "--out", "x", "--direct"],
        ["twin", "run", "--smoke"],
    ):
        args = build_parser(argv).parse_args(argv)
        assert not getattr(args, "_missing", False), argv


def test_the_in_process_twin_jobs_refuse_what_they_cannot_run_with_one_line_and_exit_1(tmp_path, capsys):
    from equidiff_ros.cli import main

    assert main(["twin", "evaluate", "--episodes", "0"]) == 1
    assert capsys.readouterr().err == "equidiff twin evaluate: --episodes must be at least 1\n"
    assert main(["twin", "replay-chunks", str(tmp_path)]) == 1
    assert capsys.readouterr().err == f"equidiff twin replay-chunks: no bags in {tmp_path}\n"


def test_nodes_never_inherit_a_real_time_scheduling_policy():
    """A job whose thread had become SCHED_FIFO 99 (libfranka's doing) started every node real-time:
    busy camera and voxel nodes then starved the machine. Nodes always start time-shared."""
    import os
    import subprocess
    import sys

    from equidiff_core.twin.processes import node_preexec

    if not hasattr(os, "sched_setscheduler"):
        pytest.skip("no POSIX scheduling API here")
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except PermissionError:
        pytest.skip("setting a real-time policy needs root or CAP_SYS_NICE")
    probe = [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"]
    try:
        node = subprocess.run(probe, preexec_fn=node_preexec(priority=True), capture_output=True, text=True, timeout=30)
        plain = subprocess.run(probe, capture_output=True, text=True, timeout=30)
    finally:
        os.sched_setscheduler(0, *before)
    assert int(plain.stdout) == os.SCHED_FIFO  # what a plain child inherits
    assert int(node.stdout) == os.SCHED_OTHER


@pytest.mark.slow
def test_bench_generalization_reports_a_failed_training_run_and_keeps_the_demos(tmp_path, capsys):
    from equidiff_ros.cli import main

    demos = tmp_path / "demos"
    demos.mkdir()  # no bags: equidiff train refuses them
    assert (
        main(
            [
                "bench",
                "generalization",
                "--demos-dir",
                str(demos),
                "--out",
                str(tmp_path / "run"),
                "--preset",
                "tiny",
                "--train-steps",
                "2",
                "--device",
                "cpu",
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert "equidiff train equidiff failed" in err and f"--demos-dir {demos}" in err
    assert "Traceback" not in err


@pytest.mark.slow
def test_bench_generalization_evaluates_policies_trained_elsewhere_in_range_first(tmp_path, capsys):
    """--trained DIR: policies trained on another machine (a GPU box) are rolled out here, no
    demos recorded and nothing trained; the steps they trained come from their history. Every
    policy is rolled out in range first; one that fails there (1 s episodes solve nothing) is
    named, the budget called too small, and nothing is rolled out at unseen yaw (exit 3)."""
    import json
    import shutil

    from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT
    from equidiff_ros.cli import main

    trained = tmp_path / "trained"
    assert main(["bench", "generalization", "--trained", str(trained), "--out", str(tmp_path / "a")]) == 2
    assert "--trained needs DIR/equidiff/policy.pt, DIR/baseline/policy.pt, DIR/baseline_aug/policy.pt" in (
        capsys.readouterr().err
    )
    steps = {"equidiff": 120, "baseline": 150, "baseline_aug": 140}
    for name, n in steps.items():  # the shipped policy stands in for all three
        (trained / name).mkdir(parents=True)
        shutil.copy(SHIPPED_CHECKPOINT, trained / name / "policy.pt")
        (trained / name / "history.json").write_text(json.dumps([{"step": n, "loss": 0.1}]))
    argv = ["bench", "generalization", "--trained", str(trained), "--out", str(tmp_path / "b")]
    argv += ["--eval-episodes", "1", "--in-range-episodes", "1", "--max-duration", "1", "--device", "cpu"]
    assert main(argv) == 3
    captured = capsys.readouterr()
    result = json.loads(captured.out.strip().splitlines()[-1])
    for name in steps:
        assert captured.out.count(f"[{name}, in_range] [eval]") == 1
        assert result[f"{name}_in_range_success"] == 0.0 and result[f"{name}_success"] is None
    assert "unseen] [eval]" not in captured.out
    assert result["failed_in_range"] == ["equidiff", "baseline", "baseline_aug"] and result["min_in_range"] == 0.6
    assert "training budget is too small" in result["verdict"] and result["verdict"] in captured.err
    assert result["goal_met"] is None and result["equidiff_minus_baseline_points"] is None
    assert result["stages"]["equidiff"].keys() == {"in_range"}
    assert result["stages"]["baseline"]["in_range"].keys() == {"reached", "lifted", "median_closest_to_block_m"}
    assert result["train_steps_by_policy"] == steps and result["train_steps"] == 120
    assert result["minutes"].keys() == {"eval"}  # nothing recorded or trained here
    assert result["rotation_aug"] == dict.fromkeys(steps, "continuous")  # as the shipped policy was trained
    assert result["training_recipes"] == dict.fromkeys(steps)  # no run.json next to them


def test_in_range_gate_names_the_policies_below_it():
    from equidiff_core.benches.generalization import in_range_failures

    rates = {"equidiff": 0.7, "baseline": 0.5, "baseline_aug": 0.6}
    assert in_range_failures(rates, 0.6) == ["baseline"]
    assert in_range_failures(rates, 0.0) == []
    assert in_range_failures({"equidiff": None, "baseline": None}, 0.6) == []  # no in-range scenes: no gate


def test_shipped_checkpoint_loads_and_its_training_is_recorded():
    """The checkpoint `equidiff twin run` uses by default: loadable, plain torch, documented next to it."""
    import numpy as np

    from equidiff_core.policy.inference import load_inference_policy
    from equidiff_core.twin.shipped import SHIPPED_CHECKPOINT

    assert SHIPPED_CHECKPOINT.is_file(), SHIPPED_CHECKPOINT
    assert SHIPPED_CHECKPOINT.stat().st_size < 20 * 2**20  # small enough for the repository
    readme = (SHIPPED_CHECKPOINT.parent / "README.md").read_text()
    assert "equidiff train" in readme and "equidiff twin collect" in readme
    policy = load_inference_policy(SHIPPED_CHECKPOINT)
    grid = np.zeros((4, 64, 64, 64), np.uint8)
    ee = np.array([0.45, 0.0, 0.3, 1, 0, 0, 0, -1, 0, 0.08], np.float32)
    actions = policy.predict(grid, ee, seed=0)
    assert actions.shape == (policy.preset.horizon, 10) and np.isfinite(actions).all()

    # its training state is kept beside it (`equidiff train --resume`), at the step its history ends, without
    # AdamW's moments (a resume starts fresh ones): the file stays small enough to keep in git
    from equidiff_core.policy.presets import preset_from_dict
    from equidiff_core.training.loop import load_policy_from_checkpoint, load_training_checkpoint

    state = load_training_checkpoint(SHIPPED_CHECKPOINT.parent / "last.ckpt")
    history = json.loads((SHIPPED_CHECKPOINT.parent / "history.json").read_text())
    assert state["step"] == max(row["step"] for row in history)
    assert preset_from_dict(state["config"]["preset"]) == policy.preset
    assert state["optimizer"] is None and state["ema"] is not None
    assert (SHIPPED_CHECKPOINT.parent / "last.ckpt").stat().st_size < 20 * 2**20
    # the learned state only, without escnn's eval-mode caches; it loads strictly into a fresh model
    assert not any(k.endswith((".filter", ".expanded_bias")) for k in state["model"])
    assert load_policy_from_checkpoint(SHIPPED_CHECKPOINT.parent / "last.ckpt").preset == policy.preset


def _generalization_settings(*flags: str):
    """The settings `equidiff bench generalization FLAGS` runs with."""
    from equidiff_ros.cli import build_parser
    from equidiff_ros.commands.bench_generalization import generalization_settings

    argv = ["bench", "generalization", *flags]
    return generalization_settings(build_parser(argv).parse_args(argv))


def test_bench_generalization_quick_is_a_smaller_bench_and_leaves_the_settings_asked_for_as_they_were():
    quick, full = _generalization_settings("--quick"), _generalization_settings()
    assert (quick.demos, quick.recipe.steps, quick.recipe.preset, quick.eval_episodes) == (4, 30, "tiny", 1)
    assert quick.min_in_range == quick.max_fit_ratio == 0.0  # no gate: no policy acts after 30 steps
    assert (quick.in_range_episodes, quick.max_duration) == (1, 6.0)
    assert full.quick() == quick and (full.demos, full.recipe.steps, full.recipe.preset) == (40, 6000, "compact")


@pytest.mark.slow
def test_bench_generalization_trains_its_policies_side_by_side_sharing_the_cores(tmp_path, monkeypatch):
    import dataclasses
    import os
    import subprocess
    import sys
    import time

    import pytest

    from equidiff_core.benches import generalization as bench

    runs = {}
    script = (
        "import pathlib, sys, time; time.sleep(float(sys.argv[2])); "
        "pathlib.Path(sys.argv[1]).write_text(str(time.time())); sys.exit(int(sys.argv[3]))"
    )
    behaviour = {"equidiff": (0.3, 0), "baseline": (0.3, 0), "baseline_aug": (0.3, 0)}  # seconds, exit code

    def fake_start(policy, bags, out, settings, threads):
        out.mkdir(parents=True, exist_ok=True)
        (out / "train.log").write_text(f"{policy} log line\n")
        runs[policy] = (time.time(), threads, settings.recipe.steps)
        seconds, code = behaviour[policy]
        return subprocess.Popen([sys.executable, "-c", script, str(out / "policy.pt"), str(seconds), str(code)])

    monkeypatch.setattr(bench, "_start_training", fake_start)
    settings = _generalization_settings("--train-steps", "7")
    policies = bench._train_all(tmp_path / "demos", tmp_path, settings)
    assert policies == {name: tmp_path / name / "policy.pt" for name in ("equidiff", "baseline", "baseline_aug")}
    started = {name: runs[name][0] for name in policies}
    ended = {name: float(policies[name].read_text()) for name in policies}
    assert max(started.values()) < min(ended.values())  # the three runs overlapped
    assert {runs[name][1] for name in policies} == {max(1, (os.cpu_count() or 2) // 3)}
    assert runs["equidiff"][2] == 7

    # one run failing stops the other at once and is reported with its log; nothing waits 60 s
    behaviour.update(equidiff=(0.0, 3), baseline=(60.0, 0), baseline_aug=(60.0, 0))
    t0 = time.monotonic()
    with pytest.raises(bench.TrainRunError) as err:
        bench._train_all(tmp_path / "demos", tmp_path / "second", settings)
    assert time.monotonic() - t0 < 20
    message = str(err.value)
    assert "equidiff train equidiff failed (exit 3" in message and "equidiff log line" in message
    assert "equidiff train baseline" not in message  # stopped by the bench, not failures of their own

    # --policies: only those train now, and they get the cores the others would have had
    runs.clear()
    behaviour.update(equidiff=(0.0, 0), baseline=(0.0, 0))
    settings = dataclasses.replace(settings, policies=("baseline",))
    assert bench._train_all(tmp_path / "demos", tmp_path / "third", settings) == {
        "baseline": tmp_path / "third" / "baseline" / "policy.pt"
    }
    assert runs.keys() == {"baseline"} and runs["baseline"][1] == max(1, os.cpu_count() or 2)


def test_the_bench_names_the_recipe_settings_its_policies_were_trained_with_differently():
    from equidiff_core.benches.training_runs import recipe_differences

    base = {"preset": "compact", "batch_size": 8, "lr": 5e-4, "ema": True, "rotation_aug": "none", "device": "cpu"}
    recipes = {
        "equidiff": base,
        "baseline": {**base, "device": "cuda", "max_minutes": 60.0},  # how fast, not what: allowed
        "baseline_aug": {**base, "rotation_aug": "continuous", "lr": 1e-4},  # the augmentation is the point
    }
    assert recipe_differences(recipes) == ["lr: equidiff 0.0005, baseline 0.0005, baseline_aug 0.0001"]
    assert recipe_differences({**recipes, "baseline_aug": None}) == []  # no run.json: nothing to compare
    assert recipe_differences({**recipes, "baseline": {**base, "noise_repeats": 4}}) == [
        "lr: equidiff 0.0005, baseline 0.0005, baseline_aug 0.0001",
        "noise_repeats: equidiff None, baseline 4, baseline_aug None",
    ]
    # each policy at the learning rate the bench names for it (the baselines' own): checked one by one
    lrs = {"equidiff": 5e-4, "baseline": 1e-3, "baseline_aug": 1e-3}
    assert recipe_differences(recipes, lrs) == [
        "lr: baseline 0.0005 where the bench asks for 0.001, baseline_aug 0.0001 where the bench asks for 0.001"
    ]
    fitting = {**recipes, "baseline": {**base, "lr": 1e-3}, "baseline_aug": {**base, "lr": 1e-3}}
    assert recipe_differences(fitting, lrs) == [] and recipe_differences(fitting) == [
        "lr: equidiff 0.0005, baseline 0.001, baseline_aug 0.001"
    ]


@pytest.mark.slow
@pytest.mark.sim
def test_bench_generalization_trains_in_parts_and_rolls_out_once_all_three_share_a_recipe(
    tmp_path, capsys, monkeypatch
):
    """On a small CPU one policy fills a working session: --policies trains a subset into --out and
    says what is pending; the call that completes the set rolls all three out, and policies trained
    with different recipes are refused rather than compared."""
    import json

    from helpers_model import export_tiny_baseline

    from equidiff_core.benches import generalization as bench
    from equidiff_ros.cli import main

    started = []

    def fake_start(name, bags, out, settings, threads):  # an instant `equidiff train`
        started.append(name)
        out.mkdir(parents=True, exist_ok=True)
        export_tiny_baseline(out / "policy.pt")
        (out / "history.json").write_text(json.dumps([{"step": settings.recipe.steps, "loss": 0.1}]))
        policy, rotation_aug = bench._recipe(name, settings)
        lr = settings.recipe.lr_of(policy)  # as the real run's
        recipe = {"preset": "tiny", "batch_size": settings.recipe.batch_size, "lr": lr, "ema": settings.recipe.ema}
        (out / "run.json").write_text(json.dumps({"recipe": {**recipe, "rotation_aug": rotation_aug}}))
        return subprocess.Popen([sys.executable, "-c", "pass"])

    monkeypatch.setattr(bench, "_start_training", fake_start)
    demos, out = tmp_path / "demos", tmp_path / "gen"
    demos.mkdir()
    argv = ["bench", "generalization", "--demos-dir", str(demos), "--out", str(out), "--train-steps", "5"]
    argv += ["--ema", "--eval-episodes", "1", "--in-range-episodes", "1", "--max-duration", "1", "--device", "cpu"]

    assert main([*argv, "--policies", "equidiff"]) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert started == ["equidiff"] and first["trained"] == ["equidiff"]
    assert first["pending"] == ["baseline", "baseline_aug"] and "--policies baseline baseline_aug" in first["next"]

    # a second session trains the other two with another batch size: refused, nothing rolled out
    assert main([*argv, "--policies", "baseline", "baseline_aug", "--batch-size", "4"]) == 2
    captured = capsys.readouterr()
    assert "not trained with the same recipe (batch_size: equidiff 8, baseline 4, baseline_aug 4)" in captured.err
    assert "[eval]" not in captured.out
    # ... or called with another learning rate than the one EquiDiff was trained at: refused too
    assert main([*argv, "--policies", "baseline", "baseline_aug", "--lr", "1e-4"]) == 2
    captured = capsys.readouterr()
    assert "(lr: equidiff 0.0005 where the bench asks for 0.0001)" in captured.err
    assert "[eval]" not in captured.out

    # the same recipe: all three are rolled out (in range first; untrained, they fail the gate)
    assert main([*argv, "--policies", "baseline", "baseline_aug"]) == 3
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert started == ["equidiff", *["baseline", "baseline_aug"] * 3]
    assert result["failed_in_range"] == ["equidiff", "baseline", "baseline_aug"]
    assert result["train_steps_by_policy"] == {"equidiff": 5, "baseline": 5, "baseline_aug": 5}
    assert result["training_recipes"]["baseline_aug"]["rotation_aug"] == "continuous"


@pytest.mark.slow
@pytest.mark.sim
def test_bench_generalization_quick_runs_end_to_end_on_the_cpu(tmp_path, capsys):
    """The benchmark runs on this CPU: one narrow-yaw demo recorded, the
    three policies trained side by side from it (tiny preset), all rolled out; one JSON line."""
    import json

    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.twin import TwinConfig
    from equidiff_core.twin.demos import collect_direct
    from equidiff_ros.cli import main

    demos = tmp_path / "demos"
    lab = load_lab_config(default_config_dir() / "lab.yaml")
    assert collect_direct(TwinConfig().with_yaw_range((-15.0, 15.0)), lab, demos, [0], log=lambda s: None)[0][1]
    # demos drawn from another yaw range than the bench's are refused before any training
    other = ["--demos-dir", str(demos), "--train-yaw", "-30", "30", "--out", str(tmp_path / "other")]
    assert main(["bench", "generalization", "--quick", *other]) == 2
    assert "another block yaw range than --train-yaw -30 30" in capsys.readouterr().err
    assert not (tmp_path / "other" / "equidiff").exists()
    assert (
        main(
            [
                "bench",
                "generalization",
                "--quick",
                "--demos-dir",
                str(demos),
                "--device",
                "cpu",
                "--out",
                str(tmp_path / "run"),
            ]
        )
        == 0
    )
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("equidiff_success", "baseline_success", "demos", "train_steps", "eval_episodes", "train_yaw_range_deg"):
        assert key in result, key
    assert result["demos"] == 1 and result["train_steps_by_policy"] == {
        "equidiff": 30,
        "baseline": 30,
        "baseline_aug": 30,
    }
    assert result["rotation_aug"] == {"equidiff": "none", "baseline": "none", "baseline_aug": "continuous"}
    assert result["preset"] == "tiny" and result["min_in_range"] == 0.0 and result["failed_in_range"] == []
    assert 0.0 <= result["baseline_aug_success"] <= 1.0 and isinstance(result["goal_met"], bool)
    assert {r["device"] for r in result["training_recipes"].values()} == {"cpu"}
    assert json.loads((tmp_path / "run" / "result.json").read_text()) == result


@pytest.mark.slow
@pytest.mark.sim
def test_twin_evaluate_rolls_out_the_main_jobs_seeds_in_process(tmp_path, capsys):
    """`equidiff twin evaluate`: twin run's seeds (100000, 100001, ...) in-process, one line per
    episode and a JSON summary; a missing checkpoint is a clear error, not a traceback."""
    import json

    from equidiff_ros.cli import main

    assert main(["twin", "evaluate", "--checkpoint", str(tmp_path / "none.pt")]) == 1
    assert capsys.readouterr().err == f"equidiff twin evaluate: no checkpoint at {tmp_path / 'none.pt'}\n"
    assert main(["twin", "evaluate", "--episodes", "2", "--max-duration", "0.6"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    result = json.loads(out[-1])
    assert [line.split()[2] for line in out if line.startswith("[eval]")] == ["100000", "100001"]
    assert result["episodes"] == 2 and result["success"] == 0 and result["successful_seeds"] == []
    assert result["latency_budget_ms"] == 100.0 and result["max_duration_s"] == 0.6
