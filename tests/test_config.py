"""Configuration: the shipped configs load; every malformed config is reported with its key path."""

from __future__ import annotations

import json
import math

import pytest
from bad_configs import CASES, GOOD, MANY, assert_issues
from conftest import CONFIGS
from helpers import arm_raw
from pydantic import ValidationError

from aiohal.config import json_schema, load_config, parse_config
from aiohal.drivers.mock_fast import FastMockDriver
from aiohal.errors import ConfigError, ConfigIssue


def _load_text(tmp_path, text: str, name: str = "robot.toml"):
    path = tmp_path / name
    path.write_text(text)
    return load_config(path)


def _issues(tmp_path, text: str) -> tuple[ConfigError, list[str]]:
    with pytest.raises(ConfigError) as info:
        _load_text(tmp_path, text)
    return info.value, [str(issue) for issue in info.value.issues]


# ---------------------------------------------------------------- shipped configs


def test_mock_arm_config_loads():
    config = load_config(CONFIGS / "mock_arm.toml")
    assert config.robot.name == "mock_arm"
    assert [j.name for j in config.joints] == ["a1", "a2", "e1", "a3", "a4", "a5", "a6"]
    assert [j.index for j in config.joints] == list(range(7))
    assert [(d.name, d.type, d.cls) for d in config.drivers] == [("arm", "mock", FastMockDriver)]
    assert config.drivers[0].joints == tuple(j.name for j in config.joints)  # "*" expanded in order
    assert config.drivers[0].options.dynamics == "first_order"
    # [joint_defaults] acceleration merged into every joint; the joints' own keys kept
    assert [j.acceleration for j in config.joints] == [10.0] * 7
    assert [j.effort for j in config.joints] == [176.0, 176.0, 100.0, 100.0, 100.0, 38.0, 38.0]
    assert config.joints[0].velocity == pytest.approx(1.920)
    assert config.joints[0].position_min == -2.967 and config.joints[0].position_max == 2.967
    assert config.controller.type == "sine"
    assert config.loop.rate_hz == 1000 and config.period_ns == 1_000_000
    assert config.path == CONFIGS / "mock_arm.toml"
    assert config.base_dir == CONFIGS.resolve()


def test_mock_humanoid_config_loads():
    config = load_config(CONFIGS / "mock_humanoid.toml")
    assert config.robot.name == "mock_humanoid"
    assert len(config.joints) == 33
    assert [d.name for d in config.drivers] == ["legs", "torso", "arms", "hands"]
    assert {d.type for d in config.drivers} == {"mock"}
    assert [len(d.joints) for d in config.drivers] == [12, 5, 14, 2]
    # globs expand in [joints] order
    assert config.drivers[1].joints == ("waist_yaw", "waist_pitch", "waist_roll", "neck_yaw", "neck_pitch")
    # every joint owned exactly once, drivers cover the joints contiguously in order
    owned = [j for d in config.drivers for j in d.joints]
    assert owned == [j.name for j in config.joints]
    assert all(j.acceleration == 20.0 for j in config.joints)
    assert config.drivers[0].devices == ("pelvis_imu", "l_ankle_ft", "r_ankle_ft")
    assert ("l_gripper", "hand", "l_hand") in config.devices
    assert len(config.devices) == 7


def test_joint_defaults_merge_but_joint_keys_win():
    raw = arm_raw(2)
    raw["joint_defaults"] = {"acceleration": 7.0, "effort": 11.0}
    del raw["joints"]["j0"]["acceleration"]
    del raw["joints"]["j1"]["effort"]
    config = parse_config(raw)
    j0, j1 = config.joints
    assert (j0.acceleration, j0.effort) == (7.0, 50.0)
    assert (j1.acceleration, j1.effort) == (20.0, 11.0)


def test_unset_limits_are_infinite():
    raw = arm_raw(1)
    raw["joints"]["j0"] = {"velocity": 1.0}
    (joint,) = parse_config(raw).joints
    assert joint.position_min == -math.inf and joint.position_max == math.inf
    assert joint.acceleration == math.inf and joint.effort == math.inf


def test_the_shared_good_config_loads(tmp_path):
    config = _load_text(tmp_path, GOOD)
    assert [j.name for j in config.joints] == ["j0", "j1", "j2"]
    assert config.controller.type == "hold"  # the default controller


# ---------------------------------------------------------------- malformed configs


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_malformed_config_is_reported_with_its_path(tmp_path, case):
    error, lines = _issues(tmp_path, case.toml)
    assert_issues(lines, case.expected)
    assert error.source == str(tmp_path / "robot.toml")
    # the exception text carries every issue too
    for line in lines:
        assert f"  {line}" in str(error)


def test_driver_unknown_joint_exact_message(tmp_path):
    case = next(c for c in CASES if c.id == "driver-unknown-joint")
    error, lines = _issues(tmp_path, case.toml)
    assert error.issues == [ConfigIssue("driver[1].joints", 'unknown joint "a8"')]
    assert lines == ['driver[1].joints: unknown joint "a8"']


def test_unknown_joint_suggests_a_close_name(tmp_path):
    text = GOOD.replace('joints = ["j0", "j1", "j2"]', 'joints = ["j0", "j1", "jj2"]')
    _, lines = _issues(tmp_path, text)
    assert lines == [
        'driver[0].joints: unknown joint "jj2" (did you mean "j2"?)',
        "joints.j2: no driver owns this joint",
    ]


