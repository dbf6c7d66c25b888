"""One TOML file per robot, validated into typed objects before anything starts.

Every error is collected with its key path (``driver[1].joints: unknown joint "a8"``) and
raised together as one :class:`~aiohal.errors.ConfigError`; the CLI prints them and exits 2.
Each section is validated on its own so that one bad section does not hide the others'
errors. Paths in a config are relative to the config file.
"""

from __future__ import annotations

import builtins
import fnmatch
import math
import re
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any, Literal, cast

from pydantic import AfterValidator, BaseModel, Field, TypeAdapter, ValidationError, ValidationInfo, field_validator

from . import plugins
from .core.feedforward import FeedforwardSection
from .core.feedforward import section_issues as feedforward_issues
from .core.realtime import RealtimeSection
from .errors import AiohalError, ConfigError, ConfigIssue, MissingDependencyError, PluginError
from .files import FileRefused, check_regular, read_regular_text
from .hal import Controller, Driver, Options, did_you_mean
from .outside.options import UNCONTROLLED, BridgeSection, ClientSection
from .outside.shm_segment import segment_name
from .record.options import RecordSection
from .robot import JointSpec, Mode, Robot
from .safety import SafetySection


def _resolve_relative(value: Path, info: ValidationInfo) -> Path:
    base = (info.context or {}).get("base_dir")
    if base is not None and not value.is_absolute():
        return (Path(base) / value).resolve()
    return value


#: A path in a config: relative paths are taken from the config file's folder.
ConfigPath = Annotated[Path, AfterValidator(_resolve_relative)]


def _name_token(name: str) -> str:
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]{0,63}", name):
        raise ValueError(
            "a letter, then at most 63 letters, digits or underscores: it names the shared-memory "
            f"segment and the ROS 2 topics (e.g. {re.sub(r'[^A-Za-z0-9_]', '_', name).strip('_') or 'robot'!r})"
        )
    return name


class RobotSection(Options):
    name: Annotated[str, AfterValidator(_name_token)] = Field(
        "robot",
        description="Robot name, shown in logs and reports, and part of the names others find it by: "
        "the shared-memory segment aiohal.<name>, ROS 2 topics /<name>/...: a letter, then letters, "
        "digits and underscores (a ROS 2 name token).",
    )
    model: ConfigPath | None = Field(None, description="Robot model file (MJCF), relative to this config.")


class LoopSection(Options):
    rate_hz: float = Field(1000.0, ge=0.1, le=50_000, description="Tick rate of the control loop.")
    clock: Literal["auto", "timerfd", "sleep", "virtual"] = Field(
        "auto",
        description="Wake source: timerfd (Linux), sleep (portable), virtual (as fast as possible, "
        "deterministic); auto picks timerfd where it exists.",
    )
    idle_wait: bool = Field(
        True,
        description="On asyncio's own event loop: a timerfd wait with nothing else due blocks on the "
        "timer instead of going round the event loop (less CPU per tick), and the virtual clock yields "
        "only when the loop has something to run; false: always through the loop.",
    )
    overrun: Literal["skip", "catch_up"] = Field(
        "skip", description="After a stall: skip the missed ticks (keep phase) or run them late."
    )
    phase_us: float | None = Field(
        None,
        ge=0,
        lt=1000,
        description="On a real clock, start the deadlines this many µs past a whole millisecond of "
        "CLOCK_MONOTONIC (e.g. to set apart two loops that share a CPU); default: between the "
        "kernel's own ticks (500 µs at 1 kHz).",
    )
    max_feedback_age: int = Field(
        50, ge=1, description="Ticks after which a joint's feedback is stale and the robot holds."
    )
    gc: Literal["freeze", "default"] = Field(
        "freeze",
        description="freeze: collect once before the drivers open and freeze every object alive "
        "(again, young generations only, before each run), so collections during the run only scan "
        "what the run allocates; default: leave gc alone.",
    )
    close_timeout_ms: float = Field(
        2000.0, gt=0, description="A driver's close() that takes longer is abandoned (after its estop)."
    )
    stall_timeout_ms: float = Field(
        500.0, ge=0, description="No tick for this long: emergency stop and end the run (0 = never)."
    )
    stats_window: int = Field(
        1 << 17, ge=1024, le=1 << 24, description="Ticks kept for percentiles (older ticks still count in max)."
    )


class JointSection(Options):
    position: tuple[float, float] = Field((-math.inf, math.inf), description="[min, max] position (rad or m).")
    velocity: float = Field(gt=0, description="Velocity limit (rad/s or m/s); inf for none.")
    acceleration: float = Field(math.inf, gt=0, description="Acceleration limit.")
    effort: float = Field(math.inf, gt=0, description="Effort limit (N·m or N).")

    @field_validator("position")
    @classmethod
    def _ordered(cls, value: tuple[float, float]) -> tuple[float, float]:
        lo, hi = value
        if not lo < hi:
            raise ValueError(f"must be [min, max] with min < max (got [{lo}, {hi}])")
        return value


class DeviceSection(Options):
    type: Literal["imu", "force_torque", "hand"]
    joint: str | None = Field(None, description="For a hand: the joint that carries it.")


