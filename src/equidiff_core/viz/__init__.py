"""rerun visualisation: what the policy sees (voxels, clouds, camera frames) and what it intends.

ROS-free. ``RerunLogger`` turns the project's messages (rclpy or rosbags flavour) into rerun
entities with one method per message kind; ``equidiff_ros.viz_node`` feeds it from the live
graph, ``bag_to_rrd`` from recorded bags, ``training.RerunTrainingCallback`` from the
trainer. rerun is an optional extra: this package imports it only inside functions, and a
missing rerun raises ``VizUnavailable`` naming the extra to install.
"""

from __future__ import annotations

from typing import Any

INSTALL_HINT = "pip install 'equidiff_ros[viz]'  (installs rerun-sdk>=0.41)"


class VizUnavailable(ImportError):
    """rerun-sdk is not installed (or too old)."""


def require_rerun() -> Any:
    """Import rerun or raise ``VizUnavailable`` with the install command."""
    try:
        import rerun
    except ImportError as err:
        raise VizUnavailable(f"rerun visualisation needs rerun-sdk, which is not installed: {INSTALL_HINT}") from err
    major_minor = tuple(int(p) for p in rerun.__version__.split(".")[:2])
    if major_minor < (0, 41):
        raise VizUnavailable(f"rerun-sdk {rerun.__version__} is too old (need >= 0.41): {INSTALL_HINT}")
    return rerun


def __getattr__(name: str) -> Any:
    # Lazy re-exports so `import equidiff_core.viz` stays cheap and never imports rerun.
    if name in ("RerunLogger", "VizConfig", "default_blueprint", "open_recording", "load_viz_config"):
        from . import logger

        return getattr(logger, name)
    if name in ("convert_bags", "ConversionReport"):
        from . import bag_to_rrd

        return getattr(bag_to_rrd, name)
    if name in ("summarize_rrd", "RrdSummary", "EntitySummary"):
        from . import rrd

        return getattr(rrd, name)
    if name == "RerunTrainingCallback":
        from .training import RerunTrainingCallback

        return RerunTrainingCallback
    raise AttributeError(f"module 'equidiff_core.viz' has no attribute {name!r}")
