"""Measuring how equivariant a policy is, on scenes like the twin's.

For g a rotation by theta about the workspace's vertical axis:

* denoiser: eps(g.o, g.x, k) against g.eps(o, x, k), relative error
  ||eps(g.o, g.x) - g.eps(o, x)|| / ||eps(o, x)|| over all scenes;
* sampler: DDIM from fixed noise z on o and from g.z on g.o, actions compared as a(g.o, g.z)
  against g.a(o, z), relative to the actions' extent about the workspace centre.

g acts on voxel grids with ``geometry.rotate_voxel_grid`` (a permutation of voxels for multiples
of 90 deg, nearest-neighbour resampling otherwise), on gripper states and actions with
``geometry.rotate_action`` about the workspace centre, and on model-space vectors with
``action_space.rep_matrix``. The elements measured are those of C8: the multiples of 90 deg (C4),
where EquiDiff is exact (rot90 permutes voxels, and rotating a 3^3 kernel by 90 deg maps it onto
the cubic grid), and the odd multiples of 45 deg, where it is only approximately equivariant: a
3^3 kernel constrained to C8 is sampled on a grid that 45 deg does not map onto itself (the
official EquiDiff code has the same limit) and the grid itself is resampled.

Scenes (``twin_scenes``): the twin's task objects (``twin.config.SceneConfig``: the block, the
bowl's base and its 16 wall segments, the table top) at random positions and yaws, as coloured
surface points voxelised by ``perception.voxels.voxelize`` like a camera cloud. Everything stays inside the
cylinder that the centred crop keeps under any rotation, so the 45 deg elements measure the
network and the resampling, not content falling off the crop. Random sparse voxels (about 1.5 %
filled) hide the 45 deg error: a network sees mostly empty space, so that is not what is measured.

Subjects: anything with ``denoise(voxels, ee, x, t)`` and ``sample(voxels, ee, noise)``:
``TrainingModel`` wraps a ``policy.diffusion.DiffusionPolicy`` (escnn for EquiDiff), ``ExportedModel`` an
``policy.inference.InferencePolicy`` (plain torch, fp32 or bf16, traced or not).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .. import geometry
from ..perception.voxels import voxelize
from . import action_space

# The non-identity elements of C8, in degrees: 90, 180, 270 form C4 (exact), the rest are 45 deg off the grid.
C8_ANGLES_DEG = tuple(45 * k for k in range(1, 8))
SURFACE_POINTS_PER_M2 = 250_000  # ~10 points per 6.25 mm voxel face: every surface voxel is hit
COLOR_NOISE = 4.0  # std of per-point colour noise (uint8 units), like a camera's


def is_c4(angle_deg: float) -> bool:
    return angle_deg % 90 == 0


# --- Observations ---------------------------------------------------------------------------------


def random_observation(policy, batch: int = 2, seed: int = 0, fill: float = 0.03) -> tuple[torch.Tensor, torch.Tensor]:
    """(voxels uint8 (B, To, 4, R, R, R), ee (B, To, 10)): random coloured voxels inside the crop's
    inscribed cylinder. Cheap valid input for timing and shape tests; for measuring equivariance use
    ``twin_scenes`` (sparse noise hides the 45 deg error)."""
    p, ws = policy.preset, policy.workspace
    R = ws.resolution
    rng = np.random.default_rng(seed)
    c = (R - 1) / 2
    ii, jj = np.meshgrid(np.arange(R), np.arange(R), indexing="ij")
    inside = ((ii - c) ** 2 + (jj - c) ** 2) <= (p.crop / 2 - 3) ** 2
    occ = (rng.random((batch, p.n_obs_steps, R, R, R)) < fill) & inside[None, None, :, :, None]
    vox = np.zeros((batch, p.n_obs_steps, p.voxel_channels, R, R, R), np.uint8)
    vox[:, :, 0] = occ * 255
    vox[:, :, 1:] = rng.integers(1, 256, (batch, p.n_obs_steps, p.voxel_channels - 1, R, R, R)) * occ[:, :, None]
    ee = _random_gripper_states(ws, rng, batch, radius=0.1)
    ee = np.repeat(ee[:, None], p.n_obs_steps, 1)
    return torch.from_numpy(vox), torch.from_numpy(ee.astype(np.float32))


def _random_gripper_states(
    ws, rng, batch: int, radius: float, z_range: tuple[float, float] | None = None
) -> np.ndarray:
    """(batch, 10) absolute gripper states pointing down, yaw uniform, within ``radius`` (m) of the centre's axis."""
    yaw = rng.uniform(-math.pi, math.pi, batch)
    Rm = np.stack([geometry.rotz(y) @ np.diag([1.0, -1.0, -1.0]) for y in yaw])
    pos = np.asarray(ws.center) + rng.uniform(-radius, radius, (batch, 3))
    if z_range is not None:
        pos[:, 2] = rng.uniform(*z_range, batch)
    return geometry.pose_to_action(geometry.make_pose(Rm, pos), rng.uniform(0.0, 0.08, batch))


