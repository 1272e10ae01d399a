"""The scripted expert: plan geometry, and it solves >= 90 % of 20 seeded episodes in the twin."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from equidiff_core import geometry
from equidiff_core.twin.config import TwinConfig
from equidiff_core.twin.expert import (
    LinePath,
    grasp_yaw,
    plan_pick_place,
    tcp_pose,
    tcp_yaw,
)

CFG = TwinConfig()


@pytest.mark.parametrize("block_yaw", np.linspace(-math.pi, math.pi, 13))
def test_grasp_yaw_closes_across_the_short_side_within_the_wrist_range(block_yaw):
    yaw = grasp_yaw(block_yaw)
    assert -math.pi / 2 - 1e-9 <= yaw <= math.pi / 2 + 1e-9
    finger_axis = tcp_pose((0, 0, 0), yaw)[:3, 1]  # fingers close along the TCP's y axis
    block_short_axis = geometry.rotz(block_yaw)[:, 1]
    assert abs(abs(finger_axis @ block_short_axis) - 1) < 1e-9


def test_plan_visits_block_then_bowl_with_the_gripper_sequence():
    start = tcp_pose(CFG.expert.ready_position, 0.0)
    block = tcp_pose((0.5, 0.1, 0.015), 0.7)
    bowl = tcp_pose((0.4, -0.1, 0.0), 0.0)
    plan = plan_pick_place(start, 0.08, block, bowl, 0.03, CFG.expert)
    phases = [k.phase for k in plan.keyframes]
    assert phases.index("grasp") < phases.index("lift") < phases.index("transfer") < phases.index("release")
    grasp = plan.keyframes[phases.index("grasp")]
    assert grasp.width == CFG.expert.close_width
    np.testing.assert_allclose(grasp.position[:2], (0.5, 0.1))
    assert grasp.position[2] < 0.03
    release = plan.keyframes[phases.index("release")]
    np.testing.assert_allclose(release.position[:2], (0.4, -0.1))
    # continuous targets, speeds bounded by the configured operator speed
    ts = np.arange(0, plan.duration, 0.01)
    xyz = np.array([plan.target_at(t)[0][:3, 3] for t in ts])
    speed = np.linalg.norm(np.diff(xyz, axis=0), axis=1) / 0.01
    assert speed.max() <= CFG.expert.speed * 1.01
    assert abs(tcp_yaw(plan.target_at(plan.duration)[0]) - grasp_yaw(0.7)) < 1e-9


def _follow(path, arm, steps, gain=0.5, knock=None, max_rot=np.inf):
    """A first-order arm following the path's targets unless franka_node would reject them as a
    jump (80 mm, 0.6 rad: it holds then); ``knock(i, arm)`` may push it away."""
    from equidiff_core.geometry import rotation_angle

    jumps = []
    for i in range(steps):
        if knock is not None:
            arm = knock(i, arm)
        target = path.next(arm)
        jumps.append((np.linalg.norm(target[:3, 3] - arm[:3, 3]), rotation_angle(target[:3, :3], arm[:3, :3])))
        if jumps[-1][0] > 0.08 or jumps[-1][1] > 0.6:
            continue
        arm = arm.copy()
        arm[:3, 3] += gain * (target[:3, 3] - arm[:3, 3])
        turn = Rotation.from_matrix(target[:3, :3] @ arm[:3, :3].T).as_rotvec()  # turns at most max_rot a tick
        turn *= min(1.0, max_rot / max(np.linalg.norm(turn), 1e-12))
        arm[:3, :3] = Rotation.from_rotvec(turn).as_matrix() @ arm[:3, :3]
    return arm, np.array(jumps)


def test_line_path_waits_for_the_arm_and_restarts_where_a_knocked_arm_is():
    home = tcp_pose(CFG.expert.ready_position, 0.0)
    start = tcp_pose((0.40, 0.10, 0.12), 0.8)
    path = LinePath(start, home, speed=0.12, hz=20.0)
    arm, jumps = _follow(path, start, 20 * 10)
    assert path.done and path.restarts == 0
    np.testing.assert_allclose(arm[:3, 3], home[:3, 3], atol=1e-3)
    assert jumps[:, 0].max() < 0.03 + 0.12 / 20 + 1e-9  # never ahead of the arm by more than the lag

    # knocked 0.3 m off the line halfway (as after a divergence stop): the old line's targets
    # would all be rejected as jumps; the path restarts from the arm and still gets home
    def knock(i, arm):
        if i != 40:
            return arm
        pushed = tcp_pose((0.26, 0.19, 0.14), -0.5)
        pushed[:3, :3] = Rotation.from_euler("x", 0.3).as_matrix() @ pushed[:3, :3]  # tilted as well
        return pushed

    path = LinePath(start, home, speed=0.12, hz=20.0)
    arm, jumps = _follow(path, start, 20 * 15, knock=knock)
    assert path.done and path.restarts == 1
    np.testing.assert_allclose(arm[:3, 3], home[:3, 3], atol=1e-3)
    assert jumps[:, 0].max() < 0.08 and jumps[:, 1].max() < 0.6  # no target was rejected

    # a hand that turns slower than the path (franka_node: 0.6 rad/s) is waited for, not restarted
    start = tcp_pose(CFG.expert.ready_position, 1.5)
    path = LinePath(start, home, hz=20.0, angular_speed=1.0)
    arm, jumps = _follow(path, start, 20 * 6, max_rot=0.6 / 20)
    assert path.done and path.restarts == 0 and abs(tcp_yaw(arm)) < 1e-6
    assert jumps[:, 1].max() < 0.2 + 1.0 / 20 + 1e-9


@pytest.mark.slow
@pytest.mark.sim
def test_expert_solves_at_least_90_percent_of_20_seeded_episodes():
    from equidiff_core.twin.expert import run_direct_episode
    from equidiff_core.twin.sim import DirectSim

    sim = DirectSim(CFG)
    try:
        results = [run_direct_episode(sim, seed, CFG) for seed in range(1000, 1020)]
    finally:
        sim.close()
    failures = [(r.seed, r.details) for r in results if not r.success]
    assert len(failures) <= 2, failures
    assert all(r.duration_s < CFG.episode.max_duration_s for r in results)


@pytest.mark.slow
@pytest.mark.sim
def test_direct_collection_writes_a_trainable_demo_bag(tmp_path):
    """`twin collect --direct`: one expert episode -> a bag with the recorder's topics that the dataset reads."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.data.bags import read_meta
    from equidiff_core.data.dataset import load_episode_arrays
    from equidiff_core.data.episode_arrays import DatasetConfig
    from equidiff_core.twin.demos import collect_direct
    from equidiff_core.twin.scene import recorded_block_yaw_range

    lab = load_lab_config(default_config_dir() / "lab.yaml")
    cfg = CFG.with_yaw_range((-10.0, 10.0))
    results = collect_direct(cfg, lab, tmp_path, [4], log=lambda s: None)
    assert results[0][1], results
    bag = tmp_path / results[0][2].split("/")[-1]
    meta = read_meta(bag)
    assert meta.success is True and meta.seed == 4 and meta.task == "twin_block_in_bowl"
    # the scene's yaw and the range it was drawn from travel with the demo
    assert recorded_block_yaw_range(meta.extra) == (-10.0, 10.0) and meta.extra["bowl_yaw_range_deg"] == "-10,10"
    assert abs(float(meta.extra["block_yaw_deg"])) <= 10.0
    arrays = load_episode_arrays(bag, DatasetConfig())
    assert len(arrays) >= 40 and arrays.dropped_steps == 0  # ~5 Hz over a ~12 s episode
    # each camera's colour image of every grid, stamped like it, as camera_node and the recorder write them
    from equidiff_core.cameras.color import image_from_msg
    from equidiff_core.data.bags import read_episode
    from equidiff_core.wire.topics import camera_color_topic

    images = read_episode(bag, topics=[camera_color_topic(c.name) for c in lab.cameras])
    for cam in lab.cameras:
        np.testing.assert_array_equal(images[camera_color_topic(cam.name)].header_ns(), arrays.stamps_ns)
        rgb, _ = image_from_msg(images[camera_color_topic(cam.name)].messages[0])
        assert rgb.shape == (CFG.render.height, CFG.render.width, 3) and rgb.std() > 5
    # the commanded targets go down to the block, close, and end open over the bowl
    targets = arrays.schedule[1:]
    assert targets[:, 2].min() < 0.03 and targets[:, 9].min() < 0.01 and targets[-1, 9] > 0.07
    final_xy = targets[-1, :2]
    assert abs(final_xy[0] - cfg.scene.region_x[0]) < 0.3  # sanity: inside the reachable region


