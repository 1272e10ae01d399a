"""What ``equidiff bench safety`` reports across its campaign: the summary fields of its JSON line (faults
survived, the largest excursion outside the safety box, auto-resumes, episodes lost after repair) and the
per-fault results under ``faults``.
"""

from __future__ import annotations

import time
from pathlib import Path

from equidiff_core.benches.fault_campaign.campaign import Campaign
from equidiff_core.data.bags import read_episode


def episodes_lost(paths: list[Path]) -> int:
    """Recorded episodes that cannot be read back (or hold no /franka/ee_pose)."""
    lost = 0
    for path in paths:
        try:
            lost += "/franka/ee_pose" not in read_episode(path, ["/franka/ee_pose"])
        except Exception:  # noqa: BLE001 - unreadable is lost, whatever the reason
            lost += 1
    return lost


def campaign_summary(
    c: Campaign, per_fault: dict, still_mm: float, wall_deceleration_m_s2: float, wall0: float
) -> dict:
    """The JSON line's fields after the campaign's own (machine, start hold, baseline...), in this order;
    ``wall0``: the campaign's start on the monotonic clock."""
    return {
        "faults_tried": len(per_fault),
        "faults_survived": sum(bool(v.get("survived")) for v in per_fault.values()),
        "max_excursion_mm": round(c.excursion_m * 1000, 2),
        "auto_resumes": c.auto_resumes,
        "episodes_recorded": len(c.episodes),
        "episodes_lost": episodes_lost(c.episodes),
        "still_mm": still_mm,
        "box_margin_mm": round(c.box_margin_m * 1000, 2),
        "wall_deceleration_m_s2": wall_deceleration_m_s2,
        "wall_s": round(time.monotonic() - wall0, 1),
        "faults": per_fault,
    }