class DriverSection(Options):
    type: str = Field(description="Driver name from `python -m aiohal plugins`.")
    name: str | None = Field(None, min_length=1, description="Unique name; defaults to the type.")
    joints: list[str] = Field(default_factory=list, description="Joint names or glob patterns.")
    devices: list[str] = Field(default_factory=list)
    options: dict[str, Any] = Field(default_factory=dict, description="The driver's own options.")
    every: int = Field(
        1,
        ge=1,
        le=1000,
        description="Exchange data with this driver on every n-th tick only (a bus slower than the loop, "
        "e.g. classic CAN); its feedback's age is judged at its own rate.",
    )


class ControllerSection(Options):
    type: str = Field("hold", description="Controller name from `python -m aiohal plugins`.")
    params: dict[str, Any] = Field(default_factory=dict, description="The controller's parameters.")
    every: int = Field(
        1,
        ge=1,
        le=1000,
        description="Run the controller on every n-th tick only (a bus faster than the controller); "
        "the drivers still exchange data on every tick.",
    )
    extrapolate: bool = Field(
        True,
        description="With every > 1: on the ticks in between, move position and velocity targets on "
        "with the controller's last target velocity and its rate of change (false: hold the last command).",
    )


class _JointDefaults(Options):
    position: tuple[float, float] | None = None
    velocity: float | None = None
    acceleration: float | None = None
    effort: float | None = None


SECTIONS: dict[str, Any] = {
    "robot": RobotSection,
    "loop": LoopSection,
    "realtime": RealtimeSection,
    "joint_defaults": _JointDefaults,
    "joints": dict[str, JointSection],
    "devices": dict[str, DeviceSection],
    "driver": list[DriverSection],
    "controller": ControllerSection,
    "record": RecordSection,
    "client": ClientSection,
    "bridge": BridgeSection,
    "safety": SafetySection,
    "feedforward": FeedforwardSection,
}
REQUIRED_SECTIONS = ("joints", "driver")
_GLOB = "*?["  # a driver's joints are names or fnmatch patterns


# ---------------------------------------------------------------- the validated result


@dataclass(frozen=True)
class DriverConfig:
    name: str
    type: str
    cls: builtins.type[Driver]  # the field "type" shadows the builtin here
    joints: tuple[str, ...]
    devices: tuple[str, ...]
    options: Options
    every: int = 1


@dataclass(frozen=True)
class ControllerConfig:
    type: str
    cls: builtins.type[Controller]  # the field "type" shadows the builtin here
    params: Options
    every: int = 1
    extrapolate: bool = True


@dataclass(frozen=True)
class Config:
    """A validated robot configuration."""

    robot: RobotSection
    loop: LoopSection
    realtime: RealtimeSection
    joints: tuple[JointSpec, ...]
    devices: tuple[tuple[str, str, str | None], ...]  # (name, kind, carrying joint)
    drivers: tuple[DriverConfig, ...]
    controller: ControllerConfig
    path: Path | None = None
    base_dir: Path = field(default_factory=Path.cwd)
    record: RecordSection = field(default_factory=RecordSection)
    client: ClientSection = field(default_factory=ClientSection)
    bridge: BridgeSection = field(default_factory=BridgeSection)
    safety: SafetySection = field(default_factory=SafetySection)
    feedforward: FeedforwardSection = field(default_factory=FeedforwardSection)

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.loop.rate_hz)

    def with_loop(self, **changes: Any) -> Config:
        """A copy with loop settings changed (e.g. the CLI's --rate), validated again."""
        loop = LoopSection.model_validate({**self.loop.model_dump(), **changes})
        if self.realtime.spin_guard_us > 1e6 / loop.rate_hz / 2:
            raise ValueError(f"realtime.spin_guard_us {self.realtime.spin_guard_us:g} is more than half the new period")
        return replace(self, loop=loop)

    def with_realtime(self, **changes: Any) -> Config:
        """A copy with real-time settings changed (e.g. the CLI's --spin-guard-us), validated again."""
        realtime = RealtimeSection.model_validate({**self.realtime.model_dump(), **changes})
        if realtime.spin_guard_us > 1e6 / self.loop.rate_hz / 2:
            raise ValueError(f"realtime.spin_guard_us {realtime.spin_guard_us:g} is more than half the period")
        return replace(self, realtime=realtime)

    def named_files(self) -> tuple[Path, ...]:
        """The config and every input file it names (the model, gains, EDS and DBC files, a
        zenoh config): what no output of a run may replace. Found by walking the sections'
        values, so that a driver's own file options are included without being listed here."""
        found: list[Path] = [self.path] if self.path is not None else []

        def walk(value: Any) -> None:
            if isinstance(value, Path):
                found.append(value if value.is_absolute() else self.base_dir / value)
            elif isinstance(value, BaseModel):
                for name in type(value).model_fields:
                    walk(getattr(value, name))
            elif isinstance(value, (list, tuple)):
                for item in value:
                    walk(item)
            elif isinstance(value, dict):
                for item in value.values():
                    walk(item)

        for section in (self.robot, self.feedforward, self.bridge, self.client, self.safety):
            walk(section)
        for driver in self.drivers:
            walk(driver.options)
        walk(self.controller.params)
        return tuple(found)

    def build_robot(self) -> Robot:
        return Robot(
            self.robot.name, self.joints, period_ns=self.period_ns, devices=self.devices, model_path=self.robot.model
        )


