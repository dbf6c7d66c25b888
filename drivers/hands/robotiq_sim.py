"""A simulated Robotiq 2F-85 behind a pymodbus server: tests and demos without the gripper.

The gripper's state is computed from the clock whenever its registers are accessed: motion
at a constant rate is integrated exactly over whatever time has passed, so no periodic task
is needed and a test can drive the simulation with its own clock.

Run it by hand::

    python -m aiohal.drivers.hands.robotiq_sim --host 127.0.0.1 --port 5020 --object 0.6
"""

from __future__ import annotations

import argparse
import asyncio
import math
import multiprocessing
import sys
import threading
import time
from collections.abc import Callable
from typing import Self, cast

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from .robotiq import (
    ACTIVATE,
    COMMAND_ADDRESS,
    FRAMERS,
    GFLT_ACTION_DELAYED,
    GFLT_NOT_ACTIVATED,
    GO_TO,
    GOBJ_AT_REQUEST,
    GOBJ_CONTACT_CLOSING,
    GSTA_ACTIVATED,
    REGISTER_COUNT,
    STATUS_ADDRESS,
)

GSTA_RESET = 0
GSTA_ACTIVATING = 1
GOBJ_MOVING = 0

FULL_STROKE_S = 0.7  # open to closed at full speed
MIN_SPEED_FRACTION = 1 / 6  # the slowest speed, as a fraction of the fastest
MAX_CURRENT = 60  # gCU (x10 mA) when holding an object at full force
MOVING_CURRENT = 5  # gCU while moving freely

STOP_TIMEOUT_S = 2.0


