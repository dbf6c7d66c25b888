"""What ``python -m aiohal`` runs beside the loop and keeps after it, besides the report: the
recording (``--record``, ``[record]``), the live Foxglove server (``--foxglove``) and the
terminal status.

The CLI calls :func:`add_arguments`, :func:`check` before anything starts, and
:class:`RunOutputs` around the run. The tick writes the loop's tick ring (:mod:`.tick_ring`);
the recording, the live view and the panel each run in a process of their own that reads it
(:mod:`.recorder`, :mod:`.recorder_writer`, :mod:`.foxglove_server`, :mod:`.terminal_status`).
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import AiohalError, MissingDependencyError
from ..files import check_output_path
from .output_process import OutputRefused
from .port import LoopPort
from .recorder_file import is_bag_path

if TYPE_CHECKING:
    from ..config import Config
    from .recorder import Recorder
    from .terminal_status import StatusPanel

log = logging.getLogger(__name__)

FOXGLOVE_PORT = 8765


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="PATH",
        help="record every tick to this MCAP file, or to this new rosbag2 directory when PATH does not "
        "end in .mcap (overrides [record] path)",
    )
    parser.add_argument(
        "--foxglove",
        type=int,
        nargs="?",
        const=FOXGLOVE_PORT,
        default=None,
        metavar="PORT",
        help=f"serve the run live to Foxglove on localhost:PORT (default {FOXGLOVE_PORT})",
    )
    parser.add_argument(
        "--no-panel",
        action="store_true",
        help="no live status panel on the terminal (the report and the log stay); the report says what the panel cost",
    )


def record_path(config: Config, args: argparse.Namespace) -> Path | None:
    return args.record if args.record is not None else config.record.path


def check(config: Config, args: argparse.Namespace) -> None:
    """Refuse what cannot work before anything starts (the CLI exits 2)."""
    path = record_path(config, args)
    if path is not None:
        try:  # the same rule as the report: only ever replace a regular file, never the config
            protect = (args.config, *config.named_files())
            if is_bag_path(path):
                check_new_directory(path, protect)
            else:
                check_output_path(path, protect=protect)
        except ValueError as exc:
            raise AiohalError(f"--record {path}: {exc}") from None
    if (path is not None or args.foxglove is not None) and not all(
        importlib.util.find_spec(m) for m in ("mcap", "rosbags")
    ):
        raise MissingDependencyError("recording needs mcap and rosbags: pip install 'aiohal[record]'")
    if args.foxglove is not None:
        if not 0 <= args.foxglove <= 65535:
            raise AiohalError(f"--foxglove {args.foxglove}: a port is 0..65535")
        if importlib.util.find_spec("foxglove") is None:
            raise MissingDependencyError("--foxglove needs foxglove-sdk: pip install 'aiohal[foxglove]'")


def check_new_directory(path: Path, protect: tuple[Path, ...]) -> None:
    """A rosbag2 directory is made new: ValueError when something is there (saying so first
    of the config and the files it names) or its parent is not."""
    if os.path.lexists(path):
        if not path.is_dir():
            check_output_path(path, protect=protect)
        raise ValueError(f"{path} exists; a rosbag2 recording makes a new directory (or name a .mcap file)")
    if not path.parent.is_dir():
        raise ValueError(f"the directory {path.parent} does not exist")


class RunOutputs:
    """Made before the robot starts (the live view's port is taken then), started once it is
    active, closed after it is deactivated. Every output reads the loop's tick ring
    (:mod:`.tick_door`) from a process of its own; the tick's part is the ring's publisher."""

    def __init__(self, port: LoopPort, args: argparse.Namespace) -> None:
        self.port = port
        self.path = record_path(port.config, args)
        self.options = port.config.record
        self.foxglove_port: int | None = args.foxglove
        self.show_status = not args.quiet and not args.no_panel and sys.stdout.isatty()
        self.recorder: Recorder | None = None
        self.live: Recorder | None = None
        self.status: StatusPanel | None = None
        self.panel_cost: dict[str, Any] | None = None

    def open_live(self) -> None:
        """Start the live view's process (before the robot starts: a port in use stops nothing)."""
        if self.foxglove_port is not None and self.live is None:
            from .recorder import Recorder

            live = Recorder(self.port, None, self.options, live_port=self.foxglove_port)
            try:
                live.start_process()
            except OutputRefused as exc:
                live.close()
                raise AiohalError(exc.reason) from None
            self.live = live
            log.info("live view: Foxglove on ws://127.0.0.1:%d", live.live_port)

    def start(self) -> None:
        self.open_live()
        port = self.port
        if self.path is not None:
            from .recorder import Recorder

            self.recorder = Recorder(port, self.path, self.options)
            self.recorder.attach()
            log.info("recording to %s", self.path)
        if self.live is not None:
            self.live.attach()
        if self.show_status:
            from .terminal_status import StatusPanel

            self.status = StatusPanel(port, self.options.buffer_ticks, health_hz=self.options.health_hz)
            try:
                self.status.start()
            except (OutputRefused, OSError) as exc:
                log.warning("no status panel: %s", exc)
                self.status.stop()
                self.status = None

    def stop_status(self) -> None:
        if self.status is not None:
            self.status.stop()
            self.panel_cost = self.status.cost()
            self.status = None

    def close(self) -> dict[str, Any]:
        """Everything stopped and written; the recording's figures for the report."""
        self.stop_status()
        out: dict[str, Any] = {}
        if self.panel_cost is not None:
            out["status_panel"] = self.panel_cost
        if self.recorder is not None:
            out["record"] = self.recorder.close()
            self.recorder = None
        if self.live is not None:
            live = self.live.close()
            self.live = None
            if live.get("error"):
                out["live_view"] = live
        return out
