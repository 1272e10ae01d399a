"""The twin's task scene on franky-sim's MuJoCo world: table, block, bowl, seeded randomisation, success.

franky-sim builds its world as an MJCF tree (``MujocoSimulator.scene``); we add to that tree
before the simulator starts, so the physics server and every camera process compile the
*same* XML and share one qpos layout: a camera only needs the state vector to render what
the server simulates. The robot's base is the world origin, so world frame = base frame.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import asdict, dataclass

import numpy as np

from ..config import CameraConfig
from ..robots.franky.hand import FINGER_BODIES, HAND_BODY
from .config import (
    BoardMountConfig,
    RenderConfig,
    SceneConfig,
    SuccessConfig,
    TwinConfig,
)

BLOCK = "block"
BOWL = "bowl"
TABLE = "table"
CALIBRATION_BOARD = "calibration_board"


class SceneError(RuntimeError):
    """The scene cannot be built or an episode cannot be set up."""


def _fmt(values: Iterable[float]) -> str:
    return " ".join(f"{float(v):.6g}" for v in values)


# --- Building the MJCF --------------------------------------------------------------------


def add_task_objects(scene: ET.Element, cfg: SceneConfig) -> None:
    """Add the table, block and bowl to franky-sim's scene tree (call before the sim starts)."""
    worldbody = scene.find("worldbody")
    if worldbody is None:
        raise SceneError("scene has no <worldbody>")
    # The robot is mounted on the table: lower franky-sim's ground plane to the floor.
    for geom in worldbody.findall("geom"):
        if geom.get("name") == "ground":
            geom.set("pos", _fmt((0, 0, -cfg.table_height)))
    hx, hy = cfg.table_half_xy
    ET.SubElement(
        worldbody,
        "geom",
        name=TABLE,
        type="box",
        pos=_fmt((*cfg.table_center_xy, -cfg.table_height / 2)),
        size=_fmt((hx, hy, cfg.table_height / 2)),
        rgba=_fmt(cfg.table_rgba),
        friction=_fmt(cfg.friction),
    )

    sx, sy, sz = (s / 2 for s in cfg.block_size)
    block = ET.SubElement(worldbody, "body", name=BLOCK, pos=_fmt((0.45, 0.1, sz)))
    ET.SubElement(block, "freejoint", name=f"{BLOCK}_joint")
    ET.SubElement(
        block,
        "geom",
        name=f"{BLOCK}_geom",
        type="box",
        size=_fmt((sx, sy, sz)),
        mass=f"{cfg.block_mass}",
        rgba=_fmt(cfg.block_rgba),
        friction=_fmt(cfg.friction),
        condim="4",
    )

    bowl = ET.SubElement(worldbody, "body", name=BOWL, pos=_fmt((0.45, -0.1, 0)))
    ET.SubElement(bowl, "freejoint", name=f"{BOWL}_joint")
    n = cfg.bowl_segments
    geom_mass = cfg.bowl_mass / (n + 1)
    outer = cfg.bowl_outer_radius
    ET.SubElement(
        bowl,
        "geom",
        name=f"{BOWL}_base",
        type="cylinder",
        size=_fmt((outer, cfg.bowl_base_thickness / 2)),
        pos=_fmt((0, 0, cfg.bowl_base_thickness / 2)),
        mass=f"{geom_mass}",
        rgba=_fmt(cfg.bowl_rgba),
        friction=_fmt(cfg.friction),
    )
    r_mid = cfg.bowl_inner_radius + cfg.bowl_wall_thickness / 2
    seg_half_len = r_mid * math.tan(math.pi / n) * 1.08  # slight overlap closes the ring
    wall_top = cfg.bowl_base_thickness + cfg.bowl_wall_height
    for i in range(n):
        a = 2 * math.pi * i / n
        ET.SubElement(
            bowl,
            "geom",
            name=f"{BOWL}_wall{i}",
            type="box",
            size=_fmt((cfg.bowl_wall_thickness / 2, seg_half_len, wall_top / 2)),
            pos=_fmt((r_mid * math.cos(a), r_mid * math.sin(a), wall_top / 2)),
            euler=_fmt((0, 0, a)),
            mass=f"{geom_mass}",
            rgba=_fmt(cfg.bowl_mark_rgba if i == 0 else cfg.bowl_rgba),
            friction=_fmt(cfg.friction),
        )


