"""Every config loader is strict: duplicate keys, YAML 1.1 surprises, wrong types and values outside a
field's declared physical range are ConfigErrors with a message, never a silent wrong value.

The plain tests are the cases of issue 40; the Hypothesis tests mutate the shipped configs (a field
set to random values and types, keys removed or duplicated, the YAML text itself) and generate
documents for every loader. The property: either a valid config that re-dumps and reloads to the
same object, with every declared field in range, or a ConfigError with a message.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from equidiff_core.cameras.realsense.config import RealSenseOptions
from equidiff_core.config import (
    ConfigError,
    LabConfig,
    default_config_dir,
    dump_yaml,
    field_bounds,
    from_dict,
    load_lab_config,
    load_mapping,
    parse_yaml,
    to_dict,
)
from equidiff_core.control import check_home_inside, load_control_config
from equidiff_core.data.recording import RecordingConfig
from equidiff_core.limits_table import limits_markdown
from equidiff_core.twin.config import load_twin_config
from equidiff_core.viz.recording_setup import load_viz_config
from equidiff_ros import cli

CONFIG = default_config_dir()
REPO = Path(__file__).resolve().parents[1]


def _shipped(name: str) -> str:
    return (CONFIG / name).read_text()


def _recorder_section() -> str:
    params = parse_yaml(_shipped("data.yaml"))["recorder_node"]["ros__parameters"]
    names = {f.name for f in dataclasses.fields(RecordingConfig)}
    return dump_yaml({k: v for k, v in params.items() if k in names})


def _from_file(cls):
    return lambda path: from_dict(cls, load_mapping(path), where=Path(path).name)


# name -> (shipped YAML text, loader of a file)
LOADERS = {
    "lab": (_shipped("lab.yaml"), load_lab_config),
    "control": (_shipped("control.yaml"), load_control_config),
    "twin": (_shipped("twin.yaml"), load_twin_config),
    "viz": (_shipped("viz.yaml"), load_viz_config),
    "recording": (_recorder_section(), _from_file(RecordingConfig)),
    "realsense_options": (
        dump_yaml(parse_yaml(_shipped("lab.yaml"))["cameras"][0]["options"]),
        _from_file(RealSenseOptions),
    ),
}


def _write(tmp_path: Path, text: str, name: str = "config.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _edit(name: str, old: str, new: str) -> str:
    text = _shipped(name)
    assert text.count(old) == 1, old
    return text.replace(old, new)


# --- the cases ----------------------------------------------------------------------


def test_every_shipped_config_file_parses_strictly_and_loads(tmp_path):
    for path in sorted(CONFIG.glob("*.yaml")):
        assert isinstance(parse_yaml(path.read_text(), path.name), dict), path
    lab = load_lab_config(CONFIG / "lab.yaml")
    control = load_control_config(CONFIG / "control.yaml")
    check_home_inside(control, lab.safety_box)
    assert [c.serial for c in lab.cameras] == ["215122250001", "215122250002", "215122250003"]
    for name, (text, load) in LOADERS.items():
        assert _valid_or_config_error(load, _write(tmp_path, text)) is not None, name


def test_a_second_safety_box_in_lab_yaml_is_a_duplicate_key_naming_both_lines(tmp_path):
    text = _shipped("lab.yaml") + "safety_box:\n  lower: [-5, -5, -5]\n  upper: [5, 5, 5]\n"
    first = 1 + text.splitlines().index("safety_box:")
    last = len(text.splitlines()) - 2
    path = _write(tmp_path, text, "lab.yaml")
    with pytest.raises(ConfigError, match=rf"lab.yaml: duplicate key 'safety_box' at line {first} and line {last}$"):
        load_lab_config(path)


def test_a_second_safety_block_in_control_yaml_is_a_duplicate_key(tmp_path):
    path = _write(tmp_path, _shipped("control.yaml") + "safety:\n  max_linear_speed_m_s: 3.0\n", "control.yaml")
    with pytest.raises(ConfigError, match=r"control.yaml: duplicate key 'safety' at line \d+ and line \d+"):
        load_control_config(path)


def test_a_duplicate_key_deep_inside_a_list_item_is_refused_too(tmp_path):
    text = _edit("lab.yaml", '    serial: "215122250002"\n', '    serial: "215122250002"\n    serial: "999"\n')
    line = 1 + _shipped("lab.yaml").splitlines().index('    serial: "215122250002"')
    with pytest.raises(ConfigError, match=rf"duplicate key 'serial' at line {line} and line {line + 1}"):
        load_lab_config(_write(tmp_path, text, "lab.yaml"))


@pytest.mark.parametrize(
    "name, old, new, message",
    [
        (
            "control.yaml",
            "max_linear_speed_m_s: 0.25",
            "max_linear_speed_m_s: 25",
            (
                r"control.yaml.safety.max_linear_speed_m_s: 25.0 m/s is out of range; allowed: 0 < x <= 1.7 m/s "
                r"\(the FR3's Cartesian velocity limit\)"
            ),
        ),
        (
            "control.yaml",
            "max_first_step_jump_m: 0.08",
            "max_first_step_jump_m: 8",
            r"safety.max_first_step_jump_m: 8.0 m is out of range; allowed: 0 < x <= 0.2 m",
        ),
        (
            "control.yaml",
            "max_step_age_s: 0.25",
            "max_step_age_s: 1e9",
            r"scheduler.max_step_age_s: 1000000000.0 s is out of range; allowed: 0 <= x <= 2 s",
        ),
        (
            "control.yaml",
            "wall_deceleration_m_s2: 0.5",
            "wall_deceleration_m_s2: 20",
            r"wall_deceleration_m_s2: 20.0 m/s\^2 is out of range; allowed: 0 < x <= 13",
        ),
        ("control.yaml", "home_on_start: true", "home_on_start: yes", r"home_on_start: expected true/false, got 'yes'"),
        ("control.yaml", "control_hz: 200.0", "control_hz: 3:20", r"control_hz: expected a finite number, got '3:20'"),
        (
            "control.yaml",
            "home_quaternion_xyzw: [1.0, 0.0, 0.0, 0.0]",
            "home_quaternion_xyzw: [1.0, 0.0, 0.0, 0.5]",
            r"home_quaternion_xyzw must be a unit quaternion",
        ),
        (
            "control.yaml",
            "max_joint_speeds_rad_s: [2.5, 2.5, 2.5, 2.5, 5.0, 4.0, 5.0]",
            "max_joint_speeds_rad_s: [2.5, 2.5, 2.5, 2.5, 5.0, 5.0, 5.0]",
            r"exceed the FR3's joint speed limits .* at joint\(s\) \[6\]",
        ),
        (
            "lab.yaml",
            "observation_hz: 5.0",
            "observation_hz: 0",
            r"lab.yaml.observation_hz: 0.0 Hz is out of range; allowed: 0 < x <= 100 Hz",
        ),
        (
            "lab.yaml",
            "state_hz: 100.0",
            "state_hz: -100",
            r"lab.yaml.robot.state_hz: -100.0 Hz is out of range; allowed: 0 < x <= 1000 Hz",
        ),
        ("lab.yaml", 'serial: "215122250003"', "serial: 215122250003", r"cameras\[2\].serial: expected a string"),
        ("lab.yaml", "[0.26, -0.19, 0.0]", "[0.26, -0.19, 1:30]", r"safety_box.lower\[2\]: expected a finite number"),
    ],
)
def test_out_of_range_and_mistyped_values_are_refused_with_path_value_unit_and_range(tmp_path, name, old, new, message):
    path = _write(tmp_path, _edit(name, old, new), name)
    load = load_lab_config if name == "lab.yaml" else load_control_config
    with pytest.raises(ConfigError, match=message):
        load(path)


def test_negative_rates_and_sizes_and_a_depth_range_upside_down_are_refused(tmp_path):
    data = parse_yaml(_shipped("lab.yaml"))
    data["cameras"][1]["width"] = -848
    with pytest.raises(
        ConfigError, match=r"lab.yaml.cameras\[1\].width: -848 px is out of range; allowed: 0 < x <= 4096 px"
    ):
        load_lab_config(_write(tmp_path, dump_yaml(data), "lab.yaml"))
    data = parse_yaml(_shipped("lab.yaml"))
    data["cameras"][0]["publish_hz"] = -5
    with pytest.raises(ConfigError, match=r"cameras\[0\].publish_hz: -5.0 Hz is out of range"):
        load_lab_config(_write(tmp_path, dump_yaml(data)))
    data = parse_yaml(_shipped("lab.yaml"))
    data["cameras"][1].update(min_depth=1.8, max_depth=1.5)
    with pytest.raises(ConfigError, match=r"cameras\[1\]: min_depth \(1.8 m\) must be below max_depth \(1.5 m\)"):
        load_lab_config(_write(tmp_path, dump_yaml(data)))
    data = parse_yaml(_shipped("lab.yaml"))
    data["cameras"][2]["publish_hz"] = 60.0
    with pytest.raises(ConfigError, match=r"publish_hz \(60.0 Hz\) cannot exceed the camera's fps \(30\)"):
        load_lab_config(_write(tmp_path, dump_yaml(data)))


def test_yaml_1_1_surprises_stay_what_was_written():
    """serial: 0123456 was the octal integer 42798; yes was True; 1:30 was 90; a date a datetime."""
    data = parse_yaml("serial: 0123456\nflag: yes\nnope: off\nduration: 1:30\nday: 2024-01-02\nbig: 1_000\nhex: 0x1F")
    assert data == {
        "serial": "0123456",
        "flag": "yes",
        "nope": "off",
        "duration": "1:30",
        "day": "2024-01-02",
        "big": "1_000",
        "hex": 31,
    }
    assert parse_yaml("[true, False, null, ~, 1e9, .5, -.inf, 7]") == [
        True,
        False,
        None,
        None,
        1e9,
        0.5,
        -float("inf"),
        7,
    ]
    with pytest.raises(ConfigError, match=r"not an integer: '012'"):
        parse_yaml("a: !!int 012")
    with pytest.raises(ConfigError, match=r"tag 'tag:yaml.org,2002:binary' is not allowed"):
        parse_yaml("a: !!binary aGk=")


def test_an_unquoted_leading_zero_serial_loads_as_written(tmp_path):
    text = _edit("lab.yaml", 'serial: "215122250001"', "serial: 0123456")
    assert load_lab_config(_write(tmp_path, text)).cameras[0].serial == "0123456"


def test_strict_types_in_from_dict():
    with pytest.raises(ConfigError, match=r"LabConfig.base_frame: expected a string \(quote it\), got int 5"):
        from_dict(LabConfig, {"cameras": [], "base_frame": 5})
    from equidiff_core.viz.recording_setup import VizConfig

    with pytest.raises(ConfigError, match=r"clouds: expected true/false, got 1"):
        from_dict(VizConfig, {"clouds": 1})
    with pytest.raises(ConfigError, match=r"max_cloud_points: expected an integer, got True"):
        from_dict(VizConfig, {"max_cloud_points": True})
    assert from_dict(VizConfig, {"ee_hz": 30}).ee_hz == 30.0  # a float field takes an int
    with pytest.raises(ConfigError, match=r"ee_hz: expected a finite number"):
        from_dict(VizConfig, {"ee_hz": 10**400})


def test_a_home_pose_outside_the_safety_box_is_refused(tmp_path):
    lab = load_lab_config(CONFIG / "lab.yaml")
    control = load_control_config(_write(tmp_path, _edit("control.yaml", "[0.45, 0.0, 0.30]", "[0.45, 0.0, 0.368]")))
    with pytest.raises(ConfigError, match=r"home_position \[0.45, 0.0, 0.368\] m is outside the safety box"):
        check_home_inside(control, lab.safety_box)  # above upper z 0.37 less the 5 mm box margin


def test_the_committed_limits_table_is_the_generated_one():
    assert (REPO / "docs" / "limits.md").read_text() == limits_markdown(), "run python scripts/gen_limits_doc.py"
    assert "| control.yaml | `safety.max_linear_speed_m_s` | m/s | 0 < x <= 1.7 | 0.25 |" in limits_markdown()


# --- the CLI: one line, never a traceback ---------------------------------------------------


def test_a_bad_lab_config_ends_dataset_pack_and_revoxelize_in_one_line(tmp_path, capsys):
    bad = _write(tmp_path, _shipped("lab.yaml") + "observation_hz: 5.0\n", "lab.yaml")
    for argv in (
        ["dataset", "pack", str(tmp_path), "--out", str(tmp_path / "out"), "--lab-config", str(bad)],
        ["dataset", "revoxelize", str(tmp_path), "--lab", str(bad), "--out", str(tmp_path / "out")],
    ):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert err == f"equidiff dataset {argv[1]}: {bad}: duplicate key 'observation_hz' at line 7 and line 52\n"


def test_dataset_stats_on_a_folder_without_episodes_is_an_error(tmp_path, capsys):
    assert cli.main(["dataset", "stats", str(tmp_path)]) == 1
    assert capsys.readouterr().err == f"equidiff dataset stats: no episodes (bag directories) in {tmp_path}\n"


# --- fuzz -----------------------------------------------------------------------------------

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.integers(),
    st.floats(),
    st.text(max_size=10),
    st.sampled_from(["yes", "no", "on", "0123456", "1:30", "0x1F", "1e9", ".inf", ".nan", "2024-01-02", "1_000"]),
)
VALUES = st.recursive(
    SCALARS,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)
RAW_TOKENS = [
    "yes",
    "no",
    "off",
    "0123456",
    "0o17",
    "1:30",
    "0x1F",
    "1e9",
    "-1e999",
    ".NaN",
    "~",
    "2024-01-02",
    "1_000",
    "'3'",
    "!!str 5",
    "!!float 1",
    "[]",
    "{}",
    "- 1",
    "&a 1",
    "*a",
    "<<",
    "=",
    "|",
    "!!python/none ''",
]


def _assert_declared_bounds_hold(obj) -> None:
    """Every declared field of a loaded config (and of the configs it holds) is inside its range."""
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            bounds = field_bounds(f)
            if bounds is not None and value is not None:
                items = value if isinstance(value, (tuple, list)) else (value,)
                assert all(bounds.allows(v) for v in items), (f.name, value)
            _assert_declared_bounds_hold(value)
    elif isinstance(obj, (tuple, list)):
        for item in obj:
            _assert_declared_bounds_hold(item)


def _valid_or_config_error(load, path: Path):
    """The property: a ConfigError with a message, or a config in range that round-trips."""
    try:
        config = load(path)
    except ConfigError as err:
        assert str(err).strip()
        return None
    _assert_declared_bounds_hold(config)
    again = path.with_name("again.yaml")
    again.write_text(dump_yaml(to_dict(config)))
    assert dump_yaml(to_dict(load(again))) == dump_yaml(to_dict(config))  # text: NaN in free-form options too
    return config


def _same(written, loaded) -> bool:
    """What a valid config holds is what was written (an int may become a float; a bool stays a bool)."""
    if isinstance(written, bool) or isinstance(loaded, bool):
        return type(written) is type(loaded) and written == loaded
    if isinstance(written, (int, float)) and isinstance(loaded, (int, float)):
        return written == loaded or (math.isnan(written) and math.isnan(loaded))
    if isinstance(written, (list, tuple)) and isinstance(loaded, (list, tuple)):
        return len(written) == len(loaded) and all(_same(a, b) for a, b in zip(written, loaded))
    if isinstance(written, dict) and isinstance(loaded, dict):  # a config section's left-out keys take defaults
        return all(k in loaded and _same(written[k], loaded[k]) for k in written)
    return type(written) is type(loaded) and written == loaded


def _paths(data, prefix=()) -> list[tuple]:
    out = [prefix] if prefix else []
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else ()
    for key, value in items:
        out += _paths(value, (*prefix, key))
    return out


def _get(data, path):
    for key in path:
        data = data[key]
    return data


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@pytest.mark.parametrize("name", LOADERS)
@FUZZ
@given(data=st.data())
def test_fuzz_a_field_set_to_any_value_loads_as_written_or_is_a_config_error(fuzz_dir, name, data):
    text, load = LOADERS[name]
    doc = parse_yaml(text)
    path = data.draw(st.sampled_from(_paths(doc)), label="path")
    value = data.draw(VALUES, label="value")
    _get(doc, path[:-1])[path[-1]] = value
    config = _valid_or_config_error(load, _write(fuzz_dir, dump_yaml(doc)))
    if config is not None:
        assert _same(value, _get(to_dict(config), path)), "a silent wrong value"


@pytest.mark.parametrize("name", LOADERS)
@FUZZ
@given(data=st.data())
def test_fuzz_a_raw_yaml_token_as_a_value_reads_as_yaml_1_2_or_is_a_config_error(fuzz_dir, name, data):
    text, load = LOADERS[name]
    lines = text.splitlines()
    scalar = [i for i, line in enumerate(lines) if re.match(r"^\s*[a-z_]+: [^\[{#\s][^#]*?(\s+#.*)?$", line)]
    i = data.draw(st.sampled_from(scalar), label="line")
    token = data.draw(st.sampled_from(RAW_TOKENS), label="token")
    key = lines[i].split(":")[0]
    lines[i] = f"{key}: {token}"
    _valid_or_config_error(load, _write(fuzz_dir, "\n".join(lines) + "\n"))


@pytest.mark.parametrize("name", LOADERS)
@FUZZ
@given(data=st.data())
def test_fuzz_a_key_removed_gives_the_default_or_a_config_error(fuzz_dir, name, data):
    text, load = LOADERS[name]
    doc = parse_yaml(text)
    path = data.draw(st.sampled_from([p for p in _paths(doc) if isinstance(_get(doc, p[:-1]), dict)]), label="path")
    del _get(doc, path[:-1])[path[-1]]
    _valid_or_config_error(load, _write(fuzz_dir, dump_yaml(doc)))


@pytest.mark.parametrize("name", LOADERS)
@FUZZ
@given(data=st.data())
def test_fuzz_a_duplicated_key_is_always_refused_naming_it(fuzz_dir, name, data):
    text, load = LOADERS[name]
    lines = text.splitlines()
    keyed = [i for i, line in enumerate(lines) if re.match(r"^\s*[a-z_]+:", line)]
    i = data.draw(st.sampled_from(keyed), label="line")
    indent, key = re.match(r"^(\s*)([a-z_]+):", lines[i]).groups()
    lines.insert(i, f"{indent}{key}: {data.draw(st.sampled_from(['1', 'x', '[]', 'true', '5.0']), label='value')}")
    with pytest.raises(ConfigError, match=rf"duplicate key '{key}' at line {i + 1} and line {i + 2}"):
        load(_write(fuzz_dir, "\n".join(lines) + "\n"))


@pytest.mark.parametrize("name", LOADERS)
@FUZZ
@given(data=st.data())
def test_fuzz_the_yaml_text_mutated_loads_validly_or_is_a_config_error(fuzz_dir, name, data):
    text, load = LOADERS[name]
    for _ in range(data.draw(st.integers(1, 3), label="edits")):
        at = data.draw(st.integers(0, len(text)), label="at")
        op = data.draw(st.sampled_from(["delete", "insert", "duplicate_line", "delete_line"]), label="op")
        if op == "delete":
            text = text[:at] + text[at + 1 :]
        elif op == "insert":
            text = (
                text[:at]
                + data.draw(st.sampled_from(list(": -[]{}#'\"\n\t!&*|>%@`,0x9.e")) | st.text(max_size=2))
                + text[at:]
            )
        else:
            lines = text.splitlines(keepends=True)
            k = min(at, len(lines) - 1)
            lines[k : k + 1] = [lines[k]] * 2 if op == "duplicate_line" else []
            text = "".join(lines)
    _valid_or_config_error(load, _write(fuzz_dir, text))


@pytest.mark.parametrize("name", LOADERS)
@FUZZ
@given(
    doc=st.dictionaries(
        st.sampled_from(["cameras", "safety", "scheduler", "render", "ee_hz", "decimation", "x"]), VALUES, max_size=4
    )
)
def test_fuzz_generated_documents_load_validly_or_are_config_errors(fuzz_dir, name, doc):
    _valid_or_config_error(LOADERS[name][1], _write(fuzz_dir, dump_yaml(doc)))
