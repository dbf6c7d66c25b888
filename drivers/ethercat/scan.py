"""What is on an EtherCAT bus, before a config is written for it (needs root: raw frames).

    python -m aiohal.drivers.ethercat.scan IFNAME [--toml | --json]

Finds the slaves on the one interface named and prints, for each, its identity (vendor id,
product code, revision, the name it gives itself), its AL state and its PDO mapping as bus
variables: byte.bit offset, address, bits, type and name, exactly as the ``ethercat`` driver
will read and link them at bring-up (from CoE, or from the SII for a slave without a mailbox).
Each slave also gets the ``kind`` the driver could run it as: ``cia402`` when it maps every
variable a drive needs with its type, ``imu`` / ``force_torque`` when it maps the sensor's
default variables, else ``other``.

``--toml`` prints a starting point for the config instead: the ``[[driver]]`` table with
every slave in bus order (names, kinds, vendor ids and product codes, which bring-up then
checks), a joint per drive and a device per sensor. What the bus cannot say (joint names and
limits, encoder counts, gear ratios, rated torques) is left for the user, with a comment.

Nothing moves: SOEM's ``config_init`` takes the slaves to PREOP to read their mapping over
CoE, no process data is exchanged, no slave reaches SAFEOP or OP, and every slave is put back
in INIT at the end. Exit status: 0 slaves found, 1 the bus did not answer as expected,
2 the interface does not exist.
"""

from __future__ import annotations

import argparse
import json
import logging
import socket
import sys
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from aiohal.fieldbus.busvar import BusVarError, PdoLayout, ProcessImage
from aiohal.fieldbus.drives import check_types

from .bus import Bus, EthercatError, shares_a_byte, state_name
from .devices import (
    DRIVE_INPUT_TYPES,
    DRIVE_INPUTS,
    DRIVE_OUTPUT_TYPES,
    DRIVE_OUTPUTS,
    ForceTorqueDevice,
    ImuDevice,
    _check_group,
)
from .options import FT_VARIABLES, IMU_VARIABLES
from .sii import has_coe

SHARES_A_BYTE = "fewer than 8 bits of process data in a direction, which the ethercat driver does not support"


@dataclass
class ScannedSlave:
    """One bus position as the scan found it."""

    position: int
    device_name: str  # SII string 1, what the slave calls itself
    vendor_id: int
    product_code: int
    revision: int
    state: int  # AL state as read at the end of the scan
    coe: bool  # has a CoE mailbox (its mapping is read over SDO, and can be remapped)
    device_type: int | None  # object 0x1000, when the slave has CoE and answered
    layout: PdoLayout | None  # None when it could not be read (``error`` says why)
    error: str = ""

    @property
    def kind(self) -> str:
        return suggest_kind(self.layout) if self.layout is not None else "other"


def suggest_kind(layout: PdoLayout) -> str:
    """The ``kind`` the driver could run a slave of this mapping as: the first whose variables
    (names, types and sizes, as the device classes check them at bring-up) are all mapped."""
    for kind in ("cia402", "imu", "force_torque"):
        if not why_not(layout, kind):
            return kind
    return "other"


def why_not(layout: PdoLayout, kind: str) -> str:
    """Why the driver would refuse this mapping for ``kind`` ("" if it would take it): the
    device class's own error at bring-up, e.g. a drive whose PDOs lack "Error code"."""
    if shares_a_byte(layout):
        return SHARES_A_BYTE
    image = ProcessImage([("slave", layout)])
    try:
        if kind == "cia402":
            check_types(image, "slave", DRIVE_INPUTS, DRIVE_INPUT_TYPES)
            check_types(image, "slave", DRIVE_OUTPUTS, DRIVE_OUTPUT_TYPES)
        elif kind == "imu":
            for key, n in ImuDevice.GROUPS:
                _check_group(image, "slave", IMU_VARIABLES[key], n)
        elif kind == "force_torque":
            for key, n in ForceTorqueDevice.GROUPS:
                _check_group(image, "slave", FT_VARIABLES[key], n)
    except BusVarError as exc:
        return str(exc).replace('"slave.', '"')
    return ""