# ---------------------------------------------------------------- validation


def _path(loc: tuple[Any, ...], prefix: str = "") -> str:
    out = prefix
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def describe_validation_error(err: Mapping[str, Any], allowed: list[str] | None = None) -> str:
    """One pydantic error as a short message (the path is reported separately)."""
    kind = err["type"]
    value = err.get("input")
    if kind == "missing":
        return "required key is missing"
    if kind == "extra_forbidden":
        return "unknown key" + did_you_mean(str(err["loc"][-1]), allowed or [])
    if isinstance(value, float) and not math.isfinite(value) and kind != "value_error":
        return f"must be a finite number (got {value})"
    msg = err["msg"]
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    msg = msg[:1].lower() + msg[1:]
    if isinstance(value, (str, int, float, bool)) and kind != "value_error":
        msg += f" (got {value!r})"
    return msg


#: pydantic names the member of a union an error came from in its location
#: (``frequency.float``, ``frequency.dict[str,float]``): not a key the user wrote
_UNION_TAG = re.compile(r"^(float|int|str|bool|none|bytes)$|[\[(]|^(function-|constrained-|lax-|json-or-python)")
#: errors that only say the value is of another member's kind
_WRONG_KIND = {
    "float_type",
    "float_parsing",
    "int_type",
    "int_parsing",
    "int_from_float",
    "string_type",
    "bool_type",
    "bool_parsing",
    "dict_type",
    "list_type",
    "tuple_type",
    "none_required",
    "literal_error",
    "model_type",
    "path_type",
    "is_instance_of",
    "enum",
}


def _kind_of(tag: str) -> str:
    if tag.startswith("literal["):
        return " or ".join(
            f'"{v.strip()[1:-1]}"' if v.strip()[:1] in "'\"" else v.strip()
            for v in tag[len("literal[") : -1].split(",")
        )
    named = {"float": "a number", "int": "an integer", "str": "a string", "bool": "true or false"}
    for prefix, kind in (("dict[", "a table"), ("list[", "an array"), ("tuple[", "an array"), ("set[", "an array")):
        if tag.startswith(prefix):
            return kind
    return named.get(tag, tag)


