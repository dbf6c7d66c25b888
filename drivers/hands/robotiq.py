"""Robotiq 2F-85 gripper over Modbus (TCP, or RTU framing tunnelled over TCP): a blocking backend.

The gripper exposes two blocks of three 16-bit registers, two bytes each, high byte first:

* command, holding registers from 0x03E8, written with FC16:
  action request (rACT bit 0, rGTO bit 3, rATR bit 4, rARD bit 5), two reserved bytes,
  rPR position request (0 open .. 255 closed), rSP speed, rFR force.
* status, input registers from 0x07D0, read with FC04:
  gripper status (gACT bit 0, gGTO bit 3, gSTA bits 4-5, gOBJ bits 6-7), a reserved byte,
  fault status (gFLT low nibble, kFLT high nibble), gPR echo, gPO position, gCU current (x10 mA).

Fault mapping: gFLT 0x5 (action delayed, activation not finished) and 0x7 (go-to without the
activation bit) only say the gripper is not activated yet, so they become ``FAULT_NOT_READY``,
the code every backend uses for that; any other gFLT becomes ``VENDOR_FAULT_BASE + gFLT``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

from aiohal.errors import MissingDependencyError

from .base import (
    FAULT_COMMUNICATION,
    FAULT_NONE,
    FAULT_NOT_READY,
    VENDOR_FAULT_BASE,
    HandBackend,
    HandError,
    HandStatus,
)

try:
    from pymodbus import FramerType
    from pymodbus.client import ModbusTcpClient
    from pymodbus.constants import ExcCodes
    from pymodbus.exceptions import ConnectionException, ModbusException
    from pymodbus.pdu import ModbusPDU
except ModuleNotFoundError as exc:
    if not (exc.name or "").startswith("pymodbus"):
        raise
    raise MissingDependencyError(
        "the Robotiq gripper backend needs the optional dependency 'pymodbus': "
        'install the extra: pip install "aiohal[modbus]"'
    ) from exc

log = logging.getLogger(__name__)

COMMAND_ADDRESS = 0x03E8
STATUS_ADDRESS = 0x07D0
REGISTER_COUNT = 3

# Bits of the action request byte; gACT and gGTO sit at the same places in the status byte.
ACTIVATE = 0x01
GO_TO = 0x08

GSTA_ACTIVATED = 3
GOBJ_CONTACT_OPENING = 1
GOBJ_CONTACT_CLOSING = 2
GOBJ_AT_REQUEST = 3

GFLT_ACTION_DELAYED = 0x5
GFLT_NOT_ACTIVATED = 0x7
NOT_READY_FAULTS = frozenset({GFLT_ACTION_DELAYED, GFLT_NOT_ACTIVATED})

#: Modbus framings on a TCP socket, by option name.
FRAMERS = {"tcp": FramerType.SOCKET, "rtu": FramerType.RTU}

ACTIVATION_POLL_S = 0.02


@dataclass(frozen=True)
class RobotiqOptions:
    """Where the gripper is and how long to wait for it."""

    host: str
    port: int = 502
    device_id: int = 9
    timeout_s: float = 0.2  # per Modbus request (and per connection attempt)
    activation_timeout_s: float = 5.0
    framing: str = "tcp"  # "tcp": Modbus TCP; "rtu": RTU frames over TCP (serial gateways)
    max_current_a: float = 0.6  # gCU at full force; effort is the current relative to it

    def __post_init__(self) -> None:
        if self.framing not in FRAMERS:
            raise ValueError(f"framing must be one of {sorted(FRAMERS)}, not {self.framing!r}")
        if not 0 < self.port < 65536:
            raise ValueError(f"port must be 1..65535, not {self.port}")
        if not 0 <= self.device_id <= 247:
            raise ValueError(f"device_id must be 0..247, not {self.device_id}")
        for name in ("timeout_s", "activation_timeout_s", "max_current_a"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, not {getattr(self, name)}")


class RawStatus(NamedTuple):
    """The status registers decoded field by field, as the gripper reports them."""

    gact: int
    ggto: int
    gsta: int
    gobj: int
    gflt: int
    kflt: int
    gpr: int
    gpo: int
    gcu: int


def encode_command(action: int, position: int, speed: int, force: int) -> list[int]:
    """The three command registers, each byte in its place (high byte first)."""
    return [action << 8, position, speed << 8 | force]


def decode_status(registers: Sequence[int]) -> RawStatus:
    status, fault, motion = registers
    gripper = status >> 8
    return RawStatus(
        gact=gripper & ACTIVATE,
        ggto=(gripper & GO_TO) >> 3,
        gsta=(gripper >> 4) & 0x3,
        gobj=(gripper >> 6) & 0x3,
        gflt=(fault >> 8) & 0x0F,
        kflt=fault >> 12,
        gpr=fault & 0xFF,
        gpo=motion >> 8,
        gcu=motion & 0xFF,
    )


def fault_code(gflt: int) -> int:
    """gFLT as a HandStatus fault (see the module docstring)."""
    if gflt == 0:
        return FAULT_NONE
    if gflt in NOT_READY_FAULTS:
        return FAULT_NOT_READY
    return VENDOR_FAULT_BASE + gflt


def _to_byte(fraction: float) -> int:
    return round(min(max(fraction, 0.0), 1.0) * 255)


class Robotiq2F85(HandBackend):
    """A Robotiq 2F-85 (or any gripper with its register map) on Modbus.

    ``Robotiq2F85(host, port=502, **options)`` takes the other ``RobotiqOptions`` fields as
    keywords. Every request is bounded by ``timeout_s``; a failure raises ``HandError`` with
    ``FAULT_COMMUNICATION``. After a lost connection the next call connects again.
    """

    #: The register map; class attributes so that a variant with another map can move them.
    COMMAND_ADDRESS = COMMAND_ADDRESS
    STATUS_ADDRESS = STATUS_ADDRESS

    def __init__(self, host: str, port: int = 502, **options) -> None:
        self.options = RobotiqOptions(host, port, **options)
        self._peer = f"{host}:{port} device {self.options.device_id}"
        # retries=0: one request, one timeout; reconnecting is decided here, not in pymodbus.
        self._client = ModbusTcpClient(
            host,
            port=port,
            framer=FRAMERS[self.options.framing],
            timeout=self.options.timeout_s,
            retries=0,
        )
        self._target = (0, 0, 0)  # rPR, rSP, rFR last commanded, kept when stopping

    def open(self) -> None:
        """Connect, reset, activate, and wait (bounded) until the gripper reports activated."""
        if not self._client.connect():
            raise HandError(
                f"cannot connect to {self._peer} (timeout {self.options.timeout_s} s)",
                FAULT_COMMUNICATION,
            )
        self._write_command(0, 0, 0, 0)  # rACT=0: reset, which also clears a latched fault
        self._write_command(ACTIVATE, 0, 0, 0)
        deadline = time.monotonic() + self.options.activation_timeout_s
        while True:
            status = self.read_raw()
            if status.gsta == GSTA_ACTIVATED:
                return
            if status.gflt and status.gflt not in NOT_READY_FAULTS:
                raise HandError(
                    f"activation of {self._peer} failed: gripper fault gFLT=0x{status.gflt:X}",
                    VENDOR_FAULT_BASE + status.gflt,
                )
            if time.monotonic() >= deadline:
                raise HandError(
                    f"activation of {self._peer} did not complete within "
                    f"{self.options.activation_timeout_s} s (gSTA={status.gsta})",
                    FAULT_NOT_READY,
                )
            time.sleep(ACTIVATION_POLL_S)

    def command(self, grasp: float, speed: float, force: float) -> None:
        self._target = (_to_byte(grasp), _to_byte(speed), _to_byte(force))
        self._write_command(ACTIVATE | GO_TO, *self._target)

    def read(self) -> HandStatus:
        raw = self.read_raw()
        effort = raw.gcu * 0.01 / self.options.max_current_a
        return HandStatus(
            position=raw.gpo / 255,
            effort=min(effort, 1.0),
            object_detected=raw.gobj in (GOBJ_CONTACT_OPENING, GOBJ_CONTACT_CLOSING),
            fault=fault_code(raw.gflt),
            ready=raw.gsta == GSTA_ACTIVATED,
        )

    def read_raw(self) -> RawStatus:
        """The status registers, decoded but not normalised (for diagnostics and open())."""
        what = f"reading status (input registers 0x{self.STATUS_ADDRESS:04X}+{REGISTER_COUNT}, FC04)"
        response = self._call(
            what,
            lambda: self._client.read_input_registers(
                self.STATUS_ADDRESS, count=REGISTER_COUNT, device_id=self.options.device_id
            ),
        )
        if len(response.registers) != REGISTER_COUNT:
            raise HandError(
                f"{what} from {self._peer}: got {len(response.registers)} registers",
                FAULT_COMMUNICATION,
            )
        return decode_status(response.registers)

    def close(self) -> None:
        """Stop the fingers where they are (rGTO=0, best effort), then disconnect."""
        try:
            if self._client.connected:
                self._write_command(ACTIVATE, *self._target)
        except HandError as exc:
            log.warning("robotiq: stop before closing failed: %s", exc.reason)
        finally:
            self._client.close()

    def _write_command(self, action: int, position: int, speed: int, force: int) -> None:
        registers = encode_command(action, position, speed, force)
        self._call(
            f"writing command (holding registers 0x{self.COMMAND_ADDRESS:04X}+{REGISTER_COUNT}, FC16)",
            lambda: self._client.write_registers(self.COMMAND_ADDRESS, registers, device_id=self.options.device_id),
        )

    def _call(self, what: str, request: Callable[[], ModbusPDU]) -> ModbusPDU:
        """Run one request. A link that was up may have been dropped while idle: then connect
        once more and retry. Anything else fails at once."""
        had_link = retry = self._client.connected
        while True:
            try:
                response = request()
            except (ConnectionException, OSError) as exc:
                self._client.close()
                if retry:
                    retry = False
                    continue
                state = "connection lost, reconnecting failed" if had_link else "not connected"
                raise HandError(f"{what} from {self._peer}: {state}: {exc}", FAULT_COMMUNICATION) from exc
            except ModbusException as exc:
                self._client.close()  # a late reply must not be taken for the next one
                raise HandError(
                    f"{what} from {self._peer}: no valid response within {self.options.timeout_s} s: {exc}",
                    FAULT_COMMUNICATION,
                ) from exc
            if response.isError():
                raise HandError(
                    f"{what} from {self._peer}: Modbus exception {_exception_name(response)}",
                    FAULT_COMMUNICATION,
                )
            return response


def _exception_name(response: ModbusPDU) -> str:
    code = getattr(response, "exception_code", 0)
    try:
        return f"{code} ({ExcCodes(code).name})"
    except ValueError:
        return str(code)