def scan(ifname: str, pysoem: Any | None = None) -> list[ScannedSlave]:
    """Find the slaves on ``ifname`` and read what each one maps; the bus is closed (every slave
    to INIT) before this returns. Raises :class:`~.bus.BringUpError` when the bus does not answer."""
    if pysoem is None:
        import pysoem as default_pysoem  # the `ethercat` extra

        pysoem = default_pysoem
    bus = Bus(pysoem, ifname)
    try:
        bus.open()
        found = []
        for position, slave in enumerate(bus.slaves):
            coe = has_coe(bus.sii(position))
            device_type = bus.device_type(position) if coe else None
            layout, error = None, ""
            try:
                layout = bus.read_layout(position)
            except (BusVarError, EthercatError) as exc:
                error = str(exc)
            found.append(
                ScannedSlave(position, slave.name, slave.man, slave.id, slave.rev, 0, coe, device_type, layout, error)
            )
        for entry, state in zip(found, bus.states(), strict=True):
            entry.state = state
        return found
    finally:
        bus.close()


# ---------------------------------------------------------------- output


def describe(ifname: str, slaves: Sequence[ScannedSlave]) -> str:
    """A readable report: one header line per slave, then its bus variables."""
    lines = [f"{ifname}: {len(slaves)} slave(s)"]
    for s in slaves:
        device_type = f" device type 0x{s.device_type:08X}" if s.device_type is not None else ""
        lines.append(
            f"{s.position:3}  {s.device_name or '?'}  vendor 0x{s.vendor_id:08X} product 0x{s.product_code:08X} "
            f"revision 0x{s.revision:08X}  {state_name(s.state)}  {'CoE' if s.coe else 'no CoE'}"
            f"{device_type}  kind {s.kind}"
        )
        if s.layout is None:
            lines.append(f"     mapping not read: {s.error}")
            continue
        if not s.layout.outputs and not s.layout.inputs:
            lines.append("     no process data")
        if s.kind == "other" and s.device_type is not None and s.device_type & 0xFFFF == 402:
            lines.append(
                f"     a CiA 402 device (0x1000), not usable as a drive as mapped: {why_not(s.layout, 'cia402')}; "
                "remap it with rx_pdos / tx_pdos (docs/ethercat.md)"
            )
        elif shares_a_byte(s.layout):
            lines.append(f"     {SHARES_A_BYTE}")
        for row in s.layout.describe().splitlines():
            lines.append("     " + row)
    return "\n".join(lines)


def config_names(slaves: Sequence[ScannedSlave]) -> list[tuple[str, str | None]]:
    """A name per slave (bus variables are ``"<name>.<variable>"``) and the joint or device it
    serves: drive1, drive2… with joint1, joint2…; imu1, ft1… with a device of the same name."""
    counts: dict[str, int] = {}
    prefix = {"cia402": "drive", "imu": "imu", "force_torque": "ft"}
    names: list[tuple[str, str | None]] = []
    for s in slaves:
        kind = s.kind
        if kind not in prefix:
            names.append((f"slave{s.position}", None))
            continue
        counts[kind] = counts.get(kind, 0) + 1
        name = f"{prefix[kind]}{counts[kind]}"
        names.append((name, f"joint{counts[kind]}" if kind == "cia402" else name))
    return names


NO_JOINT = (
    "This bus has no cia402 drive, so its driver moves no joint, and a config needs at least one "
    "(check says: joints: required section is missing). Add this [[driver]] (and its [devices.*]) "
    "to the config of the robot it is a part of, whose [joints] another driver moves; the slaves' "
    "bus variables are then reached through this driver (driver.image.link)."
)


