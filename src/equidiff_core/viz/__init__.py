"""rerun visualisation: what the policy sees (voxels, clouds, camera frames) and what it intends.

ROS-free. ``RerunLogger`` turns the project's messages (rclpy or rosbags flavour) into rerun
entities with one method per message kind; ``equidiff_ros.viz_node`` feeds it from the live
graph, ``bag_to_rrd`` from recorded bags, ``training_callback.RerunTrainingCallback`` from the
trainer. rerun is an optional extra: this package imports it only inside functions, and a
missing rerun raises ``VizUnavailable`` naming the extra to install.
"""

from __future__ import annotations

import importlib
from typing import Any

from .rerun_sdk import INSTALL_HINT, VizUnavailable, require_rerun

# Exported lazily (name -> submodule), so `import equidiff_core.viz` stays cheap and never imports rerun.
_LAZY_EXPORTS = {
    "RerunLogger": "logger",
    **dict.fromkeys(("VizConfig", "default_blueprint", "open_recording", "load_viz_config"), "recording_setup"),
    **dict.fromkeys(("convert_bags", "ConversionReport"), "bag_to_rrd"),
    **dict.fromkeys(("summarize_rrd", "RrdSummary", "EntitySummary"), "rrd"),
    "RerunTrainingCallback": "training_callback",
}

__all__ = [
    "INSTALL_HINT",
    "ConversionReport",
    "EntitySummary",
    "RerunLogger",
    "RerunTrainingCallback",
    "RrdSummary",
    "VizConfig",
    "VizUnavailable",
    "convert_bags",
    "default_blueprint",
    "load_viz_config",
    "open_recording",
    "require_rerun",
    "summarize_rrd",
]


def __getattr__(name: str) -> Any:
    if name not in _LAZY_EXPORTS:
        raise AttributeError(f"module 'equidiff_core.viz' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_LAZY_EXPORTS[name]}", __name__), name)