def add_calibration_board(scene: ET.Element, board: BoardMountConfig) -> None:
    """A textured plate fixed to the hand: the printed ChArUco board, purely visual.

    A box mesh whose printed face carries the image exactly once (explicit texture coordinates;
    MuJoCo's box texture mapping would tile it). It has no collisions and no mass worth the
    name, so the arm moves as without it.
    """
    hand = scene.find(f".//body[@name='{HAND_BODY}']")
    if hand is None:
        raise SceneError(f"scene has no hand body {HAND_BODY!r} to fix the calibration board to")
    asset = scene.find("asset")
    if asset is None:
        asset = ET.SubElement(scene, "asset")
    w, h = board.size
    t = board.thickness
    corners = [(0, 0), (w, 0), (w, h), (0, h)]
    vertices = [(x, y, 0.0) for x, y in corners] + [(x, y, t) for x, y in corners]
    # image column x/w, row y/h; MuJoCo's texture v runs from the image's top row downwards
    texcoords = [(x / w, y / h) for x, y in corners] * 2
    faces = [
        (0, 2, 1),
        (0, 3, 2),  # printed side (normal -z, towards the viewer)
        (4, 5, 6),
        (4, 6, 7),
        (0, 1, 5),
        (0, 5, 4),
        (1, 2, 6),
        (1, 6, 5),
        (2, 3, 7),
        (2, 7, 6),
        (3, 0, 4),
        (3, 4, 7),
    ]
    ET.SubElement(asset, "texture", name=CALIBRATION_BOARD, type="2d", file=str(board.texture))
    ET.SubElement(
        asset,
        "material",
        name=CALIBRATION_BOARD,
        texture=CALIBRATION_BOARD,
        specular="0",
        shininess="0",
        reflectance="0",
    )
    ET.SubElement(
        asset,
        "mesh",
        name=CALIBRATION_BOARD,
        vertex=_fmt(np.ravel(vertices)),
        face=" ".join(str(i) for f in faces for i in f),
        texcoord=_fmt(np.ravel(texcoords)),
    )
    ET.SubElement(
        hand,
        "geom",
        name=CALIBRATION_BOARD,
        type="mesh",
        mesh=CALIBRATION_BOARD,
        material=CALIBRATION_BOARD,
        pos=_fmt(board.pos),
        quat=_fmt(board.quat_wxyz),
        contype="0",
        conaffinity="0",
        mass="1e-6",
    )