def test_invalid_toml_has_no_path(tmp_path):
    error, lines = _issues(tmp_path, GOOD + "\n[loop\n")
    assert len(error.issues) == 1
    assert error.issues[0].path == ""
    assert lines[0].startswith("invalid TOML")


def test_unreadable_file(tmp_path):
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "nope.toml")
    (issue,) = info.value.issues
    assert issue.message.startswith("cannot read the file:")


def test_many_errors_are_reported_together(tmp_path):
    error, lines = _issues(tmp_path, MANY.toml)
    assert len(error.issues) == len(MANY.expected) >= 8
    assert_issues(lines, MANY.expected)
    assert str(error).startswith(f"{tmp_path / 'robot.toml'}: {len(MANY.expected)} configuration error(s)\n")


def test_one_bad_section_does_not_hide_another(tmp_path):
    # a broken [loop] and a broken controller param: both reported
    text = GOOD.replace("rate_hz = 1000", 'rate_hz = "x"') + (
        '\n[controller]\ntype = "homing"\n[controller.params]\nduration = 0\npose = {}\n'
    )
    _, lines = _issues(tmp_path, text)
    assert_issues(
        lines,
        (
            "loop.rate_hz: input should be a valid number, unable to parse string as a number (got 'x')",
            "controller.params.duration: input should be greater than 0 (got 0)",
        ),
    )


# ---------------------------------------------------------------- paths and overrides


def test_relative_paths_resolve_from_the_config_folder(tmp_path, monkeypatch):
    folder = tmp_path / "robots"
    folder.mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # the working directory must not matter
    config = _load_text(folder, GOOD.replace('name = "bad"', 'name = "bad"\nmodel = "models/x.xml"'))
    assert config.robot.model == (folder / "models" / "x.xml").resolve()
    assert config.base_dir == folder.resolve()


def test_absolute_paths_are_kept(tmp_path):
    target = tmp_path / "abs" / "m.xml"
    config = _load_text(tmp_path, GOOD.replace('name = "bad"', f'name = "bad"\nmodel = "{target}"'))
    assert config.robot.model == target


def test_with_loop_changes_the_period():
    config = parse_config(arm_raw())
    assert config.period_ns == 1_000_000
    faster = config.with_loop(rate_hz=2000)
    assert faster.loop.rate_hz == 2000
    assert faster.period_ns == 500_000
    assert faster.loop.clock == config.loop.clock == "virtual"  # the rest is kept
    assert config.period_ns == 1_000_000  # the original is unchanged
    assert faster.joints == config.joints and faster.drivers == config.drivers


@pytest.mark.parametrize(
    ("changes", "loc"),
    [({"rate_hz": -5}, ("rate_hz",)), ({"rate_hz": 0}, ("rate_hz",)), ({"clock": "wall"}, ("clock",)),
     ({"rat_hz": 5}, ("rat_hz",))],
)
def test_with_loop_rejects_invalid_overrides(changes, loc):
    config = parse_config(arm_raw())
    with pytest.raises(ValidationError) as info:
        config.with_loop(**changes)
    assert [tuple(e["loc"]) for e in info.value.errors()] == [loc]


# ---------------------------------------------------------------- JSON Schema


def test_json_schema_is_strict_json_with_plugin_options():
    schema = json_schema()
    text = json.dumps(schema, allow_nan=False)  # no inf/nan defaults leak through
    assert json.loads(text) == schema
    props = schema["properties"]
    assert {"driver", "joints", "loop", "controller"} <= set(props)
    assert set(schema["required"]) == {"joints", "driver"}
    assert props["driver"]["type"] == "array" and props["driver"]["minItems"] == 1
    assert props["joints"]["minProperties"] == 1
    defs = schema["$defs"]

    # the mock driver's options, selected by type through if/then
    driver = defs["DriverSection"]
    assert "mock" in driver["properties"]["type"]["enum"]
    clause = next(c for c in driver["allOf"] if c["if"]["properties"]["type"] == {"const": "mock"})
    ref = clause["then"]["properties"]["options"]["$ref"]
    assert ref.startswith("#/$defs/")
    mock_options = defs[ref.removeprefix("#/$defs/")]
    assert {"dynamics", "time_constant", "initial_position", "faults"} <= set(mock_options["properties"])
    assert mock_options["additionalProperties"] is False
    assert mock_options["properties"]["dynamics"]["enum"] == ["mirror", "first_order", "servo"]

    # every loadable controller's params too (circle needs the sim extra)
    from aiohal import plugins

    controller = props["controller"]
    assert controller["properties"]["type"]["enum"] == sorted(plugins.available("controller"))
    consts = [c["if"]["properties"]["type"]["const"] for c in controller["allOf"]]
    loadable = [spec.name for spec, error in plugins.describe("controller") if error is None]
    assert {"hold", "homing", "sine"} <= set(consts) and consts == loadable

    # every $ref resolves
    def refs(node):
        if isinstance(node, dict):
            for k, v in node.items():
                if k == "$ref":
                    yield v
                else:
                    yield from refs(v)
        elif isinstance(node, list):
            for v in node:
                yield from refs(v)

    for r in refs(schema):
        assert r.removeprefix("#/$defs/") in defs, r


def test_json_schema_drops_infinite_defaults():
    joint = json_schema()["$defs"]["JointSection"]["properties"]
    assert "default" not in joint["effort"]
    assert "no limit (inf)" in joint["effort"]["description"]
    assert "default" not in joint["position"]
