"""The twin's scene: seeded reproducible resets, randomisation ranges, success test, real-time server."""

import math
import time

import mujoco
import numpy as np
import pytest

from equidiff_core.config import ConfigError
from equidiff_core.twin import scene
from equidiff_core.twin.config import TwinConfig, load_twin_config
from equidiff_core.twin.shared_state import SharedStateError, StateReader

CFG = TwinConfig()


def test_same_seed_same_poses_different_seed_different():
    a, b = scene.sample_scene(CFG.scene, 7), scene.sample_scene(CFG.scene, 7)
    assert a == b
    c = scene.sample_scene(CFG.scene, 8)
    assert c.block_xy != a.block_xy and c.bowl_xy != a.bowl_xy
    assert scene.ScenePoses.from_dict(a.to_dict()) == a


def test_randomisation_respects_ranges_and_covers_the_full_yaw_circle():
    poses = [scene.sample_scene(CFG.scene, s) for s in range(400)]
    for p in poses:
        for x, y in (p.block_xy, p.bowl_xy):
            assert CFG.scene.region_x[0] <= x <= CFG.scene.region_x[1]
            assert CFG.scene.region_y[0] <= y <= CFG.scene.region_y[1]
        assert np.hypot(*np.subtract(p.block_xy, p.bowl_xy)) >= CFG.scene.min_separation
    yaws = np.array([p.block_yaw for p in poses])
    hist, _ = np.histogram(yaws, bins=8, range=(-math.pi, math.pi))
    assert hist.min() > 20, hist  # every 45-degree sector is visited


def test_narrow_yaw_range_is_respected():
    cfg = CFG.with_yaw_range((-15.0, 15.0))
    yaws = np.degrees([scene.sample_scene(cfg.scene, s).block_yaw for s in range(100)])
    assert np.all(np.abs(yaws) <= 15.0 + 1e-9)


def test_an_episodes_record_names_the_yaw_range_it_was_drawn_from():
    cfg = TwinConfig().with_yaw_range((-15.0, 15.0)).scene
    poses = scene.sample_scene(cfg, 7)
    record = scene.scene_record(cfg, poses)
    assert record["block_yaw_deg"] == f"{math.degrees(poses.block_yaw):.1f}"
    assert all(" " not in value for value in record.values())  # each travels as one recorder-command word
    assert scene.recorded_block_yaw_range(record) == (-15.0, 15.0)
    full = scene.scene_record(TwinConfig().scene, poses)
    assert scene.recorded_block_yaw_range(full) == (0.0, 360.0)
    # a range that is not round survives the record's 6 digits as the same range, and only as that
    odd = (-12.3456789, 17.0000001)
    kept = scene.recorded_block_yaw_range(scene.scene_record(TwinConfig().with_yaw_range(odd).scene, poses))
    assert kept != odd and scene.same_yaw_range(kept, odd) and not scene.same_yaw_range(kept, (-12.35, 17.0))
    for unreadable in ({}, {"block_yaw_range_deg": "wide"}, {"block_yaw_range_deg": "1,2,3"}):
        assert scene.recorded_block_yaw_range(unreadable) is None


def test_impossible_region_is_a_clear_error():
    from dataclasses import replace

    cramped = replace(CFG.scene, region_x=(0.4, 0.41), region_y=(0.0, 0.01))
    with pytest.raises(scene.SceneError, match="min|apart"):
        scene.sample_scene(cramped, 0)


def _model_and_data():
    model = scene.build_model(CFG)
    return model, mujoco.MjData(model)


def test_apply_scene_places_objects_and_reset_is_reproducible():
    model, data = _model_and_data()
    poses = scene.sample_scene(CFG.scene, 3)
    scene.apply_scene(model, data, poses, CFG.scene)
    block = scene.body_pose(model, data, scene.BLOCK)
    bowl = scene.body_pose(model, data, scene.BOWL)
    np.testing.assert_allclose(block[:2, 3], poses.block_xy, atol=1e-9)
    np.testing.assert_allclose(bowl[:2, 3], poses.bowl_xy, atol=1e-9)
    assert math.isclose(scene.yaw_of(block), poses.block_yaw, abs_tol=1e-9)
    qpos_first = data.qpos.copy()
    # disturb, then reset again from the same seed: bit-identical object state
    data.qpos[:] += 0.01
    scene.apply_scene(model, data, scene.sample_scene(CFG.scene, 3), CFG.scene)
    objects = slice(model.nq - 14, model.nq)
    np.testing.assert_array_equal(data.qpos[objects], qpos_first[objects])