class _ExpertAsPolicy:
    """Plans once per episode from the sim, then answers each observation with the next 16 targets.

    Step k is the plan's target at the observation's time + k * dt: the training data's
    convention (action 0 = the target in effect at the observation), which the evaluation
    executes on time (step k at t + k * dt), as franka_node's scheduler does."""

    def __init__(self, sim):
        from types import SimpleNamespace

        self.sim, self.plan, self.t0 = sim, None, 0.0
        self.preset = SimpleNamespace(dt=0.2, n_action_steps=8, horizon=16, n_obs_steps=1)

    def predict(self, grid, ee, seed=0):
        from equidiff_core.twin.scene import BLOCK, BOWL, body_pose

        assert grid.shape == (4, 64, 64, 64) and ee.shape == (10,)
        if self.plan is None:
            self.plan, self.t0 = (
                plan_pick_place(
                    self.sim.tcp_pose(),
                    self.sim.gripper_width(),
                    body_pose(self.sim.model, self.sim.data, BLOCK),
                    body_pose(self.sim.model, self.sim.data, BOWL),
                    CFG.scene.block_size[2],
                    CFG.expert,
                ),
                self.sim.time,
            )
        t, dt = self.sim.time - self.t0, self.preset.dt
        steps = [self.plan.target_at(t + dt * k) for k in range(16)]
        return np.stack([geometry.pose_to_action(pose, np.asarray(width)) for pose, width in steps])


