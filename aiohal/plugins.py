"""Find drivers and controllers: a built-in table, plugins registered in the process and
entry points, imported lazily.

Nothing is imported until a plugin is asked for by name, so a missing optional dependency
(MuJoCo, pysoem, python-can) only matters to the configs that use it, and then gives one
clear error naming the extra to install. Every ``"package.module:attribute"`` target is
resolved by :func:`pkgutil.resolve_name`.
"""

from __future__ import annotations

import pkgutil
from dataclasses import dataclass, field
from functools import cache
from importlib.metadata import entry_points
from typing import Literal

from .errors import MissingDependencyError, PluginError

Kind = Literal["driver", "controller"]

GROUPS: dict[str, str] = {"driver": "aiohal.drivers", "controller": "aiohal.controllers"}

#: name -> (import target "module:attribute", pip extra that provides its dependencies)
BUILTIN: dict[str, dict[str, tuple[str, str | None]]] = {
    "driver": {
        "mock": ("aiohal.drivers.mock_fast:FastMockDriver", None),
        "mujoco": ("aiohal.drivers.mujoco:MujocoDriver", "sim"),
        "nrt_hand": ("aiohal.drivers.nrt_hand:NrtHandDriver", None),
        "ethercat": ("aiohal.drivers.ethercat.driver:EthercatDriver", "ethercat"),
        "canopen": ("aiohal.drivers.canopen.driver:CanopenDriver", "can"),
        "udp": ("aiohal.drivers.udp.driver:UdpDriver", None),
        "fri": ("aiohal.drivers.fri.driver:FriDriver", None),
        "replay": ("aiohal.drivers.replay:ReplayDriver", "record"),
    },
    "controller": {
        "hold": ("aiohal.controllers.hold:HoldController", None),
        "homing": ("aiohal.controllers.homing:HomingController", None),
        "sine": ("aiohal.controllers.sine:SineController", None),
        "gait": ("aiohal.controllers.gait:GaitController", None),
        "chirp": ("aiohal.controllers.chirp:ChirpController", None),
        "circle": ("aiohal.controllers.circle_fast:FastCircleController", "sim"),
        "sequence": ("aiohal.controllers.sequence:SequenceController", None),
        "stream": ("aiohal.controllers.stream:StreamController", None),
    },
}


@dataclass(frozen=True)
class PluginSpec:
    kind: str
    name: str
    target: str
    extra: str | None
    source: str  # "built-in", "registered" or "entry point (distribution)"
    obj: type | None = field(default=None, compare=False)  # a class registered as itself


#: plugins registered in this process by register(): kind -> name -> spec
_REGISTERED: dict[str, dict[str, PluginSpec]] = {"driver": {}, "controller": {}}


def register(kind: Kind, name: str, plugin: type | str) -> None:
    """Make a driver or controller class (or its ``"package.module:Class"`` target, imported
    when first used) known by ``name`` in this process, as an entry point would make it known
    to every process: for scripts, notebooks and tests. A built-in name cannot be taken; a
    name registered again is replaced."""
    if kind not in GROUPS:
        raise ValueError(f"kind must be one of {', '.join(GROUPS)}, not {kind!r}")
    if name in BUILTIN[kind]:
        raise PluginError(f'{kind} "{name}" is built in and cannot be replaced')
    if isinstance(plugin, str):
        spec = PluginSpec(kind, name, plugin, None, "registered")
    else:
        spec = _class_spec(kind, name, plugin, "registered")
        _check_class(spec, plugin)
    _REGISTERED[kind][name] = spec
    load.cache_clear()


def check_class(kind: Kind, cls: object) -> type:
    """``cls`` given from code in place of a plugin name: checked as a loaded plugin is."""
    return _check_class(_class_spec(kind, getattr(cls, "__name__", repr(cls)), cls, "given"), cls)


def _class_spec(kind: str, name: str, cls: object, source: str) -> PluginSpec:
    target = f"{getattr(cls, '__module__', '?')}:{getattr(cls, '__qualname__', cls)!s}"
    return PluginSpec(kind, name, target, None, source, cls)  # type: ignore[arg-type]


def unregister(kind: Kind, name: str) -> None:
    """Forget a plugin given to :func:`register` (nothing happens for an unknown name)."""
    if _REGISTERED[kind].pop(name, None) is not None:
        load.cache_clear()