class SimulatedGripper:
    """The 2F-85's behaviour behind its registers. Thread-safe: the server's event loop and a
    test thread may both use it.

    Positions are in gripper units (0 open .. 255 closed) inside, 0..1 in the public setters.
    Not simulated: finger motion during activation, contact while opening (gOBJ=1), automatic
    release, kFLT.
    """

    def __init__(
        self,
        *,
        activation_time_s: float = 0.3,
        object_position: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.activation_time_s = activation_time_s
        self._clock = clock
        self._lock = threading.Lock()
        self._request = [0] * REGISTER_COUNT
        self._gsta = GSTA_RESET
        self._activated_at = 0.0
        self._position = 0.0
        self._object = _units(object_position)
        self._gflt = 0
        self._last = clock()

    # -- from the Modbus side --------------------------------------------------------------

    def write_command(self, offset: int, values: list[int]) -> None:
        """Registers written from ``COMMAND_ADDRESS + offset``: act on the new request now."""
        with self._lock:
            now = self._advance()
            was_active = self._request[0] >> 8 & ACTIVATE
            self._request[offset : offset + len(values)] = values
            action = self._request[0] >> 8
            if not action & ACTIVATE:
                self._gsta, self._gflt = GSTA_RESET, 0
            elif not was_active:
                self._gsta, self._activated_at = GSTA_ACTIVATING, now + self.activation_time_s
            if action & GO_TO:
                if not action & ACTIVATE:
                    self._gflt = GFLT_NOT_ACTIVATED
                elif self._gsta == GSTA_ACTIVATING:
                    self._gflt = GFLT_ACTION_DELAYED  # the motion starts once activated
                elif self._gflt == GFLT_NOT_ACTIVATED:
                    self._gflt = 0

    def status_registers(self) -> list[int]:
        """The three status registers as of now."""
        with self._lock:
            self._advance()
            action = self._request[0] >> 8
            gobj = self._object_status()
            gripper = action & ACTIVATE | action & GO_TO | self._gsta << 4 | gobj << 6
            if gobj == GOBJ_CONTACT_CLOSING:
                current = round(self._force() / 255 * MAX_CURRENT)
            elif self._moving() and gobj == GOBJ_MOVING:
                current = MOVING_CURRENT
            else:
                current = 0
            return [gripper << 8, self._gflt << 8 | self._target(), round(self._position) << 8 | current]

    # -- for tests and demos ---------------------------------------------------------------

    def inject_fault(self, gflt: int) -> None:
        """Raise gripper fault ``gflt`` (1..15): the fingers stop until it is cleared."""
        if not 0 < gflt <= 0xF:
            raise ValueError(f"gFLT is 1..15, not {gflt}")
        with self._lock:
            self._advance()
            self._gflt = gflt

    def clear_fault(self) -> None:
        """Clear the fault; a go-to still requested resumes."""
        with self._lock:
            self._advance()
            self._gflt = 0

    def set_object(self, position: float | None) -> None:
        """Put an object where closing fingers meet it (0 open .. 1 closed), or remove it."""
        with self._lock:
            self._advance()
            self._object = _units(position)

    @property
    def position(self) -> float:
        with self._lock:
            self._advance()
            return self._position / 255

    @property
    def fault(self) -> int:
        with self._lock:
            self._advance()
            return self._gflt

    # -- the model -------------------------------------------------------------------------

    def _target(self) -> int:
        return self._request[1] & 0xFF

    def _speed(self) -> int:
        return self._request[2] >> 8

    def _force(self) -> int:
        return self._request[2] & 0xFF

    def _moving(self) -> bool:
        """Following a go-to: activated, rGTO set, no fault."""
        go_to = self._request[0] >> 8 & GO_TO
        return bool(go_to) and self._gsta == GSTA_ACTIVATED and self._gflt == 0

    def _stop(self) -> float:
        """Where the current motion ends: the target, or an object met on the way closed."""
        target = self._target()
        if self._object is not None and self._position <= self._object < target:
            return self._object
        return target

    def _object_status(self) -> int:
        if not self._moving() or self._position != self._stop():
            return GOBJ_MOVING
        return GOBJ_AT_REQUEST if self._position == self._target() else GOBJ_CONTACT_CLOSING

    def _advance(self) -> float:
        """Bring the state to the clock's now; return now."""
        now = self._clock()
        if self._gsta == GSTA_ACTIVATING and now >= self._activated_at:
            self._gsta = GSTA_ACTIVATED
            self._last = self._activated_at  # nothing moves before activation completes
            if self._gflt == GFLT_ACTION_DELAYED:
                self._gflt = 0
        if self._moving() and now > self._last:
            fraction = max(self._speed() / 255, MIN_SPEED_FRACTION)
            step = (now - self._last) * fraction * 255 / FULL_STROKE_S
            stop = self._stop()
            if stop > self._position:
                self._position = min(self._position + step, stop)
            else:
                self._position = max(self._position - step, stop)
        self._last = now
        return now


def _units(position: float | None) -> float | None:
    if position is None:
        return None
    if not 0.0 <= position <= 1.0:
        raise ValueError(f"object position is 0..1, not {position}")
    return position * 255


class RobotiqSimServer:
    """A SimulatedGripper served on Modbus TCP (or RTU framing over TCP) in the running loop.

    ``port=0`` binds a free port, reported by ``port``; ``stop()`` then ``start()`` serve
    again on the same port with the same gripper state (a dropped network, not a power cycle).
    The command registers (0x03E8..) are read-write, the status registers (0x07D0..) read-only;
    both answer FC03 and FC04; any other address gets an ILLEGAL_ADDRESS exception.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        device_id: int = 9,
        framing: str = "tcp",
        activation_time_s: float = 0.3,
        object_position: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if framing not in FRAMERS:
            raise ValueError(f"framing must be one of {sorted(FRAMERS)}, not {framing!r}")
        self.host = host
        self.port = port
        self.device_id = device_id
        self.framing = framing
        self.gripper = SimulatedGripper(
            activation_time_s=activation_time_s, object_position=object_position, clock=clock
        )
        self._server: ModbusTcpServer | None = None

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc_info) -> None:
        await self.stop()

    async def start(self) -> None:
        """Listen (on the port bound before, if any); raises RuntimeError if it cannot."""
        if self._server is not None:
            return
        device = SimDevice(
            id=self.device_id,
            simdata=[
                SimData(COMMAND_ADDRESS, count=REGISTER_COUNT, datatype=DataType.REGISTERS),
                SimData(STATUS_ADDRESS, count=REGISTER_COUNT, datatype=DataType.REGISTERS, readonly=True),
            ],
            action=self._on_access,
        )
        server = ModbusTcpServer(device, framer=FRAMERS[self.framing], address=(self.host, self.port))
        await server.serve_forever(background=True)
        self._server = server
        # a TCP server's transport is its listening asyncio.Server
        self.port = cast(asyncio.Server, server.transport).sockets[0].getsockname()[1]

    async def stop(self) -> None:
        """Close the listener and every connection (clients see the link drop)."""
        server, self._server = self._server, None
        if server is not None:
            listener = cast(asyncio.Server, server.transport)
            await server.shutdown()
            await asyncio.wait_for(listener.wait_closed(), timeout=STOP_TIMEOUT_S)

    async def drop_connections(self) -> None:
        """Close every client connection but keep listening: clients must reconnect."""
        if self._server is not None:
            for connection in list(self._server.active_connections.values()):
                connection.close()

    def inject_fault(self, gflt: int) -> None:
        self.gripper.inject_fault(gflt)

    def clear_fault(self) -> None:
        self.gripper.clear_fault()

    def set_object(self, position: float | None) -> None:
        self.gripper.set_object(position)

    async def _on_access(
        self,
        function_code: int,
        block_start: int,
        address: int,
        count: int,
        registers: list[int],
        written: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus calls this before each access to the register block (addresses already
        checked): a write goes to the gripper, a read gets the status as of now."""
        if written is not None:
            # registers, never coils, in this device: the values are ints
            self.gripper.write_command(address - COMMAND_ADDRESS, cast(list[int], written))
        else:
            status = STATUS_ADDRESS - block_start
            registers[status : status + REGISTER_COUNT] = self.gripper.status_registers()
        return None


class BackgroundSimServer:
    """A RobotiqSimServer on its own event-loop thread, for synchronous code and tests.

    A context manager: entering starts the loop and the server, leaving stops both; every
    call into the loop waits at most ``timeout_s``.
    """

    def __init__(self, timeout_s: float = 5.0, **server_options) -> None:
        self.server = RobotiqSimServer(**server_options)
        self.timeout_s = timeout_s
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="robotiq-sim", daemon=True)

    def __enter__(self) -> Self:
        self._thread.start()
        try:
            self.start()
        except BaseException:
            self._stop_loop()
            raise
        return self

    def __exit__(self, *exc_info) -> None:
        try:
            self.stop()
        finally:
            self._stop_loop()

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def gripper(self) -> SimulatedGripper:
        return self.server.gripper

    def start(self) -> None:
        self._run(self.server.start())

    def stop(self) -> None:
        self._run(self.server.stop())

    def drop_connections(self) -> None:
        self._run(self.server.drop_connections())

    def inject_fault(self, gflt: int) -> None:
        self.server.inject_fault(gflt)

    def clear_fault(self) -> None:
        self.server.clear_fault()

    def set_object(self, position: float | None) -> None:
        self.server.set_object(position)

    def _run(self, coroutine):
        return asyncio.run_coroutine_threadsafe(coroutine, self._loop).result(self.timeout_s)

    def _stop_loop(self) -> None:
        try:
            self._run(_cancel_other_tasks())
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(self.timeout_s)
        if self._thread.is_alive():
            raise RuntimeError(f"the simulator's loop thread did not stop within {self.timeout_s} s")
        self._loop.close()


