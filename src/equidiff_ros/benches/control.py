"""The franka node on franky-sim (``equidiff bench control``): tracking, hold, workspace, NaN and policy latency.

Each phase is a function of a running ``ControlClient`` (``run_track_and_hold``, ``run_workspace``,
``run_nan``, ``run_latency``) that the tests call directly; ``run_control_bench`` starts franky-sim and the
nodes, runs them in order and prints one JSON line. The command's help text says what each phase measures.
It needs rclpy (the client is a ROS node), so it lives beside the nodes, not in the ROS-free core.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from trajectory_msgs.msg import MultiDOFJointTrajectory

from equidiff_core import geometry
from equidiff_core.config import default_config_dir, dump_yaml, load_lab_config, to_dict
from equidiff_core.control import load_control_config, metrics
from equidiff_core.policy.diffusion import make_policy
from equidiff_core.policy.file import export_policy
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.normalizer import Normalizer
from equidiff_core.policy.presets import get_preset
from equidiff_core.robots.franky.sim import SimServer
from equidiff_core.twin.processes import join_private_domain, start_node, stop_process
from equidiff_core.wire.chunk import PoseChunk, chunk_from_msg, chunk_to_msg
from equidiff_core.wire.pointcloud import grid_to_voxel_msg
from equidiff_core.wire.topics import TOPIC_COMMAND_CHUNK
from equidiff_ros.common import RELIABLE_QOS
from equidiff_ros.control_client import MS, ControlClient, down_pose

# --- the reference path ------------------------------------------------------------------


@dataclass(frozen=True)
class Circle:
    """Horizontal circle, counter-clockwise from angle 0, TCP pointing down (the home orientation)."""

    center: tuple[float, float, float] = (0.45, 0.0, 0.25)
    radius: float = 0.05
    speed: float = 0.06
    t0: float = 0.0  # time (s) at which the TCP should be at angle 0

    def position(self, t: float) -> np.ndarray:
        a = self.speed / self.radius * max(t - self.t0, 0.0)
        return np.asarray(self.center) + self.radius * np.array([np.cos(a), np.sin(a), 0.0])

    def tangent(self, t: float) -> np.ndarray:
        a = self.speed / self.radius * max(t - self.t0, 0.0)
        return np.array([-np.sin(a), np.cos(a), 0.0])

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Each point's distance (m) from the circle as a curve, wherever along it: how far off the
        path, not how late on it (a sim starved of CPU makes the TCP late, which this ignores)."""
        offset = np.asarray(points, dtype=float) - np.asarray(self.center)
        return np.hypot(np.hypot(offset[:, 0], offset[:, 1]) - self.radius, offset[:, 2])

    def arc_length(self, points: np.ndarray) -> float:
        """How far (m) along the circle the points went, counter-clockwise from the first to the last."""
        offset = np.asarray(points, dtype=float) - np.asarray(self.center)
        angle = np.unwrap(np.arctan2(offset[:, 1], offset[:, 0]))
        return float((angle[-1] - angle[0]) * self.radius)


def export_untrained(preset: str, path: Path, workspace) -> Path:
    """An untrained policy of ``preset`` with the workspace's default normaliser, for timing only."""
    policy = make_policy("equidiff", get_preset(preset), workspace)
    policy.set_normalizer(Normalizer.from_workspace(workspace))
    return export_policy(policy, path)


def approach(client: ControlClient, target: np.ndarray, speed: float = 0.05, settle: float = 0.5) -> None:
    """Stream a straight line from the current TCP position to ``target`` (the node rejects jumps)."""
    start = client.latest_position()
    t_start = client.now()
    length = float(np.linalg.norm(target - start))
    duration = max(length / speed, 0.2)

    def path(t):
        s = np.clip((t - t_start) / duration, 0.0, 1.0)
        return start + s * (target - start)

    client.stream(path, duration + settle, obs_latency=0.0)


