"""Exceptions: each inherits the package base and the matching builtin, so callers can catch either."""

from __future__ import annotations

from dataclasses import dataclass


class AiohalError(Exception):
    """Base of every error aiohal raises on purpose."""


@dataclass(frozen=True)
class ConfigIssue:
    """One problem in a configuration, located by its key path (e.g. ``driver[1].joints``)."""

    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message


class ConfigError(AiohalError, ValueError):
    """An invalid configuration. Carries every issue found, not just the first."""

    def __init__(self, issues: list[ConfigIssue], source: str | None = None) -> None:
        self.issues = list(issues)
        self.source = source
        head = f"{source}: " if source else ""
        lines = "\n".join(f"  {issue}" for issue in self.issues)
        super().__init__(f"{head}{len(self.issues)} configuration error(s)\n{lines}")


class PluginError(AiohalError, LookupError):
    """A driver or controller that cannot be found or loaded."""


class MissingDependencyError(PluginError, ImportError):
    """A plugin whose optional dependency is not installed; names the extra to install."""


class DriverError(AiohalError, RuntimeError):
    """A driver failed; ``driver`` names it, ``phase`` says where (open, read, write, close)."""

    def __init__(self, driver: str, phase: str, reason: str) -> None:
        self.driver = driver
        self.phase = phase
        self.reason = reason
        super().__init__(f"driver {driver!r} failed in {phase}: {reason}")


class ControllerError(AiohalError, RuntimeError):
    """A controller could not be configured or started."""

    def __init__(self, controller: str, phase: str, reason: str) -> None:
        self.controller = controller
        self.phase = phase
        self.reason = reason
        super().__init__(f"controller {controller!r} failed in {phase}: {reason}")


class LifecycleError(AiohalError, RuntimeError):
    """A lifecycle method was called in a state that does not allow it."""
