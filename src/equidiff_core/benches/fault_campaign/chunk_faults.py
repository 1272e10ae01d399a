"""The chunks franka_node must refuse or cut (``equidiff bench safety``): a NaN pose, a jump, a stale
chunk and one tilted out of the cone, each counted as rejected with the arm still; and chunks at the
speed limit into the safety box's floor, walls and corner, measured against the box and its margin.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from equidiff_core import geometry
from equidiff_core.benches.fault_campaign.campaign import STEP_NS, Campaign
from equidiff_core.control import metrics
from equidiff_core.geometry import down_pose
from equidiff_core.wire.chunk import PoseChunk, chunk_to_msg
from equidiff_core.wire.rosmsg import NS_PER_S

# The arm's approaches in out_of_box start here and head for the floor, the -y and +x walls and
# the corner of the -y wall and the floor. The box's corners at the floor nearest to and farthest
# from the base are out of the FR3's comfortable reach pointing down: towards x 0.26 the elbow ran
# into its joint limit, towards x 0.64 the arm oscillated until franka_node's joint-speed stop
# caught it (docs/results/control.md, "The box margin, measured"). The campaign's SCENE_SEED keeps the twin's
# objects clear of every approach.
APPROACH_START = np.array([0.50, -0.10, 0.22])
APPROACHES = {
    "floor": (0.0, 0.0, -1.0),
    "wall_y": (0.0, -1.0, 0.0),
    "wall_x": (1.0, 0.0, 0.0),
    "corner": (0.0, -1.0, -1.0),
}
APPROACH_SPEED_M_S = 0.30  # asked for; the filter's speed limit (0.25) governs


def rejected_and_still(c: Campaign, counter: str, publish: Callable[[], None]) -> dict:
    before, t0 = c.diag(counter), time.time()
    publish()
    counted = c.wait_diag(counter, before)
    moved = c.moved_m(t0, time.time())
    return {
        "survived": counted and c.alive() and moved < c.still_m,
        "rejected": counted,
        "moved_mm": round(moved * 1000, 2),
    }


def fault_nan(c: Campaign) -> dict:
    def publish():
        msg = chunk_to_msg(c.hold_chunk(), c.client.factory, c.client.lab.base_frame)
        msg.points[2].transforms[0].translation.x = float("nan")
        c.client.pub_chunk.publish(msg)

    return rejected_and_still(c, "nan_rejected", publish)


def fault_jump(c: Campaign) -> dict:
    return rejected_and_still(
        c, "jump_rejected", lambda: c.client.publish_chunk(c.hold_chunk(c.here() + [0.0, 0.15, 0.0]))
    )


def fault_stale_chunk(c: Campaign) -> dict:
    def publish():
        old = time.time_ns() - 2_000_000_000
        here = c.here() + [0.0, 0.03, 0.0]  # a valid target, only too old
        c.client.publish_chunk(
            PoseChunk(
                old, old + np.arange(4, dtype=np.int64) * STEP_NS, np.stack([down_pose(here)] * 4), np.full(4, 0.08)
            )
        )

    return rejected_and_still(c, "stale_rejected", publish)


def fault_out_of_cone(c: Campaign) -> dict:
    def publish():
        now = time.time_ns()
        here = c.here()
        poses = [down_pose(here)]
        for tilt in np.radians([20.0, 40.0, 60.0]):  # the policy tipping the hand over
            R = Rotation.from_rotvec([0.0, tilt, 0.0]).as_matrix() @ down_pose(here)[:3, :3]
            poses.append(geometry.make_pose(R, here))
        c.client.publish_chunk(
            PoseChunk(now, now + np.arange(4, dtype=np.int64) * STEP_NS, np.stack(poses), np.full(4, 0.08))
        )

    return rejected_and_still(c, "cone_rejected", publish)


def fault_out_of_box(c: Campaign) -> dict:
    """At the speed limit into the floor, two walls and their corner (see the command's help)."""
    clip_lo, clip_hi = c.box.min_corner + c.box_margin_m, c.box.max_corner - c.box_margin_m
    per = {}
    for name, direction in APPROACHES.items():
        c.probe.approach(c.client, APPROACH_START, speed=0.1, settle=0.5)
        d = np.asarray(direction) / np.linalg.norm(direction)
        limited, t0 = c.diag("speed_limited_ticks"), time.time()
        end = time.monotonic() + 3.0
        while time.monotonic() < end:
            # ahead of where franka_node's command is (its executed target), at 0.3 m/s: the speed
            # limit governs whatever the sim's pace (the command itself never runs ahead of the arm's time)
            now, start = time.time_ns(), c.client.data.targets[-1][1]
            times = now + np.arange(1, 9, dtype=np.int64) * (NS_PER_S // 10)
            poses = np.stack([down_pose(start + d * APPROACH_SPEED_M_S * 0.1 * i) for i in range(1, 9)])
            c.client.publish_chunk(PoseChunk(now, times, poses, np.full(8, 0.08)))
            time.sleep(0.1)
        time.sleep(1.0)
        _, p = c.client.samples("poses", t0, time.time())
        per[name] = {
            "overshoot_mm": round(metrics.max_outside_box(p, clip_lo, clip_hi) * 1000, 2),
            "outside_mm": round(metrics.max_outside_box(p, c.box.min_corner, c.box.max_corner) * 1000, 2),
            "travel_mm": round(float(np.linalg.norm(p[-1] - p[0])) * 1000, 1) if len(p) else 0.0,
            "speed_limited": c.wait_diag("speed_limited_ticks", limited, timeout=3.0),
        }
        c.note_excursion(t0)
    c.home()
    outside = max(a["outside_mm"] for a in per.values())
    return {
        "survived": c.alive() and outside == 0.0,
        "outside_mm": outside,
        "max_overshoot_mm": max(a["overshoot_mm"] for a in per.values()),
        "box_margin_mm": round(c.box_margin_m * 1000, 2),
        "approaches": per,
    }
