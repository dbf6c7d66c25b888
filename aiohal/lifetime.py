"""Helper processes that end with the aiohal process that started them.

A simulator or a hand's peer left running after the robot process was killed keeps its ports,
its CPU and its real-time priority, and the next run finds them taken. The parent cannot
ensure its children's end when it is killed (SIGKILL runs none of its code), so each child
asks the kernel itself: ``PR_SET_PDEATHSIG`` sends it a signal when its parent ends.

The parent starts the child with :func:`child_env` (its own pid in ``AIOHAL_PARENT_PID``);
the child calls :func:`die_with_parent` first thing in its main. That is done in the child,
after its ``exec``, rather than in a ``preexec_fn`` (unsafe with threads) or a wrapper that
``exec``s the helper (the kernel clears the setting on ``exec`` of a binary with file
capabilities, as a Python given ``cap_sys_nice`` for real-time scheduling has). The parent may
end before the child asks, so the child then compares ``getppid()`` with the pid it was given.

Linux sends the signal when the *thread* that started the child ends: start helpers from the
thread that runs the loop (the drivers do, in ``open()``).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PARENT_ENV = "AIOHAL_PARENT_PID"
PR_SET_PDEATHSIG = 1  # linux/prctl.h


def child_env() -> dict[str, str]:
    """The environment for a helper process: this one's, and this process as its parent."""
    return {**os.environ, PARENT_ENV: str(os.getpid())}


def die_with_parent(sig: int = signal.SIGTERM) -> None:
    """Get ``sig`` when the parent ends; exit now if it has ended already. Does nothing in a
    process started without :func:`child_env` (by hand, from a shell) or off Linux."""
    expected = os.environ.pop(PARENT_ENV, None)  # popped: this process's own children are not ours
    if expected is None or not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"prctl(PR_SET_PDEATHSIG): {os.strerror(err)}")
    if os.getppid() != int(expected):  # the parent ended before the prctl: no signal will come
        sys.exit(f"the aiohal process {expected} that started this one is gone")
