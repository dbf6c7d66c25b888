"""``python -m aiohal``: run a robot from its TOML file, check a config, print the schema,
list plugins. The only place that configures logging (structlog over stdlib logging).

Exit status: 0 success, 1 a fault or a driver that would not start, 2 invalid configuration
or usage (nothing was started).
"""

from __future__ import annotations

import argparse
import asyncio
import difflib
import json
import logging
import math
import os
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from . import __version__, plugins
from .config import Config, describe_validation_error, json_schema, load_config
from .core.run_report import counted
from .errors import AiohalError, ConfigError, ConfigIssue
from .files import check_output_path
from .outside import cli_outputs, doorkeeper
from .safety import SafetyLevel

if TYPE_CHECKING:
    from structlog.typing import Processor

log = logging.getLogger("aiohal.cli")

SUBCOMMANDS = ("run", "check", "schema", "plugins", "info", "replay", "plot")
#: a second SIGINT/SIGTERM this soon after the first is its echo, not a person's second Ctrl-C:
#: GNU timeout and a terminal's job control signal both the process and its group at once
SIGNAL_ECHO_S = 0.05
#: what ``--help`` says of each command
COMMANDS_HELP = """commands:
  [run] CONFIG        run a robot (the default command; its options are above)
  check CONFIG        validate a config and exit: 0 ok, 2 not (nothing is started)
  schema              print the config's JSON Schema (for editors)
  plugins             list the drivers and controllers this installation has
  info RECORDING      a recorded run's summary: see python -m aiohal info --help
  replay RECORDING --config CONFIG
                      the config's controller on a recorded run, its commands compared
  plot RECORDING      PNG figures of a recorded run: see python -m aiohal plot --help
"""


