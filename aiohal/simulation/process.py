"""A simulated bus (joint boards, a KUKA controller) as a subprocess a driver starts itself,
so that a demo config is one command: the simulator prints one JSON line on stdout once it is
listening (its ports), and one on stderr when it stops (its counters). The simulator ends with
the process that started it, however that one ends (:mod:`aiohal.lifetime`)."""

from __future__ import annotations

import asyncio
import json
from typing import Any, cast

from ..lifetime import child_env


class SimulatorStartError(RuntimeError):
    """The simulator exited or said nothing usable before the timeout."""


async def start(args: list[str], timeout_s: float) -> tuple[asyncio.subprocess.Process, dict[str, Any]]:
    """Start ``args``; the process and the JSON object of its first stdout line."""
    process = await asyncio.create_subprocess_exec(
        *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=child_env()
    )
    try:
        stdout = cast(asyncio.StreamReader, process.stdout)  # stdout=PIPE
        line = await asyncio.wait_for(stdout.readline(), timeout_s)
        return process, json.loads(line)
    except (TimeoutError, ValueError) as exc:
        process.kill()
        _out, err = await process.communicate()
        raise SimulatorStartError(f"{exc!r}: {err.decode(errors='replace')[-500:]}") from exc


async def stop(process: asyncio.subprocess.Process, key: str, timeout_s: float = 2.0) -> dict[str, Any] | None:
    """Terminate it; the last JSON object on its stderr that has ``key``, if any."""
    if process.returncode is not None:
        return None
    process.terminate()
    try:
        _out, err = await asyncio.wait_for(process.communicate(), timeout_s)
    except TimeoutError:
        process.kill()
        await process.wait()
        return None
    found = None
    for line in err.decode(errors="replace").splitlines():
        if line.startswith("{") and f'"{key}"' in line:
            try:
                found = json.loads(line)
            except ValueError:
                continue
    return found