class _FrozenPolicy(_ExpertAsPolicy):
    def __init__(self, sim):
        super().__init__(sim)
        self.threads_seen: set[int] = set()  # torch's intra-op threads at each answer

    def predict(self, grid, ee, seed=0):
        self.threads_seen.add(torch.get_num_threads())
        return np.repeat(ee[None], 16, axis=0)


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.parametrize("execute_steps, observations", [(0, 3), (1, 20)])
def test_closed_loop_evaluation_scores_the_expert_and_the_stages_a_frozen_policy_misses(execute_steps, observations):
    """`evaluate_policy` (bench generalization's rollouts) with the scripted expert in the
    policy's place solves the scene whether it answers every observation or one per chunk, and
    reports every stage; a policy that never moves reaches none."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.twin.demos import DirectRecorder
    from equidiff_core.twin.evaluate import ROLLOUT_THREADS, evaluate_policy

    lab = load_lab_config(default_config_dir() / "lab.yaml")
    rec = DirectRecorder(CFG, lab)
    threads_before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        (solved,) = evaluate_policy(
            _ExpertAsPolicy(rec.sim), CFG, lab, [3], 30.0, log=lambda s: None, recorder=rec, execute_steps=execute_steps
        )
        frozen_policy = _FrozenPolicy(rec.sim)
        (frozen,) = evaluate_policy(
            frozen_policy, CFG, lab, [3], 4.0, log=lambda s: None, recorder=rec, execute_steps=execute_steps
        )
        # the roll-outs answer on a fixed thread count, whatever the process uses, and give it back
        assert frozen_policy.threads_seen == {ROLLOUT_THREADS} and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(threads_before)
        rec.close()
    assert solved.success and solved.reached and solved.lifted
    assert solved.closest_to_bowl_m < CFG.scene.bowl_inner_radius and solved.closest_to_block_m < 0.02
    assert not (frozen.success or frozen.reached or frozen.lifted)
    # 4 s of observations, one answered every 0.2 s, or every 1.6 s (a whole chunk: 0, 1.6, 3.2)
    assert frozen.closest_to_bowl_m > 0.05 and frozen.closest_to_block_m > 0.1 and frozen.observations == observations


class _SpySim:
    """DirectSim that logs every command (sim time, target position) and the TCP after every step."""

    def __init__(self, sim):
        self._sim, self.commands, self.tcp = sim, [], []

    def __getattr__(self, name):
        return getattr(self._sim, name)

    def command(self, pose, width):
        self.commands.append((self._sim.time, np.array(pose[:3, 3])))
        self._sim.command(pose, width)

    def step(self, n=1):
        self._sim.step(n)
        self.tcp.append((self._sim.time, self._sim.tcp_pose()[:3, 3].copy()))


@pytest.mark.sim
@pytest.mark.parametrize("execute_steps, latency_s", [(1, 0.1), (1, 0.3), (8, 0.1)])
def test_a_chunk_takes_effect_only_after_the_latency_budget(execute_steps, latency_s):
    """The second answered observation's chunk jumps the target 5 cm sideways: neither the
    command nor the TCP moves toward it before that observation's time + L (the previous chunk,
    a hold, keeps running meanwhile), and both have moved within 0.3 s after."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.twin.demos import DirectRecorder
    from equidiff_core.twin.evaluate import evaluate_policy

    jump = np.array([0.0, 0.05, 0.0])

    class JumpPolicy(_ExpertAsPolicy):
        def predict(self, grid, ee, seed=0):
            self.times.append(self.sim.time)
            actions = np.repeat(ee[None].astype(np.float64), 16, axis=0)
            if len(self.times) >= 2:
                actions[:, :3] = self.times_ee[0][:3] + jump
            self.times_ee.append(ee)
            return actions

    lab = load_lab_config(default_config_dir() / "lab.yaml")
    rec = DirectRecorder(CFG, lab)
    spy = rec.sim = _SpySim(rec.sim)
    policy = JumpPolicy(spy)
    policy.times, policy.times_ee = [], []
    try:
        (episode,) = evaluate_policy(
            policy,
            CFG,
            lab,
            [3],
            1.2 if execute_steps == 1 else 2.4,
            log=lambda s: None,
            recorder=rec,
            latency_s=latency_s,
            execute_steps=execute_steps,
        )
    finally:
        rec.close()
    t_obs = policy.times[1]  # the observation whose chunk jumps
    assert np.isclose(t_obs - policy.times[0], 0.2 * execute_steps)  # answered every execute_steps frames
    effect = t_obs + latency_s
    start = policy.times_ee[0][:3]

    def toward(p):  # progress toward the jumped target along the jump, metres
        return float((p - start) @ jump / np.linalg.norm(jump))

    before = [toward(p) for t, p in spy.commands if t < effect - 1e-6]
    after = [toward(p) for t, p in spy.commands if effect - 1e-6 <= t <= effect + 0.3]
    assert max(before) < 1e-3 and after and max(after) > 0.03, (before[-3:], after)
    tcp_before = [toward(p) for t, p in spy.tcp if t <= effect + 1e-6]
    tcp_after = [toward(p) for t, p in spy.tcp if t <= effect + 0.3]
    assert max(tcp_before) < 2e-3 and max(tcp_after) > 0.01, (tcp_before[-3:], tcp_after[-3:])
    assert not episode.success


