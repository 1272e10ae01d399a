"""Real-time chunking for the DDIM policy: guided inpainting towards the previous chunk,
time-aligned; off = plain DDIM bit for bit; C4-equivariant with the equivariant policy."""

import math

import numpy as np
import pytest
import torch

from equidiff_core import geometry
from equidiff_core.config import Workspace
from equidiff_core.models import action_space, equivariance
from equidiff_core.models.sampling import ddim_sample
from equidiff_core.policy.diffusion import PolicyInputError, make_policy
from equidiff_core.policy.file import export_policy
from equidiff_core.policy.inference import load_inference_policy
from equidiff_core.policy.normalizer import Normalizer
from equidiff_core.policy.presets import get_preset
from equidiff_core.twin.config import load_twin_config
from equidiff_core.wire.chunk import RealTimeChunking, steps_to_publish

WS = Workspace()
DT_NS = 200_000_000


@pytest.fixture(scope="module")
def fast(tmp_path_factory):
    torch.manual_seed(0)
    policy = make_policy("equidiff", get_preset("tiny"), WS)
    policy.set_normalizer(Normalizer.from_workspace(WS))
    path = export_policy(policy.eval(), tmp_path_factory.mktemp("rtc") / "policy.pt")
    return load_inference_policy(path, precision="fp32", jit=True)


@pytest.fixture(scope="module")
def scene():
    voxels, ee = equivariance.twin_scenes(get_preset("tiny"), WS, count=1, seed=1, scene=load_twin_config().scene)
    return voxels[0, 0], ee[0, 0]


def test_steps_to_publish_cover_the_execution_horizon_and_the_latency():
    assert steps_to_publish(8, 0.0, 0.2, 16) == 9
    assert steps_to_publish(4, 0.1, 0.2, 16) == 6
    assert steps_to_publish(4, 0.4, 0.2, 16) == 7
    assert steps_to_publish(8, 2.0, 0.2, 16) == 16  # at most what was predicted
    assert [RealTimeChunking.delay_for(s, 0.2) for s in (0.0, 0.1, 0.2, 0.4)] == [1, 1, 2, 3]


def test_the_previous_chunk_is_aligned_in_time_hard_over_the_delay_then_decaying():
    rtc = RealTimeChunking(delay_steps=2, dt_ns=DT_NS, max_gap_m=0.08)
    assert rtc.guide(0) is None
    prev = np.arange(16, dtype=float)[:, None] * np.ones(10)
    rtc.remember(1_000 * DT_NS, prev)
    target, weights = rtc.guide(1_004 * DT_NS)  # four periods later: new step i is old step i + 4
    assert np.array_equal(target[:12], prev[4:])
    assert np.array_equal(weights[:2], [1.0, 1.0])
    assert np.all(np.diff(weights[2:12]) < 0) and 0 < weights[11] < weights[2] < 1
    assert np.array_equal(weights[12:], np.zeros(4))  # past the previous chunk: free
    assert rtc.guide(1_016 * DT_NS) is None  # no overlap left
    # a previous chunk far from where the arm is was not executed (rejected): forgotten, not pinned
    ee = prev[4].copy()
    assert rtc.guide(1_004 * DT_NS, ee) is not None
    ee[0] += 0.07  # within the 80 mm given
    assert rtc.guide(1_004 * DT_NS, ee) is not None
    ee[0] += 0.02
    assert rtc.guide(1_004 * DT_NS, ee) is None and rtc.guide(1_004 * DT_NS) is None
    assert RealTimeChunking(2, DT_NS, 0.08, max_age_ns=3 * DT_NS).guide(0) is None


def _reference_ddim(denoise, cond, scheduler, noise):
    """DDIM as it was before real-time chunking existed."""
    x = noise.float()
    for t in scheduler.timesteps:
        x = scheduler.step(denoise(x, t.expand(1), cond).float(), t, x).prev_sample
    return x


def test_rtc_off_is_plain_ddim_bit_for_bit(fast, scene):
    cond = fast.encode(scene[0].numpy(), scene[1].numpy())
    noise = torch.randn(1, 16, fast.codec.dim, generator=torch.Generator().manual_seed(5))
    plain = ddim_sample(fast.denoise, cond, noise.shape, fast.scheduler, noise=noise, guide=None)
    assert torch.equal(plain, _reference_ddim(fast.denoise, cond, fast.scheduler, noise))


