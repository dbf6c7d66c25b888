"""``python -m aiohal``: run a robot from its TOML file, check a config, print the schema,
list plugins. The only place that configures logging (structlog over stdlib logging).

Exit status: 0 success, 1 a fault or a driver that would not start, 2 invalid configuration
or usage (nothing was started).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from pydantic import ValidationError

from . import __version__, plugins
from .config import Config, describe_validation_error, json_schema, load_config
from .errors import AiohalError, ConfigError, ConfigIssue

log = logging.getLogger("aiohal.cli")

SUBCOMMANDS = ("run", "check", "schema", "plugins")


def configure_logging(fmt: str = "auto", level: int = logging.INFO) -> None:
    """Render stdlib log records through structlog: console lines on a terminal, else JSON."""
    import structlog

    if fmt == "auto":
        fmt = "console" if sys.stderr.isatty() else "json"
    shared = [
        structlog.stdlib.add_log_level,
        structlog.stdlib.add_logger_name,
        structlog.stdlib.ExtraAdder(),
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    if fmt == "json":
        renderer = structlog.processors.JSONRenderer()
        shared.append(structlog.processors.format_exc_info)
    else:
        renderer = structlog.dev.ConsoleRenderer(colors=sys.stderr.isatty())
    formatter = structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=shared,
        processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, renderer],
    )
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(formatter)
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    structlog.configure(
        processors=[*shared, structlog.stdlib.ProcessorFormatter.wrap_for_formatter],
        logger_factory=structlog.stdlib.LoggerFactory(),
        wrapper_class=structlog.stdlib.BoundLogger,
        cache_logger_on_first_use=True,
    )


def _print_config_error(exc: ConfigError) -> None:
    where = f"{exc.source}: " if exc.source else ""
    print(f"{where}invalid configuration ({len(exc.issues)} error(s)):", file=sys.stderr)
    for issue in exc.issues:
        print(f"  {issue}", file=sys.stderr)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m aiohal",
        description="Run a robot from its TOML configuration. Other commands: "
        "check CONFIG, schema, plugins.",
    )
    p.add_argument("config", type=Path, help="robot configuration (TOML)")
    p.add_argument("--duration", type=float, default=None, help="seconds to run (default: until Ctrl-C/SIGTERM)")
    p.add_argument("--rate", type=float, default=None, help="tick rate in Hz (overrides loop.rate_hz)")
    p.add_argument("--clock", choices=("auto", "timerfd", "sleep", "virtual"), default=None,
                   help="wake source (overrides loop.clock)")
    p.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio", help="event loop implementation")
    p.add_argument("--spin-guard-us", type=float, default=None, metavar="US",
                   help="precision mode: wake US early and spin to each deadline (overrides realtime.spin_guard_us)")
    p.add_argument("--log-format", choices=("auto", "console", "json"), default="auto")
    p.add_argument("--report-json", type=Path, default=None, metavar="PATH", help="write the run report as JSON")
    p.add_argument("--quiet", action="store_true", help="do not print the report")
    p.add_argument("--version", action="version", version=f"aiohal {__version__}")
    return p


def _apply_overrides(config: Config, args: argparse.Namespace) -> Config:
    changes = {}
    if args.rate is not None:
        changes["rate_hz"] = args.rate
    if args.clock is not None:
        changes["clock"] = args.clock
    if args.spin_guard_us is not None:
        try:
            config = config.with_realtime(spin_guard_us=args.spin_guard_us)
        except ValueError as exc:  # pydantic's ValidationError is a ValueError too
            raise ConfigError([ConfigIssue("realtime.spin_guard_us (command line)", str(exc).splitlines()[0])],
                              str(args.config)) from None
    if not changes:
        return config
    try:
        return config.with_loop(**changes)
    except ValidationError as exc:
        issues = [
            ConfigIssue("loop." + ".".join(map(str, e["loc"])) + " (command line)", describe_validation_error(e))
            for e in exc.errors()
        ]
        raise ConfigError(issues, str(args.config)) from None
    except ValueError as exc:
        raise ConfigError([ConfigIssue("loop.rate_hz (command line)", str(exc))], str(args.config)) from None


def _loop_factory(name: str):
    if name == "uvloop":
        try:
            import uvloop
        except ImportError:
            raise AiohalError("--loop uvloop needs uvloop: pip install uvloop") from None
        return uvloop.new_event_loop
    return asyncio.new_event_loop


#: The operator's safety requests as signals (README, "Running a robot"): SIGQUIT (Ctrl-\ on a
#: terminal) emergency-stops, SIGUSR1 holds, SIGUSR2 resets the faults and re-arms.
SAFETY_SIGNALS = {signal.SIGQUIT: "estop", signal.SIGUSR1: "hold", signal.SIGUSR2: "reset_faults+rearm"}


def on_safety_signal(control, sig: signal.Signals) -> None:
    """Run the request between two ticks; a refused one is logged with its reason."""
    from .safety import SafetyRequestRefused

    request = SAFETY_SIGNALS[sig]
    log.warning("%s received: %s", sig.name, request)
    try:
        if request == "estop":
            control.estop(f"{sig.name} received")
        elif request == "hold":
            control.hold(f"{sig.name} received")
        else:
            control.reset_faults()
            control.rearm()
    except SafetyRequestRefused as exc:
        log.error("%s: %s", sig.name, exc)


async def _run(config: Config, args: argparse.Namespace) -> int:
    from .loop import ControlLoop
    from .report import format_report, write_json

    control = ControlLoop(config)
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()

    def on_signal(name: str) -> None:
        if not control.stop_requested:
            log.info("%s received: stopping", name)
            control.request_stop(name)
        else:  # a second signal: stop the hardware now, abandon what is pending
            log.warning("%s received again: emergency stop", name)
            control.estop()
            if task is not None:
                task.cancel()

    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, on_signal, sig.name)
    for sig in SAFETY_SIGNALS:
        loop.add_signal_handler(sig, on_safety_signal, control, sig)

    log.info("starting robot %s: %d joints, %d driver(s), controller %s at %.0f Hz",
             config.robot.name, len(config.joints), len(config.drivers), config.controller.type, config.loop.rate_hz)
    try:
        await control.activate()
    except AiohalError as exc:
        log.error("bring-up failed: %s", exc)
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except asyncio.CancelledError:  # a second signal while a driver was still opening
        control.estop()
        print("error: bring-up interrupted by a second signal; drivers emergency-stopped", file=sys.stderr)
        return 1
    log.info("running%s; Ctrl-C or SIGTERM stops safely",
             f" for {args.duration:g} s" if args.duration is not None else "")
    try:
        if not control.stop_requested:
            await control.run(args.duration)
    except asyncio.CancelledError:
        control.stop_reason = "forced by a second signal"
        control.record_fault("runtime", "run", "forced by a second signal: drivers emergency-stopped")
    try:
        await control.deactivate()
    except asyncio.CancelledError:
        control.record_fault("runtime", "close", "forced by a second signal: drivers emergency-stopped, not all closed")
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM, *SAFETY_SIGNALS):
            loop.remove_signal_handler(sig)
    report = control.report()
    if not args.quiet:
        print(format_report(report), flush=True)
    if args.report_json is not None:
        write_json(report, args.report_json)
    log.info("stopped: %s", control.stop_reason)
    return 1 if control.faults else 0


def cmd_run(argv: Sequence[str]) -> int:
    args = _parser().parse_args(argv)
    try:
        config = _apply_overrides(load_config(args.config), args)
        factory = _loop_factory(args.loop)
    except ConfigError as exc:
        _print_config_error(exc)
        return 2
    except AiohalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    configure_logging(args.log_format)
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(_run(config, args))


def cmd_check(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m aiohal check", description="Validate robot configurations.")
    p.add_argument("configs", type=Path, nargs="+")
    args = p.parse_args(argv)
    status = 0
    for path in args.configs:
        try:
            config = load_config(path)
        except ConfigError as exc:
            _print_config_error(exc)
            status = 2
            continue
        drivers = ", ".join(f"{d.name} ({d.type}, {len(d.joints)} joints)" for d in config.drivers)
        print(f"{path}: ok: robot {config.robot.name}, {len(config.joints)} joints, drivers: {drivers}, "
              f"controller {config.controller.type} at {config.loop.rate_hz:g} Hz")
    return status


def cmd_schema(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m aiohal schema", description="Print the JSON Schema of robot configs.")
    p.parse_args(argv)
    print(json.dumps(json_schema(), indent=2, allow_nan=False))
    return 0


def cmd_plugins(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m aiohal plugins", description="List drivers and controllers.")
    p.parse_args(argv)
    for kind in ("driver", "controller"):
        print(f"{kind}s:")
        for spec, error in plugins.describe(kind):
            status = "ok" if error is None else f"unavailable: {error}"
            print(f"  {spec.name:<12} {spec.source:<28} {status}")
        for spec in plugins.shadowed(kind):
            print(f"  {spec.name:<12} {spec.source:<28} ignored: a built-in has this name")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv and argv[0] in SUBCOMMANDS else "run"
    if argv and argv[0] in SUBCOMMANDS:
        argv = argv[1:]
    handler = {"run": cmd_run, "check": cmd_check, "schema": cmd_schema, "plugins": cmd_plugins}[command]
    try:
        return handler(argv)
    except KeyboardInterrupt:
        return 130