async def _cancel_other_tasks() -> None:
    """pymodbus may leave request tasks behind; end them before the loop stops."""
    tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


def running_in_thread(**server_options) -> BackgroundSimServer:
    """``with running_in_thread(port=0) as sim: sim.port ...``: a simulated gripper served from
    a background thread (options as for RobotiqSimServer, plus ``timeout_s``)."""
    return BackgroundSimServer(**server_options)


class ProcessSimServer:
    """A simulated gripper in a process of its own, driven from the parent through a pipe.

    Its own interpreter and GIL: a loop under test in the parent is not slowed down by the
    server's Python work (a thread would take the GIL for every Modbus request). The same calls
    as ``BackgroundSimServer``, each answered within ``timeout_s``.
    """

    _CALLS = ("start", "stop", "drop_connections", "inject_fault", "clear_fault", "set_object")

    def __init__(self, timeout_s: float = 5.0, **server_options) -> None:
        self.timeout_s = timeout_s
        context = multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe()
        self._process = context.Process(
            target=_serve_calls, args=(child, timeout_s, server_options), name="robotiq-sim", daemon=True
        )
        self.port = 0

    def __enter__(self) -> Self:
        self._process.start()
        self.port = self._call("port", timeout_s=max(self.timeout_s, 30.0))  # a fresh interpreter
        return self

    def __exit__(self, *exc_info) -> None:
        try:
            self._conn.send(("exit", ()))
        finally:
            self._process.join(self.timeout_s)
            if self._process.is_alive():
                self._process.kill()
                self._process.join(self.timeout_s)
            self._conn.close()

    def __getattr__(self, name: str):
        if name not in self._CALLS:
            raise AttributeError(name)
        return lambda *args: self._call(name, *args)

    def _call(self, name: str, *args, timeout_s: float | None = None):
        timeout_s = timeout_s or self.timeout_s
        self._conn.send((name, args))
        if not self._conn.poll(timeout_s):
            raise TimeoutError(f"the simulated gripper did not answer {name}() within {timeout_s} s")
        ok, value = self._conn.recv()
        if not ok:
            raise RuntimeError(f"the simulated gripper failed in {name}(): {value}")
        return value


