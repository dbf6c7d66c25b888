"""aiohal: a robot hardware abstraction layer on asyncio.

One HAL protocol between controllers and hardware (drivers chosen by configuration), a
control loop that ticks at 1-2 kHz on absolute deadlines, and simulated drivers for CI.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# The public names are imported on first use (PEP 562): ``python -m aiohal`` and the
# simulators' CLIs start without loading numpy, numba and pydantic first, so a Ctrl-C during
# start-up reaches their own handling instead of a traceback from deep in an import.
_EXPORTS = {
    "Config": ".config",
    "load_config": ".config",
    "parse_config": ".config",
    "AiohalError": ".errors",
    "ConfigError": ".errors",
    "ConfigIssue": ".errors",
    "ControllerError": ".errors",
    "DriverError": ".errors",
    "LifecycleError": ".errors",
    "MissingDependencyError": ".errors",
    "PluginError": ".errors",
    "Controller": ".hal",
    "Driver": ".hal",
    "FiniteFloat": ".hal",
    "JointValues": ".hal",
    "Options": ".hal",
    "ControlLoop": ".core.loop",
    "DriverView": ".robot",
    "JointSpec": ".robot",
    "Mode": ".robot",
    "Robot": ".robot",
    "RobotView": ".robot",
    "SafetyLevel": ".safety",
}

if TYPE_CHECKING:
    from .config import Config, load_config, parse_config
    from .core.loop import ControlLoop
    from .errors import (
        AiohalError,
        ConfigError,
        ConfigIssue,
        ControllerError,
        DriverError,
        LifecycleError,
        MissingDependencyError,
        PluginError,
    )
    from .hal import Controller, Driver, FiniteFloat, JointValues, Options
    from .robot import DriverView, JointSpec, Mode, Robot, RobotView
    from .safety import SafetyLevel


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:  # a submodule (aiohal.plugins) is an attribute once imported
        try:
            return importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


__version__ = "0.1.0"

__all__ = [
    "AiohalError",
    "Config",
    "ConfigError",
    "ConfigIssue",
    "ControlLoop",
    "Controller",
    "ControllerError",
    "Driver",
    "DriverError",
    "DriverView",
    "FiniteFloat",
    "JointSpec",
    "JointValues",
    "LifecycleError",
    "MissingDependencyError",
    "Mode",
    "Options",
    "PluginError",
    "Robot",
    "RobotView",
    "SafetyLevel",
    "__version__",
    "load_config",
    "parse_config",
]