def run_track_and_hold(
    client: ControlClient,
    speed: float,
    radius: float,
    duration: float,
    settle: float,
    obs_latency: float,
    watchdog_s: float,
) -> dict:
    circle = Circle(radius=radius, speed=speed)
    approach(client, circle.position(0.0))
    circle = Circle(radius=radius, speed=speed, t0=client.now() + 0.3)
    approach_end = circle.t0

    def path(t):
        return circle.position(t) if t >= approach_end else circle.position(0.0)

    last_send, last_step = client.stream(path, duration + 0.3, obs_latency=obs_latency)
    t_from, t_to = circle.t0 + settle, last_send
    times, positions = client.samples("poses", t_from, t_to)
    t_times, t_positions = client.samples("targets", t_from, t_to)
    # Hold: the last chunk runs to its final step; the watchdog fires ~watchdog_s after that.
    # Find when the node's executed target froze (it holds the TCP pose it measured then), and
    # measure 2 s from there.
    client.sleep_until(last_step + watchdog_s + 2.5)
    e_times, e_positions = client.samples("targets", last_step, last_step + watchdog_s + 2.5)
    hold_start = metrics.settle_time(e_times, e_positions, tol_m=2e-4)
    if hold_start is None:
        hold_start = last_step + watchdog_s
    _h_times, h_positions = client.samples("poses", hold_start, hold_start + 2.0)
    at_rest = wait_for_rest(client, hold_start)
    _, held_targets = client.samples("targets", hold_start, at_rest or client.now())
    rest_position = client.latest_position()
    lag, lag_rms = metrics.tracking_lag(times, positions, circle.position)
    # the commanded TCP at each chunk switch (this process receives its own chunks as franka_node does),
    # on a 50 Hz grid: a state message that repeats a command would otherwise read as a standstill
    switches = [r for r, _ in list(client.data.chunks) if t_from <= r <= t_to]
    grid_t, grid_p = metrics.resample(t_times, t_positions, hz=50.0)
    standstill = metrics.standstill_at_switches(grid_t, grid_p, switches)
    return {
        **{f"track_{k}": v for k, v in metrics.standstill_summary(standstill, t_to - t_from).items()},
        "track_chunk_switches": len(standstill),
        "tracking_rms_mm": round(metrics.tracking_rms(times, positions, circle.position) * 1000, 2),
        "path_rms_mm": round(float(np.sqrt(np.mean(circle.distance(positions) ** 2))) * 1000, 2),
        "arc_travelled_mm": round(circle.arc_length(positions) * 1000, 1),
        "tracking_lag_ms": round(lag * 1000, 1),
        "tracking_rms_after_lag_mm": round(lag_rms * 1000, 2),
        "velocity_reversals": metrics.velocity_reversals(times, positions, circle.tangent),
        "command_rms_mm": round(metrics.tracking_rms(t_times, t_positions, circle.position) * 1000, 2),
        "command_velocity_reversals": metrics.velocity_reversals(t_times, t_positions, circle.tangent),
        "tracking_samples": len(times),
        "state_hz": round(len(times) / max(t_to - t_from, 1e-9), 1),
        # how far the arm went on after the hold engaged: with franka_node on the wall clock and a sim
        # slower than real time the arm is still catching up with the last command when the watchdog
        # fires, so this grows with the machine's load (measured in docs/results/control.md, `equidiff bench control`)
        "hold_drift_mm": round(metrics.max_drift(h_positions, h_positions[0]) * 1000, 2),
        # what the hold is, whatever the load: one target, and the arm come to rest at it
        "hold_target_span_mm": round(float(np.ptp(held_targets, axis=0).max()) * 1000, 3),
        "hold_at_rest_after_s": None if at_rest is None else round(at_rest - hold_start, 2),
        "hold_rest_distance_to_target_mm": round(float(np.linalg.norm(rest_position - held_targets[-1])) * 1000, 2),
        "hold_engaged_after_ms": round((hold_start - last_step) * 1000, 1),
    }


def wait_for_rest(
    client: ControlClient, since: float, still_m: float = 5e-4, window_s: float = 0.5, timeout_s: float = 10.0
) -> float | None:
    """When (the client's clock) the TCP had moved less than ``still_m`` over the last ``window_s``,
    waiting until ``since + timeout_s`` of that clock; None if it never did. On the wall clock a sim
    slower than real time takes longer to come to rest, so this waits rather than looking at a fixed
    window; on simulated time ``timeout_s`` is sim seconds, however long they take."""
    rested: list[float] = []

    def rested_or_late() -> bool:
        now = client.now()
        _, positions = client.samples("poses", now - window_s, now)
        if now - since >= window_s and len(positions) > 1 and np.ptp(positions, axis=0).max() < still_m:
            rested.append(now)
        return bool(rested) or now > since + timeout_s

    # the wall-clock bound only catches a clock that stopped (the sim gone): 10 s at a tenth of real time
    client.wait_for(rested_or_late, 10 * timeout_s, "the arm at rest, or the time limit on the client's clock")
    return rested[0] if rested else None


def run_workspace(client: ControlClient, workspace, duration: float = 3.0) -> dict:
    start = client.latest_position()
    t_start = client.now()
    direction = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)

    def path(t):  # 0.1 m/s diagonally up and out, for long enough to end 25+ cm past the lid
        return start + direction * 0.1 * max(t - t_start, 0.0)

    last, _ = client.stream(path, duration, obs_latency=0.0)
    client.sleep(0.5)
    times, positions = client.samples("poses", t_start, last + 0.5)
    outside = np.linalg.norm(
        np.maximum(workspace.lower - positions, 0) + np.maximum(positions - workspace.upper, 0), axis=1
    )
    worst = int(np.argmax(outside))
    return {
        "worst_outside_at": [round(float(v), 4) for v in positions[worst]],
        "worst_outside_t": round(float(times[worst] - t_start), 2),
        "max_outside_workspace_mm": round(
            metrics.max_outside_box(positions, workspace.lower, workspace.upper) * 1000, 2
        ),
        "workspace_requested_outside_mm": round(
            metrics.max_outside_box(path(last)[None], workspace.lower, workspace.upper) * 1000, 1
        ),
    }


