"""Start a simulated segment behind a fresh veth pair, for tests and benchmarks (needs root).

    with SimulatedSegment(slaves="drive*7,imu,ft") as sim:
        master = pysoem.Master()
        master.open(sim.ifname)          # the master end of the veth pair, in this namespace
        ...
        sim.control({"cmd": "drive_fault", "slave": 0, "code": 0x2310})

What it does:

1. ``unshare --net -- python -m aiohal.drivers.ethercat.sim --ifname <slave end> ...``: the
   simulator runs in a network namespace of its own and prints ``waiting ... pid=N``;
2. ``ip link add <master end> type veth peer name <slave end>`` in the caller's namespace, then
   ``ip link set <slave end> netns N``; IPv6 is disabled on the master end (no autoconf noise)
   and it is brought up; the simulator brings its end up, binds and prints ``ready``;
3. on exit the simulator is terminated: its namespace goes away and takes the veth pair with it.
   The master end is deleted explicitly if it is still there (e.g. the simulator died before
   the move).

Names: ``ah<pid % 10000><n>m`` / ``...s`` (at most 15 characters). Only these interfaces are
ever created, opened or deleted.
"""

from __future__ import annotations

import itertools
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from typing import Any

_counter = itertools.count()


class SimulatorUnavailable(RuntimeError):
    """The fixture cannot run here (not root, ``ip`` or ``unshare`` missing)."""


class SimulatorError(RuntimeError):
    """The simulator did not start or answer."""


def check_environment() -> None:
    """Raise :class:`SimulatorUnavailable` with the reason when the fixture cannot work."""
    if os.geteuid() != 0:
        raise SimulatorUnavailable("the simulated segment needs root (veth pairs, network namespaces)")
    missing = [tool for tool in ("ip", "unshare") if shutil.which(tool) is None]
    if missing:
        raise SimulatorUnavailable(f"missing tool(s): {', '.join(missing)} (iproute2, util-linux)")


def _exists(ifname: str) -> bool:
    try:
        socket.if_nametoindex(ifname)
        return True
    except OSError:
        return False


def _ip(*args: str) -> None:
    res = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10, check=False)
    if res.returncode:
        raise SimulatorError(f"ip {' '.join(args)}: {res.stderr.strip()}")


class SimulatedSegment:
    """Context manager running ``python -m aiohal.drivers.ethercat.sim`` in its own network
    namespace behind a veth pair. ``ifname`` is the master end (open it with pysoem)."""

    def __init__(
        self,
        slaves: str = "drive",
        *,
        watchdog_ms: float = 100.0,
        seed: int = 0,
        inject: list[dict[str, Any]] | None = None,
        extra_args: list[str] | None = None,
        start_timeout_s: float = 15.0,
        python: str | None = None,
    ) -> None:
        self.slaves = slaves
        self.watchdog_ms = watchdog_ms
        self.seed = seed
        self.inject = list(inject or [])
        self.extra_args = list(extra_args or [])
        self.start_timeout_s = start_timeout_s
        self.python = python or sys.executable
        self.ifname = ""
        self.peer = ""
        self.proc: subprocess.Popen[str] | None = None
        self.pid = 0
        self._dir: str | None = None
        self.control_path = ""
        self._stderr_path = ""
        self.stderr_text = ""  # what the simulator wrote to stderr (kept after stop())

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> SimulatedSegment:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _names(self) -> tuple[str, str]:
        for _ in range(1000):
            tag = f"ah{os.getpid() % 10000}{next(_counter)}"
            if len(tag) > 14:
                tag = tag[:14]
            m, s = tag + "m", tag + "s"
            if not _exists(m) and not _exists(s):
                return m, s
        raise SimulatorError("no free veth name")

    def start(self) -> None:
        check_environment()
        self._dir = tempfile.mkdtemp(prefix="aiohal-ecsim-")
        self.control_path = os.path.join(self._dir, "control.sock")
        self._stderr_path = os.path.join(self._dir, "stderr.txt")
        self.ifname, self.peer = self._names()
        cmd = [
            "unshare",
            "--net",
            "--",
            self.python,
            "-m",
            "aiohal.drivers.ethercat.sim",
            "--ifname",
            self.peer,
            "--slaves",
            self.slaves,
            "--control",
            self.control_path,
            "--watchdog-ms",
            str(self.watchdog_ms),
            "--seed",
            str(self.seed),
            "--wait-s",
            str(self.start_timeout_s),
            "--exit-with-parent",
        ]
        for c in self.inject:
            cmd += ["--inject", json.dumps(c)]
        cmd += self.extra_args
        deadline = time.monotonic() + self.start_timeout_s
        try:
            with open(self._stderr_path, "w") as err:
                self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, bufsize=1)
            line = self._line(deadline)
            if not line.startswith("waiting "):
                raise SimulatorError(f"unexpected first line {line!r}")
            self.pid = self.proc.pid
            if f"pid={self.pid}" not in line:
                raise SimulatorError(f"simulator pid mismatch: {line!r} vs {self.pid}")
            _ip("link", "add", self.ifname, "type", "veth", "peer", "name", self.peer)
            _ip("link", "set", self.peer, "netns", str(self.pid))
            try:
                with open(f"/proc/sys/net/ipv6/conf/{self.ifname}/disable_ipv6", "w") as f:
                    f.write("1")
            except OSError:
                pass
            _ip("link", "set", self.ifname, "up")
            line = self._line(deadline)
            if line != "ready":
                raise SimulatorError(f"expected 'ready', got {line!r}")
        except BaseException:
            self.stop()
            raise

    def _line(self, deadline: float) -> str:
        assert self.proc is not None and self.proc.stdout is not None
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise SimulatorError(f"simulator did not start in time{self._stderr_tail()}")
            ready, _, _ = select.select([self.proc.stdout], [], [], left)
            if ready:
                line = self.proc.stdout.readline()
                if not line:
                    raise SimulatorError(f"simulator exited (rc={self.proc.wait(2)}){self._stderr_tail()}")
                return line.strip()

    def _stderr_tail(self) -> str:
        try:
            with open(self._stderr_path) as f:
                text = f.read()[-2000:].strip()
        except OSError:
            return ""
        return f": {text}" if text else ""

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is not None:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(3)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(3)
            if proc.stdout is not None:
                proc.stdout.close()
        # the namespace is gone with the process, and the veth pair with it; wait (bounded)
        if self.ifname:
            deadline = time.monotonic() + 3.0
            while _exists(self.ifname) and time.monotonic() < deadline:
                time.sleep(0.01)
            if _exists(self.ifname):
                subprocess.run(["ip", "link", "del", self.ifname], capture_output=True, timeout=10, check=False)
        if self._dir is not None:
            try:
                with open(self._stderr_path) as f:
                    self.stderr_text = f.read()
            except OSError:
                pass
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    # ------------------------------------------------------------------ control
    def control(self, command: dict[str, Any], timeout_s: float = 5.0) -> dict[str, Any]:
        """Send one control command (see :mod:`aiohal.drivers.ethercat.sim.control`); returns
        the answer. Raises SimulatorError when the answer is ``"ok": false``."""
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(timeout_s)
            s.connect(self.control_path)
            s.sendall((json.dumps(command) + "\n").encode())
            data = b""
            while not data.endswith(b"\n"):
                chunk = s.recv(65536)
                if not chunk:
                    break
                data += chunk
        answer = json.loads(data)
        if not answer.get("ok"):
            raise SimulatorError(f"control {command}: {answer.get('error')}")
        return answer

    def status(self) -> dict[str, Any]:
        return self.control({"cmd": "status"})
