"""Shared helpers of the benchmarks: run a config, summarise, print a table, write JSON."""

from __future__ import annotations

import json
import platform
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run_cli(config: Path, *args: str, timeout: float = 600) -> dict:
    """Run ``python -m aiohal CONFIG ARGS`` in a fresh process and return its JSON report."""
    out = ROOT / ".bench-report.json"
    cmd = [sys.executable, "-m", "aiohal", str(config), "--quiet", "--log-format", "json", "--report-json", str(out), *args]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    if not out.exists():
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    report = json.loads(out.read_text())
    out.unlink()
    return report


def steal_seconds() -> float:
    """CPU seconds the hypervisor took from this VM so far, all CPUs together (/proc/stat "steal");
    divide a difference by the wall time and the CPU count for a share."""
    with open("/proc/stat") as f:
        return int(f.readline().split()[8]) / __import__("os").sysconf("SC_CLK_TCK")


def machine() -> dict:
    cpu = ""
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"python": platform.python_version(), "kernel": platform.release(), "cpu": cpu, "cores": __import__("os").cpu_count()}


def table(rows: list[dict], columns: list[tuple[str, str]]) -> str:
    head = "| " + " | ".join(title for _, title in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(str(row.get(key, "")) for key, _ in columns) + " |" for row in rows]
    return "\n".join([head, rule, *body])


def write_json(path: str | None, data: dict) -> None:
    if path:
        Path(path).write_text(json.dumps({"machine": machine(), **data}, indent=2) + "\n")