def configure_logging(fmt: str = "auto", level: int = logging.INFO) -> None:
    """Render stdlib log records through structlog: console lines on a terminal, else JSON."""
    import structlog

    if fmt == "auto":
        fmt = "console" if sys.stderr.isatty() else "json"
    shared: list[Processor] = [
        structlog.stdlib.add_log_level,
        structlog.stdlib.add_logger_name,
        structlog.stdlib.ExtraAdder(),
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    renderer: Processor
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


#: after a second signal, how long the emergency-stopped drivers may take to close
FORCED_CLOSE_S = 0.05

#: the longest --duration (about 31 years); to run for ever, leave --duration out
MAX_DURATION_S = 1e9


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number of {what} (got {text})")
    return value


def _duration(text: str) -> float:
    value = _number(text, "seconds")
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be more than 0 s (got {text}); leave it out to run until stopped")
    if value > MAX_DURATION_S:
        raise argparse.ArgumentTypeError(
            f"must be at most {MAX_DURATION_S:g} s (got {text}); leave it out to run until stopped"
        )
    return value


def _rate(text: str) -> float:
    value = _number(text, "Hz")
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be more than 0 Hz (got {text})")
    return value


def _spin_guard(text: str) -> float:
    value = _number(text, "µs")
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more µs (got {text})")
    return value


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m aiohal",
        description="Run a robot from its TOML configuration.",
        epilog=COMMANDS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("config", type=Path, help="robot configuration (TOML)")
    p.add_argument("--duration", type=_duration, default=None, help="seconds to run (default: until Ctrl-C/SIGTERM)")
    p.add_argument("--rate", type=_rate, default=None, help="tick rate in Hz (overrides loop.rate_hz)")
    p.add_argument(
        "--clock",
        choices=("auto", "timerfd", "sleep", "virtual"),
        default=None,
        help="wake source (overrides loop.clock)",
    )
    p.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio", help="event loop implementation")
    p.add_argument(
        "--spin-guard-us",
        type=_spin_guard,
        default=None,
        metavar="US",
        help="precision mode: wake US early and spin to each deadline (overrides realtime.spin_guard_us)",
    )
    p.add_argument("--log-format", choices=("auto", "console", "json"), default="auto")
    p.add_argument("--report-json", type=Path, default=None, metavar="PATH", help="write the run report as JSON")
    p.add_argument(
        "--quiet", action="store_true", help="print only warnings and errors: no report, no progress, no live status"
    )
    cli_outputs.add_arguments(p)
    p.add_argument("--version", action="version", version=f"aiohal {__version__}")
    return p


def _override_error(exc: ValueError, section: str, option: str, config_path: Path) -> ConfigError:
    """A command-line override the config models refuse, named by its option."""
    if isinstance(exc, ValidationError):
        issues = [
            ConfigIssue(f"{option} ({section}." + ".".join(map(str, e["loc"])) + ")", describe_validation_error(e))
            for e in exc.errors()
        ]
    else:
        issues = [ConfigIssue(option, str(exc))]
    return ConfigError(issues, str(config_path))


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
            raise _override_error(exc, "realtime", "--spin-guard-us", args.config) from None
    if not changes:
        return config
    try:
        return config.with_loop(**changes)
    except ValueError as exc:
        option = "--rate" if args.rate is not None else "--clock"
        raise _override_error(exc, "loop", option, args.config) from None


def _loop_factory(name: str):
    if name == "uvloop":
        try:
            import uvloop
        except ImportError:
            raise AiohalError("--loop uvloop needs uvloop: pip install uvloop") from None
        return uvloop.new_event_loop
    return asyncio.new_event_loop


#: The operator's safety requests as signals (README, "Running a robot"): SIGQUIT (Ctrl-\\ on a
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


class _Outcome:
    """What cmd_run must know of how a run ended: whether to leave at once (an emergency stop
    by a second signal, or a driver abandoned in close(): its thread may never finish)."""

    def __init__(self) -> None:
        self.leave_now = False


async def _run(config: Config, args: argparse.Namespace, outcome: _Outcome) -> int:
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    stage = "starting"  # -> running -> closing -> reporting: what a second signal interrupts
    control = None
    early: list[signal.Signals] = []  # signals before the robot was built: nothing to stop yet
    first_stop: list[float] = []  # when the first stop signal was handled

    def on_signal(name: str) -> None:
        if control is None:
            early.append(signal.Signals[name])
            return
        if not control.stop_requested:
            log.info("%s received: stopping", name)
            control.request_stop(name)
            first_stop.append(time.monotonic())
            return
        if outcome.leave_now:
            return  # the emergency stop is done and reported once
        if first_stop and time.monotonic() - first_stop[0] < SIGNAL_ECHO_S:
            log.debug(
                "%s again within %g s: the same request (a signal sent to the process and its group)",
                name,
                SIGNAL_ECHO_S,
            )
            return
        # a second signal: stop the hardware now, abandon what is pending
        log.warning("%s received again: emergency stop", name)
        outcome.leave_now = True
        control.stop_reason = f"{name} received twice: emergency stop"
        control.estop()
        control.record_fault("signal", stage, f"{name} received twice: every driver emergency-stopped")
        if task is not None and stage != "reporting":
            task.cancel()

    # while the modules load, a plain handler notes a signal at once (the loop's would only
    # run at the next await, after the robot was built)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: early.append(signal.Signals(signum)))
    try:
        from .core.lifecycle import DriverStatus
        from .core.loop import ControlLoop
        from .core.run_report import format_report

        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, on_signal, sig.name)
        if early or (task is not None and task.cancelling()):  # Ctrl-C while starting: leave quietly
            log.info("interrupted while starting: nothing was started")
            return 128 + (early[0] if early else signal.SIGINT)
        control = ControlLoop(config)
        for sig in SAFETY_SIGNALS:
            loop.add_signal_handler(sig, on_safety_signal, control, sig)
        log.info(
            "starting robot %s: %d joints, %d driver(s), controller %s at %.0f Hz",
            config.robot.name,
            len(config.joints),
            len(config.drivers),
            config.controller.type,
            config.loop.rate_hz,
        )
        outputs = cli_outputs.RunOutputs(control.port, args)
        try:
            outputs.open_live()  # a port in use is refused here, before any driver opens
        except AiohalError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        try:
            await control.activate()
        except (AiohalError, asyncio.CancelledError) as exc:
            if isinstance(exc, asyncio.CancelledError):  # a second signal while a driver was still opening
                print("error: bring-up interrupted by a second signal; drivers emergency-stopped", file=sys.stderr)
            else:
                log.error("bring-up failed: %s", exc)
                print(f"error: {exc}", file=sys.stderr)
            outputs.close()
            # the report JSON is written whatever way the run ends: here, the faults of bring-up
            if args.report_json is not None:
                _write_report_json(control.report(), args, config)
            return 1
        outputs.start()
        log.info(
            "running%s; Ctrl-C or SIGTERM stops safely",
            f" for {args.duration:g} s" if args.duration is not None else "",
        )
        stage = "running"
        try:
            if not control.stop_requested:
                await control.run(args.duration)
        except asyncio.CancelledError:
            pass  # the second signal: recorded by its handler
        stage = "closing"
        try:
            if outcome.leave_now:  # emergency-stopped: a moment to close, no waiting for a close() that hangs
                await asyncio.wait_for(control.deactivate(), FORCED_CLOSE_S)
            else:
                await control.deactivate()
        except (asyncio.CancelledError, TimeoutError):
            control.record_fault("signal", "close", "drivers emergency-stopped, not all closed")
        stage = "reporting"
        outcome.leave_now |= any(slot.status == DriverStatus.ABANDONED for slot in control.slots)
        report = control.report()
        report.update(outputs.close())
        if not args.quiet:
            print(format_report(report), flush=True)
        status = 1 if control.faults or control.worst_level <= SafetyLevel.ESTOP else 0
        if args.report_json is not None and not _write_report_json(report, args, config):
            status = 1
        log.info("stopped: %s", control.stop_reason)
        return status
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM, *SAFETY_SIGNALS):
            loop.remove_signal_handler(sig)
        # a Ctrl-C after the run (a second one while the report prints or the process ends) asks
        # for what is done: the process ends with the run's status, not killed by the signal
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _write_report_json(report: dict[str, Any], args: argparse.Namespace, config: Config) -> bool:
    """Write ``--report-json``; False (said on stderr) if it could not be written."""
    from .core.run_report import write_json

    try:
        write_json(report, args.report_json, protect=(args.config, *config.named_files()))
    except (OSError, ValueError) as exc:  # the path changed during the run
        log.error("report not written: %s", exc)
        print(f"error: --report-json: report not written: {exc}", file=sys.stderr)
        return False
    return True