def to_toml(ifname: str, slaves: Sequence[ScannedSlave]) -> str:
    """The ``[[driver]]`` table for these slaves, with a joint per drive and a device per sensor."""
    names = config_names(slaves)
    joints = [served for s, (_, served) in zip(slaves, names, strict=True) if s.kind == "cia402"]
    devices = [
        (served, s.kind) for s, (_, served) in zip(slaves, names, strict=True) if s.kind in ("imu", "force_torque")
    ]
    lines = [
        f"# Made by `python -m aiohal.drivers.ethercat.scan {ifname} --toml` from what the bus reported.",
        "# Not measured, to fill in from the robot's data before it runs: each joint's limits",
        "# (position, velocity, acceleration, effort), and each drive's units (counts_per_rev,",
        "# gear_ratio, rated_torque in N·m: drive_defaults or per slave). Rename freely: names only",
        "# have to match between the joints, the devices and the slaves.",
        "",
    ]
    if not joints:
        lines[-1:] = ["#", *textwrap.wrap(NO_JOINT, 92, initial_indent="# ", subsequent_indent="# "), ""]
    for joint in joints:
        lines += [f"[joints.{joint}]", "# position = [min, max]  velocity = ...  acceleration = ...  effort = ..."]
    for device, kind in devices:
        lines += ["", f"[devices.{device}]", f'type = "{kind}"']
    lines += ["", "[[driver]]", 'type = "ethercat"', 'name = "bus"', f"joints = {json.dumps(joints)}"]
    if devices:
        lines.append(f"devices = {json.dumps([d for d, _ in devices])}")
    lines += ["", "[driver.options]", f"interface = {json.dumps(ifname)}", "slaves = ["]
    for s, (name, served) in zip(slaves, names, strict=True):
        fields = [f'name = "{name}"', f'kind = "{s.kind}"']
        if s.kind == "cia402":
            fields.append(f'joint = "{served}"')
        elif s.kind in ("imu", "force_torque"):
            fields.append(f'device = "{served}"')
        fields += [f"vendor_id = 0x{s.vendor_id:X}", f"product_code = 0x{s.product_code:X}"]
        comment = f"  # {s.position}: {s.device_name}" if s.device_name else f"  # {s.position}"
        if s.layout is None:
            comment += " (mapping not read)"
        lines.append(f"  {{ {', '.join(fields)} }},{comment}")
    lines.append("]")
    return "\n".join(lines) + "\n"


def to_json(ifname: str, slaves: Sequence[ScannedSlave]) -> str:
    def entries(layout: PdoLayout | None, direction: str) -> list[dict]:
        if layout is None:
            return []
        return [
            {"address": e.address, "bit_offset": e.bit_offset, "bits": e.bits, "type": e.type, "name": e.name}
            for e in getattr(layout, direction)
        ]

    return json.dumps(
        {
            "interface": ifname,
            "slaves": [
                {
                    "position": s.position,
                    "device_name": s.device_name,
                    "vendor_id": s.vendor_id,
                    "product_code": s.product_code,
                    "revision": s.revision,
                    "state": state_name(s.state),
                    "coe": s.coe,
                    "device_type": s.device_type,
                    "kind": s.kind,
                    "error": s.error,
                    "outputs": entries(s.layout, "outputs"),
                    "inputs": entries(s.layout, "inputs"),
                }
                for s in slaves
            ],
        },
        indent=2,
    )


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m aiohal.drivers.ethercat.scan",
        description="List the slaves on one EtherCAT interface and what each maps "
        "(nothing moves: no slave goes beyond PREOP). Needs root.",
    )
    p.add_argument("interface", help="the network interface the slaves hang on (the only one opened)")
    out = p.add_mutually_exclusive_group()
    out.add_argument("--toml", action="store_true", help="print a [[driver]] config for these slaves")
    out.add_argument("--json", action="store_true", help="print what was found as JSON")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    try:
        socket.if_nametoindex(args.interface)
    except OSError:
        print(f"network interface {args.interface!r} does not exist", file=sys.stderr)
        return 2
    try:
        slaves = scan(args.interface)
    except EthercatError as exc:
        print(f"scan of {args.interface!r} failed: {exc}", file=sys.stderr)
        return 1
    if not slaves:
        print(f"no EtherCAT slave answered on {args.interface!r}", file=sys.stderr)
        return 1
    if args.toml:
        print(to_toml(args.interface, slaves), end="")
        if not any(s.kind == "cia402" for s in slaves):
            print(f"note: {NO_JOINT}", file=sys.stderr)
    elif args.json:
        print(to_json(args.interface, slaves))
    else:
        print(describe(args.interface, slaves))
    return 0


if __name__ == "__main__":
    sys.exit(main())
