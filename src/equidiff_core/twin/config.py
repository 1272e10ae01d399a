"""Typed configuration of the digital twin (config/twin.yaml): scene, randomisation, rendering, sim, expert.

Every number that decides what an episode looks like lives here, so a seed plus this file
reproduces an episode exactly (the scene sampler draws from ``numpy.random.default_rng(seed)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from ..config import REACH_M, LabConfig, bounded, check_unit_quaternion, default_config_dir, from_dict, load_mapping
from ..robots.base import CartesianLimits

# The policy's arithmetic in the twin: pinned, not "auto" (bf16 where the CPU has it natively),
# so an episode's result does not depend on which machine ran it.
TWIN_PRECISION = "fp32"

# The first scene seed of evaluation episodes (then +1 each): far above the demo collection's
# seeds (from 0), so a policy is judged on scenes it was not trained on.
EVALUATION_FIRST_SEED = 100_000


@dataclass(frozen=True)
class BoardMountConfig:
    """A printed calibration board rigidly fixed to the hand (``equidiff calibrate cameras --twin``).

    The board frame is OpenCV's ChArUco frame: origin at the image's top-left corner, x along
    the image's columns, y down its rows, z into the board (the printed side faces -z).
    """

    texture: str  # PNG of the board alone (no margin): what is printed
    size: tuple[float, float]  # m, extent along the board's x and y (the image's width and height)
    pos: tuple[float, float, float]  # board origin in the hand body's frame, m
    quat_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)  # board frame in the hand frame
    thickness: float = 0.003  # m, behind the printed side

    def __post_init__(self):
        if min(self.size) <= 0 or self.thickness <= 0:
            raise ValueError("board size and thickness must be positive")
        check_unit_quaternion(self.quat_wxyz, "quat_wxyz")


@dataclass(frozen=True)
class SceneConfig:
    """A table with a block and a bowl on it ("put the block in the bowl")."""

    # The robot stands on the table: the table top is the base frame's z = 0 plane.
    table_center_xy: tuple[float, float] = (0.35, 0.0)
    table_half_xy: tuple[float, float] = (0.65, 0.6)
    table_height: float = 0.75
    table_rgba: tuple[float, float, float, float] = (0.62, 0.5, 0.36, 1.0)
    # Block: a box grasped across its short side, so its yaw matters modulo 180 degrees.
    block_size: tuple[float, float, float] = (0.05, 0.03, 0.03)  # full extents, m
    block_mass: float = 0.05
    block_rgba: tuple[float, float, float, float] = (0.85, 0.12, 0.1, 1.0)
    # Bowl: a flat base and a ring of wall segments; one wall segment is a different colour
    # (a "handle mark") so its yaw is visible too.
    bowl_inner_radius: float = 0.06
    bowl_wall_thickness: float = 0.008
    bowl_wall_height: float = 0.035
    bowl_base_thickness: float = 0.006
    bowl_segments: int = 16
    bowl_mass: float = 0.5
    bowl_rgba: tuple[float, float, float, float] = (0.15, 0.35, 0.85, 1.0)
    bowl_mark_rgba: tuple[float, float, float, float] = (0.95, 0.85, 0.1, 1.0)
    friction: tuple[float, float, float] = (1.5, 0.01, 0.0002)
    # Randomisation: object centres uniform in this rectangle (base frame, m), yaw uniform in
    # the given range (degrees; [0, 360) is the full circle), at least min_separation apart.
    region_x: tuple[float, float] = bounded((0.36, 0.56), unit="m", ge=-REACH_M, le=REACH_M)
    region_y: tuple[float, float] = bounded((-0.14, 0.14), unit="m", ge=-REACH_M, le=REACH_M)
    block_yaw_deg: tuple[float, float] = bounded((0.0, 360.0), unit="deg", ge=-360, le=360)
    bowl_yaw_deg: tuple[float, float] = bounded((0.0, 360.0), unit="deg", ge=-360, le=360)
    min_separation: float = bounded(0.15, unit="m", ge=0, le=1)
    # Off (None) unless calibrating: policies' observations never show a board.
    calibration_board: BoardMountConfig | None = None

    def __post_init__(self):
        for name in ("region_x", "region_y", "block_yaw_deg", "bowl_yaw_deg"):
            lo, hi = getattr(self, name)
            if hi < lo:
                raise ValueError(f"{name}: upper bound {hi} below lower bound {lo}")
        if self.bowl_segments < 6:
            raise ValueError("bowl_segments must be >= 6")
        if min(self.block_size) <= 0 or self.bowl_inner_radius <= 0:
            raise ValueError("object sizes must be positive")

    @property
    def bowl_outer_radius(self) -> float:
        return self.bowl_inner_radius + self.bowl_wall_thickness


@dataclass(frozen=True)
class SuccessConfig:
    """The block rests inside the bowl: centred within the wall, below the rim, still, released."""

    margin: float = bounded(0.01, unit="m", ge=0, le=0.1)  # block centre at least this far inside the inner wall
    max_speed: float = bounded(0.05, unit="m/s", gt=0, le=1)
    hold_s: float = bounded(0.5, unit="s", ge=0, le=10)  # success must hold this long before an episode ends early


@dataclass(frozen=True)
class RenderConfig:
    """Simulated D455s: the poses come from lab.yaml; intrinsics, resolution and noise from here."""

    width: int = bounded(424, unit="px", ge=8, le=4096)
    height: int = bounded(240, unit="px", ge=8, le=4096)
    # D455 depth VFOV; with fx = fy this gives HFOV ~88 degrees at 16:9
    fovy_deg: float = bounded(58.0, unit="deg", gt=0, lt=180)
    # Depth noise, D455-like: sigma(z) = noise_base + noise_quadratic * z^2 (m), plus dropout.
    depth_noise: bool = True
    noise_base: float = bounded(0.0005, unit="m", ge=0, le=0.1)
    noise_quadratic: float = bounded(0.0015, unit="1/m", ge=0, le=0.1)
    dropout: float = bounded(0.02, unit="", ge=0, lt=1)  # fraction of pixels lost at random
    edge_dropout: bool = True  # lose pixels at depth discontinuities like a stereo camera
    seed: int = 0

    def __post_init__(self):
        if self.width < 8 or self.height < 8:
            raise ValueError("render resolution must be at least 8x8")
        if not 0 <= self.dropout < 1:
            raise ValueError("dropout must be in [0, 1)")


@dataclass(frozen=True)
class SimConfig:
    host: str = "127.0.0.1"  # loopback address franky-sim serves libfranka on ("auto": pick a free one)
    state_hz: float = bounded(60.0, unit="Hz", gt=0, le=1000)  # shared-memory state snapshots for the cameras
    status_hz: float = bounded(10.0, unit="Hz", gt=0, le=1000)  # /twin/state
    initial_q: tuple[float, float, float, float, float, float, float] = (0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785)


@dataclass(frozen=True)
class ExpertConfig:
    """Scripted grasp-lift-place planner (speeds like a careful SpaceMouse operator)."""

    ready_position: tuple[float, float, float] = bounded((0.45, 0.0, 0.30), unit="m", ge=-REACH_M, le=REACH_M)
    # TCP speed for transfers
    speed: float = bounded(0.15, unit="m/s", gt=0, le=CartesianLimits.translation_velocity_m_s)
    # for the last centimetres of approach and grasp
    slow_speed: float = bounded(0.05, unit="m/s", gt=0, le=CartesianLimits.translation_velocity_m_s)
    yaw_speed: float = bounded(1.5, unit="rad/s", gt=0, le=CartesianLimits.rotation_velocity_rad_s)
    approach_height: float = 0.10  # above the object before descending
    grasp_height: float = 0.018  # TCP z when closing on the block
    lift_height: float = 0.15
    place_height: float = 0.09  # TCP z when releasing above the bowl
    open_width: float = 0.08
    close_width: float = 0.0  # commanded closed width (franky-sim holds with a smaller width)
    gripper_wait_s: float = bounded(0.8, unit="s", ge=0, le=10)
    settle_s: float = bounded(0.3, unit="s", ge=0, le=10)
    command_hz: float = bounded(20.0, unit="Hz", gt=0, le=1000)  # like teleop


@dataclass(frozen=True)
class EpisodeConfig:
    max_duration_s: float = bounded(40.0, unit="s", gt=0, le=3600)
    home_timeout_s: float = bounded(15.0, unit="s", gt=0, le=300)


@dataclass(frozen=True)
class TwinConfig:
    scene: SceneConfig = field(default_factory=SceneConfig)
    success: SuccessConfig = field(default_factory=SuccessConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)

    def with_yaw_range(self, block_deg: tuple[float, float], bowl_deg: tuple[float, float] | None = None):
        """A copy whose object yaw is drawn from narrower ranges (generalisation benchmark)."""
        scene = replace(
            self.scene,
            block_yaw_deg=tuple(block_deg),
            bowl_yaw_deg=tuple(bowl_deg if bowl_deg is not None else block_deg),
        )
        return replace(self, scene=scene)


def load_twin_config(path: str | Path | None = None) -> TwinConfig:
    """config/twin.yaml (or ``path``) -> TwinConfig; missing file at the default path -> defaults."""
    if path is None:
        path = default_config_dir() / "twin.yaml"
        if not Path(path).is_file():
            return TwinConfig()
    return from_dict(TwinConfig, load_mapping(path), where=Path(path).name)


@dataclass(frozen=True)
class TwinPaths:
    """The two config files a twin job reads, resolved, and what they hold."""

    lab_path: Path
    twin_path: Path
    lab: LabConfig
    twin: TwinConfig


def load_twin_job_configs(lab_path: str | Path | None, twin_path: str | Path | None) -> TwinPaths:
    """lab.yaml + twin.yaml for the `equidiff twin …` / bench commands (defaults: the installed ones)."""
    from ..config import load_lab_config

    lab_path = Path(lab_path) if lab_path else default_config_dir() / "lab.yaml"
    twin_path = Path(twin_path) if twin_path else default_config_dir() / "twin.yaml"
    return TwinPaths(lab_path, twin_path, load_lab_config(lab_path), load_twin_config(twin_path))
