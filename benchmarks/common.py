"""Shared helpers of the benchmarks: run a config, summarise, print a table, write JSON."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run_cli(config: Path, *args: str, prefix: Sequence[str] = (), timeout: float = 600) -> dict:
    """Run ``python -m aiohal CONFIG ARGS`` (after ``prefix``, e.g. ``taskset -c 0``) in a fresh
    process and return its JSON report, with the process's ``exit_code`` added."""
    out = ROOT / ".bench-report.json"
    cmd = [*prefix, sys.executable, "-m", "aiohal", str(config), "--quiet", "--log-format", "json",
           "--report-json", str(out), *args]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    if not out.exists():
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    report = json.loads(out.read_text())
    out.unlink()
    report["exit_code"] = proc.returncode
    return report


def steal_seconds() -> float:
    """CPU seconds the hypervisor took from this VM so far, all CPUs together (/proc/stat "steal");
    divide a difference by the wall time and the CPU count for a share."""
    with open("/proc/stat") as f:
        return int(f.readline().split()[8]) / os.sysconf("SC_CLK_TCK")


class StealMeter:
    """The share of all CPUs the hypervisor took from this VM since the meter was made, in %."""

    def __init__(self) -> None:
        self.steal0, self.wall0 = steal_seconds(), time.monotonic()

    def percent(self) -> float:
        return 100 * (steal_seconds() - self.steal0) / (time.monotonic() - self.wall0) / os.cpu_count()


def machine() -> dict:
    cpu = ""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"python": platform.python_version(), "kernel": platform.release(), "cpu": cpu, "cores": os.cpu_count()}


def table(rows: list[dict], columns: list[tuple[str, str]]) -> str:
    head = "| " + " | ".join(title for _, title in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(str(row.get(key, "")) for key, _ in columns) + " |" for row in rows]
    return "\n".join([head, rule, *body])


def write_json(path: str | None, data: dict) -> None:
    if path:
        Path(path).write_text(json.dumps({"machine": machine(), **data}, indent=2) + "\n")