def test_guidance_pins_the_hard_steps_and_leaves_free_ones_nearly_alone(fast, scene):
    vox, ee = scene[0].numpy(), scene[1].numpy()
    free = fast.predict(vox, ee, seed=3)
    other = fast.predict(vox, ee, seed=4)
    weights = np.zeros(16)
    weights[:3] = 1.0
    guided = fast.predict(vox, ee, seed=3, guide=(other, weights))
    # hard steps: the target's, up to the sampler's final clip and float rounding
    assert np.abs(guided[:3, :3] - other[:3, :3]).max() < 1e-4
    assert not np.allclose(guided[:3, :3], free[:3, :3], atol=1e-3)
    with pytest.raises(PolicyInputError):
        fast.predict(vox, ee, seed=3, guide=(other[:8], weights))


def test_rtc_is_c4_equivariant_rotated_scene_and_previous_chunk_give_the_rotated_chunk(fast, scene):
    voxels, ee = scene
    noise = torch.randn(16, fast.codec.dim, generator=torch.Generator().manual_seed(7))
    previous = torch.from_numpy(fast.predict(voxels.numpy(), ee.numpy(), seed=11))
    rtc = RealTimeChunking(delay_steps=2, dt_ns=DT_NS, max_gap_m=0.08)
    rtc.remember(0, previous.numpy())
    target, weights = rtc.guide(3 * DT_NS)
    guided = torch.from_numpy(fast.predict(voxels.numpy(), ee.numpy(), noise=noise.numpy(), guide=(target, weights)))
    center = torch.zeros(10, dtype=torch.float64)
    center[:3] = torch.tensor(WS.center)
    scale = float(torch.linalg.norm(guided - center))
    for angle in (90, 180, 270):
        theta = math.radians(angle)
        rep = torch.as_tensor(action_space.rep_matrix(fast.codec.freqs, theta), dtype=torch.float32)
        vox_g, ee_g = equivariance.rotate_observation(WS, voxels[None], ee[None], theta)
        target_g = geometry.rotate_action(torch.from_numpy(target), theta, WS.center).numpy()
        out = fast.predict(vox_g[0].numpy(), ee_g[0].numpy(), noise=(noise @ rep.T).numpy(), guide=(target_g, weights))
        expected = geometry.rotate_action(guided, theta, WS.center)
        assert float(torch.linalg.norm(torch.from_numpy(out) - expected)) / scale <= 1e-5, angle


def test_chunking_probe_measures_boundary_velocity_changes_jerk_and_mode_switches():
    from types import SimpleNamespace

    from equidiff_core.twin.chunking import ChunkingProbe
    from equidiff_core.wire.chunk import PoseChunk

    def chunk(stamp_ms, y):
        times = (stamp_ms + np.arange(4) * 200) * 1_000_000
        poses = np.repeat(np.eye(4)[None], 4, axis=0)
        poses[:, 1, 3] = y
        return PoseChunk(int(times[0]), times.astype(np.int64), poses, np.full(4, 0.08))

    probe = ChunkingProbe(mode_switch_m=0.03)
    probe.start_episode(0)
    for i in range(200):  # 1 s at 200 Hz along x at 0.1 m/s, standing still for 5 ms at t = 500 ms
        x = 0.1 * (i if i < 100 else i - 1) * 0.005
        probe.command(
            SimpleNamespace(
                stamp_ns=i * 5_000_000,
                target=SimpleNamespace(pose=geometry.make_pose(np.eye(3), np.array([x, 0.0, 0.0]))),
                holding=False,
            )
        )
    assert probe.chunk(0, chunk(0, 0.0), True) is None  # the first chunk starts from rest: not a switch
    probe.chunk(500_000_000, chunk(400, 0.01), True)  # 1 cm off the previous plan: a correction
    probe.chunk(700_000_000, chunk(600, 0.10), True)  # 9 cm off: another plan
    probe.chunk(800_000_000, chunk(800, 0.0), False)  # rejected: not executed
    probe.end_episode()
    assert len(probe.boundary_dv) == 2
    assert probe.boundary_dv[0] == pytest.approx(0.1)  # the 5 ms stand-still: the whole speed lost
    assert probe.boundary_dv[1] == pytest.approx(0.0, abs=1e-9)
    summary = probe.summary()
    assert summary["mode_switches"] == 1 and summary["mode_switch_rate"] == 0.5
    assert summary["jerk_p95_mps3"] > 0 and summary["chunk_switches"] == 2
    # the 5 ms stand-still sits right before the first switch; the second switch is mid-motion
    assert probe.standstill == pytest.approx([0.005, 0.0])
    assert summary["standstill_mean_ms"] == pytest.approx(2.5) and summary["standstill_total_s"] == 0.005