def _serve_calls(conn, timeout_s: float, server_options: dict) -> None:
    """The child of ``ProcessSimServer``: run the server, answer calls until told to exit."""
    with BackgroundSimServer(timeout_s, **server_options) as sim:
        while True:
            name, args = conn.recv()
            if name == "exit":
                return
            try:
                conn.send((True, sim.port if name == "port" else getattr(sim, name)(*args)))
            except Exception as exc:
                conn.send((False, f"{type(exc).__name__}: {exc}"))


def running_in_process(**server_options) -> ProcessSimServer:
    """``with running_in_process(port=0) as sim: sim.port ...``: a simulated gripper in its own
    process (options as for RobotiqSimServer except ``clock``, plus ``timeout_s``)."""
    return ProcessSimServer(**server_options)


def _in_range(kind: type, lo: float, hi: float):
    """An argparse type: a finite number of ``kind`` within [lo, hi]."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a{'n integer' if kind is int else ' number'}") from None
        if not (math.isfinite(value) and lo <= value <= hi):
            raise argparse.ArgumentTypeError(f"must be from {lo:g} to {hi:g} (got {text})")
        return value

    return parse


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m aiohal.drivers.hands.robotiq_sim", description="A simulated Robotiq 2F-85 on Modbus TCP."
    )
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=_in_range(int, 0, 65535), default=5020, help="0 picks a free port")
    parser.add_argument("--device-id", type=_in_range(int, 1, 247), default=9, help="Modbus unit id, 1-247")
    parser.add_argument("--framing", choices=sorted(FRAMERS), default="tcp")
    parser.add_argument(
        "--object", type=_in_range(float, 0.0, 1.0), default=None, help="object position, 0 open .. 1 closed"
    )
    parser.add_argument("--activation-time", type=_in_range(float, 0.0, 3600.0), default=0.3, help="seconds")
    args = parser.parse_args(argv)

    async def serve() -> None:
        server = RobotiqSimServer(
            args.host,
            args.port,
            device_id=args.device_id,
            framing=args.framing,
            activation_time_s=args.activation_time,
            object_position=args.object,
        )
        async with server:
            print(
                f"simulated Robotiq 2F-85 on {args.host}:{server.port} ({args.framing}, device {args.device_id})",
                flush=True,
            )
            await asyncio.Event().wait()

    try:
        asyncio.run(serve())
    except KeyboardInterrupt:
        pass
    except (OSError, RuntimeError) as exc:  # the address is taken, or not this machine's
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        print(f"error: cannot serve on {args.host}:{args.port}: {reason}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