def cmd_run(argv: Sequence[str]) -> int:
    args = _parser().parse_args(argv)
    try:
        config = _apply_overrides(load_config(args.config), args)
        factory = _loop_factory(args.loop)
        cli_outputs.check(config, args)
        doorkeeper.check(config)
    except ConfigError as exc:
        _print_config_error(exc)
        return 2
    except AiohalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.report_json is not None:
        try:
            check_output_path(args.report_json, protect=(args.config, *config.named_files()))
        except ValueError as exc:
            print(f"error: --report-json: {exc}", file=sys.stderr)
            return 2
    configure_logging(args.log_format, logging.WARNING if args.quiet else logging.INFO)
    outcome = _Outcome()
    runner = asyncio.Runner(loop_factory=factory)
    try:
        status = runner.run(_run(config, args, outcome))
    finally:
        if outcome.leave_now:
            # an emergency stop or an abandoned close(): every driver is stopped and the report
            # is out; do not wait for threads that may never return (nor for a clean shutdown)
            logging.shutdown()
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(1)
        runner.close()
    return status


def cmd_check(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m aiohal check", description="Validate robot configurations.")
    p.add_argument("configs", type=Path, nargs="+")
    args = p.parse_args(argv)
    status = 0
    for path in args.configs:
        try:
            config = load_config(path)
            doorkeeper.check(config)  # what only a door's own library can read (a Zenoh config)
        except ConfigError as exc:
            _print_config_error(exc)
            status = 2
            continue
        except AiohalError as exc:
            print(f"{path}: error: {exc}", file=sys.stderr)
            status = 2
            continue
        drivers = ", ".join(f"{d.name} ({d.type}, {counted(len(d.joints), 'joint')})" for d in config.drivers)
        print(
            f"{path}: ok: robot {config.robot.name}, {counted(len(config.joints), 'joint')}, drivers: {drivers}, "
            f"controller {config.controller.type} at {config.loop.rate_hz:g} Hz"
        )
    return status


def cmd_schema(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m aiohal schema", description="Print the JSON Schema of robot configs.")
    p.parse_args(argv)
    print(json.dumps(json_schema(), indent=2, allow_nan=False))
    return 0


def cmd_plugins(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m aiohal plugins", description="List drivers and controllers.")
    p.parse_args(argv)
    tables = {
        kind: [(spec, "ok" if error is None else f"unavailable: {error}") for spec, error in plugins.describe(kind)]
        + [(spec, "ignored: a built-in has this name") for spec in plugins.shadowed(kind)]
        for kind in ("driver", "controller")
    }
    rows = [row for table in tables.values() for row in table]
    name_width = max(len(spec.name) for spec, _ in rows)
    source_width = max(len(spec.source) for spec, _ in rows)
    for kind, table in tables.items():
        print(f"{kind}s:")
        for spec, status in table:
            print(f"  {spec.name:<{name_width}}  {spec.source:<{source_width}}  {status}")
    return 0


def cmd_info(argv: Sequence[str]) -> int:
    from .record.reader import info_main

    return info_main(list(argv))


def cmd_replay(argv: Sequence[str]) -> int:
    from .record.replay import main as replay_main

    return replay_main(list(argv))


def cmd_plot(argv: Sequence[str]) -> int:
    from .record.plot import main as plot_main

    return plot_main(list(argv))


def _unknown_command(word: str) -> bool:
    """A first word that is no command, no option and no file, and does not look like a path:
    a mistyped command (``chek``), rather than a config that is missing."""
    return (
        word not in SUBCOMMANDS
        and not word.startswith("-")
        and not any(c in word for c in "./")
        and not Path(word).exists()
    )


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and _unknown_command(argv[0]):
        close = difflib.get_close_matches(argv[0], SUBCOMMANDS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        print(f"error: unknown command {argv[0]!r}{hint}, and no file of that name\n{COMMANDS_HELP}", file=sys.stderr)
        return 2
    command = argv[0] if argv and argv[0] in SUBCOMMANDS else "run"
    if argv and argv[0] in SUBCOMMANDS:
        argv = argv[1:]
    handler = {
        "run": cmd_run,
        "check": cmd_check,
        "schema": cmd_schema,
        "plugins": cmd_plugins,
        "info": cmd_info,
        "replay": cmd_replay,
        "plot": cmd_plot,
    }[command]
    try:
        return handler(argv)
    except KeyboardInterrupt:
        return 130
