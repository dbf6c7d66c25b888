"""aiohal: a robot hardware abstraction layer on asyncio.

One HAL protocol between controllers and hardware (drivers chosen by configuration), a
control loop that ticks at 1-2 kHz on absolute deadlines, and simulated drivers for CI.
"""

from .config import Config, load_config, parse_config
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
from .hal import Controller, Driver, Options
from .loop import ControlLoop
from .robot import Mode, Robot
from .safety import SafetyLevel

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
    "LifecycleError",
    "MissingDependencyError",
    "Mode",
    "Options",
    "PluginError",
    "Robot",
    "SafetyLevel",
    "__version__",
    "load_config",
    "parse_config",
]