def _settle(model, data, seconds=0.6):
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)


def _place_block(model, data, xyz, yaw=0.0):
    qadr = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "block_joint")]
    data.qpos[qadr : qadr + 3] = xyz
    data.qpos[qadr + 3 : qadr + 7] = (math.cos(yaw / 2), 0, 0, math.sin(yaw / 2))
    mujoco.mj_forward(model, data)


def test_success_only_when_block_rests_inside_the_bowl():
    model, data = _model_and_data()
    data.qpos[:7] = CFG.sim.initial_q  # robot far above the table; it sags, which is irrelevant here
    poses = scene.sample_scene(CFG.scene, 11)
    scene.apply_scene(model, data, poses, CFG.scene)
    _settle(model, data, 0.3)
    assert not scene.is_success(model, data, CFG.scene, CFG.success)  # start: block on the table
    # dropped into the bowl from 5 cm above its centre: success once it has come to rest
    _place_block(model, data, (*poses.bowl_xy, 0.07), yaw=0.3)
    falling = scene.success_details(model, data, CFG.scene, CFG.success)
    assert not falling["success"] and not falling["below_rim"]
    _settle(model, data, 0.8)
    details = scene.success_details(model, data, CFG.scene, CFG.success)
    assert details["success"], details
    # resting on the table just outside the wall: not a success
    bx, by = poses.bowl_xy
    _place_block(model, data, (bx + CFG.scene.bowl_outer_radius + 0.04, by, 0.0151))
    _settle(model, data, 0.5)
    assert not scene.is_success(model, data, CFG.scene, CFG.success)


def test_twin_yaml_loads_and_bad_keys_fail_with_the_path(tmp_path):
    cfg = load_twin_config()
    assert cfg.scene.block_yaw_deg == (0.0, 360.0)
    bad = tmp_path / "twin.yaml"
    bad.write_text("scene:\n  region_x: [0.5]\n")
    with pytest.raises(ConfigError, match="scene.region_x"):
        load_twin_config(bad)
    bad.write_text("render:\n  widht: 100\n")
    with pytest.raises(ConfigError, match="widht"):
        load_twin_config(bad)


def test_missing_shared_state_is_a_clear_error():
    with pytest.raises(SharedStateError, match="twin_node"):
        StateReader("equidiff_twin_does_not_exist")


@pytest.mark.sim
def test_sim_server_runs_in_real_time_and_shares_its_state():
    import franky

    from equidiff_core.runtime.machine import keep_thread_scheduler
    from equidiff_core.twin.sim import TwinSim

    shm = f"equidiff_twin_test_{time.time_ns()}"
    with TwinSim(CFG, host="auto", shm_name=shm).start(seed=5) as twin:
        reader = StateReader(shm, nq=twin.model.nq)
        with keep_thread_scheduler("libfranka"):  # libfranka makes this thread real-time as root
            robot = franky.Robot(twin.host, realtime_config=franky.RealtimeConfig.Ignore)
        q = np.asarray(robot.current_joint_state.position)
        np.testing.assert_allclose(q, CFG.sim.initial_q, atol=0.05)
        wall0, (_, sim0, _) = time.monotonic(), reader.read()
        time.sleep(1.5)
        wall1, (qpos, sim1, stamp) = time.monotonic(), reader.read()
        rate = (sim1 - sim0) / (wall1 - wall0)
        assert rate < 1.1, f"sim runs ahead of real time ({rate:.2f}x)"
        # a starved CPU cannot hold 1 kHz; then the loop must know it (skip-ahead overruns counted)
        assert rate > 0.85 or twin.stats.overruns > 0, f"sim at {rate:.2f}x real time without overruns"
        assert abs(stamp - time.time_ns()) < 0.2e9
        # reset from a seed moves the objects to that seed's poses, visible through shared memory
        poses = twin.reset(9)
        assert poses == scene.sample_scene(CFG.scene, 9)
        qpos, _, _ = reader.read()
        qadr = twin.model.jnt_qposadr[mujoco.mj_name2id(twin.model, mujoco.mjtObj.mjOBJ_JOINT, "block_joint")]
        np.testing.assert_allclose(qpos[qadr : qadr + 2], poses.block_xy, atol=2e-3)
        status = twin.status()
        assert status["seed"] == 9 and status["success"] is False
        reader.close()
        del robot