def optical_to_mujoco_camera(T_base_optical: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optical frame (x right, y down, z forward) -> MuJoCo camera frame (x right, y up, looks along -z)."""
    R_cam = T_base_optical[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    return T_base_optical[:3, 3].copy(), R_cam


def add_cameras(scene: ET.Element, cameras: Iterable[CameraConfig], render: RenderConfig) -> None:
    """Fixed MJCF cameras at the configured extrinsics, sized for offscreen rendering."""
    cameras = list(cameras)
    visual = scene.find("visual")
    if visual is None:
        visual = ET.SubElement(scene, "visual")
    glob = visual.find("global")
    if glob is None:
        glob = ET.SubElement(visual, "global")
    glob.set("offwidth", str(max(640, render.width)))
    glob.set("offheight", str(max(480, render.height)))
    quality = visual.find("quality")
    if quality is not None:  # cheap rendering (cameras.twin: 4x cheaper): no multisampling, no shadow map
        quality.set("offsamples", "0")
        quality.set("shadowsize", "0")
    worldbody = scene.find("worldbody")
    for cam in cameras:
        pos, R = optical_to_mujoco_camera(cam.extrinsics.matrix())
        ET.SubElement(
            worldbody,
            "camera",
            name=cam.name,
            pos=_fmt(pos),
            xyaxes=_fmt(np.concatenate([R[:, 0], R[:, 1]])),
            fovy=f"{render.fovy_deg}",
        )


def build_simulator(cfg: TwinConfig, enable_visualization: bool = False):
    """franky-sim's MujocoSimulator with one FR3 and the task objects (not started)."""
    from franky_sim.mujoco_simulator import MujocoSimulator

    sim = MujocoSimulator(enable_visualization=enable_visualization)
    robot = sim.add_robot(initial_q=cfg.sim.initial_q)
    add_task_objects(sim.scene, cfg.scene)
    if cfg.scene.calibration_board is not None:
        add_calibration_board(sim.scene, cfg.scene.calibration_board)
    return sim, robot


def scene_xml(cfg: TwinConfig, cameras: Iterable[CameraConfig] = ()) -> str:
    """The exact MJCF the sim server compiles, plus (optionally) the cameras; same qpos layout."""
    sim, _ = build_simulator(cfg)
    if cameras:
        add_cameras(sim.scene, cameras, cfg.render)
    return ET.tostring(sim.scene, encoding="unicode")


def build_model(cfg: TwinConfig, cameras: Iterable[CameraConfig] = ()):
    import mujoco

    model = mujoco.MjModel.from_xml_string(scene_xml(cfg, cameras))
    model.opt.timestep = 0.001
    return model


# --- Episodes: seeded object poses -----------------------------------------------------------


@dataclass(frozen=True)
class ScenePoses:
    """Where an episode starts: planar object poses (base frame, m / rad) and the seed that drew them."""

    seed: int
    block_xy: tuple[float, float]
    block_yaw: float
    bowl_xy: tuple[float, float]
    bowl_yaw: float

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> ScenePoses:
        return cls(
            int(d["seed"]),
            tuple(map(float, d["block_xy"])),
            float(d["block_yaw"]),
            tuple(map(float, d["bowl_xy"])),
            float(d["bowl_yaw"]),
        )


def sample_scene(cfg: SceneConfig, seed: int, max_tries: int = 1000) -> ScenePoses:
    """Draw object poses from ``cfg``'s ranges with ``default_rng(seed)``; same seed, same poses."""
    rng = np.random.default_rng(int(seed))
    for _ in range(max_tries):
        bowl = rng.uniform([cfg.region_x[0], cfg.region_y[0]], [cfg.region_x[1], cfg.region_y[1]])
        block = rng.uniform([cfg.region_x[0], cfg.region_y[0]], [cfg.region_x[1], cfg.region_y[1]])
        block_yaw = math.radians(rng.uniform(*cfg.block_yaw_deg))
        bowl_yaw = math.radians(rng.uniform(*cfg.bowl_yaw_deg))
        if np.linalg.norm(bowl - block) >= cfg.min_separation:
            return ScenePoses(
                int(seed),
                (float(block[0]), float(block[1])),
                _wrap(block_yaw),
                (float(bowl[0]), float(bowl[1])),
                _wrap(bowl_yaw),
            )
    raise SceneError(f"no object placement {cfg.min_separation} m apart fits region x {cfg.region_x}, y {cfg.region_y}")


def scene_record(cfg: SceneConfig, poses: ScenePoses) -> dict[str, str]:
    """What an episode's metadata keeps of its scene (``EpisodeMeta.extra``): the block yaw drawn
    and the yaw ranges it was drawn from, so demos of a narrow yaw range (``bench
    generalization``'s) can be told from full-circle ones after the fact."""
    return {
        "block_yaw_deg": f"{math.degrees(poses.block_yaw):.1f}",
        "block_yaw_range_deg": _range_text(cfg.block_yaw_deg),
        "bowl_yaw_range_deg": _range_text(cfg.bowl_yaw_deg),
    }


def recorded_block_yaw_range(extra: dict[str, str]) -> tuple[float, float] | None:
    """The block yaw range ``scene_record`` wrote into an episode's metadata (None: not recorded,
    or not readable as ``lo,hi``)."""
    try:
        lo, hi = (float(v) for v in extra.get("block_yaw_range_deg", "").split(","))
    except ValueError:
        return None
    return lo, hi


def same_yaw_range(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether two yaw ranges (degrees) agree to what ``scene_record`` keeps (6 significant digits)."""
    return all(math.isclose(x, y, rel_tol=1e-5, abs_tol=1e-6) for x, y in zip(a, b, strict=True))


def _range_text(bounds: tuple[float, float]) -> str:
    return f"{bounds[0]:g},{bounds[1]:g}"  # no spaces: it travels as one word of a recorder command


def _wrap(angle: float) -> float:
    return float((angle + math.pi) % (2 * math.pi) - math.pi)


def _free_qpos_addr(model, body: str) -> tuple[int, int]:
    import mujoco

    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{body}_joint")
    if jid < 0:
        raise SceneError(f"model has no free joint '{body}_joint' (not a twin scene?)")
    return int(model.jnt_qposadr[jid]), int(model.jnt_dofadr[jid])


def _yaw_quat_wxyz(yaw: float) -> np.ndarray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def apply_scene(model, data, poses: ScenePoses, cfg: SceneConfig) -> None:
    """Place block and bowl (at rest, on the table) in ``data``; the robot is left as it is."""
    import mujoco

    for body, xy, yaw, z in (
        (BLOCK, poses.block_xy, poses.block_yaw, cfg.block_size[2] / 2 + 1e-4),
        (BOWL, poses.bowl_xy, poses.bowl_yaw, 1e-4),
    ):
        qadr, dadr = _free_qpos_addr(model, body)
        data.qpos[qadr : qadr + 3] = (xy[0], xy[1], z)
        data.qpos[qadr + 3 : qadr + 7] = _yaw_quat_wxyz(yaw)
        data.qvel[dadr : dadr + 6] = 0.0
    mujoco.mj_forward(model, data)


def body_pose(model, data, body: str) -> np.ndarray:
    """4x4 world (= base) pose of a body."""
    import mujoco

    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if bid < 0:
        raise SceneError(f"model has no body {body!r}")
    T = np.eye(4)
    T[:3, :3] = data.xmat[bid].reshape(3, 3)
    T[:3, 3] = data.xpos[bid]
    return T


def yaw_of(T: np.ndarray) -> float:
    return math.atan2(T[1, 0], T[0, 0])


def object_state(model, data) -> dict:
    """Block and bowl poses as plain numbers (for status messages and logs)."""
    out = {}
    for body in (BLOCK, BOWL):
        T = body_pose(model, data, body)
        out[body] = {"xyz": [round(float(v), 5) for v in T[:3, 3]], "yaw": round(yaw_of(T), 5)}
    return out


def _touching_fingers(model, data, body: str) -> bool:
    import mujoco

    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    finger_ids = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f) for f in FINGER_BODIES}
    for i in range(data.ncon):
        c = data.contact[i]
        b1, b2 = model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]
        if (b1 == bid and b2 in finger_ids) or (b2 == bid and b1 in finger_ids):
            return True
    return False


def success_details(model, data, scene: SceneConfig, success: SuccessConfig) -> dict:
    """Each condition of "the block rests inside the bowl", and their conjunction under 'success'."""

    block = body_pose(model, data, BLOCK)
    bowl = body_pose(model, data, BOWL)
    offset = block[:3, 3] - bowl[:3, 3]
    horizontal = float(np.hypot(offset[0], offset[1]))
    rim = scene.bowl_base_thickness + scene.bowl_wall_height
    _, dadr = _free_qpos_addr(model, BLOCK)
    speed = float(np.linalg.norm(data.qvel[dadr : dadr + 3]))
    details = {
        "inside": horizontal < scene.bowl_inner_radius - success.margin,
        "below_rim": bool(0.0 < offset[2] < rim),
        "at_rest": speed < success.max_speed,
        "released": not _touching_fingers(model, data, BLOCK),
        "horizontal_m": round(horizontal, 4),
        "height_m": round(float(offset[2]), 4),
        "speed_mps": round(speed, 4),
    }
    details["success"] = bool(details["inside"] and details["below_rim"] and details["at_rest"] and details["released"])
    return details


def is_success(model, data, scene: SceneConfig, success: SuccessConfig) -> bool:
    return success_details(model, data, scene, success)["success"]
