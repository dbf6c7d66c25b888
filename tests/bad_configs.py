"""Malformed robot configs as TOML text, each with the exact issue lines it must produce.

Shared by test_config.py (loaded in-process) and test_cli.py (``python -m aiohal check``).
An expected line is a str (``str(issue)`` must equal it) or a compiled regex (must fullmatch).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Union

Expected = Union[str, "re.Pattern[str]"]

_HEAD = """\
[robot]
name = "bad"

[loop]
rate_hz = 1000
clock = "virtual"
"""

_JOINTS = """
[joints.j0]
position = [-2.0, 2.0]
velocity = 2.0

[joints.j1]
position = [-2.0, 2.0]
velocity = 2.0

[joints.j2]
position = [-2.0, 2.0]
velocity = 2.0
"""

_DRIVER = """
[[driver]]
type = "mock"
name = "arm"
joints = ["j0", "j1", "j2"]
"""

#: A valid config; every case below breaks one thing in it (or several, for "many").
GOOD = _HEAD + _JOINTS + _DRIVER


def _two_drivers(first: str, second: str) -> str:
    return (
        _HEAD
        + _JOINTS
        + f'\n[[driver]]\ntype = "mock"\nname = "a"\njoints = {first}\n'
        + f'\n[[driver]]\ntype = "mock"\nname = "b"\njoints = {second}\n'
    )


def _replace(old: str, new: str, text: str = GOOD) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


@dataclass(frozen=True)
class BadConfig:
    id: str
    toml: str
    expected: tuple[Expected, ...]


CASES: list[BadConfig] = [
    BadConfig(
        "invalid-toml",
        _replace('clock = "virtual"', "clock = "),
        (re.compile(r"invalid TOML: .*\(at line \d+, column \d+\)"),),
    ),
    BadConfig(
        "unknown-section",
        GOOD + '\n[controler]\ntype = "hold"\n',
        ('controler: unknown section (did you mean "controller"?)',),
    ),
    BadConfig(
        "unknown-loop-key",
        _replace("rate_hz = 1000", "rat_hz = 1000"),
        ('loop.rat_hz: unknown key (did you mean "rate_hz"?)',),
    ),
    BadConfig(
        "rate-wrong-type",
        _replace("rate_hz = 1000", 'rate_hz = "fast"'),
        ("loop.rate_hz: input should be a valid number, unable to parse string as a number (got 'fast')",),
    ),
    BadConfig(
        "rate-zero",
        _replace("rate_hz = 1000", "rate_hz = 0"),
        ("loop.rate_hz: input should be greater than or equal to 0.1 (got 0)",),
    ),
    BadConfig(
        "rate-negative",
        _replace("rate_hz = 1000", "rate_hz = -250.0"),
        ("loop.rate_hz: input should be greater than or equal to 0.1 (got -250.0)",),
    ),
    BadConfig(
        "bad-overrun",
        _replace('clock = "virtual"', 'clock = "virtual"\noverrun = "drop"'),
        ("loop.overrun: input should be 'skip' or 'catch_up' (got 'drop')",),
    ),
    BadConfig(
        "phase-a-whole-millisecond",
        _replace('clock = "virtual"', 'clock = "virtual"\nphase_us = 1000'),
        ("loop.phase_us: input should be less than 1000 (got 1000)",),
    ),
    BadConfig(
        "joint-min-not-below-max",
        _replace("[joints.j1]\nposition = [-2.0, 2.0]", "[joints.j1]\nposition = [1.5, 1.5]"),
        ("joints.j1.position: must be [min, max] with min < max (got [1.5, 1.5])",),
    ),
    BadConfig(
        "joint-missing-velocity",
        _replace("[joints.j2]\nposition = [-2.0, 2.0]\nvelocity = 2.0\n", "[joints.j2]\nposition = [-2.0, 2.0]\n"),
        ("joints.j2.velocity: required key is missing",),
    ),
    BadConfig(
        "driver-unknown-joint",
        _two_drivers('["j0"]', '["j1", "j2", "a8"]'),
        ('driver[1].joints: unknown joint "a8"',),
    ),
    BadConfig(
        "joint-owned-twice",
        _two_drivers('["j0", "j1"]', '["j1", "j2"]'),
        ('driver[1].joints: joint "j1" is already owned by driver[0]',),
    ),
    BadConfig(
        "driver-joints-not-contiguous",
        _two_drivers('["j0", "j2"]', '["j1"]'),
        ("driver[0].joints: a driver's joints must be a contiguous run in the order of [joints] (got j0, j2)",),
    ),
    BadConfig(
        "joint-without-driver",
        _replace('joints = ["j0", "j1", "j2"]', 'joints = ["j0", "j1"]'),
        ("joints.j2: no driver owns this joint",),
    ),
    BadConfig(
        "unknown-driver-type",
        _replace('type = "mock"', 'type = "mok"'),
        ('driver[0].type: unknown driver "mok" (available: canopen, ethercat, fri, mock, mujoco, nrt_hand, replay, udp)',),
    ),
    BadConfig(
        "unknown-driver-option",
        GOOD + '\n[driver.options]\ndynamic = "mirror"\n',
        ('driver[0].options.dynamic: unknown key (did you mean "dynamics"?)',),
    ),
    BadConfig(
        "bad-mock-option-value",
        GOOD + '\n[driver.options]\ndynamics = "second_order"\n',
        ("driver[0].options.dynamics: input should be 'mirror', 'first_order' or 'servo' (got 'second_order')",),
    ),
    BadConfig(
        "udp-sim-bad-dynamics",
        _replace('type = "mock"', 'type = "udp"')
        + '\n[driver.options]\nsimulate = true\n[driver.options.simulation]\ndynamics = "second_order"\n',
        ("driver[0].options.simulation.dynamics: input should be 'first_order' or 'servo' (got 'second_order')",),
    ),
    BadConfig(
        "udp-sim-bad-servo-parameters",
        _replace('type = "mock"', 'type = "udp"')
        + '\n[driver.options]\nsimulate = true\n[driver.options.simulation]\ndynamics = "servo"\n'
        + "[driver.options.simulation.servo]\ngear_ratio = -1\nposition_gian = 3\n",
        (
            "driver[0].options.simulation.servo.gear_ratio: input should be greater than 0 (got -1)",
            'driver[0].options.simulation.servo.position_gian: unknown key (did you mean "position_gain"?)',
        ),
    ),
    BadConfig(
        "fri-sim-bad-servo-parameter",
        _replace('type = "mock"', 'type = "fri"')
        + '\n[driver.options]\nsimulate = true\n[driver.options.simulation]\ndynamics = "servo"\n'
        + "servo = { velocity_every = 0.5 }\n",
        (
            "driver[0].options.simulation.servo.velocity_every: input should be a valid integer, "
            "got a number with a fractional part (got 0.5)",
        ),
    ),
    BadConfig(
        "mock-initial-position-unknown-joint",
        GOOD + "\n[driver.options]\ninitial_position = { j1 = 0.5, j7 = 0.1 }\n",
        ('driver[0].options.initial_position.j7: unknown joint "j7" (did you mean "j0"?)',),
    ),
    BadConfig(
        "homing-pose-unknown-joint",
        GOOD + '\n[controller]\ntype = "homing"\n[controller.params]\nduration = 1.0\npose = { j0 = 0.5, a9 = 0.1 }\n',
        ('controller.params.pose.a9: unknown joint "a9"',),
    ),
    BadConfig(
        "homing-pose-out-of-range",
        GOOD + '\n[controller]\ntype = "homing"\n[controller.params]\nduration = 1.0\npose = { j0 = 3.0 }\n',
        ("controller.params.pose.j0: 3.0 is outside the joint's range [-2.0, 2.0]",),
    ),
    BadConfig(
        "sine-too-fast",
        GOOD + '\n[controller]\ntype = "sine"\n[controller.params]\namplitude = { j1 = 1.0 }\nfrequency = 1.0\n',
        ("controller.params.amplitude.j1: peak velocity 2π·f·A exceeds the velocity limit of j1 (6.28 > 2)",),
    ),
    BadConfig(
        "sine-scalar-too-fast-is-one-line",
        GOOD + '\n[controller]\ntype = "sine"\n[controller.params]\namplitude = 1.0\nfrequency = 1.0\n',
        (
            "controller.params.amplitude: peak velocity 2π·f·A exceeds the velocity limit of "
            "j0 (6.28 > 2), j1 (6.28 > 2), j2 (6.28 > 2)",
        ),
    ),
    BadConfig(
        "unknown-controller-type",
        GOOD + '\n[controller]\ntype = "sin"\n',
        ('controller.type: unknown controller "sin" (available: chirp, circle, gait, hold, homing, sequence, sine, stream)',),
    ),
    BadConfig(
        "driver-unknown-device",
        _replace('joints = ["j0", "j1", "j2"]', 'joints = ["j0", "j1", "j2"]\ndevices = ["imu0"]'),
        ('driver[0].devices: unknown device "imu0"',),
    ),
    BadConfig(
        "hand-without-joint",
        _replace('joints = ["j0", "j1", "j2"]', 'joints = ["j0", "j1", "j2"]\ndevices = ["grip"]')
        + '\n[devices.grip]\ntype = "hand"\n',
        ("devices.grip.joint: a hand needs the joint that carries it",),
    ),
    BadConfig(
        "missing-driver-section",
        _HEAD + _JOINTS,
        ("driver: required section is missing",),
    ),
    BadConfig(
        "driver-as-table",
        _replace("[[driver]]", "[driver]"),
        ("driver: must be an array of tables: write [[driver]]",),
    ),
    # numbers that are not numbers: one plain message
    BadConfig("rate-nan", _replace("rate_hz = 1000", "rate_hz = nan"), ("loop.rate_hz: must be a finite number (got nan)",)),
    BadConfig("rate-inf", _replace("rate_hz = 1000", "rate_hz = inf"), ("loop.rate_hz: must be a finite number (got inf)",)),
    BadConfig(
        "velocity-nan",
        _replace("[joints.j1]\nposition = [-2.0, 2.0]\nvelocity = 2.0", "[joints.j1]\nposition = [-2.0, 2.0]\nvelocity = nan"),
        ("joints.j1.velocity: must be a finite number (got nan)",),
    ),
    BadConfig(
        "sine-ramp-nan",
        GOOD + '\n[controller]\ntype = "sine"\n[controller.params]\nramp = nan\n',
        ("controller.params.ramp: must be a finite number (got nan)",),
    ),
    # an error does not bring follow-on errors about what it broke
    BadConfig(
        "bad-velocity-has-no-follow-on",
        _replace("[joints.j1]\nposition = [-2.0, 2.0]\nvelocity = 2.0", "[joints.j1]\nposition = [-2.0, 2.0]\nvelocity = -1")
        + '\n[controller]\ntype = "sine"\n[controller.params]\namplitude = { j1 = 0.1 }\n',
        ("joints.j1.velocity: input should be greater than 0 (got -1)",),
    ),
    # a union's value: no pydantic member names in the path, one line
    BadConfig(
        "sine-frequency-not-a-number",
        GOOD + '\n[controller]\ntype = "sine"\n[controller.params]\nfrequency = "fast"\n',
        ("controller.params.frequency: must be a number or a table (got 'fast')",),
    ),
    BadConfig(
        "sine-frequency-nan",
        GOOD + '\n[controller]\ntype = "sine"\n[controller.params]\nfrequency = nan\n',
        ("controller.params.frequency: must be a finite number (got nan)",),
    ),
    BadConfig(
        "sine-frequency-table-entry",
        GOOD + '\n[controller]\ntype = "sine"\n[controller.params]\nfrequency = { j1 = "x" }\n',
        ("controller.params.frequency.j1: input should be a valid number, unable to parse string as a number (got 'x')",),
    ),
    BadConfig(
        "mock-fault-union",
        GOOD + '\n[driver.options.faults]\nclose_hangs = "sometimes"\n',
        ("driver[0].options.faults.close_hangs: must be true or false or \"thread\" (got 'sometimes')",),
    ),
    # each error once: a scalar that is wrong for every joint is one mistake
    BadConfig(
        "sine-negative-frequency-once",
        GOOD + '\n[controller]\ntype = "sine"\n[controller.params]\nfrequency = -1.0\n',
        ("controller.params.frequency: must be >= 0 (got -1.0)",),
    ),
    # did you mean, also for a name in another case
    BadConfig(
        "joint-in-another-case",
        GOOD + '\n[controller]\ntype = "sine"\n[controller.params]\namplitude = { J1 = 0.1 }\n',
        ('controller.params.amplitude.J1: unknown joint "J1" (did you mean "j1"?)',),
    ),
    BadConfig(
        "driver-joint-one-letter-off",
        _replace('joints = ["j0", "j1", "j2"]', 'joints = ["j0", "j1", "j8"]'),
        ('driver[0].joints: unknown joint "j8" (did you mean "j0"?)', "joints.j2: no driver owns this joint"),
    ),
    BadConfig(
        # the driver's options name joints of the robot it no longer has: not repeated as errors
        "driver-joint-unknown-beside-its-options",
        _replace('joints = ["j0", "j1", "j2"]', 'joints = ["j0", "j8"]\n[driver.options]\n'
                 'initial_position = { j1 = 0.5, j2 = -0.5 }'),
        ('driver[0].joints: unknown joint "j8" (did you mean "j0"?)', "joints.j1: no driver owns this joint",
         "joints.j2: no driver owns this joint"),
    ),
    BadConfig(
        "hand-on-a-joint-in-another-case",
        _replace('joints = ["j0", "j1", "j2"]', 'joints = ["j0", "j1", "j2"]\ndevices = ["gripper"]')
        + '\n[devices.gripper]\ntype = "hand"\njoint = "J2"\n',
        ('devices.gripper.joint: unknown joint "J2" (did you mean "j2"?)',),
    ),
    BadConfig(
        "empty-joint-name",
        GOOD.replace('[joints.j2]', '[joints.""]').replace('"j2"]', '"*"]'),
        ('joints."": a joint name must not be empty nor contain * ? [ (drivers name their joints with those patterns)',),
    ),
    # names others find the robot by: the shared-memory segment, ROS 2 topics
    BadConfig(
        "robot-name-with-a-wildcard",
        _replace('name = "bad"', 'name = "arm*"'),
        (re.compile(r"robot\.name: a letter, then at most 63 letters, digits or underscores: .*\(e\.g\. 'arm'\)"),),
    ),
    BadConfig(
        "feedforward-gain-out-of-range",
        GOOD + "\n[feedforward]\nk_e = { j0 = 1e300, j1 = -50.0 }\n",
        (
            re.compile(r"feedforward\.k_e: k_e of j0 is 1e\+300 .* within \[-1, 10\].*"),
            re.compile(r"feedforward\.k_e: k_e of j1 is -50 .* within \[-1, 10\].*"),
        ),
    ),
    BadConfig(
        "decimate-beyond-int64",
        GOOD + "\n[record]\ndecimate = { joint_state = 99999999999999999999 }\n",
        (re.compile(r"record\.decimate\.joint_state: input should be less than or equal to 1000000 .*"),),
    ),
    BadConfig(
        "udp-boards-sharing-a-port",
        _replace('type = "mock"', 'type = "udp"')
        + '[[driver.options.boards]]\nid = 1\njoints = ["j0"]\nport = 9000\n'
        + '[[driver.options.boards]]\nid = 2\njoints = ["j1", "j2"]\nport = 9000\n',
        ("driver[0].options.boards: board 2: 127.0.0.1:9000 is board 1's too; each board needs its own address and port",),
    ),
    BadConfig(
        "udp-board-ipv6",
        _replace('type = "mock"', 'type = "udp"')
        + '[[driver.options.boards]]\nid = 1\njoints = ["j0", "j1", "j2"]\naddress = "::1"\nport = 9000\n',
        (re.compile(r"driver\[0\]\.options\.boards\[0\]\.address: ::1 is an IPv6 address: .*IPv4.*"),),
    ),
]

#: One config with many independent errors: all must be reported together.
MANY = BadConfig(
    "many",
    _replace('clock = "virtual"', 'clock = "wall"\nrat_hz = 5', _replace("rate_hz = 1000", "rate_hz = -1"))
    .replace('joints = ["j0", "j1", "j2"]', 'joints = ["j0", "a8"]')
    .replace("[joints.j1]\nposition = [-2.0, 2.0]", "[joints.j1]\nposition = [2.0, -2.0]")
    + '\n[driver.options]\nfoo = 1\n\n[controller]\ntype = "nope"\n\n[extra]\n',
    (
        "extra: unknown section",
        "loop.rate_hz: input should be greater than or equal to 0.1 (got -1)",
        "loop.clock: input should be 'auto', 'timerfd', 'sleep' or 'virtual' (got 'wall')",
        'loop.rat_hz: unknown key (did you mean "rate_hz"?)',
        "joints.j1.position: must be [min, max] with min < max (got [2.0, -2.0])",
        'driver[0].joints: unknown joint "a8"',
        "driver[0].options.foo: unknown key",
        "joints.j1: no driver owns this joint",
        "joints.j2: no driver owns this joint",
        'controller.type: unknown controller "nope" (available: chirp, circle, gait, hold, homing, sequence, sine, stream)',
    ),
)


def matches(expected: Expected, line: str) -> bool:
    if isinstance(expected, str):
        return line == expected
    return expected.fullmatch(line) is not None


def assert_issues(actual: list[str], expected: tuple[Expected, ...]) -> None:
    """``actual`` holds exactly the expected lines, in any order."""
    remaining = list(actual)
    for exp in expected:
        hit = next((line for line in remaining if matches(exp, line)), None)
        assert hit is not None, f"expected issue {exp!r} not among {actual!r}"
        remaining.remove(hit)
    assert not remaining, f"unexpected extra issues {remaining!r} (all: {actual!r})"