@pytest.mark.sim
def test_the_evaluation_executes_chunks_through_franka_nodes_controller():
    """A chunk asking for 7 cm in the 0.1 s before its next step (0.7 m/s) is executed at
    franka_node's speed limit, as the live twin executes it: the in-process evaluation runs
    franka_node's own Controller (safety filter, watchdog), not just its scheduler."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.control import load_control_config
    from equidiff_core.twin.demos import DirectRecorder
    from equidiff_core.twin.evaluate import evaluate_policy

    class FarPolicy(_ExpertAsPolicy):
        def predict(self, grid, ee, seed=0):
            if self.start is None:
                self.start = ee.copy()
            actions = np.repeat(self.start[None].astype(np.float64), 16, axis=0)
            actions[:, 0] += 0.07
            return actions

    limit = load_control_config(default_config_dir() / "control.yaml").safety.max_linear_speed_m_s
    lab = load_lab_config(default_config_dir() / "lab.yaml")
    rec = DirectRecorder(CFG, lab)
    spy = rec.sim = _SpySim(rec.sim)
    policy = FarPolicy(spy)
    policy.start = None
    try:
        evaluate_policy(
            policy,
            CFG,
            lab,
            [3],
            1.6,
            log=lambda s: None,
            recorder=rec,
            latency_s=0.1,
        )
    finally:
        rec.close()
    times = np.array([t for t, _ in spy.commands])
    positions = np.stack([p for _, p in spy.commands])
    moving = times > times[0] + 1e-6  # after the homing command
    speeds = np.linalg.norm(np.diff(positions[moving], axis=0), axis=1) / np.diff(times[moving])
    assert speeds.max() <= limit * 1.01, speeds.max()
    assert speeds.max() >= limit * 0.9  # it did move, at the limit
    assert abs(positions[-1][0] - (policy.start[0] + 0.07)) < 2e-3  # and got there


class _ChunkTap:
    """An evaluation probe that keeps the chunks the Controller receives."""

    def __init__(self):
        self.chunks = []

    def start_episode(self, seed):
        self.chunks = []

    def chunk(self, now_ns, chunk, accepted):
        self.chunks.append(chunk)

    def command(self, command):
        pass

    def end_episode(self):
        pass


@pytest.mark.slow
@pytest.mark.sim
def test_replaying_recorded_chunks_executes_them_from_the_bags_scene(tmp_path):
    """`twin replay-chunks`' core: a bag of chunks that solved seed 3 (the expert as the policy,
    stamped on a live run's clock, far from 0) replays as a success; the same chunks 6 cm higher
    grasp above the block and fail. The outcome is the replay's, not the bag's."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.data.bags import EpisodeMeta
    from equidiff_core.data.mcap_reader import BagError
    from equidiff_core.data.recording import EpisodeWriter
    from equidiff_core.twin.demos import DirectRecorder
    from equidiff_core.twin.evaluate import evaluate_policy, replay_chunks
    from equidiff_core.wire.chunk import PoseChunk, chunk_to_msg
    from equidiff_core.wire.rosmsg import rosbags_factory
    from equidiff_core.wire.topics import RECORDED_TOPICS, TOPIC_COMMAND_CHUNK

    lab = load_lab_config(default_config_dir() / "lab.yaml")
    rec, tap = DirectRecorder(CFG, lab), _ChunkTap()
    try:
        (solved,) = evaluate_policy(
            _ExpertAsPolicy(rec.sim), CFG, lab, [3], 30.0, log=lambda s: None, recorder=rec, probe=tap
        )
    finally:
        rec.close()
    assert solved.success and len(tap.chunks) >= 3
    factory, t0 = rosbags_factory(), 123_456_000_000  # sim time since twin_node started, in a live bag

    def bag(name: str, lift_m: float):
        writer = EpisodeWriter(tmp_path / name, EpisodeMeta(task="twin_eval", seed=3)).open()
        writer.add_topic(TOPIC_COMMAND_CHUNK, RECORDED_TOPICS[TOPIC_COMMAND_CHUNK])
        for c in tap.chunks:
            poses = c.poses.copy()
            poses[:, 2, 3] += lift_m
            moved = PoseChunk(c.stamp_ns + t0, c.times_ns + t0, poses, c.widths)
            writer.write(TOPIC_COMMAND_CHUNK, chunk_to_msg(moved, factory, lab.base_frame), moved.stamp_ns)
        return writer.close(success=True)

    same, higher = replay_chunks([bag("same", 0.0), bag("higher", 0.06)], CFG, lab, log=lambda s: None)
    with pytest.raises(BagError, match="no such bag directory"):  # a clear error, not a traceback
        replay_chunks([tmp_path / "nope"], CFG, lab, log=lambda s: None)
    assert (same.seed, same.recorded_success, same.chunks) == (3, True, len(tap.chunks))
    assert same.success and same.reached and same.lifted
    assert not (higher.success or higher.lifted) and higher.recorded_success
    assert np.isnan(same.tcp_gap_mean_mm)  # the bags hold no /franka/ee_pose to compare with