def run_nan(client: ControlClient) -> dict:
    before = int(client.diag_value("franka_node", "nan_rejected", 0))
    now = client.now_ns()
    here = client.latest_position()
    chunk = PoseChunk(
        now, now + np.arange(4, dtype=np.int64) * 200 * MS, np.stack([down_pose(here)] * 4), np.full(4, 0.08)
    )
    msg = chunk_to_msg(chunk, client.factory, client.lab.base_frame)
    msg.points[2].transforms[0].translation.x = float("nan")
    client.pub_chunk.publish(msg)
    t_sent = client.now()
    try:
        client.wait_for(
            lambda: int(client.diag_value("franka_node", "nan_rejected", 0)) > before,
            5.0,
            "the franka node's diagnostics to count the NaN chunk",
        )
    except TimeoutError:
        pass
    client.sleep(0.3)
    alive = any(t > t_sent + 0.1 for t, _ in list(client.data.poses)[-50:])
    return {
        "nan_rejected": int(client.diag_value("franka_node", "nan_rejected", 0)) - before,
        "alive_after_nan": bool(alive),
    }


def synthetic_grid(workspace) -> np.ndarray:
    """A table and a block: a plausible, fixed observation (latency does not depend on it)."""
    rng = np.random.default_rng(0)
    r = workspace.resolution
    grid = np.zeros((4, r, r, r), np.uint8)
    grid[0, :, :, :2] = 255
    i, j = rng.integers(r // 4, 3 * r // 4 - 4, 2)
    grid[0, i : i + 5, j : j + 5, 2:7] = 255
    grid[1:, grid[0] > 0] = 150
    return grid


def bare_predict_s(checkpoint: Path, precision: str, workspace, repeats: int = 5) -> list[float]:
    """Baseline: ``InferencePolicy.predict`` alone, in this process, before anything else runs."""
    policy = load_inference_policy(checkpoint, precision=precision)
    policy.warmup()  # as the node does (bf16 kernels are slow for the first calls)
    grid = synthetic_grid(workspace)
    ee = geometry.pose_to_action(down_pose(workspace.center), np.array(0.08)).astype(np.float32)
    times = []
    for k in range(repeats):
        t0 = time.perf_counter()
        policy.predict(grid, ee, seed=k)
        times.append(time.perf_counter() - t0)
    return times


def run_latency(
    client: ControlClient,
    checkpoint: Path,
    precision: str,
    duration: float,
    log_dir: Path,
    label: str,
    params: dict | None = None,
) -> dict:
    ws = client.lab.workspace
    grid = synthetic_grid(ws)
    received = []  # (receive s, stamp s, last step s, steps) of every chunk

    def on_chunk(msg):
        chunk = chunk_from_msg(msg)
        received.append((client.now(), chunk.stamp_ns / 1e9, chunk.times_ns[-1] / 1e9, len(chunk)))

    subscription = client.node.create_subscription(MultiDOFJointTrajectory, TOPIC_COMMAND_CHUNK, on_chunk, RELIABLE_QOS)
    log_name = "policy_node.log" if not params else "policy_node_baseline.log"
    proc = start_node(
        "policy_node",
        {"checkpoint": str(checkpoint), "precision": precision, "lab_config": client.lab_path, **(params or {})},
        log_dir / log_name,
    )
    try:
        n_before = len(client.data.chunks)
        stamps = set()
        stop = threading.Event()

        def publish_voxels():
            period = 1.0 / client.lab.observation_hz
            while not stop.is_set():
                stamp = client.now_ns()
                stamps.add(stamp / 1e9)
                client.pub_voxels.publish(
                    grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, stamp, client.lab.base_frame, client.factory)
                )
                stop.wait(period)

        feeder = threading.Thread(target=publish_voxels, daemon=True)
        feeder.start()
        try:
            client.wait_for(lambda: len(client.data.chunks) > n_before, 180.0, "the policy node's first chunk", proc)
            t_first = client.now()
            client.sleep(duration)
        finally:
            stop.set()
            feeder.join(timeout=2)
        rows = [(r, s) for r, s in list(client.data.chunks)[n_before:] if r > t_first and s in stamps]
        lat = [r - s for r, s in rows]
        p50, p95 = metrics.percentiles_ms(lat)
        # The untrained policy's poses are not executable (franka_node rejects them), so the
        # standstill at its chunk switches is read off the chunks' timing: with the linear
        # scheduler a chunk's command stands at its last step until the next chunk arrives.
        ours = [row for row in received if row[0] > t_first and row[1] in stamps]
        gaps = [max(0.0, new[0] - old[2]) for old, new in itertools.pairwise(ours)]
        return {
            **{f"policy_{k}": v for k, v in metrics.standstill_summary(gaps, duration).items()},
            "policy_chunk_switches": len(gaps),
            "policy_publish_steps": sorted({row[3] for row in ours}),
            "obs_to_cmd_p50_ms": p50,
            "obs_to_cmd_p95_ms": p95,
            "policy": label,
            "policy_precision": precision,
            "policy_chunks_per_s": round(len(rows) / duration, 2),
            "policy_diagnostics": client.data.diagnostics.get("policy_node", {}),
        }
    finally:
        stop_process(proc)
        client.node.destroy_subscription(subscription)


