"""The FR3's hand as franky-sim's MuJoCo model draws it: its body and joint names, the hand-to-TCP
offset, and the fingers' visible surface.

The calibration check compares the cameras' points on the fingers with this surface, and the twin's
scene and sim use the same names and offset; both read franky-sim's own FR3 model, so they agree with
what the sim renders.
"""

from __future__ import annotations

import numpy as np

FINGER_BODIES = ("robot0_left_finger", "robot0_right_finger")
FINGER_JOINTS = ("robot0_finger_joint1", "robot0_finger_joint2")
HAND_BODY = "robot0_hand"
TCP_OFFSET = np.array([0.0, 0.0, 0.1034])  # hand body -> TCP, same rotation (franky's NE_T_EE)

# MuJoCo's geom group of franky-sim's visual meshes (what a camera sees), not the collision shapes
_VISUAL_GROUP = 2


def arm_model():
    """franky-sim's FR3 alone (no table, no objects), compiled: the model the hand's geometry is read from."""
    import xml.etree.ElementTree as ET

    import mujoco
    from franky_sim.mujoco_simulator import MujocoSimulator

    sim = MujocoSimulator(enable_visualization=False)
    sim.add_robot()
    return mujoco.MjModel.from_xml_string(ET.tostring(sim.scene, encoding="unicode"))


def finger_width(model, qpos: np.ndarray) -> float:
    """The gripper's opening (m) in a state ``qpos`` of ``model``: the two finger joints together."""
    import mujoco

    return float(
        sum(qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)]] for j in FINGER_JOINTS)
    )


def finger_surface_tcp(width: float, samples_per_m2: float = 2e7, seed: int = 0) -> np.ndarray:
    """Points (m, TCP frame) sampled uniformly over the FR3 fingers' visual meshes, opened to ``width``."""
    import mujoco

    model = arm_model()
    data = mujoco.MjData(model)
    for joint in FINGER_JOINTS:
        data.qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint)]] = width / 2
    mujoco.mj_kinematics(model, data)
    hand = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, HAND_BODY)
    R_base_tcp = data.xmat[hand].reshape(3, 3)
    t_base_tcp = data.xpos[hand] + R_base_tcp @ TCP_OFFSET
    finger_ids = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in FINGER_BODIES}
    rng = np.random.default_rng(seed)
    out = []
    for g in range(model.ngeom):
        if (
            model.geom_bodyid[g] not in finger_ids
            or model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH
            or model.geom_group[g] != _VISUAL_GROUP
        ):
            continue
        m = model.geom_dataid[g]
        verts = model.mesh_vert[model.mesh_vertadr[m] : model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        faces = model.mesh_face[model.mesh_faceadr[m] : model.mesh_faceadr[m] + model.mesh_facenum[m]]
        a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        n = max(1, int(area.sum() * samples_per_m2))
        tri = rng.choice(len(faces), size=n, p=area / area.sum())
        u, v = rng.random((2, n))
        flip = u + v > 1  # fold the square's far half back into the triangle: uniform over its area
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        pts = a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])
        out.append(pts @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g])
    return (np.concatenate(out) - t_base_tcp) @ R_base_tcp
