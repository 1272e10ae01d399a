"""Write calibrated extrinsics into a new lab YAML that the existing loader reads.

The source lab file is copied key by key with only each calibrated camera's ``extrinsics``
replaced; the result is checked with ``config.load_lab_config`` before it lands. An existing
file is never replaced unless asked (``force``), and then the old one is kept beside it.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np

from ..config import ConfigError, Extrinsics, LabConfig, dump_yaml, load_lab_config, load_yaml
from ..runtime.output_files import staged_output
from .board import CalibrationError


def write_calibrated_lab(
    source: str | Path, extrinsics: dict[str, np.ndarray], out: str | Path, force: bool = False, notes: list[str] = ()
) -> tuple[LabConfig, Path | None]:
    """Write ``source`` with the cameras' new T_base_optical to ``out``; (loaded result, backup path or None)."""
    source, out = Path(source), Path(out)
    data = load_yaml(source)
    if not isinstance(data, dict) or not isinstance(data.get("cameras"), list):
        raise CalibrationError(f"{source}: not a lab file (no 'cameras' list)")
    names = [c.get("name") for c in data["cameras"] if isinstance(c, dict)]
    unknown = sorted(set(extrinsics) - set(names))
    if unknown:
        raise CalibrationError(f"{source} has no camera(s) {unknown}; it has {names}")
    for cam in data["cameras"]:
        T = extrinsics.get(cam.get("name"))
        if T is not None:
            ext = Extrinsics.from_matrix(np.asarray(T, dtype=np.float64))
            # 1 um and 1e-6 (about 0.0001 deg) are far below what any calibration resolves
            cam["extrinsics"] = {
                "translation": [round(v, 6) for v in ext.translation],
                "quaternion_xyzw": [round(v, 6) for v in ext.quaternion_xyzw],
            }
    backup = None
    if out.exists():
        if not force:
            raise CalibrationError(
                f"{out} exists and is left as it is: choose a new --output, or pass "
                "--force to replace it (the old file is then kept as a .bak copy)"
            )
        backup = out.with_name(f"{out.name}.{time.strftime('%Y%m%d-%H%M%S')}.bak")
    header = [
        f"Written by `equidiff calibrate cameras` on {time.strftime('%Y-%m-%d %H:%M:%S %Z')} from {source}.",
        "Extrinsics are T_base_optical (colour optical frame in the robot base frame).",
        *notes,
    ]
    text = "".join(f"# {line}\n" for line in header) + dump_yaml(
        data, sort_keys=False, default_flow_style=None, width=120
    )
    with staged_output(out, force=force) as staged:
        staged.path.write_text(text)
        try:
            lab = load_lab_config(staged.path)  # what lands must load with the loader every node uses
        except ConfigError as err:
            raise CalibrationError(f"the calibrated lab file would not load: {err}") from err
        if backup is not None:
            shutil.copy2(out, backup)  # the old one stays in place until the new one replaces it
    return lab, backup