def _collapse_unions(errors: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """One error per value for a union: the errors of the member the value was meant for (a
    table's bad entry), else one "must be a number or a table" line; union tags left out."""
    out: list[Mapping[str, Any]] = []
    groups: dict[tuple[Any, ...], list[tuple[str, Mapping[str, Any]]]] = {}
    for err in errors:
        loc = tuple(err["loc"])
        at = next((i for i, part in enumerate(loc) if isinstance(part, str) and _UNION_TAG.search(part)), None)
        if at is None:
            out.append(err)
            continue
        clean = {
            **err,
            "loc": loc[:at] + tuple(p for p in loc[at + 1 :] if not (isinstance(p, str) and _UNION_TAG.search(p))),
        }
        if loc[:at] not in groups:
            groups[loc[:at]] = []
            out.append({"loc": loc[:at], "_group": True})  # keeps the order of the errors
        groups[loc[:at]].append((loc[at], clean))
    result: list[Mapping[str, Any]] = []
    for err in out:
        if not err.get("_group"):
            result.append(err)
            continue
        members = groups[err["loc"]]
        meant = [e for _, e in members if len(e["loc"]) > len(err["loc"]) or e["type"] not in _WRONG_KIND]
        if meant:
            result.extend(meant)
        else:
            kinds = " or ".join(dict.fromkeys(_kind_of(tag) for tag, _ in members))
            result.append(
                {"loc": err["loc"], "type": "union", "msg": f"must be {kinds}", "input": members[0][1].get("input")}
            )
    return result


def _model_fields(model: Any, loc: tuple[Any, ...]) -> list[str] | None:
    """Field names valid at ``loc`` inside ``model`` (for did-you-mean hints)."""
    target = model
    for part in loc:
        fields = getattr(target, "model_fields", None)
        if fields is None:
            return None
        if part in fields:
            ann = fields[part].annotation
            target = ann
        elif isinstance(part, int) or not fields:
            continue
        else:
            return list(fields)
    fields = getattr(target, "model_fields", None)
    return list(fields) if fields else None


def _validate(schema: Any, data: Any, prefix: str, issues: list[ConfigIssue], context: dict[str, Any]) -> Any:
    """Validate ``data`` against a model or type; append located issues; None on failure."""
    try:
        return TypeAdapter(schema).validate_python(data, context=context)
    except ValidationError as exc:
        for err in _collapse_unions(exc.errors()):
            loc = tuple(err["loc"])
            item_model = schema
            sub_loc = loc
            # dict[str, Model] / list[Model]: the first loc part is the key or index
            args = getattr(schema, "__args__", None)
            if args:
                item_model = args[-1]
                sub_loc = loc[1:]
            allowed = _model_fields(item_model, sub_loc[:-1])
            issues.append(ConfigIssue(_path(loc, prefix), describe_validation_error(err, allowed)))
        return None


def _expand(patterns: list[str], names: tuple[str, ...], path: str, issues: list[ConfigIssue]) -> list[str]:
    out: list[str] = []
    for pattern in patterns:
        if any(c in pattern for c in _GLOB):
            matched = [n for n in names if fnmatch.fnmatchcase(n, pattern) and n not in out]
            if not matched:
                issues.append(ConfigIssue(path, f'pattern "{pattern}" matches no joint'))
            out.extend(matched)
        elif pattern not in names:
            issues.append(ConfigIssue(path, f'unknown joint "{pattern}"{did_you_mean(pattern, names)}'))
        elif pattern in out:
            issues.append(ConfigIssue(path, f'joint "{pattern}" is listed twice'))
        else:
            out.append(pattern)
    return out


def _load_plugin(
    kind: plugins.Kind, name: str, path: str, issues: list[ConfigIssue], given: type | None = None
) -> type | None:
    """The plugin named ``name`` (or the class ``given`` from code), or None with the issue added."""
    try:
        return plugins.check_class(kind, given) if given is not None else plugins.load(kind, name)
    except MissingDependencyError as exc:
        issues.append(ConfigIssue(path, str(exc)))
    except PluginError as exc:
        issues.append(ConfigIssue(path, str(exc)))
    return None


def _plugin_checks(cls: type[Driver] | type[Controller], where: str, *args: Any) -> list[tuple[str, str]]:
    """A plugin's own config checks; a check that crashes is reported, not raised."""
    try:
        return list(cls.check_config(*args))
    except Exception as exc:
        return [("", f"{cls.__name__}.check_config failed: {type(exc).__name__}: {exc}")]


def _plugin_path(where: str, rel: str) -> str:
    """A plugin check's path: relative to its section, or from the top when it starts with /."""
    if rel.startswith("/"):
        return rel[1:]
    return f"{where}.{rel}" if rel else where


def _plugin_checks_rate(cls: type, options: Options, cycle_hz: float, every: int) -> list[tuple[str, str]]:
    """A driver's checks at the rate it is cycled at; a check that crashes is reported, not raised."""
    check = getattr(cls, "check_rate", None)
    if check is None:
        return []
    try:
        return list(check(options, cycle_hz, every))
    except Exception as exc:
        return [("", f"{cls.__name__}.check_rate failed: {type(exc).__name__}: {exc}")]


class _Document:
    """A parsed document on its way to a :class:`Config`: the raw tables, the validation
    context and every issue found so far (each section adds its own and goes on)."""

    def __init__(self, raw: dict[str, Any], base_dir: Path) -> None:
        self.raw = raw
        self.context = {"base_dir": base_dir}
        self.issues: list[ConfigIssue] = []

    def add(self, path: str, message: str) -> None:
        self.issues.append(ConfigIssue(path, message))

    def validate(self, schema: Any, data: Any, prefix: str) -> Any:
        """``data`` validated against ``schema``, or None with its issues added."""
        return _validate(schema, data, prefix, self.issues, self.context)

    def section(self, schema: Any, key: str) -> Any:
        """The top-level section ``key`` (empty when absent) validated against ``schema``."""
        return self.validate(schema, self.raw.get(key, {}), key)


def parse_config(raw: dict[str, Any], *, base_dir: Path | None = None, path: Path | None = None) -> Config:
    """Validate a parsed TOML document; raises ConfigError listing every issue.

    Each section is parsed on its own, in the order of the file's description, so one bad
    section does not hide the others' errors; the checks across sections come last. From
    code (:func:`from_parts`), a driver's or the controller's ``type`` may be the class itself.
    """
    if not isinstance(raw, dict):
        raise ConfigError([ConfigIssue("", "the document must be a table")], str(path) if path else None)
    doc = _Document(raw, Path(base_dir) if base_dir is not None else Path.cwd())
    _check_section_names(doc)
    robot = doc.section(RobotSection, "robot")
    loop, realtime = _parse_loop(doc)
    safety = doc.section(SafetySection, "safety")
    record = doc.section(RecordSection, "record")
    joints = _parse_joints(doc)
    joint_names = tuple(j.name for j in joints)
    devices = _parse_devices(doc, joint_names)
    drivers = _parse_drivers(doc, joint_names, devices, robot or RobotSection(), loop)
    controller = _parse_controller(doc, joints, robot or RobotSection())
    client = doc.section(ClientSection, "client")
    bridge = doc.section(BridgeSection, "bridge")
    feedforward = doc.section(FeedforwardSection, "feedforward")
    if feedforward is not None:
        for key, message in feedforward_issues(feedforward, list(joint_names)):
            doc.add(key, message)
    _cross_check(doc, robot, controller, client, bridge, safety)
    if controller is not None:
        doc.issues += mode_issues(controller.cls, controller.params, drivers)

    if doc.issues:  # each once: a scalar that is wrong for every joint is one mistake
        raise ConfigError(list(dict.fromkeys(doc.issues)), str(path) if path else None)
    assert robot is not None and loop is not None and realtime is not None and controller is not None
    assert safety is not None and feedforward is not None
    return Config(
        robot=robot,
        loop=loop,
        realtime=realtime,
        joints=joints,
        devices=tuple((n, d.type, d.joint) for n, d in devices.items()),
        drivers=drivers,
        controller=controller,
        path=path,
        base_dir=doc.context["base_dir"],
        record=record,
        client=client,
        bridge=bridge,
        safety=safety,
        feedforward=feedforward,
    )


def _workspace_issues(robot: RobotSection, safety: Any) -> list[ConfigIssue]:
    """Workspace limits need the robot's model, and its sites and frames in it."""
    if robot.model is None:
        return [ConfigIssue("safety.workspace", "workspace limits need the robot's model ([robot] model)")]
    try:
        from .safety.workspace import WorkspaceMonitor

        return [ConfigIssue(k, m) for k, m in WorkspaceMonitor.name_issues(robot.model, safety.workspace)]
    except ImportError as exc:
        return [ConfigIssue("safety.workspace", f"workspace limits need MuJoCo (the 'sim' extra): {exc}")]
    except ValueError as exc:
        return [ConfigIssue("robot.model", str(exc))]


def _check_section_names(doc: _Document) -> None:
    for key in doc.raw:
        if key not in SECTIONS:
            doc.add(key, "unknown section" + did_you_mean(key, SECTIONS))
    for key in REQUIRED_SECTIONS:
        if key not in doc.raw:
            doc.add(key, "required section is missing")


def _parse_loop(doc: _Document) -> tuple[LoopSection | None, RealtimeSection | None]:
    """``[loop]`` and ``[realtime]``, whose spin guard must leave most of the period free."""
    loop = doc.section(LoopSection, "loop")
    realtime = doc.section(RealtimeSection, "realtime")
    if loop is not None and realtime is not None:
        period_us = 1e6 / loop.rate_hz
        if realtime.spin_guard_us > period_us / 2:
            doc.add(
                "realtime.spin_guard_us",
                f"{realtime.spin_guard_us:g} µs is more than half the period ({period_us / 2:g} µs): "
                "the loop would spin most of the time",
            )
    return loop, realtime


def _parse_joints(doc: _Document) -> tuple[JointSpec, ...]:
    """``[joints]``, each validated on its own with ``[joint_defaults]`` filled in. A joint
    with errors still gets a spec (without limits): the plugins know its name, so nothing
    follows from its errors but their own report."""
    raw = doc.raw
    defaults = doc.section(_JointDefaults, "joint_defaults")
    default_values = defaults.model_dump(exclude_none=True) if defaults else {}
    raw_joints = raw.get("joints", {})
    if not isinstance(raw_joints, dict):
        doc.add("joints", "must be a table of joints")
        raw_joints = {}
    elif "joints" in raw and not raw_joints:
        doc.add("joints", "the robot needs at least one joint")
    specs: list[JointSpec] = []
    for name, body in raw_joints.items():
        if not name.strip() or any(c in name for c in _GLOB):
            doc.add(
                f'joints."{name}"',
                "a joint name must not be empty nor contain * ? [ (drivers name their joints with those patterns)",
            )
        if not isinstance(body, dict):
            doc.add(f"joints.{name}", "must be a table")
            joint = None
        else:
            joint = doc.validate(JointSection, {**default_values, **body}, f"joints.{name}")
        if joint is not None:
            lo, hi = joint.position
            specs.append(JointSpec(name, len(specs), lo, hi, joint.velocity, joint.acceleration, joint.effort))
        else:
            specs.append(JointSpec(name, len(specs), -math.inf, math.inf, math.inf, math.inf, math.inf))
    return tuple(specs)


def _parse_devices(doc: _Document, joint_names: tuple[str, ...]) -> dict[str, DeviceSection]:
    """``[devices]``; a hand names the joint that carries it, nothing else does."""
    devices = doc.section(dict[str, DeviceSection], "devices") or {}
    for dev_name in devices:
        if not dev_name.strip():
            doc.add('devices.""', "a device name must not be empty")
    for dev_name, dev in devices.items():
        where = f"devices.{dev_name}.joint"
        if dev.type == "hand":
            if dev.joint is None:
                doc.add(where, "a hand needs the joint that carries it")
            elif dev.joint not in joint_names:
                doc.add(where, f'unknown joint "{dev.joint}"{did_you_mean(dev.joint, joint_names)}')
        elif dev.joint is not None:
            doc.add(where, f"only a hand is carried by a joint, not a {dev.type}")
    return devices


def _parse_drivers(
    doc: _Document,
    joint_names: tuple[str, ...],
    devices: dict[str, DeviceSection],
    robot: RobotSection,
    loop: LoopSection | None,
) -> tuple[DriverConfig, ...]:
    """``[[driver]]``: each entry with its joints (a contiguous run, each owned once), its
    devices, its plugin and its options; then every joint and device must have an owner."""
    raw_drivers = doc.raw.get("driver", [])
    if not isinstance(raw_drivers, list):
        doc.add("driver", "must be an array of tables: write [[driver]]")
        raw_drivers = []
    elif "driver" in doc.raw and not raw_drivers:
        doc.add("driver", "the robot needs at least one driver")
    entries = [_given_class(body) for body in raw_drivers]
    drivers: list[DriverConfig] = []
    incomplete = False
    joint_owner: dict[str, int] = {}
    device_owner: dict[str, int] = {}
    names_seen: dict[str, int] = {}
    type_counts: dict[str, int] = {}
    for d, _ in entries:
        if isinstance(d, dict) and isinstance(d.get("type"), str):
            type_counts[d["type"]] = type_counts.get(d["type"], 0) + 1
    for i, (body, given) in enumerate(entries):
        where = f"driver[{i}]"
        section = doc.validate(DriverSection, body, where)
        if section is None:
            incomplete = True  # its joints are unknown: do not call them unowned
            continue
        name = section.name or (section.type if type_counts.get(section.type, 0) == 1 else f"{section.type}{i}")
        if name in names_seen:
            doc.add(f"{where}.name", f'"{name}" is already the name of driver[{names_seen[name]}]')
        names_seen.setdefault(name, i)

        known_before = len(doc.issues)
        joints = _expand(section.joints, joint_names, f"{where}.joints", doc.issues)
        # a joint list with an unknown name is not what the user meant: the driver's own checks
        # against it would only repeat that error (its options naming joints "not its own")
        joints_wrong = len(doc.issues) > known_before
        for j in joints:
            if j in joint_owner:
                doc.add(f"{where}.joints", f'joint "{j}" is already owned by driver[{joint_owner[j]}]')
            else:
                joint_owner[j] = i
        idx = [joint_names.index(j) for j in joints]
        if idx and idx != list(range(idx[0], idx[0] + len(idx))):
            doc.add(
                f"{where}.joints",
                f"a driver's joints must be a contiguous run in the order of [joints] (got {', '.join(joints)})",
            )

        cls = cast("type[Driver] | None", _load_plugin("driver", section.type, f"{where}.type", doc.issues, given))
        dev_kinds: dict[str, str] = {}
        for dev_name in section.devices:
            if dev_name not in devices:
                doc.add(f"{where}.devices", f'unknown device "{dev_name}"{did_you_mean(dev_name, devices)}')
                continue
            kind = devices[dev_name].type
            dev_kinds[dev_name] = kind
            if dev_name in device_owner:
                doc.add(f"{where}.devices", f'device "{dev_name}" is already owned by driver[{device_owner[dev_name]}]')
            else:
                device_owner[dev_name] = i
            if cls is not None and kind not in getattr(cls, "device_kinds", frozenset()):
                doc.add(f"{where}.devices", f'driver "{section.type}" cannot serve a {kind} ("{dev_name}")')
        if cls is None:
            continue
        options = doc.validate(cls.Options, section.options, f"{where}.options")
        if options is None or joints_wrong:
            continue
        for rel, msg in _plugin_checks(cls, where, options, joints, dev_kinds, robot):
            doc.add(_plugin_path(where, rel), msg)
        # checks that depend on the rate the driver is cycled at (e.g. a CAN bus's load)
        if loop is not None:
            for rel, msg in _plugin_checks_rate(cls, options, loop.rate_hz / section.every, section.every):
                doc.add(_plugin_path(where, rel), msg)
        drivers.append(
            DriverConfig(name, section.type, cls, tuple(joints), tuple(section.devices), options, section.every)
        )

    if isinstance(doc.raw.get("driver"), list) and not incomplete:  # raw_drivers is [] after a malformed section
        unowned = [j for j in joint_names if j not in joint_owner]
        if len(unowned) > 3:  # one line, not one per joint of a robot that lost a driver
            doc.add("joints", f"no driver owns {len(unowned)} joints: {', '.join(unowned)}")
        else:
            for j in unowned:
                doc.add(f"joints.{j}", "no driver owns this joint")
        for dev_name in devices:
            if dev_name not in device_owner:
                doc.add(f"devices.{dev_name}", "no driver owns this device")
    return tuple(drivers)


def _given_class(body: Any) -> tuple[Any, type | None]:
    """A section whose ``type`` is a class (from code) as the section naming it, and the class."""
    if isinstance(body, dict) and isinstance(body.get("type"), type):
        return {**body, "type": body["type"].__name__}, body["type"]
    return body, None


def _parse_controller(doc: _Document, joints: tuple[JointSpec, ...], robot: RobotSection) -> ControllerConfig | None:
    """``[controller]``: its plugin, its parameters and the plugin's own checks of them."""
    body, given = _given_class(doc.raw.get("controller", {}))
    section = doc.validate(ControllerSection, body, "controller")
    if section is None:
        return None
    cls = cast(
        "type[Controller] | None", _load_plugin("controller", section.type, "controller.type", doc.issues, given)
    )
    if cls is None:
        return None
    params = doc.validate(cls.Params, section.params, "controller.params")
    if params is None:
        return None
    for rel, msg in _plugin_checks(cls, "controller", params, joints, robot):
        doc.add(_plugin_path("controller", rel), msg)
    return ControllerConfig(section.type, cls, params, section.every, section.extrapolate)


def mode_issues(controller: type[Controller], params: Options, drivers: Sequence[DriverConfig]) -> list[ConfigIssue]:
    """A mode the controller commands that a driver cannot apply to its joints, with the
    driver named (as ros2_control refuses a controller whose command interfaces the hardware
    does not export). Reported at ``controller.params.mode`` when a parameter chose it."""
    where = "controller.params.mode" if "mode" in type(params).model_fields else "controller.type"
    try:
        commanded = controller.commanded_modes(params)
    except Exception as exc:
        return [ConfigIssue(where, f"{controller.__name__}.commanded_modes failed: {type(exc).__name__}: {exc}")]
    issues = []
    for driver in drivers:
        if not driver.joints:
            continue
        try:
            supported = driver.cls.supported_modes(driver.options)
        except Exception as exc:
            issues.append(
                ConfigIssue(
                    where,
                    f'driver "{driver.name}": {driver.cls.__name__}.supported_modes '
                    f"failed: {type(exc).__name__}: {exc}",
                )
            )
            continue
        missing = commanded - supported
        if missing:
            issues.append(
                ConfigIssue(
                    where,
                    f'commands {_mode_names(missing)}, which driver "{driver.name}" '
                    f"({driver.type}) cannot apply (it takes {_mode_names(supported) or 'none'})",
                )
            )
    return issues


def _mode_names(modes: Iterable[Mode]) -> str:
    return ", ".join(m.name.lower() for m in sorted(modes))


def _cross_check(
    doc: _Document,
    robot: RobotSection | None,
    controller: ControllerConfig | None,
    client: ClientSection | None,
    bridge: BridgeSection | None,
    safety: SafetySection | None,
) -> None:
    """What no section can check alone: the doors to other processes against the controller
    and the robot's name; workspace limits against the robot's model."""
    if safety is not None and safety.workspace and robot is not None:
        doc.issues += _workspace_issues(robot, safety)
    zenoh = bridge.zenoh if bridge is not None else None
    if zenoh is not None and zenoh.config_file is not None:
        try:
            check_regular(zenoh.config_file)
        except FileRefused as exc:
            doc.add("bridge.zenoh.config_file", str(exc))
    if (
        zenoh is not None
        and "setpoints" in zenoh.commands
        and (client is None or not client.shm or (controller is not None and controller.type != "stream"))
    ):
        doc.add(
            "bridge.zenoh.commands",
            "setpoints go through the shared-memory ring "
            'to the stream controller: set [client] shm = true and [controller] type = "stream"',
        )
    if zenoh is not None and zenoh.commands and not zenoh.allow_anyone and zenoh.config_file is None:
        doc.add("bridge.zenoh.commands", UNCONTROLLED)
    if client is not None and client.shm and robot is not None:
        try:
            segment_name(robot.name)
        except AiohalError as exc:
            doc.add("robot.name", str(exc))
    if controller is not None and client is not None and controller.type == "stream" and not client.shm:
        doc.add("controller.type", "the stream controller reads setpoints from shared memory: set [client] shm = true")


#: the largest config file read (the largest shipped config is about 10 KiB); a device or a
#: huge file is refused instead of read until memory runs out
MAX_CONFIG_BYTES = 1 << 20
#: how deeply tables and arrays may nest (the shipped configs use 4 levels)
MAX_DEPTH = 32


def _depth_exceeds(value: Any, limit: int) -> bool:
    """Whether tables and arrays nest more than ``limit`` levels deep (without recursion)."""
    stack = [(value, 0)]
    while stack:
        node, depth = stack.pop()
        children: Iterable[Any]
        if isinstance(node, dict):
            children = node.values()
        elif isinstance(node, list):
            children = node
        else:
            continue
        if depth >= limit:
            return True
        stack.extend((child, depth + 1) for child in children)
    return False


def load_config(path: str | Path) -> Config:
    """Read and validate a robot TOML file."""
    path = Path(path)
    source = str(path)
    try:
        text = read_regular_text(path, limit=MAX_CONFIG_BYTES)
    except FileRefused as exc:
        raise ConfigError([ConfigIssue("", f"cannot read the file: {exc}")], source) from None
    too_deep = ConfigError([ConfigIssue("", f"tables or arrays nest more than {MAX_DEPTH} levels deep")], source)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([ConfigIssue("", f"invalid TOML: {exc}")], source) from None
    except RecursionError:  # the parser recurses per nested array or inline table
        raise too_deep from None
    if _depth_exceeds(raw, MAX_DEPTH):
        raise too_deep
    return parse_config(raw, base_dir=path.resolve().parent, path=path)


def from_parts(
    *,
    joints: Mapping[str, Mapping[str, Any]] | Sequence[JointSpec],
    drivers: Sequence[Mapping[str, Any] | tuple[str | type, Mapping[str, Any]]],
    controller: str | type | Mapping[str, Any] = "hold",
    params: Mapping[str, Any] | Options | None = None,
    robot: str | Mapping[str, Any] = "robot",
    devices: Mapping[str, Mapping[str, Any]] | None = None,
    rate_hz: float | None = None,
    clock: str | None = None,
    base_dir: str | Path | None = None,
    **sections: Any,
) -> Config:
    """A :class:`Config` from Python values instead of a TOML file, validated the same way
    (the same errors, with the same key paths).

    ``joints``: ``{name: {"position": [min, max], "velocity": ..., ...}}`` as ``[joints]``, or
    :class:`JointSpec` objects in order. ``drivers``: ``[[driver]]`` tables, or ``(type,
    {"joints": [...], "options": {...}})`` pairs; a type is a plugin name or a Driver class.
    ``controller``: a name or Controller class with its ``params``, or a ``[controller]``
    table. ``robot``: its name, or the ``[robot]`` table. ``rate_hz`` and ``clock`` go into
    ``[loop]``; any other section (``loop``, ``realtime``, ``joint_defaults``, ``record``,
    ``client``, ``bridge``) is given as its table. Relative paths are taken from ``base_dir``
    (default: the working directory).
    """
    raw: dict[str, Any] = {key: dict(value) if isinstance(value, Mapping) else value for key, value in sections.items()}
    raw["robot"] = {"name": robot} if isinstance(robot, str) else dict(robot)
    loop = raw.setdefault("loop", {})
    if isinstance(loop, dict):
        loop.update({key: value for key, value in (("rate_hz", rate_hz), ("clock", clock)) if value is not None})
    if isinstance(joints, Mapping):
        raw["joints"] = {name: dict(body) if isinstance(body, Mapping) else body for name, body in joints.items()}
    else:
        raw["joints"] = {
            j.name: {
                "position": [j.position_min, j.position_max],
                "velocity": j.velocity,
                "acceleration": j.acceleration,
                "effort": j.effort,
            }
            for j in joints
        }
    if devices is not None:
        raw["devices"] = {name: dict(body) for name, body in devices.items()}
    raw["driver"] = [{"type": entry[0], **entry[1]} if isinstance(entry, tuple) else dict(entry) for entry in drivers]
    if isinstance(params, Options):
        params = params.model_dump()
    if isinstance(controller, Mapping):
        if params is not None:
            raise TypeError("give params inside the controller table, or a controller name or class with params")
        raw["controller"] = dict(controller)
    else:
        raw["controller"] = {"type": controller, "params": dict(params or {})}
    return parse_config(raw, base_dir=Path(base_dir) if base_dir is not None else None)


# ---------------------------------------------------------------- JSON Schema


def json_schema() -> dict[str, Any]:
    """A JSON Schema of robot configs for editors; plugin options included for loadable plugins."""
    props: dict[str, Any] = {}
    defs: dict[str, Any] = {}
    for key, schema in SECTIONS.items():
        sub = TypeAdapter(schema).json_schema(ref_template="#/$defs/{model}")
        defs.update(sub.pop("$defs", {}))
        props[key] = sub
    props["joints"]["minProperties"] = 1
    props["driver"]["minItems"] = 1
    for kind, section_key, field_name in (
        ("driver", "DriverSection", "options"),
        ("controller", "ControllerSection", "params"),
    ):
        clauses = []
        names = []  # only the plugins that load: a broken one is no choice for a config
        for spec, error in plugins.describe(kind):
            if error is not None:
                continue
            name = spec.name
            cls = plugins.load(kind, name)
            model = cast("type[Driver]", cls).Options if kind == "driver" else cast("type[Controller]", cls).Params
            try:
                sub = model.model_json_schema(ref_template="#/$defs/{model}")
            except Exception:  # a plugin whose options have no JSON Schema: left out
                continue
            names.append(name)
            defs.update(sub.pop("$defs", {}))
            def_name = f"{kind}_{name}_{field_name}"
            defs[def_name] = sub
            clauses.append(
                {
                    "if": {"properties": {"type": {"const": name}}, "required": ["type"]},
                    "then": {"properties": {field_name: {"$ref": f"#/$defs/{def_name}"}}},
                }
            )
        # a model used directly as a top-level section is inlined in props, not in $defs
        section_schema = defs[section_key] if section_key in defs else props[kind]
        section_schema["allOf"] = clauses
        section_schema["properties"]["type"]["enum"] = sorted(names)
    return _finite_defaults(
        {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": "aiohal robot configuration",
            "type": "object",
            "properties": props,
            "required": list(REQUIRED_SECTIONS),
            "additionalProperties": False,
            "$defs": defs,
        }
    )


def _finite_defaults(node: Any) -> Any:
    """Drop defaults JSON cannot hold (inf limits mean "no limit"; TOML writes them as inf)."""
    if isinstance(node, dict):
        out = {k: _finite_defaults(v) for k, v in node.items()}
        default = out.get("default")
        values = default if isinstance(default, (list, tuple)) else [default]
        # pydantic already renders inf inside a sequence default as null: [-inf, inf] -> [null, null]
        if any((isinstance(v, float) and not math.isfinite(v)) or (v is None and values is default) for v in values):
            del out["default"]
            out["description"] = (out.get("description", "") + " Default: no limit (inf).").strip()
        return out
    if isinstance(node, list):
        return [_finite_defaults(v) for v in node]
    return node
