"""rerun-sdk as an optional extra: imported only when asked for, with the install command when it is missing."""

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
