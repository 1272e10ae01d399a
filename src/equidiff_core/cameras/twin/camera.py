"""Simulated RealSense D455 for the digital twin: MuJoCo offscreen RGB + depth -> coloured cloud (+ the RGB image).

The camera runs in its own process (camera_node with backend ``twin``), apart from the sim
server (twin_node). It compiles the very same scene MJCF (``equidiff_core.twin.scene``),
reads the sim state (qpos + capture stamp) from the twin's shared memory, runs the
kinematics and renders from a fixed camera placed at the configured ``T_base_optical``.
MuJoCo depth is planar z, so the optical-frame point of pixel (u, v) is
x = (u + 0.5 - cx) z / fx, y = (v + 0.5 - cy) z / fy (checked against rendered boxes: points land on
them within 0.2 um; dropping the half pixel costs ~2 mm, reading depth as ray length 1-12 mm).

Rendering settings are the cheap ones (no multisampling, shadows, reflections, skybox): several
times cheaper than MuJoCo's defaults (docs/results/twin.md measures a twin episode's cost).
An EGL context belongs to one thread, so each camera renders in a worker thread of its own
(created on connect, closed on disconnect) whichever threads call ``read``; set
``MUJOCO_GL=egl`` on headless machines (osmesa does not work).

When a frame is taken: on the twin's simulated time (``lockstep``) the sim requests each frame
at its instant and waits until every camera has taken it (``twin.shared_state``), so all
cameras show exactly that instant and are stamped with it. On real time, paced reads fall on
the multiples of 1/publish_hz of the wall clock, so separate camera processes sample the same
sim snapshot, like hardware-synchronised cameras, and the voxel node's time matching succeeds.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from ...config import CameraConfig
from ..base import Camera, CameraError, CloudFrame, NoFrameYet
from .config import TwinCameraOptions

os.environ.setdefault("MUJOCO_GL", "egl")

# (trigger time ns | None) -> (qpos, sim_time, stamp_ns) of the sim state nearest that time
StateSource = Callable[[int | None], tuple[np.ndarray, float, int]]


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fovy(cls, width: int, height: int, fovy_deg: float) -> Intrinsics:
        f = (height / 2) / math.tan(math.radians(fovy_deg) / 2)  # MuJoCo cameras have square pixels
        return cls(width, height, f, f, width / 2, height / 2)


def depth_to_points(depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Planar depth (H, W) -> optical-frame points (H, W, 3)."""
    v, u = np.indices(depth.shape, dtype=np.float32)
    x = (u + 0.5 - intr.cx) * depth / intr.fx
    y = (v + 0.5 - intr.cy) * depth / intr.fy
    return np.stack([x, y, depth], axis=-1)


def degrade_depth(
    depth: np.ndarray, rng: np.random.Generator, base: float, quadratic: float, dropout: float, edge_dropout: bool
) -> np.ndarray:
    """D455-like depth: axial noise growing with z^2, random dropout and lost pixels at depth edges.

    Lost pixels become 0 (as in a RealSense depth image) and are removed with the invalid range.
    """
    out = depth.astype(np.float32, copy=True)
    if base > 0 or quadratic > 0:
        out += rng.standard_normal(out.shape).astype(np.float32) * (base + quadratic * out * out)
    lost = rng.random(out.shape) < dropout if dropout > 0 else np.zeros(out.shape, bool)
    if edge_dropout:
        # stereo matching fails on depth discontinuities: drop pixels next to a jump > 3 cm,
        # half of them at random, so silhouettes fray the way real ones do
        jump = np.zeros(out.shape, bool)
        dz_u = np.abs(np.diff(depth, axis=1)) > 0.03
        dz_v = np.abs(np.diff(depth, axis=0)) > 0.03
        jump[:, 1:] |= dz_u
        jump[1:, :] |= dz_v
        lost |= jump & (rng.random(out.shape) < 0.5)
    out[lost] = 0.0
    return out