def rotation_safe_radius(preset, workspace) -> float:
    """Horizontal distance (m) from the workspace's axis within which content stays inside the centred
    crop under any rotation (the crop's inscribed cylinder, less 3 voxels for resampling)."""
    return (preset.crop / 2 - 3) * workspace.voxel_size


def _box_surface(center, half, yaw: float, rng) -> np.ndarray:
    """Uniform random points (N, 3) on the surface of a box (half extents ``half``) yawed about z."""
    half = np.asarray(half, np.float64)
    parts = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        n = max(1, math.ceil(4 * half[u] * half[v] * SURFACE_POINTS_PER_M2))
        for sign in (-1.0, 1.0):
            p = np.empty((n, 3))
            p[:, axis] = sign * half[axis]
            p[:, u] = rng.uniform(-half[u], half[u], n)
            p[:, v] = rng.uniform(-half[v], half[v], n)
            parts.append(p)
    return np.concatenate(parts) @ geometry.rotz(yaw).T + np.asarray(center)


def _disc(center, radius: float, rng) -> np.ndarray:
    """Uniform random points (N, 3) on a horizontal disc."""
    n = max(1, math.ceil(math.pi * radius**2 * SURFACE_POINTS_PER_M2))
    r = radius * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * math.pi, n)
    return np.asarray(center) + np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], 1)


def _colored(points: np.ndarray, rgba, rng) -> tuple[np.ndarray, np.ndarray]:
    rgb = np.asarray(rgba[:3]) * 255 + rng.normal(0, COLOR_NOISE, (len(points), 3))
    return points, np.clip(np.round(rgb), 0, 255).astype(np.uint8)