def _entry_point_specs(kind: str) -> list[PluginSpec]:
    specs = []
    for ep in entry_points(group=GROUPS[kind]):
        dist = getattr(ep, "dist", None)
        origin = f"entry point ({dist.name})" if dist is not None else "entry point"
        specs.append(PluginSpec(kind, ep.name, ep.value, None, origin))
    return specs


def available(kind: str) -> dict[str, PluginSpec]:
    """Every known plugin of a kind; a built-in name cannot be taken over, and a registered
    one goes before an entry point of the same name."""
    found = {name: PluginSpec(kind, name, target, extra, "built-in") for name, (target, extra) in BUILTIN[kind].items()}
    for name, spec in _REGISTERED[kind].items():
        found.setdefault(name, spec)
    for spec in _entry_point_specs(kind):
        found.setdefault(spec.name, spec)
    return found


def shadowed(kind: str) -> list[PluginSpec]:
    """Entry points ignored because a built-in has the same name."""
    return [s for s in _entry_point_specs(kind) if s.name in BUILTIN[kind]]


def _import_target(spec: PluginSpec) -> type:
    if spec.obj is not None:
        return spec.obj
    module_name = spec.target.partition(":")[0]
    try:
        return pkgutil.resolve_name(spec.target)
    except ModuleNotFoundError as exc:
        missing = exc.name or "?"
        if missing == module_name or module_name.startswith(missing + "."):
            raise PluginError(f'{spec.kind} "{spec.name}": module {module_name!r} not found') from exc
        if spec.extra:
            hint = f'install the extra: pip install "aiohal[{spec.extra}]"'
        else:
            hint = f"install the package that provides {missing!r}"
        raise MissingDependencyError(
            f'{spec.kind} "{spec.name}" needs the optional dependency {missing!r}: {hint}'
        ) from exc
    except AttributeError as exc:
        if exc.name not in spec.target.replace(":", ".").split("."):  # raised by the module's own code
            raise PluginError(
                f'{spec.kind} "{spec.name}": importing {module_name} failed: AttributeError: {exc}'
            ) from exc
        raise PluginError(f'{spec.kind} "{spec.name}": {spec.target} does not exist') from exc
    except ValueError as exc:  # not a name at all
        raise PluginError(f'{spec.kind} "{spec.name}": {spec.target!r} is not a "package.module:Class" name') from exc
    except Exception as exc:  # a plugin module that fails while importing
        raise PluginError(
            f'{spec.kind} "{spec.name}": importing {module_name} failed: {type(exc).__name__}: {exc}'
        ) from exc


def _check_class(spec: PluginSpec, obj: object) -> type:
    """The target must be a Driver or Controller class with its options model: anything else
    would only fail later, inside a config that uses it (``AttributeError: Options``)."""
    from .hal import Controller, Driver, Options

    base, model_attr = (Driver, "Options") if spec.kind == "driver" else (Controller, "Params")
    where = f'{spec.kind} "{spec.name}": {spec.target}'
    if not (isinstance(obj, type) and issubclass(obj, base)):
        what = f"a {type(obj).__name__}" if not isinstance(obj, type) else f"the class {obj.__name__}"
        raise PluginError(f"{where} is {what}, not a subclass of aiohal.{base.__name__}")
    model = getattr(obj, model_attr, None)
    if not (isinstance(model, type) and issubclass(model, Options)):
        raise PluginError(f"{where}: its {model_attr} is not a subclass of aiohal.Options")
    if getattr(obj, "__abstractmethods__", None):
        missing = ", ".join(sorted(obj.__abstractmethods__))
        raise PluginError(f"{where} does not implement {missing}")
    return obj


@cache
def load(kind: str, name: str) -> type:
    """The driver or controller class registered under ``name``."""
    specs = available(kind)
    if name not in specs:
        known = ", ".join(sorted(specs)) or "none"
        raise PluginError(f'unknown {kind} "{name}" (available: {known})')
    return _check_class(specs[name], _import_target(specs[name]))


def describe(kind: str) -> list[tuple[PluginSpec, str | None]]:
    """Each plugin with None if it loads, else the reason it does not."""
    rows: list[tuple[PluginSpec, str | None]] = []
    for name, spec in sorted(available(kind).items()):
        try:
            load(kind, name)
            rows.append((spec, None))
        except Exception as exc:  # a broken third-party plugin must not hide the others
            rows.append((spec, str(exc) or type(exc).__name__))
    return rows
