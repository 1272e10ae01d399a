"""How well the cameras' extrinsics agree with known geometry, in millimetres.

Two references, each measured per camera after moving its cloud into the base frame with the
extrinsics under test:

* **the other cameras' clouds**: distance from each point to the surface the other cameras
  see there (point-to-plane against a local plane fitted to their nearest points), over the
  points where the views overlap. A camera off by a few mm shows it as a shift against the others,
  except a shift *along* a plane that dominates the overlap (the table): a point's distance
  to the plane does not change. The fingertips catch that one.
* **the fingertips at the measured TCP**: distance from the camera's points on the fingers to
  the FR3 fingers' surface (franky-sim's visual meshes, opened to the measured width) placed at
  the TCP pose the robot reports. This ties each camera to the robot, not only to its peers.

Medians are reported (a few depth outliers at silhouettes must not decide it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..config import LabConfig
from ..robots.franky.hand import finger_surface_tcp


def to_base(points: np.ndarray, T_base_optical: np.ndarray) -> np.ndarray:
    return points.astype(np.float64) @ T_base_optical[:3, :3].T + T_base_optical[:3, 3]


def point_to_surface(points: np.ndarray, surface: np.ndarray, k: int = 10, max_gap: float = 0.02) -> np.ndarray:
    """Distance (m) from each point to the plane through its ``k`` nearest ``surface`` points.

    Points whose nearest surface point is farther than ``max_gap`` are not on that surface
    (a part the reference does not see): they get NaN. Point-to-plane, not point-to-point,
    so the reference's sampling density (a few mm at 1 m) does not count as misalignment.
    """
    if len(points) == 0 or len(surface) < k:
        return np.full(len(points), np.nan)
    tree = cKDTree(surface)
    nearest, idx = tree.query(points, k=k)
    neigh = surface[idx]  # (N, k, 3)
    centred = neigh - neigh.mean(axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    normal = vt[:, -1, :]  # smallest principal direction = the local plane's normal
    d = np.abs(np.einsum("nk,nk->n", points - neigh.mean(axis=1), normal))
    d[nearest[:, 0] > max_gap] = np.nan
    return d


def _median_mm(d: np.ndarray) -> float | None:
    d = d[np.isfinite(d)]
    return round(float(np.median(d)) * 1000, 3) if len(d) else None


@dataclass
class CameraCheck:
    name: str
    points: int  # in the workspace box
    overlap_points: int  # of those, seen by another camera too
    cloud_to_cloud_mm: float | None  # median point-to-plane distance to the other cameras' clouds
    finger_points: int
    fingertips_mm: float | None  # median distance of its finger points to the finger model

    def summary(self) -> dict:
        return {
            "points": self.points,
            "overlap_points": self.overlap_points,
            "cloud_to_cloud_mm": self.cloud_to_cloud_mm,
            "finger_points": self.finger_points,
            "fingertips_mm": self.fingertips_mm,
        }


def check_alignment(
    lab: LabConfig,
    clouds: dict[str, np.ndarray],
    T_base_tcp: np.ndarray | None = None,
    gripper_width: float | None = None,
    fingertip_length: float = 0.04,
    overlap_gap: float = 0.01,
) -> dict[str, CameraCheck]:
    """Each camera's misalignment against the others' clouds and the fingertips.

    ``clouds``: camera name -> (N, 3) points in that camera's optical frame; the extrinsics come
    from ``lab``. Only points inside the workspace box count (that is what the policy sees).
    """
    ws = lab.workspace
    in_base = {}
    for cam in lab.cameras:
        if cam.name not in clouds:
            continue
        p = to_base(clouds[cam.name], cam.extrinsics.matrix())
        in_base[cam.name] = p[np.all((p >= ws.lower) & (p <= ws.upper), axis=1)]
    fingers = None
    if T_base_tcp is not None and gripper_width is not None and np.isfinite(gripper_width):
        model = finger_surface_tcp(gripper_width)
        model = model[model[:, 2] > -fingertip_length]  # the tips: the TCP's z runs along the fingers
        lo, hi = model.min(axis=0) - 0.01, model.max(axis=0) + 0.01
        fingers = to_base(model, T_base_tcp)
    results = {}
    for name, pts in in_base.items():
        others = [p for n, p in in_base.items() if n != name]
        c2c = np.full(len(pts), np.nan)
        if others:
            c2c = point_to_surface(pts, np.concatenate(others), max_gap=overlap_gap)
        tips, n_tips = None, 0
        if fingers is not None:
            in_tcp = (pts - T_base_tcp[:3, 3]) @ T_base_tcp[:3, :3]
            near = pts[np.all((in_tcp >= lo) & (in_tcp <= hi), axis=1)]  # around the tips, not the block below
            d = point_to_surface(near, fingers, max_gap=0.01)
            n_tips = int(np.isfinite(d).sum())
            tips = _median_mm(d)
        results[name] = CameraCheck(name, len(pts), int(np.isfinite(c2c).sum()), _median_mm(c2c), n_tips, tips)
    return results


def log_check(
    rec,
    lab: LabConfig,
    clouds: dict[str, tuple[np.ndarray, np.ndarray]],
    results: dict[str, CameraCheck],
    T_base_tcp: np.ndarray | None,
    gripper_width: float | None,
) -> None:
    """The check in rerun: each camera's cloud in the base frame, its frame, and the finger model at the TCP."""
    import rerun as rr

    from ..viz.logger import RerunLogger

    logger = RerunLogger(rec, lab)
    logger.log_static_scene()
    palette = [(230, 80, 60), (60, 170, 80), (70, 110, 230), (220, 180, 40)]
    for i, cam in enumerate(lab.cameras):
        if cam.name not in clouds:
            continue
        pts, colors = clouds[cam.name]
        p = to_base(pts, cam.extrinsics.matrix())
        stride = max(1, len(p) // 100_000)
        r = results.get(cam.name)
        label = f"{cam.name}: clouds {r.cloud_to_cloud_mm} mm, fingertips {r.fingertips_mm} mm" if r else cam.name
        rec.log(f"check/{cam.name}/rgb", rr.Points3D(p[::stride], colors=colors[::stride], radii=0.001))
        rec.log(f"check/{cam.name}/tinted", rr.Points3D(p[::stride], colors=palette[i % len(palette)], radii=0.001))
        rec.log(f"check/{cam.name}/summary", rr.TextDocument(label))
    if T_base_tcp is not None and gripper_width is not None and np.isfinite(gripper_width):
        fingers = to_base(finger_surface_tcp(gripper_width), T_base_tcp)
        rec.log("check/fingers_model", rr.Points3D(fingers[::4], colors=(255, 255, 255), radii=0.0008))