class TwinCamera(Camera):
    """A coloured point cloud of the twin, as a D455 at ``camera.extrinsics`` would see it."""

    def __init__(self, camera: CameraConfig, state_source: StateSource | None = None, **options):
        from ...twin.config import load_twin_config

        unknown = set(options) - set(TwinCameraOptions.__dataclass_fields__)
        if unknown:
            raise CameraError(
                f"twin camera {camera.name}: unknown option(s) {sorted(unknown)}; "
                f"allowed: {sorted(TwinCameraOptions.__dataclass_fields__)}"
            )
        self.options = TwinCameraOptions(**options)
        self.camera = camera
        cfg = options.get("twin_config")
        self.twin_cfg = cfg if not isinstance(cfg, (str, os.PathLike, type(None))) else load_twin_config(cfg)
        render = self.twin_cfg.render
        o = self.options
        render = replace(
            render,
            width=o.width or render.width,
            height=o.height or render.height,
            depth_noise=render.depth_noise if o.depth_noise is None else o.depth_noise,
            dropout=render.dropout if o.dropout is None else o.dropout,
        )
        self.render_cfg = render
        self.intrinsics = Intrinsics.from_fovy(render.width, render.height, render.fovy_deg)
        self._state_source = state_source
        self._reader = None
        self._model = self._data = self._renderer = None
        self._worker: ThreadPoolExecutor | None = None
        self._rng = self._noise_rng()
        self._last_tick = -1
        self._last_frame = 0
        self._connected = False

    def _noise_rng(self, episode_seed: int | None = None) -> np.random.Generator:
        key = [self.render_cfg.seed, sum(map(ord, self.camera.name))]
        return np.random.default_rng(key if episode_seed is None else [*key, episode_seed])

    def reseed(self, episode_seed: int) -> None:
        """Start the depth noise afresh for an episode: its frames then depend on its scene seed alone,
        not on how many frames this camera rendered before (the in-process roll-outs and demos call it
        for every scene; a live camera node renders one stream and keeps its generator)."""
        self._rng = self._noise_rng(episode_seed)

    # -- Camera interface --------------------------------------------------------------------
    def connect(self) -> None:
        import mujoco

        from ...twin.scene import build_model

        if self._connected:
            return
        try:
            self._model = build_model(self.twin_cfg, cameras=[self.camera])
        except Exception as err:  # a broken scene config must name the camera that needed it
            raise CameraError(f"twin camera {self.camera.name}: cannot build the twin scene: {err}") from err
        self._model.vis.quality.offsamples = 0
        # the offscreen buffer must hold the frame (MuJoCo's default is 640x480; a D455 is 848x480)
        glob = self._model.vis.global_
        glob.offwidth, glob.offheight = (
            max(glob.offwidth, self.render_cfg.width),
            max(glob.offheight, self.render_cfg.height),
        )
        self._data = mujoco.MjData(self._model)
        if self._state_source is None:
            from ...twin.shared_state import SharedStateError, StateReader

            try:
                self._reader = StateReader(self.options.shm_name, nq=self._model.nq)
            except SharedStateError as err:
                raise CameraError(f"twin camera {self.camera.name}: {err}") from err
            reader = self._reader
            self._state_source = lambda t: reader.read() if t is None else reader.read_nearest(t)
            if self.options.lockstep:
                try:
                    reader.register(self.options.slot)
                except SharedStateError as err:
                    raise CameraError(f"twin camera {self.camera.name}: {err}") from err
                self._last_frame = 0
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"render-{self.camera.name}")
        self._connected = True

    def disconnect(self) -> None:
        if self._worker is not None:
            self._worker.submit(self._close_renderer).result()
            self._worker.shutdown(wait=True)
            self._worker = None
        if self._reader is not None:
            self._reader.close()
            self._reader = None
            self._state_source = None
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def read(self, timeout_s: float = 1.0) -> CloudFrame:
        if not self._connected:
            raise CameraError(f"twin camera {self.camera.name} is not connected")
        if self.options.stall_flag and os.path.exists(self.options.stall_flag):
            time.sleep(timeout_s)
            raise CameraError(f"twin camera {self.camera.name}: no frame within {timeout_s} s (stalled)")
        if self.options.lockstep:
            qpos, stamp_ns = self._take_frame(timeout_s)
        else:
            trigger = self._wait_for_tick(timeout_s) if self.options.paced else None
            try:
                qpos, _, stamp_ns = self._state_source(trigger)
            except Exception as err:
                raise CameraError(f"twin camera {self.camera.name}: no sim state: {err}") from err
        if not np.all(np.isfinite(qpos)):
            raise CameraError(f"twin camera {self.camera.name}: sim state contains NaN")
        rgb, depth = self.render(qpos)
        points, colors = self.to_cloud(rgb, depth)
        if len(points) == 0:
            raise CameraError(
                f"twin camera {self.camera.name}: no valid depth in range "
                f"[{self.camera.min_depth}, {self.camera.max_depth}] m"
            )
        return CloudFrame(points, colors, int(stamp_ns), rgb)

    def _take_frame(self, timeout_s: float) -> tuple[np.ndarray, int]:
        """The next frame the sim requests (simulated time): its state and its instant."""
        from ...twin.shared_state import SharedStateError

        if self._reader is None:
            raise CameraError(f"twin camera {self.camera.name}: lockstep needs the twin's shared state")
        try:
            self._last_frame, qpos, _, stamp_ns = self._reader.take_frame(self._last_frame, timeout_s)
        except SharedStateError as err:
            raise NoFrameYet(f"twin camera {self.camera.name}: {err}") from err
        return qpos, stamp_ns

    def _wait_for_tick(self, timeout_s: float) -> int:
        """Sleep to the next multiple of the publish period on the wall clock (shared by all
        cameras) and return it: the trigger time whose sim state this frame shows."""
        period_ns = int(1e9 / max(self.camera.publish_hz, 1e-3))
        now = time.time_ns()
        tick = now // period_ns + 1
        if tick <= self._last_tick:
            tick = self._last_tick + 1
        wait = (tick * period_ns - now) / 1e9
        if wait > timeout_s:
            raise CameraError(f"twin camera {self.camera.name}: no frame within {timeout_s} s")
        time.sleep(max(0.0, wait))
        self._last_tick = tick
        return tick * period_ns

    # -- rendering ---------------------------------------------------------------------------
    def _close_renderer(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def _ensure_renderer(self):
        import mujoco

        if self._renderer is None:
            r = self.render_cfg
            self._renderer = mujoco.Renderer(self._model, height=r.height, width=r.width)
            flags = self._renderer.scene.flags
            for flag in (
                mujoco.mjtRndFlag.mjRND_SHADOW,
                mujoco.mjtRndFlag.mjRND_REFLECTION,
                mujoco.mjtRndFlag.mjRND_SKYBOX,
            ):
                flags[flag] = 0
        return self._renderer

    def render(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(RGB uint8 (H, W, 3), planar depth float32 (H, W) in metres) of the state ``qpos``."""
        if self._worker is None:
            raise CameraError(f"twin camera {self.camera.name} is not connected")
        return self._worker.submit(self._render, np.array(qpos, dtype=np.float64)).result()

    def _render(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import mujoco

        self._data.qpos[:] = qpos
        mujoco.mj_kinematics(self._model, self._data)
        mujoco.mj_camlight(self._model, self._data)
        renderer = self._ensure_renderer()
        renderer.update_scene(self._data, camera=self.camera.name)
        rgb = renderer.render().copy()
        renderer.enable_depth_rendering()
        try:
            depth = renderer.render().astype(np.float32)
        finally:
            renderer.disable_depth_rendering()
        return rgb, depth

    def to_cloud(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = self.render_cfg
        if r.depth_noise:
            depth = degrade_depth(depth, self._rng, r.noise_base, r.noise_quadratic, r.dropout, r.edge_dropout)
        elif r.dropout > 0:
            depth = degrade_depth(depth, self._rng, 0.0, 0.0, r.dropout, False)
        valid = (depth >= self.camera.min_depth) & (depth <= self.camera.max_depth)
        points = depth_to_points(depth, self.intrinsics)[valid]
        return points.astype(np.float32), rgb[valid]
