"""`equidiff bench images`: what recording each camera's colour image costs.

Prints ONE JSON line (``equidiff_core.benches.images.measure``): per image size (the twin's
render size, lab.yaml's camera size, and that size with sensor-like noise as an estimate for a
real D455) the JPEG bytes per frame, camera_node's CPU per frame to encode it against the cloud
message it already builds per frame, the recorder's CPU per image written against the /voxels
grid it already writes, and MB per minute of demonstrations for all cameras against /voxels'.
"""

from __future__ import annotations

import json

from equidiff_core.benches.images import measure
from equidiff_core.config import default_config_dir, load_lab_config
from equidiff_core.runtime.machine import cpu_description
from equidiff_core.twin.config import load_twin_config


def add_arguments(parser) -> None:
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per measurement")
    parser.add_argument("--quality", type=int, default=90, help="JPEG quality (camera_node's jpeg_quality)")
    parser.add_argument("--lab-config", default=None, help="lab.yaml (default: the installed one)")
    parser.add_argument("--twin-config", default=None, help="twin.yaml (default: the installed one)")


def run(args) -> int:
    lab = load_lab_config(args.lab_config or default_config_dir() / "lab.yaml")
    result = measure(lab, load_twin_config(args.twin_config), repeats=args.repeats, quality=args.quality)
    print(json.dumps({**result, "cpu": cpu_description()}))
    return 0