def twin_scene_cloud(scene_cfg, workspace, safe_radius: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Coloured surface points (float32 (N, 3), uint8 (N, 3)) of the twin's table top, block and
    bowl (``twin.config.SceneConfig``'s sizes and colours), objects at random positions and yaws
    inside ``safe_radius`` of the workspace axis, resting on the table (z = 0), as twin/scene.py
    builds them."""
    c = np.array([workspace.center[0], workspace.center[1], 0.0])
    block_half = np.asarray(scene_cfg.block_size) / 2
    block_reach = float(np.hypot(*block_half[:2]))
    bowl_reach = scene_cfg.bowl_outer_radius
    for _ in range(1000):  # rejection sampling: both inside the safe disc, apart as the twin keeps them
        block_xy = _in_disc(rng, safe_radius - block_reach)
        bowl_xy = _in_disc(rng, safe_radius - bowl_reach)
        if np.linalg.norm(block_xy - bowl_xy) >= max(scene_cfg.min_separation, block_reach + bowl_reach):
            break
    else:
        raise ValueError(f"the twin's block and bowl do not fit apart in a {safe_radius:.3f} m disc")
    clouds = [_colored(_disc(c, safe_radius, rng), scene_cfg.table_rgba, rng)]
    block_yaw, bowl_yaw = rng.uniform(0, 2 * math.pi, 2)
    block_center = c + [*block_xy, block_half[2]]
    clouds.append(_colored(_box_surface(block_center, block_half, block_yaw, rng), scene_cfg.block_rgba, rng))
    bowl = c + [*bowl_xy, 0.0]
    base = scene_cfg.bowl_base_thickness
    clouds.append(_colored(_disc(bowl + [0, 0, base], bowl_reach, rng), scene_cfg.bowl_rgba, rng))
    n = scene_cfg.bowl_segments
    r_mid = scene_cfg.bowl_inner_radius + scene_cfg.bowl_wall_thickness / 2
    seg_half_len = r_mid * math.tan(math.pi / n) * 1.08  # as twin/scene.py: slight overlap closes the ring
    wall_top = base + scene_cfg.bowl_wall_height
    for i in range(n):
        a = 2 * math.pi * i / n + bowl_yaw
        center = bowl + [r_mid * math.cos(a), r_mid * math.sin(a), wall_top / 2]
        half = (scene_cfg.bowl_wall_thickness / 2, seg_half_len, wall_top / 2)
        rgba = scene_cfg.bowl_mark_rgba if i == 0 else scene_cfg.bowl_rgba
        clouds.append(_colored(_box_surface(center, half, a, rng), rgba, rng))
    points = np.concatenate([p for p, _ in clouds]).astype(np.float32)
    return points, np.concatenate([col for _, col in clouds])


def _in_disc(rng, radius: float) -> np.ndarray:
    r = max(radius, 0.0) * math.sqrt(rng.random())
    a = rng.uniform(0, 2 * math.pi)
    return np.array([r * math.cos(a), r * math.sin(a)])


def twin_scenes(preset, workspace, count: int = 2, seed: int = 0, *, scene) -> tuple[torch.Tensor, torch.Tensor]:
    """(voxels uint8 (B, To, 4, R, R, R), ee float32 (B, To, 10)): ``count`` scenes of ``scene``'s objects
    (``twin.config.SceneConfig``, e.g. ``load_twin_config().scene``) voxelised by ``perception.voxels.voxelize`` (the
    points given in the base frame), a static history, and a downward gripper above the table at a random yaw."""
    scene_cfg = scene
    rng = np.random.default_rng(seed)
    radius = rotation_safe_radius(preset, workspace)
    grids = [
        voxelize([twin_scene_cloud(scene_cfg, workspace, radius, rng)], [np.eye(4)], workspace) for _ in range(count)
    ]
    vox = np.repeat(np.stack(grids)[:, None], preset.n_obs_steps, 1)
    ee = _random_gripper_states(workspace, rng, count, radius=radius / 2**0.5 * 0.8, z_range=(0.03, 0.25))
    ee = np.repeat(ee[:, None], preset.n_obs_steps, 1)
    return torch.from_numpy(vox), torch.from_numpy(ee.astype(np.float32))


def rotate_observation(workspace, voxels: torch.Tensor, ee: torch.Tensor, theta: float):
    vox = geometry.rotate_voxel_grid(voxels, theta, mode="nearest")
    return vox, geometry.rotate_action(ee.double(), theta, workspace.center).float()


# --- Subjects -----------------------------------------------------------------------------------------


class TrainingModel:
    """A ``policy.diffusion.DiffusionPolicy`` (escnn for EquiDiff), one observation at a time."""

    def __init__(self, policy):
        self.policy = policy.eval()
        self.preset, self.workspace = policy.preset, policy.workspace
        self.freqs, self.dim = policy.action_freqs, policy.codec.dim

    @torch.no_grad()
    def denoise(self, voxels: torch.Tensor, ee: torch.Tensor, x: torch.Tensor, t: int) -> torch.Tensor:
        vox, ee_n = self.policy.prepare_input(voxels[None], ee[None], "center")
        return self.policy.model(x, torch.tensor([t]), vox, ee_n).float()

    @torch.no_grad()
    def sample(self, voxels: torch.Tensor, ee: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        out = self.policy.predict_action({"voxels": voxels[None], "ee": ee[None]}, noise=noise)
        return out["action_pred"][0].double()


class ExportedModel:
    """An ``policy.inference.InferencePolicy`` (plain torch; its single-step history is the newest observation)."""

    def __init__(self, fast):
        self.fast = fast
        self.preset, self.workspace = fast.preset, fast.workspace
        self.freqs, self.dim = fast.codec.freqs, fast.codec.dim

    def denoise(self, voxels: torch.Tensor, ee: torch.Tensor, x: torch.Tensor, t: int) -> torch.Tensor:
        cond = self.fast.encode(voxels[-1].numpy(), ee[-1].numpy())
        return self.fast.denoise(x.to(self.fast.device), torch.tensor([t]), cond).float().cpu()

    def sample(self, voxels: torch.Tensor, ee: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(self.fast.predict(voxels[-1].numpy(), ee[-1].numpy(), noise=noise[0].numpy()))


# --- Errors ------------------------------------------------------------------------------------------------


def _rep(subject, theta: float) -> torch.Tensor:
    return torch.as_tensor(action_space.rep_matrix(subject.freqs, theta), dtype=torch.float32)


def denoiser_errors(
    subject, voxels: torch.Tensor, ee: torch.Tensor, angles_deg=C8_ANGLES_DEG, timestep: int = 10, seed: int = 0
) -> dict[float, float]:
    """{angle (deg): ||eps(g.o, g.x) - g.eps(o, x)|| / ||eps(o, x)||} over the scenes (B, To, ...)."""
    gen = torch.Generator().manual_seed(seed)
    xs = [torch.randn(1, subject.preset.horizon, subject.dim, generator=gen) for _ in range(len(voxels))]
    eps = [subject.denoise(v, e, x, timestep) for v, e, x in zip(voxels, ee, xs)]
    ref = math.sqrt(sum(float(torch.sum(e**2)) for e in eps))
    errors = {}
    for angle in angles_deg:
        theta = math.radians(angle)
        rep = _rep(subject, theta)
        vox_g, ee_g = rotate_observation(subject.workspace, voxels, ee, theta)
        diff = sum(
            float(torch.sum((subject.denoise(v, e, x @ rep.T, timestep) - ep @ rep.T) ** 2))
            for v, e, x, ep in zip(vox_g, ee_g, xs, eps)
        )
        errors[angle] = math.sqrt(diff) / ref
    return errors


def sampling_errors(
    subject, voxels: torch.Tensor, ee: torch.Tensor, angles_deg=C8_ANGLES_DEG, seed: int = 0
) -> dict[float, float]:
    """{angle (deg): ||a(g.o, g.z) - g.a(o, z)|| / ||a(o, z) - centre||} for DDIM from fixed noise z."""
    gen = torch.Generator().manual_seed(seed + 1)
    zs = [torch.randn(1, subject.preset.horizon, subject.dim, generator=gen) for _ in range(len(voxels))]
    actions = [subject.sample(v, e, z) for v, e, z in zip(voxels, ee, zs)]
    center = torch.zeros(geometry.ACTION_DIM, dtype=torch.float64)
    center[geometry.POS] = torch.tensor(subject.workspace.center, dtype=torch.float64)
    ref = math.sqrt(sum(float(torch.sum((a - center) ** 2)) for a in actions))
    errors = {}
    for angle in angles_deg:
        theta = math.radians(angle)
        rep = _rep(subject, theta)
        vox_g, ee_g = rotate_observation(subject.workspace, voxels, ee, theta)
        diff = 0.0
        for v, e, z, a in zip(vox_g, ee_g, zs, actions):
            expected = geometry.rotate_action(a, theta, subject.workspace.center)
            diff += float(torch.sum((subject.sample(v, e, z @ rep.T) - expected) ** 2))
        errors[angle] = math.sqrt(diff) / ref
    return errors


def summarize(errors: dict[float, float]) -> dict:
    """``c4_max_rel_err`` (90, 180, 270 deg), ``rot45_max_rel_err`` (45, 135, 225, 315 deg), ``per_element``."""
    c4 = [e for a, e in errors.items() if is_c4(a)]
    off = [e for a, e in errors.items() if not is_c4(a)]

    def r(e):  # 3 significant digits: the errors span 0 to ~1, their last digits are rounding noise
        return float(f"{e:.3g}")

    return {
        "c4_max_rel_err": r(max(c4)) if c4 else None,
        "rot45_max_rel_err": r(max(off)) if off else None,
        "per_element": {f"{a:g}deg": r(e) for a, e in errors.items()},
    }


def measure(
    subject,
    voxels: torch.Tensor,
    ee: torch.Tensor,
    sampling: bool = True,
    timestep: int = 10,
    seed: int = 0,
    angles_deg=C8_ANGLES_DEG,
) -> dict:
    """{"denoiser": summary, "sampling": summary or None} of ``subject`` on the scenes (see ``summarize``)."""
    den = summarize(denoiser_errors(subject, voxels, ee, angles_deg, timestep, seed))
    samp = summarize(sampling_errors(subject, voxels, ee, angles_deg, seed)) if sampling else None
    return {"denoiser": den, "sampling": samp}


def noise_predictor_error(policy, theta: float, batch: int = 2, seed: int = 0, timestep: int = 10, *, scene) -> float:
    """The denoiser's relative error at one rotation ``theta`` (rad) on ``batch`` scenes of ``scene``'s objects."""
    voxels, ee = twin_scenes(policy.preset, policy.workspace, batch, seed, scene=scene)
    angle = math.degrees(theta)
    return denoiser_errors(TrainingModel(policy), voxels, ee, (angle,), timestep, seed)[angle]