class _DriftingPolicy:
    """Stands in for an exported policy in bench chunking: a slow straight drift from the current
    TCP (2 cm/s, along +x or -x by the sampling seed's parity, so consecutive chunks can disagree);
    records the real-time chunking guide it is given."""

    def __init__(self):
        from types import SimpleNamespace

        self.preset = SimpleNamespace(name="drift", dt=0.2, n_action_steps=8, horizon=16, n_obs_steps=1)
        self.guides = []

    def warmup(self):
        pass

    def predict(self, grid, ee, seed=0, guide=None):
        self.guides.append(guide)
        actions = np.repeat(np.asarray(ee, dtype=np.float64)[None], 16, axis=0)
        actions[:, 0] += (1 if seed % 2 else -1) * 0.02 * 0.2 * np.arange(16)
        if guide is not None:  # what RTC asks: the pinned steps are the target's
            target, weights = guide
            actions[weights == 1.0] = target[weights == 1.0]
        return actions


def test_bench_chunking_refuses_what_it_cannot_run_with_one_line_and_exit_1(tmp_path, capsys):
    from equidiff_ros.cli import main

    assert main(["bench", "chunking", "--seeds", "0"]) == 1
    assert capsys.readouterr().err == (
        "equidiff bench chunking: need --seeds >= 1, --duration > 0 and latencies >= 0\n"
    )
    assert main(["bench", "chunking", "--checkpoint", str(tmp_path / "none.pt")]) == 1
    assert capsys.readouterr().err == f"equidiff bench chunking: no checkpoint at {tmp_path / 'none.pt'}\n"


@pytest.mark.slow
@pytest.mark.sim
def test_bench_chunking_prints_one_json_line_with_every_mode_and_latency(tmp_path, capsys, monkeypatch):
    import json

    from equidiff_core.benches import chunk_modes
    from equidiff_ros.cli import main

    policy = _DriftingPolicy()
    monkeypatch.setattr(chunk_modes, "load_inference_policy", lambda path, device: policy)
    checkpoint = tmp_path / "policy.pt"
    checkpoint.write_bytes(b"stands in")
    assert (
        main(
            [
                "bench",
                "chunking",
                "--checkpoint",
                str(checkpoint),
                "--seeds",
                "1",
                "--duration",
                "2",
                "--latencies",
                "0",
                "400",
                "--execute-steps",
                "2",
            ]
        )
        == 0
    )
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert len(lines) == 1
    out = json.loads(lines[0])
    for key in (
        "rtc_0ms_success",
        "rtc_400ms_success",
        "replace_400ms_success",
        "rtc_400ms_boundary_dv_p95_mps",
        "replace_400ms_boundary_dv_p95_mps",
    ):
        assert key in out
    for label in (f"{mode}_{ms}ms" for mode in ("replace", "horizon", "rtc") for ms in (0, 400)):
        assert out[f"{label}_success"] == 0.0  # drifting 2 cm/s solves nothing in 2 s
        assert out[f"{label}_chunk_switches"] >= 2
        assert 0 <= out[f"{label}_boundary_dv_p95_mps"] <= 2 * 0.25 + 1e-6  # within the 0.25 m/s speed limit
        assert out[f"{label}_jerk_p95_mps3"] >= 0
        assert out[f"{label}_standstill_total_s"] >= 0 and out[f"{label}_standstill_p95_ms"] is not None
    for label in (f"{mode}_{ms}ms" for mode in ("horizon", "rtc") for ms in (0, 400)):
        assert out[f"{label}_standstill_total_s"] == 0.0  # each chunk lasts until the next one is there
    assert out["whole_400ms_publish_steps"] == 8  # n_action_steps whatever L: the former default
    assert out["replace_400ms_publish_steps"] == 8 and out["horizon_400ms_publish_steps"] == 2 + 2 + 1
    assert out["horizon_0ms_publish_steps"] == 2 + 0 + 1 and out["execute_steps"] == 2 and out["seeds"] == [100000]
    # replace flips direction every chunk (> 3 cm apart within its 8 steps); RTC pins the overlap
    assert out["replace_0ms_mode_switch_rate"] > 0.5 and out["rtc_400ms_mode_switches"] == 0
    # RTC was asked with the previous chunk: at 400 ms the three steps due before arrival pinned
    pinned = [g for g in policy.guides if g is not None]
    assert pinned and all(np.array_equal(g[1][:3], np.ones(3)) for g in pinned[len(pinned) // 2 :])