# --- entry point ---------------------------------------------------------------------------


def run_control_bench(args) -> int:
    """The whole bench for ``equidiff bench control``'s parsed arguments: one JSON line; returns the exit status."""
    join_private_domain(args.domain_id)

    lab_path = default_config_dir() / "lab.yaml"
    lab = load_lab_config(lab_path)
    control_path = default_config_dir() / "control.yaml"
    control = load_control_config(control_path)
    result: dict = {"machine": f"{os.cpu_count()} CPU cores", "ros_domain_id": int(os.environ["ROS_DOMAIN_ID"])}
    with tempfile.TemporaryDirectory(prefix="bench_control_") as tmp_name:
        tmp = Path(tmp_name)
        if args.interpolation:
            control = dataclasses.replace(
                control, scheduler=dataclasses.replace(control.scheduler, interpolation=args.interpolation)
            )
            control_path = tmp / "control.yaml"
            control_path.write_text(dump_yaml(to_dict(control)))
        result["interpolation"] = control.scheduler.interpolation
        checkpoint = label = None
        if not args.no_policy:
            checkpoint, label = args.policy_checkpoint, "checkpoint"
            if checkpoint is None:
                checkpoint = export_untrained(args.policy_preset, tmp / "untrained.pt", lab.workspace)
                label = f"untrained-{args.policy_preset}"
            result["baseline_bare_predict_p50_ms"] = metrics.percentiles_ms(
                bare_predict_s(checkpoint, args.precision, lab.workspace)
            )[0]
        franka = client = None
        with SimServer() as sim:
            try:
                franka = start_node(
                    "franka_node",
                    {
                        "robot_ip": sim.host,
                        "realtime": False,
                        "control_config": str(control_path),
                        "lab_config": str(lab_path),
                        "require_ack_on_start": False,  # the bench homes and drives it at once
                    },
                    tmp / "franka_node.log",
                    priority=True,
                )
                client = ControlClient(lab, str(lab_path))
                client.wait_for(
                    lambda: len(client.data.poses) > 10, 90.0, "/franka/ee_pose from the franka node", franka
                )
                t_track = time.monotonic()
                result.update(
                    run_track_and_hold(
                        client,
                        args.speed,
                        args.radius,
                        args.duration,
                        args.settle,
                        args.obs_latency,
                        control.safety.watchdog_timeout_s,
                    )
                )
                rtf = sim.realtime_factor(since=t_track)
                result["sim_realtime_factor"] = None if rtf is None else round(rtf, 3)
                result.update(run_workspace(client, lab.workspace))
                result.update(run_nan(client))
                if args.no_policy:
                    result.update({"obs_to_cmd_p50_ms": None, "obs_to_cmd_p95_ms": None, "policy": None})
                else:
                    approach(client, np.asarray(control.home_position))
                    result.update(run_latency(client, checkpoint, args.precision, args.latency_duration, tmp, label))
                    # baseline in the same run: policy_node as it ran before latency_s auto (whole chunks)
                    baseline = run_latency(
                        client, checkpoint, args.precision, args.latency_duration, tmp, label, {"latency_s": -1.0}
                    )
                    result.update(
                        {f"baseline_whole_chunks_{k}": v for k, v in baseline.items() if k.startswith("policy_")}
                    )
                result["franka_diagnostics"] = client.data.diagnostics.get("franka_node", {})
            except Exception as err:  # noqa: BLE001 - report any failure with the node's log
                log = tmp / "franka_node.log"
                tail = log.read_text()[-2000:] if log.exists() else ""
                print(
                    f"bench control failed: {type(err).__name__}: {err}\n--- franka_node log ---\n{tail}",
                    file=sys.stderr,
                )
                return 1
            finally:
                if client is not None:
                    client.close()
                code = stop_process(franka)
                result["franka_node_exit_code"] = code
    print(json.dumps(result))
    return 0
