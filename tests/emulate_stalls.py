"""Run a command while emulating the stalls of a shared VM: every process of the command's
tree is stopped (SIGSTOP) for up to ``--max-stall`` seconds, at random intervals, then
continued. CI's machine stalls like this (steal, up to 1.3 s seen); a test that fails under it
would fail there some day. Only the command's own processes are ever signalled.

    python tests/emulate_stalls.py [--max-stall 0.8] [--seed 1] [--seconds 1800] -- COMMAND...

e.g. ``CI=true python tests/emulate_stalls.py --max-stall 1.5 -- .venv/bin/python -m pytest -q
tests/test_ethercat_driver.py`` (as root for the EtherCAT tests). One caveat: continuing the
tree also continues a process a test stopped on purpose (tests/test_pipe.py has one).
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import time


def process_tree(pid: int) -> list[int]:
    """``pid`` and every descendant (via /proc/PID/task/TID/children)."""
    found, todo = [], [pid]
    while todo:
        p = todo.pop()
        found.append(p)
        try:
            tasks = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for task in tasks:
            try:
                with open(f"/proc/{p}/task/{task}/children") as f:
                    todo.extend(int(child) for child in f.read().split())
            except OSError:
                pass
    return found


def _signal_all(pids: list[int], sig: int) -> None:
    for pid in pids:
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--max-stall", type=float, default=0.8, help="longest stall, s (each is uniform in 0.01..this)")
    p.add_argument("--min-gap", type=float, default=0.3, help="shortest time between stalls, s")
    p.add_argument("--max-gap", type=float, default=2.0, help="longest time between stalls, s")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--seconds", type=float, default=1800.0, help="stop stalling (and wait) after this long")
    p.add_argument("command", nargs=argparse.REMAINDER)
    args = p.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        p.error("no command given (after --)")
    rng = random.Random(args.seed)
    proc = subprocess.Popen(command)
    stalls, longest, end = 0, 0.0, time.monotonic() + args.seconds
    try:
        while proc.poll() is None and time.monotonic() < end:
            time.sleep(rng.uniform(args.min_gap, args.max_gap))
            if proc.poll() is not None:
                break
            pids = process_tree(proc.pid)
            stall = rng.uniform(0.01, args.max_stall)
            _signal_all(pids, signal.SIGSTOP)
            try:
                time.sleep(stall)
            finally:
                _signal_all(pids, signal.SIGCONT)
            stalls, longest = stalls + 1, max(longest, stall)
        code = proc.wait()
    except KeyboardInterrupt:
        _signal_all(process_tree(proc.pid), signal.SIGCONT)
        proc.terminate()
        code = proc.wait()
    print(f"emulate_stalls: {stalls} stalls, the longest {longest:.2f} s; exit {code}", file=sys.stderr)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
