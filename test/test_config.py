from pathlib import Path

import numpy as np
import pytest
import yaml

from equidiff_core.config import (
    ConfigError,
    LabConfig,
    from_dict,
    load_lab_config,
    to_dict,
)

ROOT = Path(__file__).resolve().parents[1]
LAB = ROOT / "config" / "lab.yaml"


def test_lab_yaml_loads_into_typed_config():
    lab = load_lab_config(LAB)
    assert [c.name for c in lab.cameras] == ["cam_front", "cam_left", "cam_right"]
    assert lab.workspace.edge == 0.4 and lab.workspace.resolution == 64
    assert lab.workspace.voxel_size == pytest.approx(0.4 / 64)
    np.testing.assert_allclose(lab.workspace.upper - lab.workspace.lower, 0.4)
    assert lab.camera("cam_left").serial == "215122250002"
    assert lab.camera("cam_left").topic == "/cameras/cam_left/points"


def test_every_camera_looks_at_the_workspace_centre():
    lab = load_lab_config(LAB)
    for cam in lab.cameras:
        T = cam.extrinsics.matrix()
        to_center = np.asarray(lab.workspace.center) - T[:3, 3]
        forward = T[:3, 2]  # optical z
        cos = forward @ to_center / np.linalg.norm(to_center)
        assert cos > 0.99, cam.name


def test_round_trip_through_dict():
    lab = load_lab_config(LAB)
    assert from_dict(LabConfig, to_dict(lab)) == lab


def _write(tmp_path, data) -> Path:
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return path


@pytest.mark.parametrize(
    "mutate, message",
    [
        (
            lambda d: d["cameras"][1]["extrinsics"].update(translation=[0, 1]),
            r"cameras\[1\].extrinsics.translation: expected 3 items",
        ),
        (lambda d: d["cameras"][0].pop("serial"), r"cameras\[0\]: missing required key 'serial'"),
        (lambda d: d["workspace"].update(edge="big"), r"workspace.edge: expected a finite number"),
        (
            lambda d: d["workspace"].update(edge=-1.0),
            r"workspace.edge: -1.0 m is out of range; allowed: 0 < x <= 2.4 m",
        ),
        (lambda d: d.update(colour="red"), r"unknown key\(s\) \['colour'\]"),
        (lambda d: d["cameras"][2]["extrinsics"].update(quaternion_xyzw=[0, 0, 0, 3]), r"not unit length"),
        (lambda d: d["cameras"][2].update(name="cam_front"), r"unique"),
        (lambda d: d["workspace"].update(resolution=64.5), r"expected an integer"),
    ],
)
def test_malformed_config_gives_a_clear_error(tmp_path, mutate, message):
    data = yaml.safe_load(LAB.read_text())
    mutate(data)
    with pytest.raises(ConfigError, match=message):
        load_lab_config(_write(tmp_path, data))


def test_malformed_yaml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="malformed YAML"):
        load_lab_config(_write(tmp_path, "cameras: [\n"))
    with pytest.raises(ConfigError, match="no such file"):
        load_lab_config(tmp_path / "nope.yaml")