@pytest.mark.sim
def test_an_answer_with_no_valid_chunk_is_skipped_and_counted_as_policy_node_skips_it():
    """Every other answer's rotation is degenerate (its 6-D rows parallel, as a one-step sampler can give):
    the episode goes on with the running chunk, and counts each skipped answer."""
    from equidiff_core.config import default_config_dir, load_lab_config
    from equidiff_core.twin.demos import DirectRecorder
    from equidiff_core.twin.evaluate import evaluate_policy

    class SometimesDegenerate(_ExpertAsPolicy):
        calls = 0

        def predict(self, grid, ee, seed=0):
            self.calls += 1
            actions = np.repeat(ee[None].astype(np.float64), 16, axis=0)
            if self.calls % 2 == 0:
                actions[:, 6:9] = actions[:, 3:6]  # the second rotation row = the first
            return actions

    lab = load_lab_config(default_config_dir() / "lab.yaml")
    rec = DirectRecorder(CFG, lab)
    policy = SometimesDegenerate(rec.sim)
    try:
        (episode,) = evaluate_policy(policy, CFG, lab, [3], 1.0, log=lambda s: None, recorder=rec, execute_steps=1)
    finally:
        rec.close()
    assert episode.observations == policy.calls >= 4
    assert episode.failed_predictions == policy.calls // 2 and not episode.success
